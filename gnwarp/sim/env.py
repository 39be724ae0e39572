"""Persistent batched environments on the true simulator: where every planned action runs.

``make_env(system, n_worlds, backend)`` gives an ``Env`` of ``n_worlds`` worlds that stay
allocated between calls (on MuJoCo-Warp the Model and Data stay on the device; on CUDA the data
step is captured as a graph once and replayed). The interface is the same on every backend::

    env = make_env("pendulum", 8, backend="mujoco")     # "auto" | "mujoco" | "mujoco_warp" | "mujoco_warp_cpu"
    body = env.reset(qpos0, qvel0)                       # [N, nq], [N, nv] -> body states [N, B, 13]
    body = env.step(ctrl)                                # [N, U] -> [N, B, 13] one data step (env.dt)
    traj = env.rollout(ctrl_seq)                         # [N, T, U] -> [N, T+1, B, 13], env left at the end
    obs = env.rollout(ctrl_seq, states=True)             # Observation: qpos [N, T+1, nq], qvel, body

Body states are the datasets' 13 numbers per body (``gnwarp.state``), written by the same code as
the datasets' (frame sensors on MuJoCo C, ``kernels/sim/mujoco_warp.record_body_state`` on
MuJoCo-Warp); the MuJoCo-Warp datasets are simulated on ``MujocoWarpEnv`` itself
(``gnwarp.sim.mujoco_warp``). Controls are clamped to the actuators' ranges as MuJoCo does
(``ctrl_policy="clamp"``) or refused (``"error"``); NaN / Inf in states or controls raise
``EnvInputError``.
"""
from __future__ import annotations

import contextlib
import os
from typing import NamedTuple, Sequence

import mujoco
import numpy as np
import torch

from gnwarp.sim.common import put_batched_model, resolve_backend
from gnwarp.sim.mujoco_c import system_sensor_model
from gnwarp.sim.systems import System, make
from gnwarp.state import DYN_NODE_SIZE, world_state

__all__ = ["Env", "MujocoEnv", "MujocoWarpEnv", "EnvInputError", "Observation", "make_env", "dataset_states",
           "CTRL_POLICIES"]

CTRL_POLICIES = ("clamp", "error")


class EnvInputError(ValueError):
    """A state or control an environment cannot take (shape, NaN / Inf, outside the range)."""


class Observation(NamedTuple):
    """The true state of every world: ``qpos`` [N, nq], ``qvel`` [N, nv], ``body`` [N, B, 13]
    (from ``rollout(..., states=True)``: with a time axis, [N, T+1, ...])."""
    qpos: torch.Tensor
    qvel: torch.Tensor
    body: torch.Tensor


def _as_tensor(x, name: str, dtype=None) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        t = x.detach()
    else:
        try:
            t = torch.as_tensor(np.asarray(x))
        except (TypeError, ValueError) as e:
            raise EnvInputError(f"{name} must be an array, got {type(x).__name__}") from e
    if not (t.is_floating_point() or t.dtype in (torch.int32, torch.int64)):
        raise EnvInputError(f"{name} must hold numbers, got dtype {t.dtype}")
    return t.to(dtype) if dtype is not None else t


def _first_bad(t: torch.Tensor) -> tuple[int, ...] | None:
    bad = ~torch.isfinite(t)
    if not bool(bad.any()):
        return None
    return tuple(int(i) for i in bad.nonzero()[0])


