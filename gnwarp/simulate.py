"""Batched simulation of many sequences under given controls, on three backends.

- ``mujoco_warp``: MuJoCo-Warp, many worlds at once (CUDA; Warp's CPU device works too, slowly).
  Per-world parameters through batched Model fields; one Model per topology. The step loop of
  one data step is captured as a graph on CUDA.
- ``mujoco``: MuJoCo C through ``mujoco.rollout`` on a thread pool, for CPU machines; body poses
  and velocities come from frame sensors added to a copy of the model.
- ``auto``: ``mujoco_warp`` when a CUDA device is present, else ``mujoco``.

All return the same ``Trajectories``: node states at every data step (the initial one included).
"""
from __future__ import annotations

import dataclasses
import functools
import os
import weakref
from dataclasses import dataclass
from typing import Callable, Sequence

import mujoco
import numpy as np

from gnwarp.interop import cuda_available, warp
from gnwarp.convert import DYN_NODE_SIZE

BACKENDS = ("auto", "mujoco", "mujoco_warp", "mujoco_warp_cpu")


@dataclass
class Trajectories:
    body: np.ndarray   # [S, T+1, nbody, 13] node states (float32)
    qpos: np.ndarray   # [S, T+1, nq] (float32)
    qvel: np.ndarray   # [S, T+1, nv] (float32)


def resolve_backend(backend: str) -> str:
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend '{backend}'; choose one of {BACKENDS}")
    if backend == "auto":
        return "mujoco_warp" if cuda_available() else "mujoco"
    if backend == "mujoco_warp" and not cuda_available():
        raise RuntimeError("backend 'mujoco_warp' needs a CUDA device; use 'mujoco_warp_cpu' or 'mujoco'")
    return backend


def _check_inputs(models, qpos0, qvel0, ctrl):
    m = models[0]
    S = qpos0.shape[0]
    if qpos0.shape != (S, m.nq) or qvel0.shape != (S, m.nv):
        raise ValueError(f"initial state shapes {qpos0.shape}, {qvel0.shape} do not match "
                         f"({S}, nq={m.nq}), ({S}, nv={m.nv})")
    if ctrl.ndim != 3 or ctrl.shape[0] != S or ctrl.shape[2] != m.nu:
        raise ValueError(f"controls must be [S={S}, T, nu={m.nu}], got {ctrl.shape}")
    if len(models) not in (1, S):
        raise ValueError(f"got {len(models)} models for {S} sequences (need 1 or {S})")
    for name, a in (("initial qpos", qpos0), ("initial qvel", qvel0), ("controls", ctrl)):
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} contain NaN or Inf")
    sig = _topology_signature(m)
    for k, mk in enumerate(models):
        if _topology_signature(mk) != sig:
            raise ValueError(f"model {k} has a different topology than model 0; simulate groups separately")


def _topology_signature(m: mujoco.MjModel):
    return (m.nq, m.nv, m.nu, m.nbody, m.njnt, m.ngeom, tuple(m.body_parentid), tuple(m.jnt_type))


# -- MuJoCo C --------------------------------------------------------------------------------

_SENSORS = (mujoco.mjtSensor.mjSENS_FRAMEPOS, mujoco.mjtSensor.mjSENS_FRAMEQUAT,
            mujoco.mjtSensor.mjSENS_FRAMELINVEL, mujoco.mjtSensor.mjSENS_FRAMEANGVEL)


def sensor_model(spec: mujoco.MjSpec) -> tuple[mujoco.MjModel, int]:
    """Compile a copy of ``spec`` with frame sensors for every body appended.

    Returns the model and the offset of the appended sensors in sensordata. The sensors read
    position, quaternion, and world-frame linear and angular velocity of each body frame, in
    that order: the dynamic node layout.
    """
    s = spec.copy()
    s.option.disableflags &= ~int(mujoco.mjtDisableBit.mjDSBL_SENSOR)
    # an unstable simulation must surface as NaN, not be reset silently to the initial pose
    s.option.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_AUTORESET)
    base = s.compile().nsensordata
    for i, b in enumerate(s.bodies):
        if i == 0:
            continue
        if not b.name:
            b.name = f"gnwarp_body_{i}"
        for t in _SENSORS:
            s.add_sensor(type=t, objtype=mujoco.mjtObj.mjOBJ_XBODY, objname=b.name)
    return s.compile(), base


