"""What a planner maximizes over a rollout, and the gradient conditioning gradient planners share.

``planned_return``: the task's reward of a rollout, optionally discounted per step, plus an
optional terminal value of its last state::

    R = sum_t discount^t r_t + discount^T terminal(states[:, T])

where ``r_t = reward(states[:, t:t+2], actions[:, t:t+1])`` is the reward of step t (for
``discount == 1`` the task's reward is called once on the whole rollout, exactly as without this
module). A task whose reward reads state 0 as a reference (swimmer-reach: the direction to its
target) reads state t instead in its per-step terms.

``scale_gradient``: the identity whose backward scales the gradient, for a soft truncated
backprop window: between model steps, the state's gradient carried back one step is multiplied
by a decay, so the gradient of step t+k's reward reaching action t is weighted decay^k (an
effective window of about 1 / (1 - decay) steps).

``condition_gradient``: per-time-step normalization of a gradient with respect to a plan
[N, T, U]: each step's gradient is scaled to the plan's root-mean-square step norm, so that no
step dominates Adam's moments (gradients through a long contact-rich rollout grow by orders of
magnitude from the last control step to the first), and non-finite entries are zeroed.

    >>> r = planned_return(task.reward, states, actions, target, discount=0.99, terminal=value)   # [M]

What every planner shares about the plan it optimized: ``PlanningError`` (a planner refused its
inputs) and ``ActsOnPlan``, the ``act`` / ``step`` of a planner whose ``optimize(state)`` sets
``self.plan`` [N, T, U] (``plan_action`` reads a plan at a later step).
"""
from __future__ import annotations

from typing import Callable

import numpy as np
import torch

from gnwarp.state import QUAT, QUAT_MIN

__all__ = ["step_rewards", "planned_return", "condition_gradient", "check_terminal", "scale_gradient", "GRAD_NORMS",
           "PlanningError", "plan_action", "ActsOnPlan", "check_states"]

GRAD_NORMS = ("none", "step")


def step_rewards(reward: Callable, states: torch.Tensor, actions: torch.Tensor, target=None) -> torch.Tensor:
    """[M, T] per-step rewards of ``reward(states [M', 2, B, 13], actions [M', 1, U], target) ->
    [M']`` on each step of ``states`` [M, T+1, B, 13] under ``actions`` [M, T, U] (``target``
    [M, ...] repeated per step; None: called without it). One batched call of M x T rows."""
    if states.ndim != 4 or actions.ndim != 3 or states.shape[0] != actions.shape[0] \
            or states.shape[1] != actions.shape[1] + 1:
        raise ValueError(f"states must be [M, T+1, B, 13] and actions [M, T, U], got {tuple(states.shape)} and "
                         f"{tuple(actions.shape)}")
    M, T = actions.shape[:2]
    pairs = torch.stack([states[:, :-1], states[:, 1:]], 2).reshape(M * T, 2, *states.shape[2:])
    acts = actions.reshape(M * T, 1, actions.shape[-1])
    if target is None:
        r = reward(pairs, acts)
    else:
        r = reward(pairs, acts, torch.as_tensor(target).repeat_interleave(T, 0))
    return torch.as_tensor(r).reshape(M, T)


def planned_return(reward: Callable, states: torch.Tensor, actions: torch.Tensor, target=None,
                   discount: float = 1.0, terminal: Callable | None = None) -> torch.Tensor:
    """[M] the return a planner maximizes (see the module's docstring): ``reward(states, actions[,
    target]) -> [M]`` summed over the steps (``discount`` < 1: per-step terms weighted
    discount^t), plus discount^T x ``terminal(states[:, -1] [M, B, 13]) -> [M]`` when given.
    Differentiable through all of them."""
    if discount == 1.0:
        r = reward(states, actions) if target is None else reward(states, actions, target)
    else:
        per = step_rewards(reward, states, actions, target)
        w = discount ** torch.arange(per.shape[1], device=per.device, dtype=per.dtype)
        r = (per * w).sum(1)
    if terminal is not None:
        v = terminal(states[:, -1])
        r = r + (discount ** actions.shape[1]) * v.to(r.dtype)
    return r


