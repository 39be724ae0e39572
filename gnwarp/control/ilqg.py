"""iLQG on the true MuJoCo C model (Tassa, Mansard, Todorov 2014): the true-model planning baseline.

As MuJoCo MPC's iLQG: per knot, dynamics linearized by ``mujoco.mjd_transitionFD`` in tangent
space (state ``dx = [dqpos (nv), dqvel (nv), dact (na)]``, size ``nx = 2 nv + na``), cost
derivatives by finite differences (or a cost's own ``derivatives``), a backward pass whose
feedforward step is the box QP of ``mujoco.mju_boxQP`` (feedback rows of clamped controls zeroed),
a forward line search over step sizes (1 down to 1e-3) that only accepts a lower cost, and
Levenberg-Marquardt regularization of Quu that grows when the backward pass or the line search
fails. Knots hold one control for ``substeps`` physics steps: ``ILQG.for_system`` plans on a
System's data timestep, ``substeps=1`` on the physics timestep. Derivatives run on a thread pool,
each thread with its own MjData (MuJoCo-Warp 4.0 has no derivatives, hence MuJoCo C).

``ILQG`` is a ``gnwarp.control.planner.Planner`` of N episodes (one plan each, planned one after
another) from the simulator's state; ``ILQG.for_task`` plans a ``Task``'s reward as its cost.
Its options are one validated ``ILQGSettings``.
"""
from __future__ import annotations

import dataclasses
import os
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Callable

import mujoco
import numpy as np
import torch

from gnwarp.control.returns import plan_action
from gnwarp.control.task_base import check_targets
from gnwarp.sim.actuators import Actuators
from gnwarp.sim.body_state import body_states
from gnwarp.validation import ConfigError, Flag, FloatRange, IntRange, PositiveFloat, PositiveInt, check_fields

__all__ = ["ILQG", "ILQGSettings", "BodyPointCost", "BodyStateCost", "QuadraticCost", "body_state_cost", "task_cost",
           "tangent_difference"]

# running_cost(data, u) and terminal_cost(data): ``data`` holds the state after mj_forward
RunningCost = Callable[[mujoco.MjData, np.ndarray], float]
TerminalCost = Callable[[mujoco.MjData], float]
# costs(episode, target, qpos, qvel) -> (running_cost, terminal_cost or None): each episode's costs,
# asked at every optimize from the episode's state (a cost measured from the current state)
EpisodeCosts = Callable[[int, "np.ndarray | None", np.ndarray, np.ndarray], tuple]
_INTEGRATION = mujoco.mjtState.mjSTATE_INTEGRATION  # qpos, qvel, act, ctrl, warm start, ...


def tangent_difference(model: mujoco.MjModel, qpos, qvel, act, qpos_ref, qvel_ref, act_ref) -> np.ndarray:
    """[2 nv + na] tangent-space difference of a state from a reference state (quaternions via
    ``mj_differentiatePos``), the coordinates of ``mjd_transitionFD``'s A and B."""
    dq = np.zeros(model.nv)
    mujoco.mj_differentiatePos(model, dq, 1.0, np.asarray(qpos_ref, float), np.asarray(qpos, float))
    return np.concatenate([dq, np.asarray(qvel) - qvel_ref, np.asarray(act) - act_ref])


class QuadraticCost:
    """0.5 dx' Q dx + 0.5 (u - u_ref)' R (u - u_ref), dx = tangent difference from a target state.

    Q: [nx, nx]; R: [nu, nu] or None (a terminal cost). Targets default to qpos0 and zeros. Gives
    analytic derivatives (exact for hinge and slide joints; ball and free joints get the
    Gauss-Newton approximation).
    """

    def __init__(self, model: mujoco.MjModel, Q, R=None, qpos_ref=None, qvel_ref=None, act_ref=None,
                 u_ref=None):
        self.model = model
        self.Q = np.asarray(Q, float)
        self.R = None if R is None else np.asarray(R, float)
        self.qpos_ref = np.array(model.qpos0 if qpos_ref is None else qpos_ref, float)
        self.qvel_ref = np.zeros(model.nv) if qvel_ref is None else np.asarray(qvel_ref, float)
        self.act_ref = np.zeros(model.na) if act_ref is None else np.asarray(act_ref, float)
        self.u_ref = np.zeros(model.nu) if u_ref is None else np.asarray(u_ref, float)
        nx = 2 * model.nv + model.na
        if self.Q.shape != (nx, nx) or (self.R is not None and self.R.shape != (model.nu,) * 2):
            raise ValueError(f"QuadraticCost: Q must be [{nx}, {nx}] and R [{model.nu}, {model.nu}]")

    def _dx(self, data):
        return tangent_difference(self.model, data.qpos, data.qvel, data.act,
                                  self.qpos_ref, self.qvel_ref, self.act_ref)

    def __call__(self, data: mujoco.MjData, u=None) -> float:
        dx = self._dx(data)
        c = 0.5 * dx @ self.Q @ dx
        if self.R is not None and u is not None:
            du = np.asarray(u) - self.u_ref
            c += 0.5 * du @ self.R @ du
        return float(c)

    def derivatives(self, data: mujoco.MjData, u=None):
        """(lx [nx], lu [nu], lxx [nx, nx], luu [nu, nu], lux [nu, nx])."""
        nu, nx = self.model.nu, self.Q.shape[0]
        R = np.zeros((nu, nu)) if self.R is None or u is None else self.R
        du = np.zeros(nu) if u is None else np.asarray(u) - self.u_ref
        return self.Q @ self._dx(data), R @ du, self.Q, R, np.zeros((nu, nx))


