"""What every planner shares about its plan: the error a planner raises for refused inputs, and
acting on the last plan (``act`` reads it at a later step, ``step`` plans then acts).

    >>> class MyPlanner(ActsOnPlan):     # sets self.plan [N, T, U] in optimize(state)
    ...     def optimize(self, state): self.plan = ...
"""
from __future__ import annotations

import numpy as np
import torch

__all__ = ["PlanningError", "plan_action", "ActsOnPlan"]


class PlanningError(ValueError):
    """A planner refused its inputs: a model of another system, a state with NaN / Inf, shapes,
    acting before any plan."""


def plan_action(plan, time):
    """``plan`` [N, T, U] (a tensor or an array) at step ``time`` (clamped to the last): [N, U];
    ``PlanningError`` before any plan (``plan`` None) or for a ``time`` that is no integer >= 0."""
    if plan is None:
        raise PlanningError("no plan to act on: call optimize(state) (or step) first")
    if isinstance(time, bool) or not isinstance(time, (int, np.integer)) or time < 0:
        raise PlanningError(f"time must be an integer >= 0 (steps since the plan's state), got {time!r}")
    return plan[:, min(int(time), plan.shape[1] - 1)]


class ActsOnPlan:
    """``act`` and ``step`` of a planner whose ``optimize(state)`` sets ``self.plan`` [N, T, U]."""

    plan = None

    def act(self, state, time: int = 0) -> torch.Tensor:
        """Actions [N, U] of the last plan, ``time`` steps after the state it planned from
        (clamped to the horizon)."""
        return plan_action(self.plan, time)

    def step(self, state) -> torch.Tensor:
        """``optimize(state)`` then ``act(state, 0)``: the first actions [N, U]."""
        self.optimize(state)
        return self.act(state, 0)