def condition_gradient(g: torch.Tensor, mode: str = "step", eps: float = 1e-12) -> torch.Tensor:
    """``g`` [N, T, U] conditioned (a new tensor): "none": non-finite entries zeroed; "step":
    also each step's gradient g[n, t] scaled to norm = the root mean square over t of the
    episode's step norms (the episode's overall scale kept, the steps equalized; a zero step
    stays zero). No host synchronization."""
    if mode not in GRAD_NORMS:
        raise ValueError(f"grad_norm must be one of {GRAD_NORMS}, got {mode!r}")
    g = torch.where(torch.isfinite(g), g, torch.zeros_like(g))
    if mode == "none":
        return g
    norm = torch.linalg.vector_norm(g, dim=-1, keepdim=True)                  # [N, T, 1]
    rms = norm.square().mean(1, keepdim=True).sqrt()                          # [N, 1, 1]
    # where every finite step norm overflowed the square, fall back to the largest
    rms = torch.where(torch.isfinite(rms), rms, norm.amax(1, keepdim=True))
    return g * (rms / norm.clamp_min(eps)).where(norm > eps, torch.zeros_like(norm))


def check_terminal(terminal, device=None) -> Callable | None:
    """``terminal`` if None or callable, else TypeError naming what it is. A ``torch.nn.Module``
    is moved to ``device`` (in place; a planner's rollouts stay on their device, and a captured
    planning iteration copies nothing to the host)."""
    if terminal is not None and not callable(terminal):
        raise TypeError("terminal must be a callable terminal(states_last [M, B, 13]) -> [M] (e.g. a "
                        f"gnwarp.control.value.TerminalValue) or None, got {type(terminal).__name__}")
    if isinstance(terminal, torch.nn.Module) and device is not None:
        terminal.to(device)
    return terminal


class _ScaleGradient(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, scale: float):
        ctx.scale = scale
        return x.view_as(x)

    @staticmethod
    def backward(ctx, g):
        return g * ctx.scale, None


def scale_gradient(x: torch.Tensor, scale: float) -> torch.Tensor:
    """``x`` unchanged forward; its gradient multiplied by ``scale`` backward."""
    return _ScaleGradient.apply(x, float(scale))


class PlanningError(ValueError):
    """A planner refused its inputs: a model of another system, a state with NaN / Inf, shapes,
    acting before any plan."""


def check_states(x, n: int, bodies: int | None = None) -> torch.Tensor:
    """Episodes' body states ``x`` [n, B, 13] (B = ``bodies`` where given) as a tensor once they
    are states a planner can plan from: finite, each body's orientation a quaternion (not ~zero);
    else ``PlanningError`` naming the episode and body (a planner would plan on them silently)."""
    x = torch.as_tensor(x)
    if x.ndim != 3 or x.shape[0] != n or x.shape[2] != 13 or (bodies is not None and x.shape[1] != bodies):
        raise PlanningError(f"states must be [N, B, 13] = [{n}, {bodies if bodies is not None else 'B'}, 13] "
                            f"(episodes, bodies), got {list(x.shape)}")
    bad = ~torch.isfinite(x)
    flat = x[..., QUAT].square().sum(-1) <= QUAT_MIN ** 2   # no orientation at all
    any_bad, any_flat = torch.stack([bad.any(), flat.any()]).tolist()   # one host sync a planning step
    if any_bad:
        e, b, f = (int(i) for i in bad.nonzero()[0])
        raise PlanningError(f"the state of episode {e} has NaN or Inf (body {b}, feature {f}): the true "
                            "simulator diverged or was given bad values")
    if any_flat:
        e, b = (int(i) for i in flat.nonzero()[0])
        raise PlanningError(f"the state of episode {e} has no orientation (body {b}'s quaternion, features 3:7, "
                            "is ~zero): body states carry unit quaternions")
    return x


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
