"""Gradient MPC through a learned model (supplementary F.1.1, Algorithm F.1), and closed-loop
episodes on the true simulator.

Each planning iteration rolls the model out from the current state under the action sequence
[N, H, U], scores the rollout with the task's reward, back-propagates it to the actions (the
rollout engine's adjoint loop) and takes one Adam step. Actions stay inside each actuator's
control range by construction: ``a = mid + half * tanh(z)`` with Adam on ``z`` (an unlimited
actuator takes ``a = z``). Receding horizon: after planning, the first action is applied, the
sequence (and Adam's moments) shift by one step with the last repeated, and the shifted sequence
warm-starts the next state's plan. The first state starts from a sampled proposal: the reset's
random sequence, the mid sequence (z = 0) and ``proposals`` more random sequences are rolled out
through the model (forward only, batched) and Adam starts from each episode's best; then
``warmup`` extra iterations (default ``4 x iterations``, so the first action costs a bounded few
iterations more than any other; the paper's ``iterations x horizon`` from a random sequence is
``warmup=iterations * horizon, proposals=0``). Every operation is batched over the N episodes;
the rewards are independent per episode, so one backward of their sum gives each episode its own
gradient. The planner counts what it runs: ``evals`` (model steps per episode evaluated forward
and backward by Adam iterations), ``proposal_evals`` (forward only, by proposals),
``model_evals_per_step`` (iterations x horizon, every control step after the first).

The plan, Adam's moments and step count, and the state planned from live in device buffers
updated in place, so one iteration (rollout, reward, backward through the adjoint loop, Adam
update) has no host synchronization; on CUDA it is recorded once in a CUDA graph and replayed
(``capture``), on the CPU it runs eagerly. The host syncs once per control step, to check the
true state.

    >>> planner = GradientMPC(model, "pendulum-balance", systems.make("pendulum"), n=64)
    >>> out = run_episodes(planner, env, planner.task, steps=100, x0=env.reset(qpos, qvel))
    >>> out["returns"]        # [N] true returns of the closed loop
"""
from __future__ import annotations

import dataclasses
from typing import Literal

import torch

from gnwarp.control.returns import (GRAD_NORMS, ActsOnPlan, PlanningError, check_states, check_terminal,
                                    condition_gradient,
                                    planned_return, scale_gradient)
from gnwarp.control.tasks import Task, get_task
from gnwarp.control.task_base import check_targets
from gnwarp.data.layout import LayoutMismatchError
from gnwarp.gn.mlp import prime_dense_async
from gnwarp.state import DYN_NODE_SIZE
from gnwarp.interop import Graphed
from gnwarp.sim.families import family_name
from gnwarp.validation import Flag, FloatRange, IntRange, PositiveFloat, PositiveInt, check_fields

__all__ = ["GradientMPCConfig", "GradientMPC", "PlanningError", "model_systems", "WARMUP_PER_ITERATION",
           "PROPOSAL_ROWS"]

WARMUP_PER_ITERATION = 4   # the default warm-up at the first state: this many x iterations
PROPOSAL_ROWS = 4096       # rollout rows (episodes x proposals) evaluated together at most


