"""The ``Task`` record and its error: what every task module (the paper's in ``tasks``, the
DeepMind Control Suite's in ``dmc``) builds, and what planners and episode runners read.

    reward(states [N, T+1, B, 13], actions [N, T, U], target=None) -> [N]

summed over the T steps after state 0 (a per-step reward is ``f(states[:, t:t+2], actions[:, t:t+1])``).
"""
from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np
import torch

from gnwarp.sim.families import family_name

__all__ = ["Task", "TaskError", "Reward", "Initial", "SUITES", "check_targets"]

SUITES = ("paper", "dmc")


class TaskError(ValueError):
    """An unknown task, a task for another system, or a target of the wrong shape."""


Reward = Callable[..., torch.Tensor]
# (system, n, rng) -> (qpos [n, nq], qvel [n, nv]), numpy float64
Initial = Callable[..., "tuple[np.ndarray, np.ndarray]"]


@dataclasses.dataclass(frozen=True)
class Task:
    """A control task: ``reward(states [N, T+1, B, 13], actions [N, T, U], target=None) -> [N]``
    (to maximize, summed over steps) for ``system`` (a built-in name; a family such as
    "swimmer" fits every SwimmerN), planned over ``horizon`` steps. ``target``: what a per-episode
    target is ("position" for the swimmer and DMC's reacher and swimmer, "pose" / "poses" for the
    JACO, None without one).

    ``score``: the exact reward episodes are scored with, same signature (None: ``reward``); where
    it is set, ``reward`` is a declared smooth surrogate that planners optimize. ``episode_steps``:
    the task's episode length in control steps (DMC: 1000; None: none of its own). ``initial``:
    ``(system, n, rng) -> (qpos [n, nq], qvel [n, nv])`` numpy float64, the task's random initial
    states (None: the caller's). ``suite``: "paper" or "dmc"."""
    name: str
    system: str
    horizon: int
    reward: Reward
    target: str | None = None
    doc: str = ""
    score: Reward | None = None
    episode_steps: int | None = None
    initial: Initial | None = None
    suite: str = "paper"

    def __post_init__(self):
        if not callable(self.reward):
            raise TaskError(f"task {self.name!r}: reward must be callable, got {type(self.reward).__name__}")
        if self.score is not None and not callable(self.score):
            raise TaskError(f"task {self.name!r}: score must be callable or None, got {type(self.score).__name__}")
        if self.initial is not None and not callable(self.initial):
            raise TaskError(f"task {self.name!r}: initial must be callable or None, got {type(self.initial).__name__}")
        if isinstance(self.horizon, bool) or not isinstance(self.horizon, int) or self.horizon < 1:
            raise TaskError(f"task {self.name!r}: horizon must be an integer >= 1, got {self.horizon!r}")
        steps = self.episode_steps
        if steps is not None and (isinstance(steps, bool) or not isinstance(steps, int) or steps < 1):
            raise TaskError(f"task {self.name!r}: episode_steps must be an integer >= 1 or None, got {steps!r}")
        if self.suite not in SUITES:
            raise TaskError(f"task {self.name!r}: suite must be one of {SUITES}, got {self.suite!r}")

    @property
    def scorer(self) -> Reward:
        """The reward episodes are scored with: ``score`` where set, else ``reward``."""
        return self.score if self.score is not None else self.reward

    def fits(self, system: str) -> bool:
        """Whether the task applies to system ``system`` (e.g. "swimmer6" for a "swimmer" task)."""
        return system == self.system or family_name(system) == self.system

    def check_system(self, system: str, what: str = "system") -> None:
        """``TaskError`` unless the task applies to ``system``."""
        if not self.fits(system):
            raise TaskError(f"task {self.name!r} is for {self.system}, but the {what} is {system}")


def check_targets(targets, n: int, task: Task | None = None, error: type[Exception] = TaskError) -> torch.Tensor:
    """``targets`` as a tensor once it is known to give each of ``n`` episodes a finite target of
    the shape ``task`` reads (a "position" task: [n, 2] or [n, 3]); else ``error`` naming what is
    wrong. A NaN or a wrong width would otherwise be planned for and scored without a word."""
    t = torch.as_tensor(np.asarray(targets) if not isinstance(targets, torch.Tensor) else targets)
    if t.shape[:1] != (n,):
        raise error(f"targets must have one entry per episode ({n}), got shape {tuple(t.shape)}")
    if (t.is_floating_point() or t.is_complex()) and not bool(torch.isfinite(t).all()):
        bad = int((~torch.isfinite(t)).reshape(n, -1).any(1).nonzero()[0, 0])
        raise error(f"targets must be finite: episode {bad}'s holds a NaN or Inf")
    if task is not None and task.target == "position" and (t.ndim != 2 or t.shape[1] not in (2, 3)):
        raise error(f"task {task.name!r} takes target positions [{n}, 2] or [{n}, 3], got shape {tuple(t.shape)}")
    return t
