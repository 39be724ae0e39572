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
    >>> planner = make_planner("hybrid", model, task, system, n, {"samples": 32}, targets)   # through a model
"""
from __future__ import annotations

import dataclasses
from typing import Any, Protocol, runtime_checkable

import torch

from gnwarp.control.gradient import GradientMPC, GradientMPCConfig
from gnwarp.control.hybrid import HybridConfig, HybridPlanner
from gnwarp.control.ilqg import ILQG, ILQGSettings
from gnwarp.control.sampling import RandomPlanner, RandomSettings, SamplingConfig, SamplingPlanner

__all__ = ["Planner", "PlannerEntry", "PLANNERS", "MODEL_PLANNERS", "planner_name", "get_planner", "planner_settings",
           "make_planner", "plan_bytes", "check_plan_memory"]


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
    """The registered planner ``name`` (one of ``PLANNERS``), or ValueError naming the choices.
    "policy" (a trained agent of ``gnwarp rl``) registers itself when ``gnwarp.rl.planner`` is
    imported (the ``gnwarp`` commands import it)."""
    if name == "policy" and name not in PLANNERS:
        raise ValueError("planner 'policy' (a trained gnwarp rl agent) is registered by importing "
                         "gnwarp.rl.planner")
    if name not in PLANNERS:
        raise ValueError(f"unknown planner {name!r}; registered: {', '.join(PLANNERS)}")
    return PLANNERS[name]


def planner_name(planner) -> str:
    """The registered name of ``planner`` (an instance), or ValueError for one not registered."""
    for name, entry in PLANNERS.items():
        if entry.matches(planner):
            return name
    raise ValueError(f"{type(planner).__name__} is not a registered planner ({', '.join(PLANNERS)})")


# the registered planners that plan through a learned model (``make_planner`` on a ``Dynamics``)
MODEL_PLANNERS = ("gradient", "hybrid", "sampling", "mppi")


def planner_settings(name: str, settings=None):
    """The settings of the registered planner ``name``: ``settings`` None (its defaults), a dict
    of its settings dataclass's fields, or an instance of that dataclass (checked against the
    fields the name fixes). An unknown key raises ``ConfigError`` naming the fields there are."""
    from gnwarp.validation import ConfigError
    entry = get_planner(name)
    names = [f.name for f in dataclasses.fields(entry.settings)]
    if settings is None:
        settings = {}
    elif isinstance(settings, entry.settings):
        settings = {k: getattr(settings, k) for k in names}
    elif not isinstance(settings, dict):
        raise TypeError(f"settings of planner {name!r} must be a dict or a {entry.settings.__name__}, "
                        f"got {type(settings).__name__}")
    unknown = [k for k in settings if k not in names]
    if unknown:
        raise ConfigError(unknown[0], f"is not a setting of planner {name!r}; {entry.settings.__name__} has "
                                      f"{', '.join(names)}")
    return entry.make_settings(**dict(settings))


def make_planner(name: str, dynamics, task, system, n: int, settings=None, targets=None, terminal=None,
                 ctrlrange=None):
    """The registered planner ``name`` for ``n`` episodes of ``system`` (a ``System`` or a
    built-in name) on ``task`` (a ``Task`` or its name), planning through ``dynamics``.

    ``dynamics``: a learned ``gnwarp.dynamics.Dynamics`` model (bound here to ``system``) or a
    ``RolloutDynamics`` (``sampling.true_dynamics``: the true simulator; not for "gradient", which
    differentiates a model). "gradient": ``GradientMPC``; "hybrid": ``HybridPlanner``;
    "sampling" / "mppi": ``SamplingPlanner`` on ``sampling.model_dynamics`` of the model (of
    ``samples`` x ``horizon`` rollouts) or on the given rollout dynamics; "random":
    ``RandomPlanner``. ``settings``: as ``planner_settings`` takes them. ``targets`` [n, ...]: the
    task's per-episode targets; ``terminal``: an optional ``terminal(states_last [M, B, 13]) ->
    [M]`` added to planned returns (a ``gnwarp.control.value.TerminalValue``); ``ctrlrange``
    [U, 2]: where sampling planners draw actions (None: the system's actuators' sample range,
    an env's ``ctrlrange``)."""
    from gnwarp.control.returns import PlanningError
    from gnwarp.control.sampling import model_dynamics
    from gnwarp.control.tasks import get_task
    from gnwarp.dynamics import Dynamics
    from gnwarp.sim.systems import System, make
    entry = get_planner(name)
    settings = planner_settings(name, settings)
    learned = isinstance(dynamics, Dynamics)

    def one_system():
        return system if isinstance(system, System) else make(system)

    if entry.cls is GradientMPC and not learned:
        raise PlanningError(f"planner 'gradient' differentiates a learned Dynamics model; {type(dynamics).__name__} "
                            "has no gradients (plan on it with sampling, mppi or hybrid)")
    if entry.cls in (GradientMPC, HybridPlanner):
        return entry.cls(dynamics, task, system, n, settings, targets, terminal)
    if entry.cls is SamplingPlanner:
        sys_ = one_system()
        settings = settings.for_task(get_task(task))
        dyn = model_dynamics(dynamics.bind(sys_), n, settings.samples, settings.horizon) if learned else dynamics
        cr = ctrlrange if ctrlrange is not None else sys_.actuators.sample_range()
        return SamplingPlanner(dyn, task, cr, n, settings, targets, terminal)
    if entry.cls is RandomPlanner:
        return RandomPlanner(ctrlrange if ctrlrange is not None else one_system().actuators, n, seed=settings.seed)
    build = getattr(entry.cls, "for_model", None)
    if build is None:
        raise ValueError(f"planner {name!r} ({entry.cls.__name__}) is not built through a dynamics model; "
                         f"make_planner builds {', '.join(MODEL_PLANNERS)} and random")
    return build(dynamics, task, system, n, settings, targets)


def plan_bytes(n: int, horizon: int, bodies: int, nu: int, candidates: int = 1, copies: int = 8) -> int:
    """A floor on the memory of a planner's rollouts: ``n`` episodes x ``candidates`` rollouts
    over ``horizon`` steps of float32 states and actions, ``copies`` of them (gradient planners
    ~8: the rollouts, their gradients, the plan and its optimizer's moments, the best found;
    sampling planners ~2)."""
    return 4 * copies * n * candidates * (horizon + 1) * (bodies * 13 + nu)


def check_plan_memory(planner: str, settings, n: int, task, system, device, models: int = 1,
                      hint: str = "Use a shorter horizon (or fewer samples or episodes)") -> None:
    """Refuse, before planning, settings whose rollouts cannot fit: planner ``planner``'s
    ``settings`` (their ``horizon``, else ``task``'s; their ``samples``, else 1) for ``n``
    episodes of ``system``, through ``models`` models (an ensemble: a sampling planner rolls every
    sample through each): ``plan_bytes`` in ``device``'s free memory (the host's for the CPU)
    and ~1 kB of Python objects a planned step (the rollout engine's per-step slots) in the
    host's, each ``ValueError`` naming the sizes, then ``hint``."""
    from gnwarp.validation import check_memory
    horizon = getattr(settings, "horizon", None) or task.horizon
    candidates = int(getattr(settings, "samples", 1) or 1) * max(1, int(models))
    copies = 8 if planner in ("gradient", "hybrid") else 2
    what = f"planning {n} episodes x {candidates} rollouts x horizon {horizon} x {system.nbody} bodies"
    arrays = plan_bytes(n, horizon, system.nbody, system.nu, candidates, copies)
    device = torch.device(device)
    if device.type == "cuda":
        free = torch.cuda.mem_get_info(device)[0]
        if arrays > free:
            raise ValueError(f"{what} needs about {arrays / 2**30:.3g} GiB of GPU memory; {device} has "
                             f"{free / 2**30:.3g} GiB free. {hint}")
        arrays = 0
    check_memory(arrays + 1000 * horizon, what, hint)