@dataclasses.dataclass
class GradientMPCConfig:
    """``horizon``: planning steps (None: the task's). ``iterations``: Adam steps per control step
    (the paper: 3-51). ``warmup``: extra iterations at the first state (None: ``4 x iterations``,
    a bounded first action; the paper's warm-up is ``iterations x horizon``, set it explicitly
    with ``proposals=0``). ``proposals``: random sequences rolled out at the first state besides
    the reset's random sequence and the mid sequence (z = 0); Adam starts from each episode's
    best (0: from the reset's random sequence). ``lr``: Adam's step size on the unconstrained
    actions z. ``init_std``: the random initial z ~ N(0, init_std^2) (and the proposals').
    ``seed``: of those sequences. ``capture``: replay one planning iteration from a CUDA graph
    (None: on CUDA; ignored on the CPU); ``capture_warmup``: eager iterations before it is
    recorded (each costs about one eager iteration of the first action,
    ``bench/results/first_action/``); 0 (default): none, one model step forward and backward
    through a one-step engine primes the kernels instead (``_prime``: the plan untouched), and
    the first iteration is the recording.
    ``fused``: the rollout engine's model step fused (``ForwardModel.rollout_engine``; None:
    automatic). ``discount``: per-step weight of the
    planned return (``gnwarp.control.returns.planned_return``; 1: the task's reward as is; < 1
    shortens the effective horizon of the gradient and weights a ``terminal`` value by
    discount^H). ``grad_norm``: "step" scales each time step's gradient to the plan's RMS step
    norm before Adam (``returns.condition_gradient``: a step whose gradient explodes through a
    long rollout neither dominates nor freezes Adam's moments); "none": the raw gradient (its
    non-finite entries zeroed either way). ``grad_decay``: the state's gradient carried back
    through each model step is multiplied by it (``returns.scale_gradient``): a soft truncated
    backprop window of about 1 / (1 - grad_decay) steps (1: the full gradient; 0: each action
    sees only the next step's reward); below 1 the gradient's rollout runs one model step per
    engine call, recomputing the forward in the backward. ``prime_dense``: on CUDA, the model's
    dense-layer GEMMs run once on a thread beside construction (``gnwarp.gn.mlp.prime_dense``:
    cuBLAS's first use in the process, ~0.2 s on an H100, overlaps binding and engine set-up)."""
    horizon: PositiveInt | None = None
    iterations: PositiveInt = 5
    warmup: IntRange(0) | None = None
    proposals: IntRange(0) = 30
    lr: PositiveFloat = 0.1
    init_std: FloatRange(ge=0) = 0.5
    betas: tuple[FloatRange(ge=0, le=0.999999), FloatRange(ge=0, le=0.999999)] = (0.9, 0.999)
    seed: IntRange(0) = 0
    capture: Flag | None = None
    capture_warmup: IntRange(0) = 0
    fused: Flag | None = None
    discount: FloatRange(gt=0, le=1) = 1.0
    grad_norm: Literal[GRAD_NORMS] = "none"
    grad_decay: FloatRange(ge=0, le=1) = 1.0
    prime_dense: Flag = True

    def __post_init__(self):
        check_fields(self)


def model_systems(model) -> list[str]:
    """The systems a model loaded from a checkpoint was trained on (its config.json), or []."""
    info = getattr(model, "checkpoint_info", None) or {}
    return [d["system"] for d in info.get("data", []) if isinstance(d, dict) and d.get("system")]