class BodyPointCost:
    """A cost of one body's world position p = xpos[body]: lin' (p - ref) + (p - ref)' W (p - ref),
    plus 0.5 u' R u with R given and a control u.

    ref [3], lin [3] (default zeros), W [3, 3] (default zeros; symmetric), R [nu, nu] or None.
    Analytic derivatives from the body's position Jacobian (``mj_jacBody``): lx is exact, lxx the
    Gauss-Newton 2 J' W J (the Jacobian's own curvature dropped, as MuJoCo MPC does for residual
    norms), so a knot costs one Jacobian instead of O(nx^2) finite-difference cost evaluations.
    """

    def __init__(self, model: mujoco.MjModel, body: int, ref, lin=None, W=None, R=None):
        if not 0 <= int(body) < model.nbody:
            raise ValueError(f"BodyPointCost: body {body} out of range [0, {model.nbody})")
        self.model, self.body = model, int(body)
        self.ref = np.asarray(ref, float).reshape(3)
        self.lin = np.zeros(3) if lin is None else np.asarray(lin, float).reshape(3)
        self.W = np.zeros((3, 3)) if W is None else np.asarray(W, float).reshape(3, 3)
        self.R = None if R is None else np.asarray(R, float).reshape(model.nu, model.nu)
        self._jacp = np.zeros((3, model.nv))

    def __call__(self, data: mujoco.MjData, u=None) -> float:
        e = data.xpos[self.body] - self.ref
        c = self.lin @ e + e @ self.W @ e
        if self.R is not None and u is not None:
            c += 0.5 * np.asarray(u, float) @ self.R @ np.asarray(u, float)
        return float(c)

    def derivatives(self, data: mujoco.MjData, u=None):
        """(lx [nx], lu [nu], lxx [nx, nx], luu [nu, nu], lux [nu, nx]) at data's state."""
        m = self.model
        nv, nu, nx = m.nv, m.nu, 2 * m.nv + m.na
        mujoco.mj_jacBody(m, data, self._jacp, None, self.body)
        J = self._jacp
        e = data.xpos[self.body] - self.ref
        Ws = self.W + self.W.T
        lx, lxx = np.zeros(nx), np.zeros((nx, nx))
        lx[:nv] = J.T @ (self.lin + Ws @ e)
        lxx[:nv, :nv] = J.T @ Ws @ J
        R = np.zeros((nu, nu)) if self.R is None or u is None else self.R
        lu = np.zeros(nu) if u is None else R @ np.asarray(u, float)
        return lx, lu, lxx, R, np.zeros((nu, nx))


def body_state_cost(model: mujoco.MjModel, reward_fn: Callable, scale: float = 1.0) -> Callable:
    """A cost ``cost(data, u=None) = -scale * reward_fn(body [nbody, 13], u [nu])`` of the bodies'
    13-number states (``gnwarp.state``, the world body included) read from MjData by
    ``gnwarp.sim.body_state.body_states``, so a task reward of graph states serves as a running
    (and, with u = zeros, terminal) cost. ``reward_fn`` gets float64 numpy arrays and returns a
    scalar (numpy, float or a one-element CPU tensor)."""
    zeros = np.zeros(model.nu)

    def cost(data: mujoco.MjData, u=None) -> float:
        r = reward_fn(body_states(model, data), zeros if u is None else np.asarray(u, float))
        return -scale * np.asarray(r, dtype=np.float64).item()
    return cost


