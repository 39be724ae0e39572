"""Control tasks as Gymnasium vector environments: the true simulator and a learned model behind
one API, switched by one argument.

    env = make_vector_env("pendulum-balance", 64, dynamics="true", episode_steps=200, seed=0)
    env = make_vector_env("pendulum-balance", 64, dynamics=model, episode_steps=200, seed=0)
    obs, infos = env.reset(seed=0)                       # obs [N, D] float32
    obs, rewards, terminations, truncations, infos = env.step(actions)   # actions [N, U]

``dynamics="true"``: the true simulator, ``gnwarp.sim.env.make_env`` of ``num_envs`` worlds
(``backend`` "auto": MuJoCo-Warp on CUDA, else MuJoCo C; "mujoco", "mujoco_warp",
"mujoco_warp_cpu"). A ``gnwarp.dynamics.Dynamics`` model (a ``ForwardModel``, bound to the task's
system here when unbound): the learned model as the environment, every env stepped by one batched
``RolloutEngine`` call per step on the model's device, from initial states computed by MuJoCo C.

- Observations: ``gnwarp.control.env_observation.ObservationLayout`` (body states only, the same
  for both dynamics; ``env.obs_names`` names the entries), or ``observation=f(body, target)``.
  The raw body states [N, B, 13] are ``env.body_states``, the targets ``env.targets``, the true
  simulator's qpos / qvel ``env.observe()`` (for planners with ``needs_sim_state``).
- Actions: ``single_action_space`` is the Box of the actuators' sampling range
  (``Env.ctrlrange``; [-1, 1] for an unlimited actuator). Actions outside it are clamped to the
  actuators' control ranges as the true simulator does (``Env`` with ``ctrl_policy="clamp"``;
  an unlimited actuator takes any finite value); rewards see the clamped actions. NaN / Inf
  actions raise ``VectorEnvError`` naming the env: at once for actions on the host (NumPy, a CPU
  tensor) and whenever the env's outputs go to the host anyway (``output="numpy"``). Actions
  given as device tensors with ``output="torch"`` on CUDA are checked without a host sync: a
  non-finite row steps with zero actions and is flagged on the device, and the flag is read
  every ``action_check_every`` env steps, at an episode's end and at ``reset`` (or at once by
  ``check_actions()``), which raises naming the first such env and the step it happened at.
- Divergence of a learned model: every step of a learned-model env reports
  ``infos["diverged"]`` [N] bool (``infos["_diverged"]``: all True, Gymnasium's mask), True
  where the model's state has turned NaN / Inf at this step or before (an env stays diverged
  until it is reset: reset it with ``options={"reset_mask": infos["diverged"]}``). It is read
  from the device without a host sync (a tensor with ``output="torch"``).
- Rewards: the task's per-step reward, ``task.scorer`` (else ``task.reward``) on states
  [:, t:t+2] and actions [:, t:t+1] (for a reward that reads the episode's first state, such as
  swimmer-reach, the per-step rewards do not add up to the episode's reward).
- Episodes end by time limit only: ``truncations`` is True once an env's episode has run
  ``episode_steps`` control steps (the task's ``episode_steps``, else the argument);
  ``terminations`` is always False. ``action_repeat=k``: each env step applies its action for k
  control steps (rolled out in one call) and returns their rewards' sum; ``env.elapsed`` and
  ``env.control_steps`` (all envs' control steps since construction) count control steps.
- Autoreset (``metadata["autoreset_mode"]``, ``autoreset_mode=``): ``NEXT_STEP`` (default,
  Gymnasium's): the step after a truncation resets that env, ignores its action and returns its
  first observation with reward 0 and both flags False. ``SAME_STEP``: the truncating step
  returns the new episode's first observation; the last one is ``infos["final_obs"]`` [N, D] and
  its body states ``infos["final_body_states"]`` [N, B, 13] (rows where ``infos["_final_obs"]``).
  ``DISABLED``: stepping an env whose episode ended raises; ``reset(options={"reset_mask": m})``.
- Initial states: the task's ``initial(system, 1, rng)`` (else
  ``gnwarp.data.generation.initial_states``) and targets (``sample_targets``), drawn from each
  env's own generator: ``reset(seed=s)`` seeds env i with s + i (a list: one seed each), so the
  same seed gives the same observations whatever else runs (``per_env_seeds=False``: one shared
  generator, one call for every env being reset). ``options``: ``"reset_mask"`` [N]
  bool, ``"qpos"`` [N, nq] / ``"qvel"`` [N, nv] / ``"targets"`` [N, ...] to start from given
  states (rows outside the mask ignored). A partial reset of the true simulator re-sets every world
  (the others at their current qpos / qvel: on MuJoCo-Warp their solver warm start restarts).
- ``output="numpy"`` (Gymnasium's arrays) or ``"torch"`` (tensors on ``env.device``: no copy to
  the host, for agents on the GPU).
"""
from __future__ import annotations

