"""Hybrid MPC: sampled proposals refined by gradient steps through the same learned model.

Each planning step, for each of N episodes:

1. **Sample** K action sequences around the warm-started nominal plan [H, U]: the nominal
   itself and K-1 with Gaussian noise on P spline knots (``gnwarp.control.sampling.spline_basis``),
   interpolated over the horizon and added to the nominal, clamped to the actuators' ranges.
2. **Score** them through the dynamics (``gnwarp.control.returns.planned_return``: the task's
   reward, an optional discount and terminal value) and keep the E best (the elites).
3. **Refine** the elites for G iterations:
   - on a learned model (a ``gnwarp.dynamics.Dynamics``): G Adam steps on each elite through
     the model's differentiable rollout, by a ``GradientMPC`` of N x E rows (its tanh
     parameterization, Adam, gradient conditioning ``grad_norm`` and ``terminal``);
   - on dynamics without gradients (a ``gnwarp.dynamics.RolloutDynamics`` such as
     ``EnvDynamics``, the true simulator: the oracle; or an ``EnsembleDynamics`` of models,
     scored mean - penalty x spread): G cross-entropy (CEM) iterations in the
     knot-noise space: K new candidates drawn from the elites' per-knot mean and standard
     deviation (floored at ``min_noise``), the elites' mean and the best so far among them; the
     E best of each iteration are the next elites.
4. **Act** from the best sequence seen (sampled or refined: the refined best's predicted
   return is never below the sampled best's); its shift by one step (last action repeated)
   warm-starts the next step.

Both refinements run in the same ``HybridPlanner`` class, chosen by the dynamics given
(``refine="auto"``). Cost per control step and episode: K rollouts forward (plus K x G for CEM)
and, for the gradient refinement, E x G forward-and-backward rollouts plus E forward.

    >>> planner = HybridPlanner(model, "cheetah-forward", "cheetah", n=8, config=HybridConfig(samples=64))
    >>> oracle = HybridPlanner(true_dynamics("cheetah", 8, 64), "cheetah-forward", "cheetah", n=8,
    ...                        config=HybridConfig(samples=64))       # CEM refinement on the true simulator
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from gnwarp.control.gradient import WARMUP_PER_ITERATION, GradientMPC, GradientMPCConfig
from gnwarp.control.returns import GRAD_NORMS, ActsOnPlan, PlanningError, check_states, check_terminal, planned_return
from gnwarp.control.sampling import INTERPOLATIONS, EnvDynamics, model_dynamics, score_rollouts, spline_basis
from gnwarp.control.tasks import Task, get_task
from gnwarp.control.task_base import check_targets
from gnwarp.dynamics import Dynamics
from gnwarp.sim.env import Observation
from gnwarp.validation import ConfigError, Flag, FloatRange, IntRange, PositiveFloat, PositiveInt, check_fields

__all__ = ["HybridConfig", "HybridPlanner", "REFINEMENTS"]

REFINEMENTS = ("auto", "gradient", "cem")


@dataclass
class HybridConfig:
    """``horizon``: planning steps (None: the task's). ``samples``: K candidates per episode (the
    nominal included). ``elites``: E refined (<= K). ``iterations``: G refinement iterations
    (0: sampling alone). ``warmup``: extra refinement iterations at the first state after a reset
    (None: ``4 x iterations``, as ``GradientMPC``; the nominal starts at the middle of the range
    there, with no plan to warm-start from). ``knots`` / ``interpolation``: the spline of the sampling noise (as
    ``SamplingConfig``). ``noise``: its standard deviation relative to half of each actuator's
    range. ``refine``: "gradient" (Adam through a learned model), "cem" (derivative-free), "auto"
    (gradient on a ``Dynamics`` model, CEM on other dynamics). ``lr`` / ``betas``: Adam's, on the
    unconstrained actions (``GradientMPC``). ``min_noise``: CEM's floor of its standard deviation
    (relative as ``noise``). ``discount``, ``grad_norm``, ``grad_decay``, ``capture``, ``fused``: as
    ``GradientMPCConfig``. ``seed``: of the noise."""
    horizon: PositiveInt | None = None
    samples: PositiveInt = 64
    elites: PositiveInt = 4
    iterations: IntRange(0) = 5
    warmup: IntRange(0) | None = None
    knots: PositiveInt = 4
    interpolation: Literal[INTERPOLATIONS] = "linear"
    noise: FloatRange(ge=0) = 0.2
    refine: Literal[REFINEMENTS] = "auto"
    lr: PositiveFloat = 0.05
    betas: tuple[FloatRange(ge=0, le=0.999999), FloatRange(ge=0, le=0.999999)] = (0.9, 0.999)
    min_noise: FloatRange(ge=0) = 0.02
    discount: FloatRange(gt=0, le=1) = 1.0
    grad_norm: Literal[GRAD_NORMS] = "none"
    grad_decay: FloatRange(ge=0, le=1) = 1.0
    seed: IntRange(0) = 0
    capture: Flag | None = None
    fused: Flag | None = None

    def __post_init__(self):
        check_fields(self)
        if self.elites > self.samples:
            raise ConfigError("elites", f"must not exceed samples ({self.samples}), got {self.elites}")
        if self.interpolation != "zero" and self.knots < 2:
            raise ConfigError("knots", f"{self.interpolation} interpolation needs knots >= 2, got {self.knots}")
        if self.horizon is not None and self.knots > self.horizon:
            raise ConfigError("knots", f"must not exceed the horizon ({self.horizon}), got {self.knots}")


class HybridPlanner(ActsOnPlan):
    """Sampling proposals refined by gradient steps (or CEM on dynamics without gradients) for
    ``n`` episodes of one system (a ``gnwarp.control.planner.Planner``; see the module's docstring).

    ``dynamics``: a learned ``Dynamics`` model (bound here to ``system``; sampled through a
    ``RolloutEngine`` of n x K rows, refined by a ``GradientMPC`` of n x E rows) or a
    ``RolloutDynamics`` (``EnvDynamics`` of n x K worlds: ``true_dynamics(system, n, K)``;
    ``ModelDynamics``). ``task``: a ``Task`` or its name; ``system``: a ``System`` or a built-in
    name; ``targets`` [n, ...]: per-episode targets; ``terminal``: an optional
    ``terminal(states_last [M, B, 13]) -> [M]`` added to every return (gradient included).

    ``optimize(state)`` plans from the episodes' true states (body states [n, B, 13], or an
    ``Observation`` for ``EnvDynamics`` without a ``source``); ``act(state, t)`` -> [n, U];
    ``step`` = both. After each ``optimize``: ``last_sampled`` [n] (the best sampled return),
    ``last_refined`` [n] (the plan's predicted return, >= ``last_sampled``), ``plan`` [n, H, U]."""

    def __init__(self, dynamics, task, system, n: int, config: HybridConfig | None = None, targets=None,
                 terminal=None):
        from gnwarp.sim.systems import System, make
        if not isinstance(config, (HybridConfig, type(None))):
            raise TypeError(f"config must be a HybridConfig, got {type(config).__name__}")
        self.settings = cfg = config if config is not None else HybridConfig()
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise PlanningError(f"n (episodes) must be an integer >= 1, got {n!r}")
        self.n = int(n)
        self.system = system if isinstance(system, System) else make(system)
        self.task: Task = get_task(task, self.system.name)
        self.terminal = check_terminal(terminal, getattr(dynamics, "device", None))
        self.horizon = H = cfg.horizon or self.task.horizon
        if cfg.knots > H:
            raise ConfigError("knots", f"must not exceed the horizon ({H}), got {cfg.knots}")
        learned = isinstance(dynamics, Dynamics)
        mode = cfg.refine if cfg.refine != "auto" else ("gradient" if learned else "cem")
        if mode == "gradient" and not learned:
            raise PlanningError(f"refine='gradient' needs a learned Dynamics model to differentiate; "
                                f"{type(dynamics).__name__} has no gradients (use refine='cem' or 'auto')")
        self.refinement = mode
        K, E = cfg.samples, cfg.elites
        self.refiner = None
        if learned:
            # the refiner binds the model to the system; the sampler's engine reads that binding
            gcfg = GradientMPCConfig(horizon=H, iterations=max(1, cfg.iterations), warmup=0, proposals=0, lr=cfg.lr,
                                     init_std=0.0, betas=cfg.betas, seed=cfg.seed, capture=cfg.capture,
                                     fused=cfg.fused, discount=cfg.discount, grad_norm=cfg.grad_norm,
                                     grad_decay=cfg.grad_decay)
            self.refiner = GradientMPC(dynamics, self.task, self.system, self.n * E, gcfg, terminal=self.terminal)
            self.model = dynamics
            self.dynamics = model_dynamics(dynamics, self.n, K, H)
            self.device, self.dtype = dynamics.device, dynamics.dtype
        else:
            if not callable(getattr(dynamics, "rollout", None)):
                raise TypeError("dynamics must be a learned gnwarp.dynamics.Dynamics model or a RolloutDynamics "
                                f"(rollout(obs, actions, samples)), got {type(dynamics).__name__}")
            self.model, self.dynamics = None, dynamics
            self.device, self.dtype = torch.device(dynamics.device), torch.float32
        cr = torch.as_tensor(self.system.actuators.sample_range())
        self.lo, self.hi = cr[:, 0].to(self.device, self.dtype), cr[:, 1].to(self.device, self.dtype)
        self.U = self.system.nu
        per_step = cfg.knots / H if cfg.interpolation == "zero" else (cfg.knots - 1) / max(H - 1, 1)
        basis = spline_basis(cfg.interpolation, cfg.knots, np.arange(H) * per_step)
        self._basis = torch.tensor(basis, device=self.device, dtype=self.dtype)          # [H, P]
        self._gen = torch.Generator(device=self.device)
        self.targets = None
        self.reset(self.n, targets)

    # -- Planner --------------------------------------------------------------------------------
    @property
    def needs_sim_state(self) -> bool:
        """Whether ``optimize`` needs the simulator's state (``env.observe()``): planning on the
        true simulator without a ``source`` env to read it from."""
        return isinstance(self.dynamics, EnvDynamics) and self.dynamics.source is None

    def reset(self, n: int | None = None, targets=None, seed: int | None = None) -> None:
        """A nominal at the middle of the range, no plan, the noise re-seeded (``seed``; None: the
        settings'); ``targets`` [n, ...] (None: those held). ``n`` is fixed at construction (the
        rollouts' batch): another value raises ``PlanningError``."""
        if n is not None and n != self.n:
            raise PlanningError(f"this planner plans {self.n} episodes (its rollouts' batch), got n={n!r}")
        held = self.targets if targets is None else targets
        if held is not None:
            held = check_targets(held, self.n, self.task, PlanningError).to(self.device)
        self.targets = held
        if self.refiner is not None:
            self.refiner.reset(targets=None if held is None else held.repeat_interleave(self.settings.elites, 0))
        self._gen.manual_seed(int(self.settings.seed if seed is None else seed))
        mid = 0.5 * (self.lo + self.hi)
        self.nominal = mid.expand(self.n, self.horizon, self.U).clone()
        self.plan = None
        self.last_sampled = self.last_refined = None
        self.started = False

    def optimize(self, obs) -> None:
        """One planning budget from the episodes' true states ``obs`` (body states [n, B, 13] or an
        ``Observation``): sample, score, refine the elites (``iterations``; after a reset
        ``warmup`` more); the best becomes ``plan`` and, shifted one step, the next nominal."""
        body = check_states(obs.body if isinstance(obs, Observation) else obs, self.n)
        cfg, N, K, E = self.settings, self.n, self.settings.samples, self.settings.elites
        eps = self._noise((N, K - 1, cfg.knots, self.U), cfg.noise)
        eps = torch.cat([torch.zeros_like(eps[:, :1]), eps], 1)                     # the nominal first
        acts, r = self._score(obs, eps)
        r_top, idx = r.topk(E, dim=1)                                                 # [N, E]
        rows = torch.arange(N, device=self.device)[:, None]
        best_a, best_r = acts[rows[:, 0], idx[:, 0]], r_top[:, 0]
        self.last_sampled = best_r.clone()
        warmup = cfg.warmup if cfg.warmup is not None else WARMUP_PER_ITERATION * cfg.iterations
        G = cfg.iterations + (0 if self.started else warmup)
        if G > 0:
            if self.refinement == "gradient":
                best_a, best_r = self._refine_gradient(body, acts[rows, idx], best_a, best_r, G)
            else:
                best_a, best_r = self._refine_cem(obs, eps[rows, idx], best_a, best_r, G)
        self.started = True
        self.last_refined = best_r
        self.plan = best_a.detach().clone()
        self.nominal = torch.cat([self.plan[:, 1:], self.plan[:, -1:]], 1)

    # -- parts ----------------------------------------------------------------------------------
    def _noise(self, shape, rel, mean=None) -> torch.Tensor:
        """Knot noise of ``shape`` [N, M, P, U]: N(mean, (rel x half range)^2); ``rel`` a number
        or a tensor broadcasting to ``shape`` (already scaled when a tensor)."""
        z = torch.randn(shape, generator=self._gen, device=self.device, dtype=self.dtype)
        scale = rel * 0.5 * (self.hi - self.lo) if not torch.is_tensor(rel) else rel
        return z * scale + (0.0 if mean is None else mean)

    def sequences(self, eps: torch.Tensor) -> torch.Tensor:
        """Action sequences [N, M, H, U] of knot noise ``eps`` [N, M, P, U] around the nominal,
        clamped to the range."""
        a = self.nominal[:, None] + torch.einsum("tp,nmpu->nmtu", self._basis, eps)
        return torch.maximum(torch.minimum(a, self.hi), self.lo)

    def _returns(self, states: torch.Tensor, acts: torch.Tensor, per: int) -> torch.Tensor:
        tgt = None if self.targets is None else self.targets.to(states.device).repeat_interleave(per, 0)
        return planned_return(self.task.reward, states, acts.to(states.device, states.dtype), tgt,
                              self.settings.discount, self.terminal)

    def _score(self, obs, eps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(sequences [N, K, H, U], returns [N, K]) of knot noise ``eps`` [N, K, P, U]; a
        non-finite return scores -inf (a diverged rollout never wins)."""
        N, K = eps.shape[:2]
        acts = self.sequences(eps)
        flat = acts.reshape(N * K, self.horizon, self.U)
        with torch.no_grad():
            r = score_rollouts(self.dynamics, obs, flat, K, lambda states: self._returns(states, flat, K))
        r = torch.as_tensor(r).to(self.device, self.dtype).reshape(N, K)
        return acts, torch.nan_to_num(r, nan=-torch.inf, posinf=-torch.inf)

    def _refine_gradient(self, body, elites, best_a, best_r, G: int):
        """``G`` Adam steps on the elites [N, E, H, U] through the model (the refiner); the per-episode best
        of the refined elites and ``best_a`` [N, H, U] (return ``best_r`` [N])."""
        N, E = elites.shape[:2]
        g = self.refiner
        g.start_from(g.from_actions(elites.reshape(N * E, self.horizon, self.U)))
        x = g.check_state(body.repeat_interleave(E, 0))
        g.iterate(x, G)
        r = torch.nan_to_num(g.planned_reward(x), nan=-torch.inf, posinf=-torch.inf).reshape(N, E)
        top, k = r.max(1)
        better = top > best_r
        refined = g.actions.detach().reshape(N, E, self.horizon, self.U)[torch.arange(N, device=self.device), k]
        return torch.where(better[:, None, None], refined, best_a), torch.where(better, top, best_r)

    def _refine_cem(self, obs, elite_eps, best_a, best_r, G: int):
        """``G`` CEM iterations in the knot-noise space from the elites' noise [N, E, P, U]; the
        best sequence seen and its return."""
        cfg, N, K, E = self.settings, self.n, self.settings.samples, self.settings.elites
        floor = cfg.min_noise * 0.5 * (self.hi - self.lo)
        rows = torch.arange(N, device=self.device)
        best_eps = elite_eps[:, 0]
        for _ in range(G):
            mean = elite_eps.mean(1, keepdim=True)                                   # [N, 1, P, U]
            std = torch.maximum(elite_eps.std(1, keepdim=True, unbiased=False), floor)
            eps = torch.cat([mean, best_eps[:, None], self._noise((N, K - 2, cfg.knots, self.U), std, mean)], 1) \
                if K >= 2 else mean
            acts, r = self._score(obs, eps)
            r_top, idx = r.topk(E, dim=1)
            elite_eps = eps[rows[:, None], idx]
            better = r_top[:, 0] > best_r
            best_r = torch.where(better, r_top[:, 0], best_r)
            best_a = torch.where(better[:, None, None], acts[rows, idx[:, 0]], best_a)
            best_eps = torch.where(better[:, None, None], elite_eps[:, 0], best_eps)
        return best_a, best_r