_SENSOR_MODELS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def system_sensor_model(system) -> tuple[mujoco.MjModel, int]:
    """``sensor_model(system.spec)``, cached per System, with the System's model parameters
    copied in, so in-place edits of ``system.model`` (``opt.timestep``, ``body_mass`` ...) count."""
    if system.spec is None:
        raise ValueError(f"system '{system.name}' has no MjSpec; the MuJoCo C backend needs one")
    if system not in _SENSOR_MODELS:
        _SENSOR_MODELS[system] = sensor_model(system.spec)
    m, base = _SENSOR_MODELS[system]
    src = system.model
    for name in batchable_fields():
        if hasattr(src, name):
            a, b = getattr(src, name), getattr(m, name)
            if np.shape(a) == np.shape(b):
                b[...] = a
    for name in ("timestep", "gravity", "wind", "magnetic", "density", "viscosity", "impratio",
                 "o_margin", "o_solref", "o_solimp", "o_friction", "integrator", "cone", "iterations"):
        setattr(m.opt, name, getattr(src.opt, name))
    keep = int(mujoco.mjtDisableBit.mjDSBL_SENSOR) | int(mujoco.mjtDisableBit.mjDSBL_AUTORESET)
    m.opt.disableflags = (int(src.opt.disableflags) & ~keep) | int(mujoco.mjtDisableBit.mjDSBL_AUTORESET)
    m.opt.enableflags = src.opt.enableflags
    return m, base


def _world_state(n: int) -> np.ndarray:
    w = np.zeros((n, DYN_NODE_SIZE), dtype=np.float32)
    w[:, 3] = 1.0
    return w


def simulate_mujoco(specs: Sequence[mujoco.MjSpec], substeps: int, qpos0: np.ndarray, qvel0: np.ndarray,
                    ctrl: np.ndarray, nthread: int | None = None, chunk: int = 512,
                    progress: Callable[[int], None] | None = None,
                    sensor_models: Sequence[tuple[mujoco.MjModel, int]] | None = None) -> Trajectories:
    """MuJoCo C via ``mujoco.rollout`` on a thread pool. ``specs``: one spec or one per sequence."""
    import mujoco.rollout as rollout

    sms = list(sensor_models) if sensor_models is not None else [sensor_model(s) for s in specs]
    models = [m for m, _ in sms]
    _check_inputs(models, qpos0, qvel0, ctrl)
    S, T, _ = ctrl.shape
    m0, base = sms[0]
    nb = m0.nbody
    nthread = nthread or max(1, os.cpu_count() or 1)
    datas = [mujoco.MjData(m0) for _ in range(nthread)]
    nstep = T * substeps + 1  # one extra step reads the sensors of the last state
    body = np.empty((S, T + 1, nb, DYN_NODE_SIZE), dtype=np.float32)
    qpos = np.empty((S, T + 1, m0.nq), dtype=np.float32)
    qvel = np.empty((S, T + 1, m0.nv), dtype=np.float32)
    body[:, :, 0] = _world_state(1)
    spec_full = mujoco.mjtState.mjSTATE_FULLPHYSICS
    nstate = mujoco.mj_stateSize(m0, spec_full)
    d = datas[0]
    for s0 in range(0, S, chunk):
        s1 = min(S, s0 + chunk)
        n = s1 - s0
        state0 = np.empty((n, nstate))
        for k in range(n):  # initial states: one mj_setState/mj_getState pair per sequence
            mk = models[s0 + k] if len(models) > 1 else m0
            mujoco.mj_resetData(mk, d)
            d.qpos[:] = qpos0[s0 + k]
            d.qvel[:] = qvel0[s0 + k]
            mujoco.mj_getState(mk, d, state0[k], spec_full)
        u = np.repeat(ctrl[s0:s1], substeps, axis=1)
        u = np.concatenate([u, u[:, -1:]], axis=1)
        mlist = models[s0:s1] if len(models) > 1 else m0
        state, sens = rollout.rollout(mlist, datas, state0, u, nstep=nstep)
        sens = sens[:, ::substeps][:, :T + 1, base:base + (nb - 1) * DYN_NODE_SIZE]
        body[s0:s1, :, 1:] = sens.reshape(n, T + 1, nb - 1, DYN_NODE_SIZE)
        # state[k] is the state after step k; the state at data step t is after step t*substeps-1
        idx = np.arange(1, T + 1) * substeps - 1
        qa = 1  # FULLPHYSICS state = [time, qpos, qvel, act, ...]
        qpos[s0:s1, 0] = qpos0[s0:s1]
        qvel[s0:s1, 0] = qvel0[s0:s1]
        qpos[s0:s1, 1:] = state[:, idx, qa:qa + m0.nq]
        qvel[s0:s1, 1:] = state[:, idx, qa + m0.nq:qa + m0.nq + m0.nv]
        if progress:
            progress(n)
    return Trajectories(body, qpos, qvel)