from typing import Callable

import gymnasium as gym
import numpy as np
import torch
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from gnwarp.control.env_observation import ObservationLayout
from gnwarp.control.tasks import Task, episode_starts, get_task, sample_targets
from gnwarp.control.task_base import check_targets

__all__ = ["make_vector_env", "ControlVectorEnv", "VectorEnvError", "AutoresetMode", "OUTPUTS"]

OUTPUTS = ("numpy", "torch")
_MODES = {m.value.lower(): m for m in AutoresetMode} | {m.name.lower(): m for m in AutoresetMode}


class VectorEnvError(ValueError):
    """Inputs a vector environment cannot take: actions of the wrong shape or with NaN / Inf,
    reset options, a step where an episode has ended and autoreset is disabled."""


class TrueDynamics:
    """The true simulator of ``n`` worlds (``gnwarp.sim.env.Env``) behind a vector env."""

    kind = "true"

    def __init__(self, system, n: int, backend: str = "auto", device=None, **kw):
        from gnwarp.sim.env import make_env
        self.env = make_env(system, n, backend=backend, device=device, **kw)
        self.device = torch.device(self.env.device)
        self.dtype = torch.float32
        self.backend = self.env.backend if self.device.type != "cpu" or self.env.backend == "mujoco" \
            else "mujoco_warp_cpu"

    def reset(self, qpos: np.ndarray, qvel: np.ndarray, mask: np.ndarray) -> torch.Tensor:
        """Body states [N, B, 13] after putting worlds ``mask`` in (qpos, qvel) [N, nq], [N, nv]."""
        if not mask.all():
            q, v = self.env.qpos.cpu().double().numpy(), self.env.qvel.cpu().double().numpy()
            q[mask], v[mask] = qpos[mask], qvel[mask]
            qpos, qvel = q, v
        return self.env.reset(qpos, qvel)

    def rollout(self, ctrl: torch.Tensor) -> torch.Tensor:
        """Body states [N, k+1, B, 13] under ``ctrl`` [N, k, U] (the current state first)."""
        return self.env.rollout(ctrl)

    def close(self) -> None:
        self.env.close()


