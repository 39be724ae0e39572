"""Sampling MPC: predictive sampling (MuJoCo MPC's simplest sampling planner), MPPI as an option.

For each of N episodes the planner keeps a nominal action sequence over the horizon, a spline
through P knots. Each planning step it draws K candidates (the nominal itself and K-1 with
Gaussian noise on the knots, clamped to the control range), rolls all N*K out from the episode's
current true state, scores them with ``reward(states [M, T+1, B, 13], actions [M, T, U]) -> [M]``,
and makes the best candidate (``method="best"``) or the reward-weighted mean (``"mppi"``) the
new nominal. Its first action is applied; the nominal is then shifted one step (the warm start).

Rollouts come from a ``dynamics``, any ``gnwarp.dynamics.RolloutDynamics`` (``rollout(obs,
actions, samples)``): ``EnvDynamics`` (the true simulator, an ``Env`` of N*K worlds reset to each
episode's state: the oracle) or ``ModelDynamics`` (a learned model's rollout callable,
``(x0 [M, B, 13], actions [M, T, U]) -> [M, T+1, B, 13]``, e.g. ``ForwardModel.rollout`` or a
``RolloutEngine``'s; ``model_dynamics`` makes one from a ``Dynamics`` model). Both planners here
implement ``gnwarp.control.planner.Planner``; ``gnwarp.control.episodes.run_episodes`` runs any
planner in closed loop.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, Literal

import numpy as np
import torch
import torch.nn.functional as F

from gnwarp.control.returns import ActsOnPlan, check_states, check_terminal, planned_return
from gnwarp.control.tasks import Task, get_task
from gnwarp.control.task_base import check_targets
from gnwarp.sim.actuators import Actuators
from gnwarp.sim.env import Env, Observation, make_env
from gnwarp.sim.excitation import catmull_rom
from gnwarp.validation import ConfigError, FloatRange, IntRange, PositiveFloat, PositiveInt, check_fields

__all__ = ["SamplingConfig", "SamplingPlanner", "RandomSettings", "RandomPlanner", "EnvDynamics", "ModelDynamics",
           "EnsembleDynamics", "true_dynamics", "model_dynamics", "ensemble_dynamics", "score_rollouts", "spline_basis"]

Reward = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
INTERPOLATIONS = ("zero", "linear", "cubic")
METHODS = ("best", "mppi")


@dataclass
class SamplingConfig:
    """horizon: data steps planned ahead (T; None: the task's, as the other planners); samples: candidates per episode (K, the nominal
    included); knots: spline knots P over the horizon (``interpolation`` "zero": piecewise
    constant, P spans; "linear" / "cubic": P points from the first step to the last);
    noise: standard deviation of the knot noise, relative to half of each actuator's range;
    method: "best" (predictive sampling) or "mppi" (softmax of reward / (temperature x the
    episode's reward spread)); seed: of the noise; discount: per-step weight of the scored return
    (``gnwarp.control.returns.planned_return``; 1: the reward as is; a ``terminal`` value is
    weighted discount^horizon)."""
    horizon: PositiveInt | None = None
    samples: PositiveInt = 64
    knots: PositiveInt = 4
    interpolation: Literal[INTERPOLATIONS] = "zero"
    noise: FloatRange(ge=0) = 0.2
    method: Literal[METHODS] = "best"
    temperature: PositiveFloat = 0.1
    seed: IntRange(0) = 0
    discount: FloatRange(gt=0, le=1) = 1.0

    def __post_init__(self):
        check_fields(self)   # ConfigError naming the field
        if self.interpolation != "zero" and self.knots < 2:
            raise ConfigError("knots", f"{self.interpolation} interpolation needs knots >= 2, got {self.knots}")
        if self.horizon is not None and self.knots > self.horizon:
            raise ConfigError("knots", f"must not exceed the horizon ({self.horizon}), got {self.knots}")

    def for_task(self, task: Task | None) -> "SamplingConfig":
        """These settings with the horizon set: their own, else ``task``'s (``ConfigError`` when
        both are None: a reward callable has no horizon of its own)."""
        if self.horizon is not None:
            return self
        if task is None:
            raise ConfigError("horizon", "None means the task's horizon, and a reward callable has none: give "
                                         "SamplingConfig(horizon=...)")
        return replace(self, horizon=task.horizon)


@dataclass
class RandomSettings:
    """seed: of the uniform random actions."""
    seed: IntRange(0) = 0

    def __post_init__(self):
        check_fields(self)


def spline_basis(kind: str, knots: int, times: np.ndarray) -> np.ndarray:
    """[len(times), knots] weights: actions at ``times`` (in knot units, clamped to the knots'
    span) = weights @ knot values, for "zero", "linear" or "cubic" (Catmull-Rom) interpolation."""
    s = np.clip(np.asarray(times, dtype=np.float64), 0.0, knots - 1)
    if kind == "zero":
        return np.eye(knots)[np.floor(s + 1e-9).astype(np.int64).clip(0, knots - 1)]
    if kind == "linear":
        return np.maximum(0.0, 1.0 - np.abs(s[:, None] - np.arange(knots)[None, :]))
    return catmull_rom(np.eye(knots), np.broadcast_to(s, (knots, s.size))).T


def _basis_pair(cfg: SamplingConfig) -> tuple[np.ndarray, np.ndarray]:
    """(actions from knots [T, P], shifted knots from knots [P, P]): the shift moves the spline
    one data step earlier, holding its last value."""
    T, P = cfg.horizon, cfg.knots
    per_step = P / T if cfg.interpolation == "zero" else (P - 1) / max(T - 1, 1)
    at = spline_basis(cfg.interpolation, P, np.arange(T) * per_step)
    shift = spline_basis(cfg.interpolation, P, np.arange(P) + per_step)
    return at, shift


# -- dynamics ---------------------------------------------------------------------------------

class EnvDynamics:
    """The true simulator as a planner's dynamics (a ``gnwarp.dynamics.RolloutDynamics``): ``env``
    holds N*K worlds; each rollout resets world n*K + k to episode n's state (qpos, qvel) and
    steps the candidates."""

    def __init__(self, env: Env, source: Env | None = None):
        self.env, self.source = env, source
        self.device = env.device

    def rollout(self, obs, actions: torch.Tensor, samples: int) -> torch.Tensor:
        if not isinstance(obs, Observation):
            if self.source is None:
                raise ValueError("planning on the true simulator needs the true qpos / qvel: pass env.observe(), "
                                 "or build the dynamics with source=the closed-loop env")
            obs = self.source.observe()
        n = obs.qpos.shape[0]
        if n * samples != self.env.n_worlds:
            raise ValueError(f"the planning env has {self.env.n_worlds} worlds; {n} episodes x {samples} samples "
                             f"need {n * samples} (make it with true_dynamics(system, n_episodes, samples))")
        self.env.reset(obs.qpos.repeat_interleave(samples, 0), obs.qvel.repeat_interleave(samples, 0))
        return self.env.rollout(actions)


class ModelDynamics:
    """A learned model as a planner's dynamics (a ``gnwarp.dynamics.RolloutDynamics``):
    ``rollout_fn(x0 [M, B, 13], actions [M, T, U]) -> [M, T+1, B, 13]`` from the episodes' body
    states, without gradients."""

    def __init__(self, rollout_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], device=None,
                 bodies: int | None = None):
        self.rollout_fn = rollout_fn
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self.bodies = bodies   # B of the states it rolls out (None: not known)

    def rollout(self, obs, actions: torch.Tensor, samples: int) -> torch.Tensor:
        body = obs.body if isinstance(obs, Observation) else torch.as_tensor(obs)
        with torch.no_grad():
            return self.rollout_fn(body.to(self.device).repeat_interleave(samples, 0), actions)


class EnsembleDynamics:
    """Several dynamics (e.g. learned models trained from different seeds) as one
    ``RolloutDynamics`` whose candidates a planner scores pessimistically: each member rolls the
    candidates out, the planner's score is taken of each member's states, and the candidates are
    ranked by ``mean - penalty x std`` over the members (``combine``), so that a plan exploiting
    one model's error is not preferred. ``rollout`` alone returns the members' mean states."""

    def __init__(self, members, penalty: float = 1.0):
        self.members = list(members)
        if len(self.members) < 2 or not all(callable(getattr(m, "rollout", None)) for m in self.members):
            raise ValueError(f"an ensemble needs >= 2 RolloutDynamics members (rollout(obs, actions, samples)), got "
                             f"{[type(m).__name__ for m in self.members]}")
        if isinstance(penalty, bool) or not isinstance(penalty, (int, float)) or not np.isfinite(penalty) \
                or penalty < 0:
            raise ValueError(f"penalty must be a finite number >= 0, got {penalty!r}")
        self.penalty = float(penalty)
        self.device = torch.device(self.members[0].device)

    def rollouts(self, obs, actions: torch.Tensor, samples: int) -> torch.Tensor:
        """[S, M, T+1, B, 13]: every member's rollouts of ``actions`` [M, T, U]."""
        return torch.stack([m.rollout(obs, actions, samples).to(self.device) for m in self.members])

    def rollout(self, obs, actions: torch.Tensor, samples: int) -> torch.Tensor:
        return self.rollouts(obs, actions, samples).mean(0)

    def combine(self, returns: torch.Tensor) -> torch.Tensor:
        """[M] ``mean - penalty x std`` over the members of ``returns`` [S, M]."""
        return returns.mean(0) - self.penalty * returns.std(0, unbiased=False)


def score_rollouts(dynamics, obs, actions: torch.Tensor, samples: int, score) -> torch.Tensor:
    """[M] ``score(states [M, T+1, B, 13]) -> [M]`` of the rollouts of ``actions`` [M, T, U]
    through ``dynamics``; an ``EnsembleDynamics`` scores each member's and combines them."""
    if isinstance(dynamics, EnsembleDynamics):
        return dynamics.combine(torch.stack([score(s) for s in dynamics.rollouts(obs, actions, samples)]))
    return score(dynamics.rollout(obs, actions, samples))


def true_dynamics(system, n_episodes: int, samples: int, backend: str = "auto", device=None,
                  source: Env | None = None, **kw) -> EnvDynamics:
    """``EnvDynamics`` on a fresh env of ``n_episodes * samples`` worlds of ``system``; ``source``:
    the closed-loop env whose true state a planning step reads when given body states only."""
    return EnvDynamics(make_env(system, n_episodes * samples, backend=backend, device=device, **kw), source)


def model_dynamics(model, n_episodes: int, samples: int, horizon: int) -> ModelDynamics:
    """``ModelDynamics`` through a bound ``gnwarp.dynamics.Dynamics`` model: one ``RolloutEngine``
    of ``n_episodes * samples`` rollouts of ``horizon`` steps of instance 0, the controls used as
    given (a sampling planner keeps them in range) and not checked."""
    engine = model.rollout_engine(torch.zeros(n_episodes * samples, dtype=torch.int64), horizon, ctrl_policy="none",
                                  check=False)
    return ModelDynamics(lambda x, u: engine.rollout(x.to(model.dtype), u.to(model.device, model.dtype)),
                         device=model.device, bodies=int(engine.template.B))


def ensemble_dynamics(models, n_episodes: int, samples: int, horizon: int, penalty: float = 1.0) -> EnsembleDynamics:
    """``EnsembleDynamics`` of ``model_dynamics`` of each bound ``Dynamics`` model of ``models``."""
    return EnsembleDynamics([model_dynamics(m, n_episodes, samples, horizon) for m in models], penalty)


# -- planners ---------------------------------------------------------------------------------

class SamplingPlanner(ActsOnPlan):
    """Predictive sampling / MPPI over ``n_episodes`` episodes at once (a ``Planner``).

    ``dynamics``: a ``RolloutDynamics`` (``EnvDynamics``, ``ModelDynamics``); ``reward``: a
    callable of (states [M, T+1, B, 13], actions [M, T, U]) -> [M], higher is better, or a
    ``Task`` (or its name), whose reward gets each candidate its episode's ``targets`` [N, ...];
    ``ctrlrange`` [U, 2]: where actions are sampled and clamped (an env's ``ctrlrange``);
    ``terminal``: an optional ``terminal(states_last [M, B, 13]) -> [M]`` added to each
    candidate's reward (``gnwarp.control.returns.planned_return``).
    ``optimize(obs)`` samples and scores K candidates per episode; ``act(obs, t)`` -> [N, U];
    ``step(obs)`` = both."""

    def __init__(self, dynamics, reward: Reward | Task | str, ctrlrange, n_episodes: int,
                 config: SamplingConfig | None = None, targets=None, terminal=None):
        if not isinstance(config, (SamplingConfig, type(None))):
            raise TypeError(f"config must be a SamplingConfig, got {type(config).__name__}")
        self.dynamics = dynamics
        self.task = get_task(reward) if isinstance(reward, (str, Task)) else None
        self.reward = self._task_reward if self.task is not None else reward
        self.terminal = check_terminal(terminal, dynamics.device)
        self.settings = (config or SamplingConfig()).for_task(self.task)
        self.horizon = self.settings.horizon
        self.n = _episodes(n_episodes)
        self.device = dynamics.device
        cr = (ctrlrange.detach().double() if isinstance(ctrlrange, torch.Tensor)   # e.g. a CUDA env's ctrlrange
              else torch.as_tensor(np.asarray(ctrlrange, dtype=np.float64)))
        cr = cr.reshape(-1, 2).to(self.device, torch.float32)
        if not bool(torch.isfinite(cr).all()) or bool((cr[:, 1] < cr[:, 0]).any()):
            raise ValueError(f"ctrlrange must be finite [U, 2] with lower <= upper, got {cr.tolist()}")
        self.lo, self.hi = cr[:, 0], cr[:, 1]
        self.nu = cr.shape[0]
        at, shift = _basis_pair(self.settings)
        self._at = torch.tensor(at, dtype=torch.float32, device=self.device)
        self._shift = torch.tensor(shift, dtype=torch.float32, device=self.device)
        self._gen = torch.Generator(device=self.device)
        self.targets = None
        self.reset(self.n, targets)

    def reset(self, n: int | None = None, targets=None, seed: int | None = None) -> None:
        """Start ``n`` episodes (None: as many as before): nominal knots at the middle of the
        range, no plan, the noise generator re-seeded (``seed``; None: the settings'); ``targets``
        [n, ...] for a task's reward (None: those held)."""
        self.n = self.n if n is None else _episodes(n)
        held = self.targets if targets is None else targets
        self.targets = None if held is None else check_targets(held, self.n, self.task, ValueError).to(self.device)
        self._gen.manual_seed(self.settings.seed if seed is None else seed)
        mid = 0.5 * (self.lo + self.hi)
        self.knots = mid.expand(self.n, self.settings.knots, self.nu).clone()
        self.last_rewards = None
        self.plan = None

    def _task_reward(self, states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """The task's reward of rows of episodes x candidates, each with its episode's target."""
        tgt = None
        if self.targets is not None:
            tgt = self.targets.to(states.device).repeat_interleave(states.shape[0] // self.n, 0)
        return self.task.reward(states, actions.to(states.device, states.dtype), tgt)

    def scored(self, states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """[M] the score of rollouts ``states`` [M, T+1, B, 13] under ``actions`` [M, T, U] (rows
        of episodes x candidates): the reward, discounted per the settings, plus the terminal
        value."""
        actions = actions.to(states.device, states.dtype)
        if self.task is not None:
            tgt = None
            if self.targets is not None:
                tgt = self.targets.to(states.device).repeat_interleave(states.shape[0] // self.n, 0)
            return planned_return(self.task.reward, states, actions, tgt, self.settings.discount, self.terminal)
        return planned_return(self.reward, states, actions, None, self.settings.discount, self.terminal)

    def actions(self, knots: torch.Tensor) -> torch.Tensor:
        """Action sequences [..., T, U] of knots [..., P, U], inside the range."""
        a = torch.einsum("tp,...pu->...tu", self._at, knots)
        return torch.maximum(torch.minimum(a, self.hi), self.lo)

    def nominal(self) -> torch.Tensor:
        """The current nominal action sequences [N, T, U]."""
        return self.actions(self.knots)

    def candidates(self) -> torch.Tensor:
        """Knots of the K candidates of each episode [N, K, P, U]: the nominal first."""
        cfg = self.settings
        shape = (self.n, cfg.samples - 1, cfg.knots, self.nu)
        scale = cfg.noise * 0.5 * (self.hi - self.lo)
        noise = torch.randn(shape, generator=self._gen, device=self.device) * scale
        cand = torch.cat([self.knots[:, None], self.knots[:, None] + noise], 1)
        return torch.maximum(torch.minimum(cand, self.hi), self.lo)

    @property
    def needs_sim_state(self) -> bool:
        """Whether ``step`` needs the simulator's state (``env.observe()``), not body states
        alone: planning on the true simulator without a ``source`` env to read it from."""
        return isinstance(self.dynamics, EnvDynamics) and self.dynamics.source is None

    def optimize(self, obs) -> None:
        """One planning budget from the episodes' true states ``obs`` (an ``Observation``, or body
        states [N, B, 13]): K candidates rolled out and scored; the chosen sequences become the
        plan [N, T, U] (``act``) and, shifted one step, the nominal."""
        body = torch.as_tensor(obs.body if isinstance(obs, Observation) else obs)
        if body.ndim == 0 or body.shape[0] != self.n:
            raise ValueError(f"this planner holds {self.n} episodes, got states of shape {list(body.shape)}")
        if not isinstance(obs, Observation):   # body states: planned from as given (the true env's are its own)
            obs = check_states(body, self.n, getattr(self.dynamics, "bodies", None))
        cfg, N, K = self.settings, self.n, self.settings.samples
        cand = self.candidates()                                       # [N, K, P, U]
        acts = self.actions(cand).reshape(N * K, cfg.horizon, self.nu)
        r = score_rollouts(self.dynamics, obs, acts, K, lambda states: self.scored(states, acts))
        r = torch.as_tensor(r).to(self.device, torch.float32).reshape(N, K)
        r = torch.where(torch.isfinite(r), r, torch.full_like(r, -torch.inf))   # a diverged rollout never wins
        if cfg.method == "best":
            chosen = cand[torch.arange(N, device=self.device), r.argmax(1)]
        else:
            top = r.max(1, keepdim=True).values
            spread = (top - r.masked_fill(~torch.isfinite(r), torch.inf).min(1, keepdim=True).values).clamp_min(1e-9)
            w = torch.softmax((r - top) / (cfg.temperature * spread), 1)
            # an episode whose every rollout diverged keeps its nominal (candidate 0), not NaN weights
            w = torch.where(torch.isfinite(top), w, F.one_hot(torch.zeros_like(r[:, 0], dtype=torch.int64), K).to(w))
            chosen = torch.einsum("nk,nkpu->npu", w, cand)
        self.last_rewards = r
        self.plan = self.actions(chosen)
        self.knots = torch.einsum("qp,npu->nqu", self._shift, chosen)


class RandomPlanner(ActsOnPlan):
    """The random-actions baseline (a ``Planner``): uniform in ``ctrlrange`` [U, 2], independent
    each step: ``optimize`` draws them, ``act`` returns them. ``seed``: ``RandomSettings.seed``.

    ``ctrlrange``: a [U, 2] range (an env's ``ctrlrange``) or an ``Actuators`` record (an env's
    ``actuators``), whose ``sample_range`` is used: unlimited actuators draw in
    ``UNLIMITED_SAMPLE_RANGE``."""

    needs_sim_state = False

    def __init__(self, ctrlrange, n_episodes: int, seed: int = 0, device="cpu"):
        self.settings = RandomSettings(seed=seed)
        if isinstance(ctrlrange, Actuators):
            ctrlrange = ctrlrange.sample_range()
        cr = torch.as_tensor(ctrlrange).detach().to("cpu", torch.float64).reshape(-1, 2)
        if not bool(torch.isfinite(cr).all()) or bool((cr[:, 1] < cr[:, 0]).any()):
            raise ValueError(f"ctrlrange must be finite [U, 2] with lower <= upper, got {cr.tolist()}")
        cr = cr.to(device, torch.float32)
        self.lo, self.hi, self.n = cr[:, 0], cr[:, 1], _episodes(n_episodes)
        self.device = self.lo.device
        self._gen = torch.Generator(device=device)
        self.targets = None
        self.reset(self.n)

    def reset(self, n: int | None = None, targets=None, seed: int | None = None) -> None:
        """Start ``n`` episodes (None: as many as before), the generator re-seeded (``seed``; None:
        the settings'); ``targets`` are kept for the caller's reward only."""
        self.n = self.n if n is None else _episodes(n)
        self.targets = targets if targets is not None else self.targets
        self._gen.manual_seed(self.settings.seed if seed is None else seed)
        self.plan = None

    def optimize(self, obs) -> None:
        """Draw this step's actions [N, U]."""
        u = torch.rand((self.n, self.lo.shape[0]), generator=self._gen, device=self.lo.device)
        self.plan = (self.lo + u * (self.hi - self.lo))[:, None]


def _episodes(n) -> int:
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"n (episodes) must be an integer >= 1, got {n!r}")
    return int(n)