class Env:
    """What every backend shares: sizes, control ranges, input checks. Subclasses implement
    ``_reset(qpos, qvel)``, ``_rollout(ctrl [N, T, U], states) -> [N, T+1, B, 13]`` (an
    ``Observation`` with a time axis when ``states``) and the state accessors.

    Control ranges, from the system's ``Actuators`` record (``actuators``): ``ctrl_lo`` /
    ``ctrl_hi`` [U] what controls are clamped to (+-inf where MuJoCo does not clamp), ``ctrlrange``
    [U, 2] where planners sample (``Actuators.sample_range``: [-1, 1] for unlimited actuators)."""

    backend = ""

    def __init__(self, systems: Sequence[System], n_worlds: int, ctrl_policy: str, device: torch.device):
        if not isinstance(n_worlds, int) or isinstance(n_worlds, bool) or n_worlds < 1:
            raise ValueError(f"n_worlds must be an integer >= 1, got {n_worlds!r}")
        if len(systems) not in (1, n_worlds):
            raise ValueError(f"got {len(systems)} systems for {n_worlds} worlds (need 1 or {n_worlds})")
        if len({s.substeps for s in systems}) != 1 or len({s.dt for s in systems}) != 1:
            raise ValueError("all systems of one environment must share their data timestep and sub-steps")
        if ctrl_policy not in CTRL_POLICIES:
            raise ValueError(f"unknown ctrl_policy '{ctrl_policy}'; choose one of {CTRL_POLICIES}")
        self.systems = list(systems)
        self.system = systems[0]
        m = self.system.model
        self.n_worlds, self.nu, self.nq, self.nv, self.nbody = n_worlds, m.nu, m.nq, m.nv, m.nbody
        self.dt, self.substeps = float(self.system.dt), int(self.system.substeps)
        self.ctrl_policy = ctrl_policy
        self.device = device
        self.actuators = self.system.actuators
        # what MuJoCo clamps to (unlimited: nothing) and what planners sample in (unlimited: [-1, 1])
        lo, hi = self.actuators.clamp_bounds()
        self.ctrl_lo = torch.tensor(lo, device=device)
        self.ctrl_hi = torch.tensor(hi, device=device)
        self.ctrlrange = torch.tensor(self.actuators.sample_range(), device=device)
        self.last_ctrl = torch.zeros(n_worlds, self.nu, device=device)
        self._ready = False

    # -- inputs ---------------------------------------------------------------------------------
    def check_state(self, qpos, qvel=None) -> tuple[torch.Tensor, torch.Tensor]:
        """``qpos`` [N, nq] (and ``qvel`` [N, nv], zeros when None) as float64 CPU tensors, checked."""
        qpos = _as_tensor(qpos, "qpos", torch.float64).cpu()
        qvel = torch.zeros(qpos.shape[0] if qpos.ndim else 0, self.nv, dtype=torch.float64) if qvel is None \
            else _as_tensor(qvel, "qvel", torch.float64).cpu()
        want = ((self.n_worlds, self.nq), (self.n_worlds, self.nv))
        if (tuple(qpos.shape), tuple(qvel.shape)) != want:
            raise EnvInputError(f"reset takes qpos [N={self.n_worlds}, nq={self.nq}] and qvel [N, nv={self.nv}], "
                                f"got {tuple(qpos.shape)} and {tuple(qvel.shape)}")
        for name, t in (("qpos", qpos), ("qvel", qvel)):
            bad = _first_bad(t)
            if bad is not None:
                raise EnvInputError(f"reset: {name} holds NaN or Inf (world {bad[0]}, coordinate {bad[1]})")
        return qpos, qvel

    def check_ctrl(self, ctrl, ndim: int = 2) -> torch.Tensor:
        """Controls [N, U] (``ndim`` 2) or [N, T, U] (3) on this env's device, clamped to the
        actuators' ranges (``ctrl_policy`` "clamp") or refused outside them ("error")."""
        ctrl = _as_tensor(ctrl, "ctrl", torch.float64).to(self.device)
        ok = ctrl.ndim == ndim and ctrl.shape[0] == self.n_worlds and ctrl.shape[-1] == self.nu
        if not ok or (ndim == 3 and ctrl.shape[1] < 1):
            want = "[N, U]" if ndim == 2 else "[N, T >= 1, U]"
            raise EnvInputError(f"controls must be {want} with N={self.n_worlds}, U={self.nu}, got {tuple(ctrl.shape)}")
        bad = _first_bad(ctrl)
        if bad is not None:
            raise EnvInputError(f"controls hold NaN or Inf (at index {bad})")
        if self.ctrl_policy == "error":
            out = (ctrl < self.ctrl_lo) | (ctrl > self.ctrl_hi)
            if bool(out.any()):
                i = tuple(int(k) for k in out.nonzero()[0])
                a = i[-1]
                raise EnvInputError(f"control {ctrl[i].item():.4g} of actuator {a} (at index {i}) is outside its "
                                    f"range [{self.ctrl_lo[a].item():.4g}, {self.ctrl_hi[a].item():.4g}]")
        return torch.maximum(torch.minimum(ctrl, self.ctrl_hi), self.ctrl_lo)

    def _need_reset(self):
        if not self._ready:
            raise RuntimeError("call env.reset(qpos, qvel) before stepping")

    # -- the interface --------------------------------------------------------------------------
    def reset(self, qpos, qvel=None) -> torch.Tensor:
        """Put every world in state ``qpos`` [N, nq], ``qvel`` [N, nv] (zeros when None); time,
        activations and solver warm starts reset. Returns the body states [N, B, 13]."""
        qpos, qvel = self.check_state(qpos, qvel)
        self._reset(qpos, qvel)
        self._ready = True
        self.last_ctrl.zero_()
        return self.body_states()

    def step(self, ctrl) -> torch.Tensor:
        """One data step (``substeps`` physics steps) under ``ctrl`` [N, U] -> body states [N, B, 13]."""
        return self.rollout(self.check_ctrl(ctrl, 2)[:, None])[:, 1]

    def rollout(self, ctrl, states: bool = False):
        """``T`` data steps under ``ctrl`` [N, T, U] from the current state -> body states
        [N, T+1, B, 13] (the current one included); the env is left in the last state. With
        ``states``, an ``Observation`` of every data step: qpos [N, T+1, nq], qvel [N, T+1, nv]
        (float32 on MuJoCo-Warp, float64 on MuJoCo C) and body [N, T+1, B, 13]."""
        self._need_reset()
        ctrl = self.check_ctrl(ctrl, 3)
        out = self._rollout(ctrl, bool(states))
        self.last_ctrl = ctrl[:, -1].to(self.last_ctrl.dtype)
        return out

    def observe(self) -> Observation:
        """Copies of the current ``qpos``, ``qvel`` and body states."""
        return Observation(self.qpos, self.qvel, self.body_states())

    def body_states(self) -> torch.Tensor:
        raise NotImplementedError

    @property
    def qpos(self) -> torch.Tensor:
        raise NotImplementedError

    @property
    def qvel(self) -> torch.Tensor:
        raise NotImplementedError

    def close(self) -> None:
        pass

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(system={self.system.name!r}, n_worlds={self.n_worlds}, nu={self.nu}, "
                f"dt={self.dt}, device={str(self.device)!r})")