class LearnedDynamics:
    """A learned ``Dynamics`` model behind a vector env: one ``RolloutEngine`` of one step for
    all ``n`` envs; initial body states from MuJoCo C (``make_env(..., "mujoco")``)."""

    kind = "learned"
    backend = "model"

    def __init__(self, model, system, n: int, repeat: int = 1):
        from gnwarp.control.gradient import model_systems
        from gnwarp.data.layout import LayoutMismatchError
        from gnwarp.sim.env import make_env
        from gnwarp.sim.families import family_name
        trained = model_systems(model)
        if trained and not any(family_name(s) == family_name(system.name) for s in trained):
            raise VectorEnvError(f"the model was trained on {', '.join(trained)}, not on {system.name}")
        if getattr(model, "builder", None) is None:
            try:
                model.bind(system)
            except LayoutMismatchError as e:
                raise VectorEnvError(f"the model does not fit {system.name}: {e}") from None
        self.model = model
        self.device, self.dtype = model.device, model.dtype
        # controls arrive clamped (the vector env clamps them): the engine neither clamps nor checks
        self.engine = model.rollout_engine(torch.zeros(n, dtype=torch.int64), repeat, ctrl_policy="none",
                                           check=False)
        if self.engine.template.B != system.nbody:
            raise VectorEnvError(f"the model is bound to a source of {self.engine.template.B} bodies, but "
                                 f"{system.name} has {system.nbody}: bind it to {system.name}")
        self.kinematics = make_env(system, n, backend="mujoco")
        self.qpos0 = np.asarray(system.model.qpos0, dtype=np.float64)
        self.body = None

    def reset(self, qpos: np.ndarray, qvel: np.ndarray, mask: np.ndarray) -> torch.Tensor:
        if not mask.all():
            qpos, qvel = np.where(mask[:, None], qpos, self.qpos0), np.where(mask[:, None], qvel, 0.0)
        body = self.kinematics.reset(qpos, qvel).to(self.device, self.dtype)
        if self.body is not None and not mask.all():
            body = torch.where(torch.as_tensor(mask, device=self.device)[:, None, None], body, self.body)
        self.body = body
        return body

    def rollout(self, ctrl: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            traj = self.engine.rollout(self.body, ctrl.to(self.device, self.dtype))
        self.body = traj[:, -1]
        return traj

    def close(self) -> None:
        self.kinematics.close()


def _int(x, name: str, lo: int = 1) -> int:
    if isinstance(x, bool) or not isinstance(x, (int, np.integer)) or x < lo:
        raise ValueError(f"{name} must be an integer >= {lo}, got {x!r}")
    return int(x)


class ControlVectorEnv(VectorEnv):
    """A control task as a Gymnasium vector environment of ``num_envs`` episodes stepped together
    (see the module's docstring; build one with ``make_vector_env``).

    Besides Gymnasium's attributes: ``task``, ``system``, ``dynamics`` ("true" or "learned"),
    ``backend``, ``device``, ``dt`` (seconds per env step), ``episode_steps``, ``action_repeat``,
    ``elapsed`` [N] (control steps of each env's episode), ``control_steps`` (of all envs, in
    all), ``body_states`` [N, B, 13] (copy, on ``device``), ``targets`` [N, ...] or None,
    ``last_actions`` [N, U] (as applied, clamped), ``ctrl_lo`` / ``ctrl_hi`` [U] (what actions are
    clamped to), ``obs_layout`` (``ObservationLayout``) and ``obs_names``; ``defer_action_checks``
    (whether device actions are checked for NaN / Inf every ``action_check_every`` steps rather
    than at once: with ``output="torch"`` on CUDA)."""

    def __init__(self, task: Task, system, dynamics, num_envs: int, episode_steps: int,
                 autoreset_mode: AutoresetMode = AutoresetMode.NEXT_STEP, seed=None, output: str = "numpy",
                 observation: str | Callable = "bodies", action_repeat: int = 1, per_env_seeds: bool = True,
                 action_check_every: int = 100):
        self.task, self.system, self.sim = task, system, dynamics
        self.per_env_seeds = bool(per_env_seeds)
        self.num_envs, self.episode_steps, self.action_repeat = num_envs, episode_steps, action_repeat
        self.control_steps = 0
        self.autoreset_mode, self.output = autoreset_mode, output
        self.action_check_every = _int(action_check_every, "action_check_every")
        self.defer_action_checks = output == "torch" and torch.device(dynamics.device).type == "cuda"
        self.env_steps = 0       # step() calls since construction (what a deferred action check names)
        self._bad_step = None    # [N] int64 on the device: the first env step of non-finite actions, else -1
        self._diverged = torch.zeros(num_envs, dtype=torch.bool, device=dynamics.device)   # learned model: NaN / Inf
        self.dynamics, self.backend = dynamics.kind, dynamics.backend
        self.device, self.dt = dynamics.device, float(system.dt) * action_repeat
        self.metadata = {"autoreset_mode": autoreset_mode, "render_modes": [], "render_fps": 1.0 / self.dt}
        act = system.actuators
        lo, hi = act.clamp_bounds()
        self.ctrl_lo = torch.as_tensor(lo, device=self.device)
        self.ctrl_hi = torch.as_tensor(hi, device=self.device)
        box = np.asarray(act.sample_range(), dtype=np.float32).reshape(-1, 2)
        self.nu = box.shape[0]
        self.single_action_space = gym.spaces.Box(box[:, 0], box[:, 1], dtype=np.float32)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._scorer = getattr(task, "scorer", None) or task.reward
        self.obs_layout = ObservationLayout(system, task, None if observation == "bodies" else observation)
        self._rngs = self._generators(seed, [None] * num_envs)
        self._body = None
        self.targets = None
        self.elapsed = np.zeros(num_envs, dtype=np.int64)
        self._ended = np.zeros(num_envs, dtype=bool)     # truncated at the last step, not reset since
        self.last_actions = torch.zeros(num_envs, self.nu, device=self.device)
        if not self.obs_layout.sized:   # a custom observation: sized on the model's rest pose
            everyone = np.ones(num_envs, dtype=bool)
            q0 = np.tile(np.asarray(system.model.qpos0, dtype=np.float64), (num_envs, 1))
            body = self.sim.reset(q0, np.zeros((num_envs, system.model.nv)), everyone)
            tgt = sample_targets(task, system, num_envs) if task.target is not None else None
            self.obs_layout.bind_size(body, None if tgt is None else tgt.to(self.device))
        self.single_observation_space = gym.spaces.Box(-np.inf, np.inf, (self.obs_layout.size,), np.float32)
        self.observation_space = batch_space(self.single_observation_space, num_envs)

    # -- seeding and initial states -------------------------------------------------------------
    def _generators(self, seed, rngs: list) -> list:
        """Per-env generators: ``seed`` None keeps ``rngs`` (fresh entropy where None), an int
        seeds env i with seed + i, a list one seed (or None) each. With ``per_env_seeds`` off, one
        generator shared by every env (an int seeds it)."""
        n = self.num_envs
        if seed is None:
            if not self.per_env_seeds:
                return rngs if rngs[0] is not None else [np.random.default_rng()] * n
            return [r if r is not None else np.random.default_rng() for r in rngs]
        def whole(s) -> bool:   # a seed numpy takes: an integer >= 0
            return isinstance(s, (int, np.integer)) and not isinstance(s, bool) and s >= 0
        if not self.per_env_seeds:
            if not whole(seed):
                raise VectorEnvError(f"with per_env_seeds=False, seed must be None or an integer >= 0, got {seed!r}")
            return [np.random.default_rng(int(seed))] * n
        if whole(seed):
            seeds = [int(seed) + i for i in range(n)]
        else:
            if isinstance(seed, (str, bytes)) or not hasattr(seed, "__len__"):
                raise VectorEnvError(f"seed must be None, an integer >= 0 or a list of {n} of them (one per env), "
                                     f"got {seed!r}")
            seeds = list(seed)
            if len(seeds) != n:
                raise VectorEnvError(f"seed must be None, an int or a list of {n} seeds (one per env), "
                                     f"got {len(seeds)}")
            bad = [s for s in seeds if s is not None and not whole(s)]
            if bad:
                raise VectorEnvError(f"seeds must be integers >= 0 (or None), got {bad[0]!r}")
        return [np.random.default_rng(s) for s in seeds]

    def _draw(self, mask: np.ndarray, rngs: list):
        """(qpos [N, nq], qvel [N, nv], targets [N, ...] or None) with rows ``mask`` drawn from
        each env's generator, or all in one call from the shared one (``per_env_seeds`` off);
        other rows: the model's qpos0, zero velocities, no target."""
        system, n = self.system, self.num_envs
        qpos = np.tile(np.asarray(system.model.qpos0, dtype=np.float64), (n, 1))
        qvel = np.zeros((n, system.model.nv))
        rows = np.flatnonzero(mask)
        groups = [(rows, rngs[rows[0]])] if not self.per_env_seeds else [(rows[k:k + 1], rngs[i])
                                                                          for k, i in enumerate(rows)]
        tgt = None
        for idx, rng in groups:
            qpos[idx], qvel[idx], t = episode_starts(self.task, system, len(idx), rng)
            if t is not None:
                if tgt is None:
                    tgt = torch.zeros((n,) + tuple(t.shape[1:]), dtype=torch.float32)
                tgt[torch.as_tensor(idx)] = t
        return qpos, qvel, tgt

    # -- outputs --------------------------------------------------------------------------------
    def _out(self, x: torch.Tensor):
        return x if self.output == "torch" else x.detach().cpu().numpy()

    def _flags(self, x: np.ndarray):
        return torch.as_tensor(x, device=self.device) if self.output == "torch" else x.copy()

    def _observe(self, body: torch.Tensor) -> torch.Tensor:
        return self.obs_layout(body, self.targets)

    @property
    def body_states(self) -> torch.Tensor:
        """The current body states [N, B, 13] of every env (a copy, on ``device``)."""
        self._need_reset()
        return self._body.clone()

    def observe(self):
        """The true simulator's state (``gnwarp.sim.env.Observation``: qpos [N, nq], qvel [N, nv],
        body [N, B, 13]) for planners that plan on it (``needs_sim_state``); true dynamics only."""
        self._need_reset()
        if self.dynamics != "true":
            raise RuntimeError("a learned model's environment has body states only (env.body_states), no qpos / qvel")
        return self.sim.env.observe()

    @property
    def obs_names(self) -> list[str]:
        return list(self.obs_layout.names)

    def _need_reset(self) -> None:
        if self._body is None:
            raise RuntimeError("call env.reset() before stepping")

    # -- the API --------------------------------------------------------------------------------
    def reset(self, *, seed=None, options: dict | None = None):
        """Start new episodes: every env, or those of ``options["reset_mask"]`` ([N] bool).
        ``seed``: None (continue each env's generator), an int (env i: seed + i) or a list.
        ``options``: also ``"qpos"`` [N, nq], ``"qvel"`` [N, nv], ``"targets"`` [N, ...] (the
        episodes' initial states / targets instead of drawn ones). Returns (obs [N, D], {})."""
        options = dict(options or {})
        mask = options.pop("reset_mask", None)
        n = self.num_envs
        if mask is None:
            mask = np.ones(n, dtype=bool)
        else:
            mask = np.asarray(mask.detach().cpu() if isinstance(mask, torch.Tensor) else mask)
            if mask.shape != (n,) or mask.dtype != np.bool_ or not mask.any():
                raise VectorEnvError(f"options['reset_mask'] must be a bool array [{n}] with a True value, got "
                                     f"{mask.dtype} {mask.shape}")
            if self._body is None and not mask.all():
                raise VectorEnvError("the first reset must reset every env (no reset_mask)")
        unknown = set(options) - {"qpos", "qvel", "targets"}
        if unknown:
            raise VectorEnvError(f"unknown reset options {sorted(unknown)}; known: reset_mask, qpos, qvel, targets")
        if seed is not None:
            fresh = self._generators(seed, [None] * n)
            self._rngs = fresh if not self.per_env_seeds else [f if m else r for f, r, m in
                                                                 zip(fresh, self._rngs, mask)]
            if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
                self._np_random, self._np_random_seed = seeding.np_random(int(seed))
        elif self._np_random is None:
            self._np_random, self._np_random_seed = seeding.np_random()
        self.check_actions()
        self._start(mask, options)
        return self._out(self._observe(self._body)), {}

    def _start(self, mask: np.ndarray, options: dict | None = None) -> None:
        """New episodes in envs ``mask``: initial states and targets drawn (or from ``options``)."""
        options = options or {}
        qpos, qvel, tgt = self._draw(mask, self._rngs)
        nq, nv = self.system.model.nq, self.system.model.nv
        for key, arr, width in (("qpos", qpos, nq), ("qvel", qvel, nv)):
            if key in options:
                given = np.asarray(torch.as_tensor(options[key]).detach().cpu().double())
                if given.shape != (self.num_envs, width):
                    raise VectorEnvError(f"options[{key!r}] must be [{self.num_envs}, {width}], got {given.shape}")
                arr[mask] = given[mask]
        if "targets" in options:
            if self.task.target is None:
                raise VectorEnvError(f"task {self.task.name!r} has no targets; options['targets'] is not taken")
            given = torch.as_tensor(options["targets"]).detach().cpu().float()
            check_targets(given, self.num_envs, self.task, VectorEnvError)
            if tgt is None or given.shape != tgt.shape:
                raise VectorEnvError(f"options['targets'] must have shape {None if tgt is None else tuple(tgt.shape)}, "
                                     f"got {tuple(given.shape)}")
            tgt[torch.as_tensor(mask)] = given[torch.as_tensor(mask)]
        body = self.sim.reset(qpos, qvel, mask)
        if tgt is not None:
            tgt = tgt.to(self.device)
            if self.targets is not None and not mask.all():
                m = torch.as_tensor(mask, device=self.device).reshape((-1,) + (1,) * (tgt.ndim - 1))
                tgt = torch.where(m, tgt, self.targets)
        self.targets = tgt
        self._body = body
        self.elapsed[mask] = 0
        self._ended[mask] = False
        self._diverged = self._diverged & torch.as_tensor(~mask, device=self.device)
        self.last_actions[torch.as_tensor(mask, device=self.device)] = 0

    def check_actions(self) -> None:
        """Read the deferred NaN / Inf action flag (one host sync; nothing to do without deferred
        checks): ``VectorEnvError`` naming the first env and env step with non-finite actions."""
        if self._bad_step is None:
            return
        flagged, self._bad_step = self._bad_step, None
        first = flagged.cpu()
        if bool((first >= 0).any()):
            i = int(torch.where(first >= 0, first, torch.iinfo(torch.int64).max).argmin())
            raise VectorEnvError(f"the actions of env {i} held NaN or Inf at env step {int(first[i])} (actions on the "
                                 f"device are checked every {self.action_check_every} steps; that step and later "
                                 "ones applied zero actions in that env)")

    def _actions(self, actions, stepping: np.ndarray) -> torch.Tensor:
        """``actions`` [N, U] as a tensor on ``device``, finite where envs step, clamped to the
        actuators' ranges; rows of envs that do not step are zero."""
        a = actions.detach() if isinstance(actions, torch.Tensor) else torch.as_tensor(np.asarray(actions))
        if not (a.is_floating_point() or a.dtype in (torch.int32, torch.int64)):   # bool, complex: refused
            raise VectorEnvError(f"actions must hold real numbers, got dtype {a.dtype}")
        if tuple(a.shape) != (self.num_envs, self.nu):
            raise VectorEnvError(f"actions must be [num_envs={self.num_envs}, U={self.nu}], got {tuple(a.shape)}")
        # deferred for tensors already on the env's device (a CUDA tensor, or any with the checks forced)
        deferred = (self.defer_action_checks and isinstance(actions, torch.Tensor)
                    and a.device == torch.device(self.device))
        stepping_on = None if stepping.all() else torch.as_tensor(stepping, device=a.device)
        bad = ~torch.isfinite(a).all(1)
        if stepping_on is not None:
            bad &= stepping_on
        if not deferred:   # host actions, or outputs read on the host each step anyway: checked at once
            if bool(bad.any()):
                i = int(bad.nonzero()[0, 0])
                raise VectorEnvError(f"the actions of env {i} hold NaN or Inf: {a[i].tolist()}")
        a = a.to(self.device, torch.float64)
        if deferred:       # flagged on the device, read by check_actions
            bad = bad.to(self.device)
            if self._bad_step is None:
                self._bad_step = torch.full((self.num_envs,), -1, dtype=torch.int64, device=self.device)
            self._bad_step = torch.where(bad & (self._bad_step < 0), self.env_steps, self._bad_step)
            a = torch.where(bad[:, None], torch.zeros_like(a), a)
        step_t = None if stepping_on is None else stepping_on.to(self.device)
        a = torch.maximum(torch.minimum(a, self.ctrl_hi), self.ctrl_lo)
        if step_t is not None:
            a = torch.where(step_t[:, None], a, torch.zeros_like(a))
        return a

    def step(self, actions):
        """One env step (``action_repeat`` control steps) of every env under ``actions`` [N, U]
        -> (obs [N, D], rewards [N], terminations [N] (always False), truncations [N], infos)."""
        self._need_reset()
        mode, n = self.autoreset_mode, self.num_envs
        ended = self._ended.copy()
        if mode == AutoresetMode.DISABLED and ended.any():
            raise VectorEnvError(f"the episodes of envs {np.flatnonzero(ended).tolist()} have ended and autoreset is "
                                 "disabled: reset(options={'reset_mask': ...}) them first")
        stepping = ~ended if mode == AutoresetMode.NEXT_STEP else np.ones(n, dtype=bool)
        rewards = torch.zeros(n, device=self.device)
        if stepping.any():
            u = self._actions(actions, stepping)
            k = self.action_repeat
            traj = self.sim.rollout(u[:, None].expand(n, k, self.nu))
            body = traj[:, -1]
            if self.dynamics == "learned":
                self._diverged = self._diverged | ~torch.isfinite(body).flatten(1).all(1)
            r = self._scorer(traj, u.to(traj.dtype)[:, None].expand(n, k, self.nu), self.targets)
            r = torch.as_tensor(r).to(self.device, torch.float32).reshape(n)
            rewards = r if stepping.all() else torch.where(torch.as_tensor(stepping, device=self.device), r, rewards)
            self._body = body
            self.last_actions = u.float()
            self.elapsed[stepping] += self.action_repeat
            self.control_steps += int(stepping.sum()) * self.action_repeat
        truncated = stepping & (self.elapsed >= self.episode_steps)
        self.env_steps += 1
        if self._bad_step is not None and (self.env_steps % self.action_check_every == 0 or truncated.any()):
            self.check_actions()
        infos = {}
        if self.dynamics == "learned":
            infos = {"diverged": self._out(self._diverged.clone()), "_diverged": np.ones(n, dtype=bool)}
        if mode == AutoresetMode.NEXT_STEP and ended.any():
            self._start(ended)
        obs = self._observe(self._body)
        if mode == AutoresetMode.SAME_STEP and truncated.any():
            infos.update({"final_obs": self._out(obs.clone()), "_final_obs": truncated.copy(),
                          "final_body_states": self._out(self._body.clone()), "_final_body_states": truncated.copy()})
            self._start(truncated)
            obs = self._observe(self._body)
        else:
            self._ended = truncated
        return (self._out(obs), self._out(rewards), self._flags(np.zeros(n, dtype=bool)), self._flags(truncated),
                infos)

    def close_extras(self, **kwargs) -> None:
        if getattr(self, "sim", None) is not None:   # also when construction stopped early
            self.sim.close()

    def __repr__(self) -> str:
        return (f"ControlVectorEnv(task={self.task.name!r}, system={self.system.name!r}, num_envs={self.num_envs}, "
                f"dynamics={self.dynamics!r}, backend={self.backend!r}, episode_steps={self.episode_steps}, "
                f"autoreset_mode={self.autoreset_mode.name})")


def make_vector_env(task, num_envs: int, dynamics="true", backend: str = "auto", seed=None,
                    episode_steps: int | None = None, system=None, autoreset_mode="next_step",
                    output: str = "numpy", observation: str | Callable = "bodies", action_repeat: int = 1,
                    per_env_seeds: bool = True, device=None, action_check_every: int = 100,
                    **env_kw) -> ControlVectorEnv:
    """``num_envs`` episodes of ``task`` (a ``Task`` or its name) as a ``gymnasium.vector.VectorEnv``.

    ``dynamics``: "true" (the true simulator on ``backend``: "auto", "mujoco", "mujoco_warp",
    "mujoco_warp_cpu"; ``device``: MuJoCo-Warp's Warp device; ``env_kw``: ``make_env``'s
    ``nthread`` / ``capture``) or a ``gnwarp.dynamics.Dynamics`` model (bound to ``system`` here
    when unbound; a bound model steps instance 0 of its source). ``system``: a ``System`` or
    built-in name the task applies to (None: the task's own). ``episode_steps``: the time limit
    (None: the task's ``episode_steps``; one of the two is required). ``seed``: of each env's
    generator before the first seeded reset (an int: env i gets seed + i; None: fresh entropy).
    ``autoreset_mode``: an ``AutoresetMode`` or "next_step" / "same_step" / "disabled".
    ``output``: "numpy" or "torch". ``observation``: "bodies" (``ObservationLayout``) or
    ``f(body [N, B, 13], target) -> [N, D]``. ``action_repeat``: control steps (of ``system.dt``)
    each env step applies its action for, its reward their sum; ``episode_steps`` counts control
    steps (a multiple of it). ``per_env_seeds``: each env draws its initial states from its own
    generator (default; one call of the task's ``initial`` per env), or all envs from one shared
    generator in one call (False: faster resets of many envs; the same seed gives the same
    observations only for the same ``num_envs``). ``action_check_every``: env steps between reads
    of the NaN / Inf flag of device actions (``output="torch"`` on CUDA; see the module's
    docstring)."""
    from gnwarp.sim.systems import System, make
    task = get_task(task)
    num_envs = _int(num_envs, "num_envs")
    if system is None:
        system = task.system
    if not isinstance(system, System):
        try:
            system = make(system)
        except (ValueError, KeyError) as e:
            raise VectorEnvError(f"task {task.name!r}: cannot build system {system!r} ({e}); pass system=") from None
    task.check_system(system.name)
    steps = episode_steps if episode_steps is not None else getattr(task, "episode_steps", None)
    if steps is None:
        raise VectorEnvError(f"task {task.name!r} has no episode_steps: pass episode_steps= (the time limit in steps)")
    steps = _int(steps, "episode_steps")
    k = _int(action_repeat, "action_repeat")
    _int(action_check_every, "action_check_every")
    if steps % k:
        raise VectorEnvError(f"episode_steps ({steps}) must be a multiple of action_repeat ({k})")
    mode = autoreset_mode if isinstance(autoreset_mode, AutoresetMode) else _MODES.get(str(autoreset_mode).lower())
    if mode is None:
        raise VectorEnvError(f"unknown autoreset_mode {autoreset_mode!r}; choose next_step, same_step or disabled")
    if output not in OUTPUTS:
        raise VectorEnvError(f"output must be one of {OUTPUTS}, got {output!r}")
    if observation != "bodies" and not callable(observation):
        raise VectorEnvError(f"observation must be 'bodies' or a callable (body, target) -> [N, D], "
                             f"got {observation!r}")
    if isinstance(dynamics, str):
        if dynamics != "true":
            raise VectorEnvError(f"dynamics must be 'true' or a Dynamics model, got {dynamics!r}")
        sim = TrueDynamics(system, num_envs, backend=backend, device=device, **env_kw)
    else:
        if not callable(getattr(dynamics, "rollout_engine", None)):
            raise VectorEnvError(f"dynamics must be 'true' or a gnwarp.dynamics.Dynamics model (with rollout_engine), "
                                 f"got {type(dynamics).__name__}")
        if env_kw:
            raise VectorEnvError(f"options {sorted(env_kw)} are for the true simulator, not a learned model")
        sim = LearnedDynamics(dynamics, system, num_envs, k)
    return ControlVectorEnv(task, system, sim, num_envs, steps, mode, seed, output, observation, k,
                            bool(per_env_seeds), action_check_every)
