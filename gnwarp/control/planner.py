"""The ``Planner`` protocol every closed-loop controller implements, and the registry of planner
names that results records use.

After MuJoCo MPC's planner interface, the expensive optimization is kept apart from the cheap
action: ``optimize(state)`` spends one planning budget and keeps the plan it made; ``act(state,
time)`` reads an action from that plan; ``step(state)`` is ``optimize(state)`` then
``act(state, 0)``. Shapes: N episodes, U controls.

- ``reset(n, targets=None, seed=None)``: start N new episodes: a fresh plan (the first
  ``optimize`` warms up again), the random numbers re-seeded (``seed``; None: the settings'),
  the per-episode ``targets`` [N, ...] of the task (None: those the planner holds).
- ``optimize(state)``: one planning budget from the episodes' current true state; the working
  plan is then shifted one data step as the next budget's warm start.
- ``act(state, time=0)``: actions [N, U] of the plan made by the last ``optimize``, ``time``
  data steps after the state it planned from (clamped to the plan's last step).
- ``needs_sim_state``: whether ``state`` must be the simulator's state (``env.observe()``: qpos,
  qvel and body states) rather than body states [N, B, 13] alone.
- ``n`` (episodes), ``targets`` (None for a task without targets), ``device`` (of the actions).

A trained policy plugs in as a planner whose ``optimize`` does nothing.

    >>> entry = get_planner("mppi")                 # PlannerEntry(SamplingPlanner, SamplingConfig, method "mppi")
    >>> planner = entry.cls(dynamics, task, ctrlrange, n, entry.make_settings(samples=32))
    >>> isinstance(planner, Planner), planner_name(planner)
    (True, 'mppi')
"""
from __future__ import annotations

import dataclasses
from typing import Any, Protocol, runtime_checkable

import torch

from gnwarp.control.gradient import GradientMPC, GradientMPCConfig
from gnwarp.control.hybrid import HybridConfig, HybridPlanner
from gnwarp.control.ilqg import ILQG, ILQGSettings
from gnwarp.control.sampling import RandomPlanner, RandomSettings, SamplingConfig, SamplingPlanner

__all__ = ["Planner", "PlannerEntry", "PLANNERS", "planner_name", "get_planner"]


@runtime_checkable
class Planner(Protocol):
    """A closed-loop controller of N episodes (see the module's docstring)."""

    n: int
    targets: Any
    device: torch.device

    @property
    def needs_sim_state(self) -> bool: ...

    def reset(self, n: int, targets=None, seed: int | None = None) -> None: ...

    def optimize(self, state) -> None: ...

    def act(self, state, time: int = 0) -> torch.Tensor: ...

    def step(self, state) -> torch.Tensor: ...


@dataclasses.dataclass(frozen=True)
class PlannerEntry:
    """A registered planner: its class, its settings dataclass and the settings fields the name
    fixes (``"mppi"``: a ``SamplingPlanner`` with ``method="mppi"``)."""
    cls: type
    settings: type
    fixed: tuple[tuple[str, Any], ...] = ()

    def make_settings(self, **fields):
        """The name's settings: ``fields`` with the fixed ones (a conflicting value: ValueError)."""
        for k, v in self.fixed:
            if k in fields and fields[k] != v:
                raise ValueError(f"{self.cls.__name__} registered with {k}={v!r}; got {k}={fields[k]!r}")
            fields[k] = v
        return self.settings(**fields)

    def matches(self, planner) -> bool:
        if type(planner) is not self.cls:
            return False
        settings = planner.settings
        return all(getattr(settings, k) == v for k, v in self.fixed)


# the names results records give planners (their settings go beside them)
PLANNERS: dict[str, PlannerEntry] = {
    "gradient": PlannerEntry(GradientMPC, GradientMPCConfig),
    "sampling": PlannerEntry(SamplingPlanner, SamplingConfig, (("method", "best"),)),
    "mppi": PlannerEntry(SamplingPlanner, SamplingConfig, (("method", "mppi"),)),
    "ilqg": PlannerEntry(ILQG, ILQGSettings),
    "random": PlannerEntry(RandomPlanner, RandomSettings),
    "hybrid": PlannerEntry(HybridPlanner, HybridConfig),
}


def get_planner(name: str) -> PlannerEntry:
    """The registered planner ``name`` (one of ``PLANNERS``), or ValueError naming the choices."""
    if name not in PLANNERS:
        raise ValueError(f"unknown planner {name!r}; registered: {', '.join(PLANNERS)}")
    return PLANNERS[name]


def planner_name(planner) -> str:
    """The registered name of ``planner`` (an instance), or ValueError for one not registered."""
    for name, entry in PLANNERS.items():
        if entry.matches(planner):
            return name
    raise ValueError(f"{type(planner).__name__} is not a registered planner ({', '.join(PLANNERS)})")