# -- MuJoCo-Warp -----------------------------------------------------------------------------

@functools.lru_cache(maxsize=None)
def batchable_fields() -> frozenset[str]:
    """Model fields MuJoCo-Warp accepts with a leading world dimension."""
    import mujoco_warp._src.types as mjw_types
    from mujoco_warp._src import warp_util
    out = set()
    for f in dataclasses.fields(mjw_types.Model):
        if warp_util.is_array_spec(f.type) and getattr(f.type, "shape", ())[:1] == ("*",):
            out.add(f.name)
    return frozenset(out)


def varying_model_fields(models: Sequence[mujoco.MjModel]) -> dict[str, np.ndarray]:
    """Fields of MjModel that differ between ``models``, stacked with a leading batch axis."""
    if len(models) <= 1:
        return {}
    out = {}
    m0 = models[0]
    for name in batchable_fields():
        if not hasattr(m0, name):
            continue
        a0 = np.asarray(getattr(m0, name))
        if a0.dtype == object:
            continue
        vals = [np.asarray(getattr(m, name)) for m in models]
        if any(v.shape != a0.shape for v in vals):
            raise ValueError(f"model field {name} changes shape between instances (topology differs)")
        if any(not np.array_equal(v, a0) for v in vals[1:]):
            out[name] = np.stack(vals)
    return out


def _put_batched_model(models: Sequence[mujoco.MjModel], device):
    import mujoco_warp as mjw
    wp = warp()
    varying = varying_model_fields(models)
    mw = mjw.put_model(models[0], batch_sizes={k: len(models) for k in varying})
    for name, vals in varying.items():
        arr = getattr(mw, name)
        setattr(mw, name, wp.array(vals, dtype=arr.dtype, device=device))
    return mw