class MujocoEnv(Env):
    """MuJoCo C: the full physics state of each world kept in float64 on the host; steps run
    through ``mujoco.rollout`` on a persistent thread pool; body states from the frame sensors of
    ``gnwarp.sim.mujoco_c.system_sensor_model`` (as the datasets)."""

    backend = "mujoco"

    def __init__(self, systems: Sequence[System], n_worlds: int, ctrl_policy: str = "clamp",
                 nthread: int | None = None):
        import mujoco.rollout as mjrollout
        super().__init__(systems, n_worlds, ctrl_policy, torch.device("cpu"))
        sms = [system_sensor_model(s) for s in self.systems]
        self._models = [m for m, _ in sms]
        m0, self._base = sms[0]
        nthread = min(n_worlds, nthread or os.cpu_count() or 1)
        self._pool = mjrollout.Rollout(nthread=nthread if nthread > 1 else 0)
        self._datas = [mujoco.MjData(m0) for _ in range(max(1, nthread))]
        self._spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
        d = self._datas[0]
        mujoco.mj_resetData(m0, d)
        template = np.empty(mujoco.mj_stateSize(m0, self._spec))
        mujoco.mj_getState(m0, d, template, self._spec)
        self._template = template
        self._state = np.tile(template, (n_worlds, 1))
        self._body = torch.zeros(n_worlds, self.nbody, DYN_NODE_SIZE)

    def _run(self, ctrl: np.ndarray, nstep: int):
        model = self._models if len(self._models) > 1 else self._models[0]
        return self._pool.rollout(model, self._datas, self._state, ctrl, nstep=nstep)

    def _bodies(self, sens: np.ndarray) -> torch.Tensor:
        """Body states [N, k, B, 13] from sensordata [N, k, nsensordata]."""
        n, k = sens.shape[:2]
        out = np.empty((n, k, self.nbody, DYN_NODE_SIZE), dtype=np.float32)
        out[:, :, 0] = world_state(1)
        out[:, :, 1:] = sens[..., self._base:self._base + (self.nbody - 1) * DYN_NODE_SIZE].reshape(
            n, k, self.nbody - 1, DYN_NODE_SIZE)
        return torch.from_numpy(out)

    def _reset(self, qpos: torch.Tensor, qvel: torch.Tensor) -> None:
        # FULLPHYSICS state = [time, qpos, qvel, act, ...]: the reset pose with qpos and qvel written in
        self._state = np.tile(self._template, (self.n_worlds, 1))
        self._state[:, 1:1 + self.nq] = qpos.numpy()
        self._state[:, 1 + self.nq:1 + self.nq + self.nv] = qvel.numpy()
        _, sens = self._run(np.zeros((self.n_worlds, 1, self.nu)), 1)   # sensors read the state before a step
        self._body = self._bodies(sens)[:, 0]

    def _rollout(self, ctrl: torch.Tensor, states: bool = False):
        T, sub = ctrl.shape[1], self.substeps
        u = np.repeat(ctrl.numpy(), sub, axis=1)
        u = np.concatenate([u, u[:, -1:]], axis=1)   # one extra step reads the sensors of the last state
        state, sens = self._run(u, T * sub + 1)
        # state[:, k] is the state after step k: data step t is after step t * sub - 1
        full = np.concatenate([self._state[:, None], state[:, np.arange(1, T + 1) * sub - 1]], axis=1)
        self._state = np.ascontiguousarray(full[:, -1])
        out = self._bodies(sens[:, ::sub][:, :T + 1])
        self._body = out[:, -1].clone()
        if not states:
            return out
        q = torch.from_numpy(np.ascontiguousarray(full[..., 1:1 + self.nq + self.nv]))
        return Observation(q[..., :self.nq], q[..., self.nq:], out)

    def body_states(self) -> torch.Tensor:
        self._need_reset()
        return self._body.clone()

    @property
    def qpos(self) -> torch.Tensor:
        return torch.from_numpy(self._state[:, 1:1 + self.nq].copy())

    @property
    def qvel(self) -> torch.Tensor:
        return torch.from_numpy(self._state[:, 1 + self.nq:1 + self.nq + self.nv].copy())

    def close(self) -> None:
        if self._pool is not None and self._pool.rollout_ is not None:
            self._pool.close()