class BodyStateCost:
    """``cost(data, u=None) = -scale * reward(body [nbody, 13], u [nu])`` of the bodies' 13-number
    states (``gnwarp.sim.body_state.body_states``, the world body included) for a ``reward`` written
    in torch (tensors in, a scalar tensor out, differentiable), with Gauss-Newton derivatives as
    MuJoCo MPC takes them for residual costs: the bodies' states are the residual, their Jacobian
    J = d body / dx by central differences of the kinematics in tangent space (2 nx ``mj_forward``),
    the reward's gradient and Hessian with respect to (body, u) by torch autograd; then
    lx = -s J' g_b, lxx = -s J' H_bb J, lu = -s g_u, luu = -s H_uu, lux = -s H_ub J (the
    kinematics' own curvature dropped). A knot costs 2 nx kinematics and one small Hessian in place
    of O((nx + nu)^2) evaluations of the reward. u = None (a terminal cost): zero controls."""

    def __init__(self, model: mujoco.MjModel, reward: Callable, scale: float = 1.0, eps: float = 1e-6):
        self.model, self.reward, self.scale, self.eps = model, reward, float(scale), float(eps)
        self._d = mujoco.MjData(model)

    def _reward(self, body, u):
        import torch
        with torch.no_grad():
            r = self.reward(torch.as_tensor(body, dtype=torch.float64), torch.as_tensor(u, dtype=torch.float64))
        return float(r)

    def __call__(self, data: mujoco.MjData, u=None) -> float:
        u = np.zeros(self.model.nu) if u is None else np.asarray(u, float)
        return -self.scale * self._reward(body_states(self.model, data), u)

    def _jacobian(self, data: mujoco.MjData) -> np.ndarray:
        """d body_states / d x [nbody * 13, nx] at data's state, by central differences."""
        m, d, h = self.model, self._d, self.eps
        nv, nx = m.nv, 2 * m.nv + m.na
        J = np.empty((m.nbody * 13, nx))
        for i in range(nx):
            cols = []
            for sign in (1.0, -1.0):
                d.qpos[:], d.qvel[:], d.act[:] = data.qpos, data.qvel, data.act
                if i < nv:
                    dq = np.zeros(nv)
                    dq[i] = sign * h
                    mujoco.mj_integratePos(m, d.qpos, dq, 1.0)
                elif i < 2 * nv:
                    d.qvel[i - nv] += sign * h
                else:
                    d.act[i - 2 * nv] += sign * h
                mujoco.mj_forward(m, d)
                cols.append(body_states(m, d).reshape(-1))
            J[:, i] = (cols[0] - cols[1]) / (2 * h)
        return J

    def derivatives(self, data: mujoco.MjData, u=None):
        """(lx [nx], lu [nu], lxx [nx, nx], luu [nu, nu], lux [nu, nx]) at data's state (after
        ``mj_forward``)."""
        import torch
        m = self.model
        nu = m.nu
        body = body_states(m, data)
        nb = body.size
        uu = np.zeros(nu) if u is None else np.asarray(u, float)
        z0 = torch.as_tensor(np.concatenate([body.reshape(-1), uu]), dtype=torch.float64)

        def f(z):
            return self.reward(z[:nb].reshape(body.shape), z[nb:])
        g = torch.autograd.functional.jacobian(f, z0).numpy()
        H = torch.autograd.functional.hessian(f, z0, vectorize=True).numpy()
        J = self._jacobian(data)
        s = -self.scale
        lx = s * (J.T @ g[:nb])
        lxx = s * (J.T @ H[:nb, :nb] @ J)
        if u is None:
            return lx, np.zeros(nu), lxx, np.zeros((nu, nu)), np.zeros((nu, lx.size))
        return lx, s * g[nb:], lxx, s * H[nb:, nb:], s * (H[nb:, :nb] @ J)


def task_cost(model: mujoco.MjModel, task, target=None) -> Callable:
    """``BodyStateCost`` of a ``gnwarp.control.tasks.Task``: minus its reward of the one-step
    trajectory [x, x] with action u, i.e. of the state x. Its total over the knots is minus the
    task's return up to a constant (the start state's term) for rewards that add up a function of
    each state: every built-in task but swimmer-reach, whose displacement reward is not one.
    target: one episode's target (no leading batch axis)."""
    import torch
    if getattr(task, "target", None) == "position":
        raise ValueError(f"task {task.name!r} rewards displacements between states, not states; "
                         "give ILQG a running and a terminal cost of your own")
    tgt = None if target is None else torch.as_tensor(np.asarray(target), dtype=torch.float64)[None]

    def reward(body, u):
        return task.reward(torch.stack([body, body])[None], u[None, None], target=tgt)[0]   # [1, 2, B, 13]
    return BodyStateCost(model, reward)


@dataclasses.dataclass
class _Trajectory:
    U: np.ndarray      # [H, nu] the controls applied (clamped into the box)
    qpos: np.ndarray   # [H+1, nq] knot states
    qvel: np.ndarray   # [H+1, nv]
    act: np.ndarray    # [H+1, na]
    phys: np.ndarray   # [H, substeps, nstate] integration state before each physics step
    cost: np.ndarray   # [H+1] running costs, then the terminal cost