def simulate_mujoco_warp(models: Sequence[mujoco.MjModel], substeps: int, qpos0: np.ndarray,
                         qvel0: np.ndarray, ctrl: np.ndarray, device: str | None = None,
                         max_worlds: int = 32768, progress: Callable[[int], None] | None = None,
                         capture: bool | None = None) -> Trajectories:
    """MuJoCo-Warp with one world per sequence (chunks of ``max_worlds``)."""
    wp = warp()
    import mujoco_warp as mjw

    from gnwarp.kernels import sim_io

    _check_inputs(models, qpos0, qvel0, ctrl)
    S, T, nu = ctrl.shape
    m0 = models[0]
    device = device or ("cuda:0" if cuda_available() else "cpu")
    body = np.empty((S, T + 1, m0.nbody, DYN_NODE_SIZE), dtype=np.float32)
    qpos = np.empty((S, T + 1, m0.nq), dtype=np.float32)
    qvel = np.empty((S, T + 1, m0.nv), dtype=np.float32)
    with wp.ScopedDevice(device):
        dev = wp.get_device()
        use_graph = dev.is_cuda if capture is None else capture
        for s0 in range(0, S, max_worlds):
            s1 = min(S, s0 + max_worlds)
            n = s1 - s0
            mw = _put_batched_model(models[s0:s1] if len(models) > 1 else [m0], dev)
            d = mjw.make_data(m0, nworld=n)
            wp.copy(d.qpos, wp.array(qpos0[s0:s1].astype(np.float32)))
            wp.copy(d.qvel, wp.array(qvel0[s0:s1].astype(np.float32)))
            ctrl_seq = wp.array(np.ascontiguousarray(ctrl[s0:s1], dtype=np.float32))
            body_out = wp.zeros((n, T + 1, m0.nbody, DYN_NODE_SIZE), dtype=float)
            qpos_out = wp.zeros((n, T + 1, m0.nq), dtype=float)
            qvel_out = wp.zeros((n, T + 1, m0.nv), dtype=float)
            step = wp.zeros(1, dtype=int)
            nq_nv = max(m0.nq, m0.nv)
            rk4 = int(m0.opt.integrator) == int(mujoco.mjtIntegrator.mjINT_RK4)

            def data_step():
                # record the state at this data step, feed its control, then take the sub-steps;
                # the first sub-step's kinematics (xpos, cvel) belong to the recorded state
                wp.launch(sim_io.record_qstate, dim=(n, nq_nv), inputs=[step, d.qpos, d.qvel],
                          outputs=[qpos_out, qvel_out])
                if nu:
                    wp.launch(sim_io.ctrl_feed, dim=(n, nu), inputs=[step, ctrl_seq], outputs=[d.ctrl])
                if rk4:  # RK4 leaves its last stage's kinematics behind: compute the state's own
                    mjw.kinematics(mw, d)
                    mjw.com_pos(mw, d)
                    mjw.com_vel(mw, d)
                else:
                    mjw.step(mw, d)
                wp.launch(sim_io.record_body_state, dim=(n, m0.nbody),
                          inputs=[mw.body_rootid, step, d.xpos, d.xquat, d.cvel, d.subtree_com],
                          outputs=[body_out])
                for _ in range(substeps if rk4 else substeps - 1):
                    mjw.step(mw, d)
                wp.launch(sim_io.advance, dim=1, inputs=[step])

            data_step()  # first data step also compiles every kernel outside any capture
            graph = None
            if use_graph and T > 0:
                with wp.ScopedCapture() as cap:
                    data_step()
                graph = cap.graph
            for _ in range(T):  # capturing executed nothing: T more data steps, T+1 states in all
                if graph is not None:
                    wp.capture_launch(graph)
                else:
                    data_step()
            wp.synchronize_device()
            body[s0:s1] = body_out.numpy()
            qpos[s0:s1] = qpos_out.numpy()
            qvel[s0:s1] = qvel_out.numpy()
            if progress:
                progress(n)
    return Trajectories(body, qpos, qvel)


def simulate(systems, qpos0: np.ndarray, qvel0: np.ndarray, ctrl: np.ndarray, backend: str = "auto",
             progress: Callable[[int], None] | None = None, **kw) -> Trajectories:
    """Simulate ``S`` sequences of ``T`` data steps from initial states under controls.

    ``systems``: one ``System`` for all sequences, or a list of one per sequence (same topology).
    ``qpos0`` [S, nq], ``qvel0`` [S, nv], ``ctrl`` [S, T, nu] -> ``Trajectories`` with T+1 states.
    """
    systems = list(systems) if isinstance(systems, (list, tuple)) else [systems]
    substeps = {s.substeps for s in systems}
    if len(substeps) != 1:
        raise ValueError("all systems of one simulate() call must share their number of sub-steps")
    sub = substeps.pop()
    backend = resolve_backend(backend)
    if backend == "mujoco":
        return simulate_mujoco([s.spec for s in systems], sub, qpos0, qvel0, ctrl, progress=progress,
                               sensor_models=[system_sensor_model(s) for s in systems], **kw)
    device = "cpu" if backend == "mujoco_warp_cpu" else None
    return simulate_mujoco_warp([s.model for s in systems], sub, qpos0, qvel0, ctrl, device=device,
                                progress=progress, **kw)