class MujocoWarpEnv(Env):
    """MuJoCo-Warp: one Model (per-world parameters batched) and one Data of ``n_worlds`` worlds
    on a Warp device, kept between calls; torch tensors alias its ``qpos``, ``qvel``, ``ctrl`` and
    the body-state buffer. A data step is ``substeps`` ``mjw.step`` calls, then the kinematics of
    the new state and ``record_body_state``; on CUDA it is captured once and replayed on torch's
    current stream."""

    backend = "mujoco_warp"

    def __init__(self, systems: Sequence[System], n_worlds: int, ctrl_policy: str = "clamp",
                 device: str | None = None, capture: bool | None = None):
        import mujoco_warp as mjw

        from gnwarp.interop import cuda_available, warp
        from gnwarp.kernels.sim import mujoco_warp as K
        wp = warp()
        # default: torch's current GPU (a rank's own under torchrun), else the CPU
        wdev = wp.get_device(device or (f"cuda:{torch.cuda.current_device()}" if cuda_available() else "cpu"))
        super().__init__(systems, n_worlds, ctrl_policy, wp.device_to_torch(wdev))
        self._wp, self._mjw, self._K, self._wdev = wp, mjw, K, wdev
        self._capture = wdev.is_cuda if capture is None else bool(capture)
        self._graph = None
        self._side = None   # the env's CUDA stream (made on first use)
        m0 = self.system.model
        with wp.ScopedDevice(wdev):
            self._m = put_batched_model([s.model for s in self.systems], wdev)
            self._d = mjw.make_data(m0, nworld=n_worlds)
            self._body_w = wp.zeros((n_worlds, 1, self.nbody, DYN_NODE_SIZE), dtype=float)
            self._step0 = wp.zeros(1, dtype=int)   # record_body_state writes time index 0 of _body_w
        self._qpos_t = wp.to_torch(self._d.qpos)
        self._qvel_t = wp.to_torch(self._d.qvel)
        self._ctrl_t = wp.to_torch(self._d.ctrl)
        self._body_t = wp.to_torch(self._body_w)[:, 0]

    @contextlib.contextmanager
    def _stream(self):
        """Warp launches of this env on its own CUDA stream, ordered after the caller's torch
        stream and before whatever the caller runs next (a CUDA graph cannot be captured on the
        legacy default stream, torch's default); on the CPU, the Warp CPU device."""
        wp = self._wp
        if not self._wdev.is_cuda:
            with wp.ScopedDevice(self._wdev):
                yield
            return
        from gnwarp.interop import warp_stream
        if self._side is None:
            self._side = torch.cuda.Stream(self.device)
        main = torch.cuda.current_stream(self.device)
        self._side.wait_stream(main)
        with torch.cuda.stream(self._side), wp.ScopedStream(warp_stream(self._side)):
            yield
        main.wait_stream(self._side)

    def _observe(self) -> None:
        """Kinematics of the current state, then its body states into ``_body_w``."""
        m, d, mjw = self._m, self._d, self._mjw
        mjw.kinematics(m, d)
        mjw.com_pos(m, d)
        mjw.com_vel(m, d)
        self._wp.launch(self._K.record_body_state, dim=(self.n_worlds, self.nbody),
                        inputs=[m.body_rootid, self._step0, d.xpos, d.xquat, d.cvel, d.subtree_com],
                        outputs=[self._body_w])

    def _data_step(self) -> None:
        for _ in range(self.substeps):
            self._mjw.step(self._m, self._d)
        self._observe()

    def _reset(self, qpos: torch.Tensor, qvel: torch.Tensor) -> None:
        with self._stream():
            self._mjw.reset_data(self._m, self._d)
            self._qpos_t.copy_(qpos.to(self.device, self._qpos_t.dtype))
            self._qvel_t.copy_(qvel.to(self.device, self._qvel_t.dtype))
            self._ctrl_t.zero_()
            self._observe()

    def _rollout(self, ctrl: torch.Tensor, states: bool = False):
        wp = self._wp
        N, T = self.n_worlds, ctrl.shape[1]
        out = torch.empty(N, T + 1, self.nbody, DYN_NODE_SIZE, device=self.device)
        qpos = torch.empty(N, T + 1, self.nq, device=self.device, dtype=self._qpos_t.dtype) if states else None
        qvel = torch.empty(N, T + 1, self.nv, device=self.device, dtype=self._qvel_t.dtype) if states else None
        ctrl = ctrl.to(self._ctrl_t.dtype)
        with self._stream():
            for t in range(T + 1):
                out[:, t] = self._body_t
                if states:
                    qpos[:, t] = self._qpos_t
                    qvel[:, t] = self._qvel_t
                if t == T:
                    break
                self._ctrl_t.copy_(ctrl[:, t])
                if self._graph is not None:
                    wp.capture_launch(self._graph)
                else:
                    self._data_step()   # the first data step compiles every kernel outside any capture
                    if self._capture:
                        with wp.ScopedCapture() as cap:
                            self._data_step()
                        self._graph = cap.graph   # capturing ran nothing: the next steps replay it
        return Observation(qpos, qvel, out) if states else out

    def body_states(self) -> torch.Tensor:
        self._need_reset()
        return self._body_t.clone()

    @property
    def qpos(self) -> torch.Tensor:
        return self._qpos_t.clone()

    @property
    def qvel(self) -> torch.Tensor:
        return self._qvel_t.clone()