@dataclasses.dataclass
class ILQGSettings:
    """``horizon``: knots H (None: the task's, with ``ILQG.for_task``). ``iterations``: most iLQG
    iterations per plan; ``warmup``: at the first state after a reset (None: ``iterations``).
    ``substeps``: physics steps per knot, one control held over them (None: the system's data
    step with ``for_system`` / ``for_task``, else 1). ``fd_eps`` / ``fd_centered``: the dynamics'
    finite differences (``mjd_transitionFD``); ``cost_eps``: the costs' (without their own
    ``derivatives``). ``reg_init``, ``reg_min``, ``reg_max``, ``reg_factor``: Levenberg-Marquardt
    regularization of Quu, its start, bounds and growth factor. ``step_sizes``: the line search's
    (None: 1 down to 1e-3, 10 of them). ``tol``: relative decrease below which a plan stops.
    ``nthread``: derivative threads (None: the CPU cores, at most H)."""
    horizon: PositiveInt | None = None
    iterations: IntRange(0) = 10
    warmup: IntRange(0) | None = None
    substeps: PositiveInt | None = None
    fd_eps: PositiveFloat = 1e-6
    fd_centered: Flag = False
    cost_eps: PositiveFloat = 1e-4
    reg_init: PositiveFloat = 1e-6
    reg_min: PositiveFloat = 1e-6
    reg_max: PositiveFloat = 1e6
    reg_factor: FloatRange(gt=1) = 10.0
    step_sizes: tuple[PositiveFloat, ...] | None = None
    tol: FloatRange(ge=0) = 1e-8
    nthread: PositiveInt | None = None

    def __post_init__(self):
        check_fields(self)
        if self.reg_min > self.reg_max:
            raise ConfigError("reg_min", f"must not exceed reg_max ({self.reg_max:g}), got {self.reg_min:g}")
        if self.step_sizes is not None and not self.step_sizes:
            raise ConfigError("step_sizes", "must hold at least one step size (or be None)")