def _ctrl_range(system, device, dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-actuator (mid, half width) [U] of the control range; half = inf where unlimited."""
    mid, half = system.actuators.mid_half()
    t = lambda a: torch.as_tensor(a, device=device, dtype=dtype)  # noqa: E731
    return t(mid), t(half)


class GradientMPC(ActsOnPlan):
    """Gradient-based MPC with a learned ``ForwardModel`` for N episodes of one system.

    ``model``: a ForwardModel (bound here to ``system``); ``task``: a ``Task`` or its name;
    ``system``: a ``gnwarp.systems.System`` (or a built-in name); ``n``: episodes planned together;
    ``targets``: per-episode targets for tasks with one (see ``tasks.sample_targets``);
    ``terminal``: an optional ``terminal(states_last [N, B, 13]) -> [N]`` (e.g. a
    ``gnwarp.control.value.TerminalValue``, moved to the model's device) added to the planned
    return, differentiated with it.

    A ``gnwarp.control.planner.Planner``: ``optimize(x [N, B, 13])`` runs the Adam iterations from
    the true states ``x`` (after a reset: the proposal, then the warm-up), keeps the plan (``plan`` [N, H, U])
    and shifts the working sequence for the next call; ``act(x, t)`` -> the plan's actions [N, U]
    at step t; ``step(x)`` = both; ``actions`` [N, H, U] is the working sequence; ``reset()``
    draws a new random sequence from the settings' seed (the next ``optimize`` warms up again).
    Raises ``PlanningError`` for a model trained on another system (or whose static features do
    not fit it), ``TaskError`` for a task of another system, and, at every step, for states of
    the wrong shape or with NaN / Inf (naming the episode and body). Counters (per episode, since
    the planner's construction): ``iterations_run`` Adam iterations, ``evals`` model steps evaluated
    forward and backward (iterations x horizon), ``proposal_evals`` model steps evaluated forward
    only by proposals; ``last_evals``: the last ``optimize``'s {"iterations", "evals",
    "proposal_evals"}; ``model_evals_per_step``: iterations x horizon.
    """

    needs_sim_state = False   # plans from body states

    def __init__(self, model, task, system, n: int, config: GradientMPCConfig | None = None, targets=None,
                 terminal=None):
        from gnwarp.sim.systems import System, make
        # a list of n Systems of one topology: episode i plans through instance i's static graph
        # (a parameterized model given each episode's true parameters, Figure 10)
        instances = list(system) if isinstance(system, (list, tuple)) else None
        if instances is not None:
            if len(instances) != n:
                raise PlanningError(f"{len(instances)} systems given for {n} episodes: give one per episode")
            instances = [s if isinstance(s, System) else make(s) for s in instances]
            system = instances[0]
            act = system.actuators
            for i, s in enumerate(instances):
                if s.nbody != system.nbody or s.nu != system.nu or not s.actuators.same_ranges(act):
                    raise PlanningError(f"system {i} ({s.name}) differs from system 0 in bodies, actuators or "
                                        "control ranges; per-episode systems must share them")
        self.system = system if isinstance(system, System) else make(system)
        self.task: Task = get_task(task, self.system.name)
        if not isinstance(config, (GradientMPCConfig, type(None))):
            raise TypeError(f"config must be a GradientMPCConfig, got {type(config).__name__}")
        self.settings = config if config is not None else GradientMPCConfig()
        self.terminal = check_terminal(terminal, model.device)
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise PlanningError(f"n (episodes) must be an integer >= 1, got {n!r}")
        trained = model_systems(model)
        if trained and not any(s == self.system.name or family_name(s) == family_name(self.system.name)
                               for s in trained):
            raise PlanningError(f"the model was trained on {', '.join(trained)}, not on {self.system.name} "
                                f"(task {self.task.name!r})")
        # cuBLAS's first use on a thread while the rest is built; joined whatever happens, before
        # anything can record a CUDA graph
        primer = prime_dense_async(model) if self.settings.prime_dense else None
        try:
            self._build(model, instances, n, targets)
        finally:
            if primer is not None:
                primer.join()
        self.reset(n)

    def _build(self, model, instances, n: int, targets) -> None:
        """The binding, engines and device state of ``__init__`` (after its checks)."""
        try:
            model.bind(instances if instances is not None else self.system)
        except LayoutMismatchError as e:
            raise PlanningError(f"the model does not fit {self.system.name} (task {self.task.name!r}): {e}") from None
        self.model, self.n = model, n
        self.horizon = self.settings.horizon or self.task.horizon
        its = self.settings.iterations
        self.warmup = self.settings.warmup if self.settings.warmup is not None else WARMUP_PER_ITERATION * its
        dev, dt = model.device, model.dtype
        self.device, self.dtype = dev, dt
        self.B, self.U = self.system.nbody, self.system.nu
        self.mid, self.half = _ctrl_range(self.system, dev, dt)
        cap = self.settings.capture
        self.capture = dev.type == "cuda" and (cap is None or bool(cap))
        # the planner's actions are in range by construction: the engine need not clamp or check;
        # captured, the whole iteration is one graph, so the engine's loops run inside it
        inst = torch.arange(n) if instances is not None else torch.zeros(n, dtype=torch.int64)
        self._inst = inst
        self.engine = self._rollout_engine(inst, graphs=not self.capture)
        # a soft truncated window: one model step per call, the state's gradient scaled between
        self._step_engine = (self._rollout_engine(inst, graphs=not self.capture, horizon=1)
                             if self.settings.grad_decay < 1 else None)
        # the proposal's batched forward rollouts (made here, on the graphs bound here)
        self._proposal_engine = self._make_proposal_engine() if self.settings.proposals else None
        self.iterations_run = self.evals = self.proposal_evals = 0
        self.last_evals = {"iterations": 0, "evals": 0, "proposal_evals": 0}
        self.targets = None if targets is None else self._targets(targets)
        self._gen = torch.Generator(device="cpu")
        shape = (n, self.horizon, self.U)
        # device state, updated in place (a captured iteration reads and writes these tensors)
        self.z = torch.zeros(shape, device=dev, dtype=dt)
        self._m, self._v = torch.zeros_like(self.z), torch.zeros_like(self.z)
        self._t = torch.zeros((), device=dev, dtype=torch.float64)      # Adam's step count
        self._x = torch.zeros((n, self.B, DYN_NODE_SIZE), device=dev, dtype=dt)
        self._r = torch.zeros(n, device=dev, dtype=dt)                  # planned reward before the last step
        w = self.settings.capture_warmup
        self._graph = (Graphed(self._iterate_once, warmup=w, prime=self._prime if w == 0 else None)
                       if self.capture else None)
        self.progress = None  # called with 1 after each planning iteration (e.g. a progress bar's update)

    def _rollout_engine(self, instance: torch.Tensor, graphs: bool, store: bool | str = "auto",
                        horizon: int | None = None):
        """The model's ``RolloutEngine`` over ``instance`` [rows] for ``horizon`` steps (None: the
        planning horizon): the planner's actions are in range by construction, so it neither
        clamps nor checks them."""
        return self.model.rollout_engine(instance, horizon or self.horizon, ctrl_policy="none", check=False,
                                         graphs=graphs, store=store, fused=self.settings.fused)

    def gradient_rollout(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """States [N, H+1, B, 13] from ``x`` [N, B, 13] under ``u`` [N, H, U], differentiable, the
        state's gradient scaled by ``grad_decay`` at every step back (the full engine when 1)."""
        if self._step_engine is None:
            return self.engine.rollout(x, u)
        decay, states = self.settings.grad_decay, [x]
        for t in range(self.horizon):
            prev = states[-1] if t == 0 else scale_gradient(states[-1], decay)
            states.append(self._step_engine.rollout(prev, u[:, t:t + 1])[:, 1])
        return torch.stack(states, 1)

    @property
    def model_evals_per_step(self) -> int:
        """Model steps each episode's plan evaluates forward and backward in a control step after
        the first: iterations x horizon."""
        return self.settings.iterations * self.horizon

    # -- the action sequence ------------------------------------------------------------------------
    def _targets(self, targets) -> torch.Tensor:
        return check_targets(targets, self.n, self.task).to(self.device, self.dtype)

    def reset(self, n: int | None = None, targets=None, seed: int | None = None) -> None:
        """A new random sequence drawn from ``seed`` (None: the settings' seed) and fresh Adam
        moments; the next ``optimize`` warms up again. ``targets``: the episodes' targets (None:
        those held). ``n``: the episodes, fixed when the planner is made (the rollout engine's
        batch): another value raises ``PlanningError``."""
        if n is not None and n != self.n:
            raise PlanningError(f"this planner plans {self.n} episodes (its rollout engine's batch), got n={n!r}: "
                                "make a GradientMPC for that many")
        if targets is not None:
            self.targets = self._targets(targets)
        self._gen.manual_seed(int(self.settings.seed if seed is None else seed))
        self.plan = None
        shape = (self.n, self.horizon, self.U)
        z = torch.randn(shape, generator=self._gen, dtype=torch.float64) * self.settings.init_std
        self.z.copy_(z)
        self._m.zero_()
        self._v.zero_()
        self._t.zero_()
        self.started = False

    def to_actions(self, z: torch.Tensor) -> torch.Tensor:
        """Actions in each actuator's range from unconstrained ``z`` [..., U] (differentiable)."""
        limited = torch.isfinite(self.half)
        return torch.where(limited, self.mid + torch.where(limited, self.half, 1.0) * torch.tanh(z), z)

    @property
    def actions(self) -> torch.Tensor:
        """The current plan [N, H, U]."""
        return self.to_actions(self.z)

    # -- planning ------------------------------------------------------------------------------
    def check_state(self, x) -> torch.Tensor:
        """``x`` [N, B, 13] as a tensor on the model's device, or ``PlanningError``."""
        x = torch.as_tensor(x)
        want = (self.n, self.B, DYN_NODE_SIZE)
        if tuple(x.shape) != want:
            raise PlanningError(f"states must be [N, B, 13] = {list(want)} (episodes, bodies of "
                                f"{self.system.name}), got {list(x.shape)}")
        return check_states(x, self.n, self.B).to(self.device, self.dtype)

    def planned_reward(self, x: torch.Tensor, z: torch.Tensor | None = None) -> torch.Tensor:
        """[N] the model's predicted reward of the plan (or of ``z``) from states ``x``."""
        z = self.z if z is None else z
        with torch.no_grad():
            u = self.to_actions(z)
            return self.planned_return(self.engine.rollout(x, u), u, self.targets)

    def planned_return(self, states: torch.Tensor, actions: torch.Tensor, targets=None) -> torch.Tensor:
        """[M] what the planner maximizes of rollouts ``states`` [M, H+1, B, 13] under ``actions``
        [M, H, U]: the task's reward (discounted per the settings) plus the terminal value."""
        return planned_return(self.task.reward, states, actions, targets, self.settings.discount, self.terminal)

    def _make_proposal_engine(self) -> tuple[int, object]:
        """(sequences per episode in one batched rollout, the eager engine of that batch)."""
        per = max(1, min(self.settings.proposals + 2, PROPOSAL_ROWS // self.n))
        try:
            return per, self._rollout_engine(self._inst.repeat(per), graphs=False, store=False)
        except ValueError:   # a model held to the planner's N graphs (a fixed G_ID): one sequence at a time
            return 1, self._rollout_engine(self._inst, graphs=False, store=False)

    def propose(self, x: torch.Tensor) -> torch.Tensor:
        """Warm start from sampled proposals at checked states ``x`` [N, B, 13]: the working
        sequence, the mid sequence (z = 0) and ``proposals`` random ones (z ~ N(0, init_std^2),
        drawn on the device from a seed of the planner's generator) are rolled out through the
        model, forward only, ``PROPOSAL_ROWS`` rollout rows at a time (the last batch filled
        with more random sequences; one sequence per episode at a time for a model that rolls
        out only the planner's N graphs, such as a fixed G_ID); the working sequence becomes each
        episode's best. Returns the best's planned reward [N] (-inf where every proposal's reward
        is NaN: the working sequence is kept)."""
        n, H, U = self.n, self.horizon, self.U
        total = self.settings.proposals + 2
        if self._proposal_engine is None:
            self._proposal_engine = self._make_proposal_engine()
        per, engine = self._proposal_engine
        xs = x.expand(per, *x.shape).reshape(per * n, *x.shape[1:])
        tgt = None if self.targets is None else self.targets.repeat(per, *([1] * (self.targets.ndim - 1)))
        best_r = torch.full((n,), -torch.inf, device=self.device, dtype=self.dtype)
        best_z = self.z.clone()
        rows = torch.arange(n, device=self.device)
        # drawn where they are used (thousands of sequences), seeded from the planner's generator
        gen = torch.Generator(device=self.device)
        gen.manual_seed(int(torch.randint(0, 2 ** 62, (1,), generator=self._gen)))
        done = 0
        while done < total:
            z = torch.randn((per, n, H, U), generator=gen, device=self.device, dtype=self.dtype)
            z *= self.settings.init_std
            if done == 0:
                z[0] = self.z
                if per > 1:
                    z[1] = 0.0
            elif done == 1:   # one sequence per batch: the mid sequence leads the second
                z[0] = 0.0
            with torch.no_grad():
                u = self.to_actions(z).reshape(per * n, H, U)
                r = self.planned_return(engine.rollout(xs, u), u, tgt).reshape(per, n)
            r = torch.nan_to_num(r, nan=-torch.inf)
            top, k = r.max(0)
            better = top > best_r
            best_r = torch.where(better, top, best_r)
            best_z = torch.where(better[:, None, None], z[k, rows], best_z)
            done += per
            self.proposal_evals += per * H
            self.last_evals["proposal_evals"] += per * H
        self.z.copy_(best_z)
        return best_r

    def iterate(self, x: torch.Tensor, k: int = 1) -> torch.Tensor:
        """``k`` Adam steps on the plan from checked states ``x``; returns the planned reward [N]
        before the last step."""
        self._x.copy_(x)
        for _ in range(k):
            if self._graph is not None:
                self._graph()
            else:
                self._iterate_once()
            self.iterations_run += 1
            self.evals += self.horizon
            self.last_evals["iterations"] += 1
            self.last_evals["evals"] += self.horizon
            if self.progress is not None:
                self.progress(1)
        return self._r.clone()

    def return_gradient(self, x: torch.Tensor, z: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(planned return [N], its raw gradient [N, H, U] with respect to the unconstrained
        actions ``z`` (None: the working sequence)) from checked states ``x`` [N, B, 13]: one
        rollout forward and its adjoint backward, no host sync."""
        with torch.enable_grad():
            z = (self.z if z is None else z).detach().requires_grad_(True)
            u = self.to_actions(z)
            r = self.planned_return(self.gradient_rollout(x, u), u, self.targets)
            (g,) = torch.autograd.grad(r.sum(), z)
        return r.detach(), g

    def _prime(self) -> None:
        """What recording the first iteration needs, without running one (``capture_warmup``
        0): one model step forward and backward, eagerly, from ``_x`` under the plan's first
        action, through a one-step engine like the iteration's (the step engine itself where
        the gradient's rollout runs step by step), the return and its gradient as an iteration
        makes them (Warp's modules load; torch's lazy state, the autograd thread, the GEMM
        handles, are made); the engine's activation store is sized from that step's recording,
        so that no budget query runs in the capture. The plan, Adam's moments and the counts
        are untouched."""
        one = self._step_engine if self._step_engine is not None else self.engine.one_step()
        with torch.enable_grad():
            z = self.z[:, :1].detach().clone().requires_grad_(True)
            u = self.to_actions(z)
            r = self.planned_return(one.rollout(self._x, u), u, self.targets)
            torch.autograd.grad(r.sum(), z)
        if one is not self._step_engine:
            self.engine.size_store(one)

    def _iterate_once(self) -> None:
        """One planning iteration on the device buffers, in place, no host sync: rollout from
        ``_x`` under the plan, reward, its gradient w.r.t. z (the engine's adjoint loop), Adam."""
        b1, b2 = self.settings.betas
        lr = self.settings.lr
        r, g = self.return_gradient(self._x)
        with torch.no_grad():
            g = condition_gradient(-g, self.settings.grad_norm)
            self._r.copy_(r.detach())
            self._t.add_(1)
            self._m.mul_(b1).add_(g, alpha=1 - b1)
            self._v.mul_(b2).addcmul_(g, g, value=1 - b2)
            c1 = (1 - torch.pow(b1, self._t)).to(self.z.dtype)
            c2 = (1 - torch.pow(b2, self._t)).to(self.z.dtype)
            step = (self._m / c1) / ((self._v / c2).sqrt() + 1e-8)
            self.z.sub_(lr * step)

    def start_from(self, z: torch.Tensor) -> None:
        """Make ``z`` [N, H, U] (unconstrained, see ``to_actions``) the working sequence with fresh
        Adam moments, in place (a caller that proposes its own sequences, e.g. the hybrid planner)."""
        z = torch.as_tensor(z)
        if tuple(z.shape) != tuple(self.z.shape):
            raise PlanningError(f"z must be [N, H, U] = {list(self.z.shape)}, got {list(z.shape)}")
        self.z.copy_(z)
        self._m.zero_()
        self._v.zero_()
        self._t.zero_()

    def from_actions(self, actions: torch.Tensor, margin: float = 0.99) -> torch.Tensor:
        """Unconstrained z [..., U] of ``actions`` [..., U] (inverse of ``to_actions``); actions at
        or beyond a limit are taken ``margin`` of the half width from the middle, where tanh's
        gradient is still usable."""
        a = torch.as_tensor(actions).to(self.device, self.dtype)
        limited = torch.isfinite(self.half)
        s = ((a - self.mid) / torch.where(limited, self.half, 1.0)).clamp(-margin, margin)
        return torch.where(limited, torch.atanh(s), a)

    def shift(self) -> None:
        """Drop the first step of the plan (and of Adam's moments); repeat the last (in place)."""
        for a in (self.z, self._m, self._v):
            a[:, :-1] = a[:, 1:].clone()

    def optimize(self, x) -> None:
        """One planning budget from the true states ``x`` [N, B, 13]: ``iterations`` Adam steps
        (after a reset: first the proposal, then ``warmup`` more steps); the plan (``plan``
        [N, H, U]) is kept for ``act`` and the working sequence shifted one step for the next call."""
        x = self.check_state(x)
        self.last_evals = {"iterations": 0, "evals": 0, "proposal_evals": 0}
        if not self.started and self.settings.proposals > 0:
            self.propose(x)
        k = self.settings.iterations + (0 if self.started else self.warmup)
        self.iterate(x, k)
        self.started = True
        self.plan = self.actions.detach().clone()
        self.shift()