def make_env(system, n_worlds: int, backend: str = "auto", device: str | None = None,
             ctrl_policy: str = "clamp", **kw) -> Env:
    """A persistent batched environment of ``n_worlds`` worlds of ``system`` (a ``System``, a
    built-in name, or a list of ``n_worlds`` Systems of one topology for per-world parameters).

    ``backend``: "auto" (MuJoCo-Warp on CUDA, else MuJoCo C), "mujoco", "mujoco_warp",
    "mujoco_warp_cpu" (MuJoCo-Warp on Warp's CPU device). ``device``: the Warp device of
    MuJoCo-Warp (default: CUDA when present). ``kw``: ``nthread`` (MuJoCo C) or ``capture``
    (MuJoCo-Warp; default on CUDA)."""
    systems = list(system) if isinstance(system, (list, tuple)) else [system]
    systems = [make(s) if isinstance(s, str) else s for s in systems]
    backend = resolve_backend(backend)
    if backend == "mujoco":
        return MujocoEnv(systems, n_worlds, ctrl_policy, **kw)
    dev = "cpu" if backend == "mujoco_warp_cpu" else device
    return MujocoWarpEnv(systems, n_worlds, ctrl_policy, device=dev, **kw)


def dataset_states(dataset, split: str = "test", seqs=None, t: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Initial conditions from a dataset: (qpos [S, nq], qvel [S, nv]) of sequences ``seqs``
    (default: all) of ``split`` at data step ``t``, for ``env.reset``."""
    sp = dataset[split]
    seqs = np.arange(len(sp)) if seqs is None else np.asarray(seqs, dtype=np.int64).reshape(-1)
    S, T = len(sp), sp.num_steps
    if seqs.size == 0 or seqs.min() < 0 or seqs.max() >= S:
        raise IndexError(f"dataset_states: sequences {seqs.tolist()[:8]} must be in [0, {S}) (split '{split}' has "
                         f"{S})" if seqs.size else "dataset_states: no sequences asked for")
    if isinstance(t, bool) or not isinstance(t, (int, np.integer)) or not 0 <= t <= T:
        raise IndexError(f"dataset_states: step {t!r} outside [0, {T}] of split '{split}'")
    rows, back = np.unique(seqs, return_inverse=True)   # a file's arrays read sorted, unique rows
    read = lambda a: np.asarray(a[rows, t], dtype=np.float64)[back]   # noqa: E731
    return read(sp.qpos), read(sp.qvel)