class ILQG:
    """Box-constrained iLQG on MuJoCo C, a ``Planner`` of N episodes.

    model: the true model (read only). running_cost(data, u) -> float and terminal_cost(data) ->
    float (or None) see the state after ``mj_forward``; a cost with a ``derivatives(data, u)``
    method (``QuadraticCost``) gives its own derivatives. The total cost is the plain sum of
    running costs over knots plus the terminal cost. settings: ``ILQGSettings`` (its horizon is
    needed here). costs: in place of the two costs, ``costs(episode, target, qpos, qvel) ->
    (running_cost, terminal_cost)`` asked at every ``optimize`` for each episode (per-episode
    targets, costs measured from the current state). n, targets: as ``reset``'s.

    ``plan`` / ``action`` plan one state (the current episode's plan and regularization);
    ``optimize(obs)`` plans every episode from ``obs`` (an ``Observation``: qpos [N, nq], qvel
    [N, nv]), ``act(obs, t)`` -> the plans' controls [N, nu] at knot t, ``step(obs)`` = both.
    """

    needs_sim_state = True    # plans from qpos and qvel
    device = torch.device("cpu")

    def __init__(self, model: mujoco.MjModel, running_cost: RunningCost | None = None,
                 terminal_cost: TerminalCost | None = None, settings: ILQGSettings | None = None, *,
                 costs: EpisodeCosts | None = None, n: int = 1, targets=None):
        if not isinstance(settings, (ILQGSettings, type(None))):
            raise TypeError(f"settings must be an ILQGSettings, got {type(settings).__name__}")
        settings = settings if settings is not None else ILQGSettings()
        if settings.horizon is None:
            raise ConfigError("horizon", "ILQG needs a horizon (ILQGSettings.horizon; for_task takes the task's)")
        if (running_cost is None) == (costs is None):
            raise ValueError("ILQG: give running_cost (and terminal_cost), or costs, not both")
        if model.nu < 1:
            raise ValueError("ILQG: the model has no actuators")
        self.settings = settings
        substeps = settings.substeps or 1
        horizon, iterations = settings.horizon, settings.iterations
        self.model, self.horizon, self.substeps, self.iterations = model, horizon, substeps, iterations
        self.warmup = settings.iterations if settings.warmup is None else settings.warmup
        self.running_cost, self.terminal_cost, self.costs = running_cost, terminal_cost, costs
        self.fd_eps, self.fd_centered, self.cost_eps, self.tol = (settings.fd_eps, settings.fd_centered,
                                                                  settings.cost_eps, settings.tol)
        self.reg_min, self.reg_max, self.reg_factor = settings.reg_min, settings.reg_max, settings.reg_factor
        self.reg = settings.reg_init  # kept across plans, as MuJoCo MPC does
        step_sizes, nthread = settings.step_sizes, settings.nthread
        self.step_sizes = np.logspace(0, -3, 10) if step_sizes is None else np.asarray(step_sizes, float)
        self.nx, self.nu = 2 * model.nv + model.na, model.nu
        act = Actuators.from_model(model)
        self.lower, self.upper = act.low, act.high
        self.nthread = max(1, min(nthread or os.cpu_count() or 1, horizon))
        self._datas = [mujoco.MjData(model) for _ in range(self.nthread)]
        self._pool = ThreadPoolExecutor(self.nthread) if self.nthread > 1 else None
        self._nstate = mujoco.mj_stateSize(model, _INTEGRATION)
        self._U: np.ndarray | None = None
        self.n, self.targets = 1, None
        self.reset(n, targets)

    @classmethod
    def for_system(cls, system, running_cost: RunningCost | None = None, terminal_cost: TerminalCost | None = None,
                   settings: ILQGSettings | None = None, **kw) -> "ILQG":
        """Plan on a ``gnwarp.sim.System``'s data timestep (one knot = ``system.substeps`` physics
        steps, unless ``settings.substeps`` says otherwise); ``kw`` as the constructor's."""
        settings = settings if settings is not None else ILQGSettings()
        if settings.substeps is None:
            settings = dataclasses.replace(settings, substeps=system.substeps)
        return cls(system.model, running_cost, terminal_cost, settings, **kw)

    @classmethod
    def for_task(cls, system, task, n: int = 1, settings: ILQGSettings | None = None, targets=None,
                 model: mujoco.MjModel | None = None) -> "ILQG":
        """Plan ``task``'s reward (a ``Task`` or its name) as the cost (``task_cost``: running and
        terminal, each episode's target its own) for ``n`` episodes on ``system`` (a System or a
        built-in name); ``model``: the MjModel planned on (default ``system.model``, e.g. an
        implicit-integrator copy). ``settings.horizon`` None: the task's. A task ``task_cost``
        refuses raises ValueError here."""
        from gnwarp.control.tasks import get_task
        from gnwarp.sim.systems import System, make
        system = system if isinstance(system, System) else make(system)
        task = get_task(task, system.name)
        settings = settings if settings is not None else ILQGSettings()
        settings = dataclasses.replace(settings, horizon=settings.horizon or task.horizon,
                                       substeps=settings.substeps or system.substeps)
        model = system.model if model is None else model
        task_cost(model, task, None)   # a refused task raises before any planning
        made: dict = {}

        def costs(episode, target, qpos, qvel):
            key = None if target is None else np.asarray(target).tobytes()
            if episode not in made or made[episode][0] != key:   # one cost per episode and target
                c = task_cost(model, task, target)
                made[episode] = (key, (c, c))
            return made[episode][1]
        return cls(model, settings=settings, costs=costs, n=n, targets=targets)

    def reset(self, n: int | None = None, targets=None, seed: int | None = None) -> None:
        """Forget the plans: each episode's next plan starts from zeros (or ``u_init``) with
        ``warmup`` iterations. ``n``: the episodes (None: as many as before); ``targets`` [n, ...]:
        the episodes' targets given to ``costs`` (None: those held); ``seed``: unused (iLQG draws
        no random numbers)."""
        if n is not None:
            if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
                raise ValueError(f"n (episodes) must be an integer >= 1, got {n!r}")
            self.n = int(n)
        if targets is not None:
            # no task to read a width from: for_task refuses the position tasks iLQG has no cost for
            self.targets = np.asarray(check_targets(torch.as_tensor(targets).detach().cpu(), self.n, None, ValueError))
        elif self.targets is not None and self.targets.shape[0] != self.n:
            raise ValueError(f"the targets held are for {self.targets.shape[0]} episodes, not {self.n}: give targets")
        self._U = None
        # per episode: its plan, its regularization, whether it has planned since the reset
        self._episodes = [(None, self.settings.reg_init, False) for _ in range(self.n)]
        self.plan_U = None
        self.last_info: list[dict] = []

    # -- the Planner protocol ----------------------------------------------------------------------

    def optimize(self, obs) -> None:
        """Plan every episode from the simulator's state ``obs`` (qpos [N, nq], qvel [N, nv]: an
        ``Observation``), ``warmup`` iterations for an episode's first plan, then ``iterations``;
        the plans [N, H, nu] are kept for ``act`` and each warm-starts the next, shifted."""
        qpos = np.asarray(torch.as_tensor(obs.qpos).detach().cpu(), dtype=np.float64)
        qvel = np.asarray(torch.as_tensor(obs.qvel).detach().cpu(), dtype=np.float64)
        if qpos.shape != (self.n, self.model.nq) or qvel.shape != (self.n, self.model.nv):
            raise ValueError(f"ILQG plans {self.n} episodes: qpos must be [{self.n}, {self.model.nq}] and qvel "
                             f"[{self.n}, {self.model.nv}], got {qpos.shape} and {qvel.shape}")
        plans, infos = [], []
        for i in range(self.n):
            self._U, self.reg, started = self._episodes[i]
            if self.costs is not None:
                tgt = None if self.targets is None else self.targets[i]
                self.running_cost, self.terminal_cost = self.costs(i, tgt, qpos[i], qvel[i])
            U, info = self.plan(qpos[i], qvel[i], iterations=self.iterations if started else self.warmup)
            self._episodes[i] = (self._U, self.reg, True)
            plans.append(U)
            infos.append(info)
        self.plan_U, self.last_info = np.stack(plans), infos

    def act(self, obs, time: int = 0) -> torch.Tensor:
        """Controls [N, nu] (float64) of the last plans at knot ``time`` (clamped to the horizon)."""
        return torch.from_numpy(plan_action(self.plan_U, time).copy())

    def step(self, obs) -> torch.Tensor:
        """``optimize(obs)`` then ``act(obs, 0)``: the first controls [N, nu]."""
        self.optimize(obs)
        return self.act(obs, 0)

    # -- public -----------------------------------------------------------------------------------

    def plan(self, qpos, qvel, act=None, u_init=None, iterations: int | None = None) -> tuple[np.ndarray, dict]:
        """Optimize H controls from the state (qpos [nq], qvel [nv], act [na]) in at most
        ``iterations`` iterations (None: ``self.iterations``).

        The start is ``u_init`` [H, nu] if given, else the previous plan shifted one knot (the
        receding-horizon warm start, last control repeated), else zeros; clamped into the box.
        Returns U [H, nu] and info: ``cost`` (final total), ``costs`` (after each iteration, first
        entry the start; never increasing), ``iterations``, ``reg`` (regularization after each
        iteration), ``backward_failures``, ``alphas`` (accepted step sizes, 0 = none accepted),
        ``K`` [H, nu, nx] feedback gains, ``qpos`` [H+1, nq], ``qvel`` [H+1, nv], ``time_s``.
        """
        t0 = time.perf_counter()
        state0 = self._initial_state(qpos, qvel, act)
        if u_init is not None:
            U = np.array(u_init, float).reshape(self.horizon, self.nu)
        elif self._U is not None:
            U = np.concatenate([self._U[1:], self._U[-1:]])
        else:
            U = np.zeros((self.horizon, self.nu))
        if not np.all(np.isfinite(U)):
            raise ValueError("ILQG.plan: u_init has NaN or Inf")
        traj = self._rollout(state0, np.clip(U, self.lower, self.upper))
        J = traj.cost.sum()
        info = {"costs": [J], "reg": [], "alphas": [], "backward_failures": 0, "iterations": 0}
        K = np.zeros((self.horizon, self.nu, self.nx))
        for _ in range(self.iterations if iterations is None else iterations):
            info["iterations"] += 1
            D = self._derivatives(traj)
            bp = self._backward(D, traj.U, self.reg)
            while bp is None and self.reg < self.reg_max:  # Quu not PD: regularize more
                info["backward_failures"] += 1
                self.reg = min(self.reg_max, max(self.reg_min, self.reg * self.reg_factor))
                bp = self._backward(D, traj.U, self.reg)
            if bp is None:
                info["reg"].append(self.reg)
                info["costs"].append(J)
                info["alphas"].append(0.0)
                break
            k, K, dV = bp
            alpha, new = 0.0, None
            for a in self.step_sizes:
                cand = self._rollout(state0, traj.U, k, K, traj, a)
                if cand.cost.sum() < J:  # accept only a decrease: the cost never rises
                    alpha, new = float(a), cand
                    break
            info["alphas"].append(alpha)
            if new is None:  # no step lowered the cost: damp the next step
                self.reg = min(self.reg_max, max(self.reg_min, self.reg * self.reg_factor))
                info["reg"].append(self.reg)
                info["costs"].append(J)
                if self.reg >= self.reg_max or -(dV[0] + dV[1]) < self.tol * max(1.0, abs(J)):
                    break
                continue
            self.reg = max(self.reg_min, self.reg / self.reg_factor)
            info["reg"].append(self.reg)
            dJ, J, traj = J - new.cost.sum(), new.cost.sum(), new
            info["costs"].append(J)
            if dJ < self.tol * max(1.0, abs(J)):
                break
        self._U = traj.U.copy()
        info.update(cost=J, K=K, qpos=traj.qpos, qvel=traj.qvel, time_s=time.perf_counter() - t0)
        return traj.U.copy(), info

    def action(self, qpos, qvel, act=None) -> np.ndarray:
        """Receding horizon: plan from the measured state (warm-started from the previous plan
        shifted) and return the first control [nu]."""
        U, _ = self.plan(qpos, qvel, act)
        return U[0]

    def total_cost(self, qpos, qvel, U, act=None) -> float:
        """The total cost of applying U [H, nu] (clamped into the box) open loop from a state."""
        U = np.clip(np.asarray(U, float).reshape(self.horizon, self.nu), self.lower, self.upper)
        return float(self._rollout(self._initial_state(qpos, qvel, act), U).cost.sum())

    # -- rollouts ---------------------------------------------------------------------------------

    def _initial_state(self, qpos, qvel, act) -> np.ndarray:
        m, d = self.model, self._datas[0]
        mujoco.mj_resetData(m, d)
        d.qpos[:], d.qvel[:] = qpos, qvel
        if act is not None:
            d.act[:] = act
        state = np.empty(self._nstate)
        mujoco.mj_getState(m, d, state, _INTEGRATION)
        if not np.all(np.isfinite(state)):
            raise ValueError("ILQG: the initial state has NaN or Inf")
        return state

    def _rollout(self, state0, U, k=None, K=None, nominal: _Trajectory | None = None,
                 alpha: float = 1.0) -> _Trajectory:
        """Simulate from state0; with gains, u_t = clamp(U_t + alpha k_t + K_t (x_t - nominal x_t))."""
        m, d, H, S = self.model, self._datas[0], self.horizon, self.substeps
        tr = _Trajectory(np.empty((H, self.nu)), np.empty((H + 1, m.nq)), np.empty((H + 1, m.nv)),
                         np.empty((H + 1, m.na)), np.empty((H, S, self._nstate)), np.zeros(H + 1))
        mujoco.mj_setState(m, d, state0, _INTEGRATION)
        for t in range(H + 1):
            mujoco.mj_forward(m, d)
            tr.qpos[t], tr.qvel[t], tr.act[t] = d.qpos, d.qvel, d.act
            if t == H:
                break
            u = U[t]
            if k is not None:
                dx = tangent_difference(m, d.qpos, d.qvel, d.act, nominal.qpos[t], nominal.qvel[t], nominal.act[t])
                u = u + alpha * k[t] + K[t] @ dx
            tr.U[t] = u = np.clip(u, self.lower, self.upper)
            tr.cost[t] = self.running_cost(d, u)
            d.ctrl[:] = u
            for s in range(S):
                mujoco.mj_getState(m, d, tr.phys[t, s], _INTEGRATION)
                mujoco.mj_step(m, d)
        if self.terminal_cost is not None:
            tr.cost[H] = self.terminal_cost(d)
        if not np.all(np.isfinite(tr.cost)):
            tr.cost[:] = np.inf  # a diverged rollout is never accepted
        return tr

    # -- derivatives ------------------------------------------------------------------------------

    def _derivatives(self, tr: _Trajectory) -> dict:
        """A [H, nx, nx], B [H, nx, nu] per knot and cost derivatives [H+1, ...], on the pool."""
        H, nx, nu = self.horizon, self.nx, self.nu
        D = {"A": np.empty((H, nx, nx)), "B": np.empty((H, nx, nu)), "lx": np.zeros((H + 1, nx)),
             "lu": np.zeros((H, nu)), "lxx": np.zeros((H + 1, nx, nx)), "luu": np.zeros((H, nu, nu)),
             "lux": np.zeros((H, nu, nx))}
        chunks = np.array_split(np.arange(H + 1), self.nthread)

        def work(i):
            for t in chunks[i]:
                self._knot(self._datas[i], tr, int(t), D)
        if self._pool is None:
            work(0)
        else:
            list(self._pool.map(work, range(self.nthread)))
        return D

    def _knot(self, d: mujoco.MjData, tr: _Trajectory, t: int, D: dict) -> None:
        m, H, nx = self.model, self.horizon, self.nx
        if t < H:  # chain the physics steps of one knot: A = A_S..A_1, B = sum A_S..A_{s+1} B_s
            A, B = np.eye(nx), np.zeros((nx, self.nu))
            As, Bs = np.empty((nx, nx)), np.empty((nx, self.nu))
            for s in range(self.substeps):
                mujoco.mj_setState(m, d, tr.phys[t, s], _INTEGRATION)
                mujoco.mjd_transitionFD(m, d, self.fd_eps, self.fd_centered, As, Bs, None, None)
                A, B = As @ A, As @ B + Bs
            D["A"][t], D["B"][t] = A, B
        base = tr.phys[t, 0] if t < H else tr.phys[H - 1, 0]
        mujoco.mj_setState(m, d, base, _INTEGRATION)
        d.qpos[:], d.qvel[:], d.act[:] = tr.qpos[t], tr.qvel[t], tr.act[t]
        if t == H:
            if self.terminal_cost is not None:
                lx, _, lxx, _, _ = self._cost_derivatives(d, self.terminal_cost, None)
                D["lx"][H], D["lxx"][H] = lx, lxx
            return
        lx, lu, lxx, luu, lux = self._cost_derivatives(d, self.running_cost, tr.U[t])
        D["lx"][t], D["lu"][t], D["lxx"][t], D["luu"][t], D["lux"][t] = lx, lu, lxx, luu, lux

    def _cost_derivatives(self, d: mujoco.MjData, fn, u):
        """(lx, lu, lxx, luu, lux) of fn at d's state and u (None: a terminal cost), by central
        differences in tangent space (gradient, Hessian diagonal) and forward ones (cross terms)."""
        m, nx = self.model, self.nx
        if hasattr(fn, "derivatives"):
            mujoco.mj_forward(m, d)
            return fn.derivatives(d, u)
        nu = 0 if u is None else self.nu
        n, h = nx + nu, self.cost_eps
        qpos0, qvel0, act0 = d.qpos.copy(), d.qvel.copy(), d.act.copy()
        last = [None]

        def f(z):
            key = z[:nx].tobytes()
            if key != last[0]:  # only a state change needs a new mj_forward
                d.qpos[:] = qpos0
                mujoco.mj_integratePos(m, d.qpos, z[:m.nv], 1.0)
                d.qvel[:] = qvel0 + z[m.nv:2 * m.nv]
                d.act[:] = act0 + z[2 * m.nv:nx]
                mujoco.mj_forward(m, d)
                last[0] = key
            return fn(d) if u is None else fn(d, u + z[nx:])

        E = h * np.eye(n)
        f0 = f(np.zeros(n))
        fp, fm = np.array([f(E[i]) for i in range(n)]), np.array([f(-E[i]) for i in range(n)])
        g = (fp - fm) / (2 * h)
        Hs = np.diag((fp - 2 * f0 + fm) / h ** 2)
        for i in range(n):
            for j in range(i + 1, n):
                Hs[i, j] = Hs[j, i] = (f(E[i] + E[j]) - fp[i] - fp[j] + f0) / h ** 2
        return g[:nx], g[nx:], Hs[:nx, :nx], Hs[nx:, nx:], Hs[nx:, :nx]

    # -- backward pass ----------------------------------------------------------------------------

    def _backward(self, D: dict, U: np.ndarray, reg: float):
        """Feedforward k [H, nu], feedback K [H, nu, nx] and the expected change (dV1, dV2), or
        None when a regularized Quu is not positive definite (``mju_boxQP`` fails)."""
        H, nx, nu = self.horizon, self.nx, self.nu
        k, K = np.zeros((H, nu)), np.zeros((H, nu, nx))
        Vx, Vxx = D["lx"][H].copy(), D["lxx"][H].copy()
        dV = np.zeros(2)
        R, index = np.zeros((nu, nu + 7)), np.zeros(nu, np.int32)
        boxed = bool(np.any(np.isfinite(self.lower)) or np.any(np.isfinite(self.upper)))
        for t in range(H - 1, -1, -1):
            A, B = D["A"][t], D["B"][t]
            Qx, Qu = D["lx"][t] + A.T @ Vx, D["lu"][t] + B.T @ Vx
            Qxx = D["lxx"][t] + A.T @ Vxx @ A
            Qux = D["lux"][t] + B.T @ Vxx @ A
            Quu = D["luu"][t] + B.T @ Vxx @ B
            Quu = 0.5 * (Quu + Quu.T)
            Hr = np.ascontiguousarray(Quu + reg * np.eye(nu))
            kt = np.zeros(nu)
            lo, hi = (self.lower - U[t], self.upper - U[t]) if boxed else (None, None)
            rank = mujoco.mju_boxQP(kt, R, index, Hr, Qu, lo, hi)
            if rank < 0 or not np.all(np.isfinite(kt)):
                return None
            free = index[:rank]
            Kt = np.zeros((nu, nx))
            if rank:  # clamped controls get no feedback (Tassa et al. 2014, eq. 7)
                Kt[free] = -np.linalg.solve(Hr[np.ix_(free, free)], Qux[free])
            Vx = Qx + Kt.T @ Quu @ kt + Kt.T @ Qu + Qux.T @ kt
            Vxx = Qxx + Kt.T @ Quu @ Kt + Kt.T @ Qux + Qux.T @ Kt
            Vxx = 0.5 * (Vxx + Vxx.T)
            dV += (kt @ Qu, 0.5 * kt @ Quu @ kt)
            k[t], K[t] = kt, Kt
        return k, K, dV
