"""The MuJoCo C simulation backend: ``mujoco.rollout`` on a thread pool, for CPU machines.

Body poses and velocities come from frame sensors added to a copy of each model (``sensor_model``).
"""
from __future__ import annotations

import os
import weakref
from typing import Callable, Sequence

import mujoco
import numpy as np

from gnwarp.sim.common import Trajectories, batchable_fields, check_inputs
from gnwarp.state import DYN_NODE_SIZE, world_state

__all__ = ["sensor_model", "system_sensor_model", "simulate_mujoco"]

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


def simulate_mujoco(specs: Sequence[mujoco.MjSpec], substeps: int, qpos0: np.ndarray, qvel0: np.ndarray,
                    ctrl: np.ndarray, nthread: int | None = None, chunk: int = 512,
                    progress: Callable[[int], None] | None = None,
                    sensor_models: Sequence[tuple[mujoco.MjModel, int]] | None = None) -> Trajectories:
    """MuJoCo C via ``mujoco.rollout`` on a thread pool. ``specs``: one spec or one per sequence."""
    import mujoco.rollout as rollout

    sms = list(sensor_models) if sensor_models is not None else [sensor_model(s) for s in specs]
    models = [m for m, _ in sms]
    check_inputs(models, qpos0, qvel0, ctrl)
    S, T, _ = ctrl.shape
    m0, base = sms[0]
    nb = m0.nbody
    nthread = nthread or max(1, os.cpu_count() or 1)
    datas = [mujoco.MjData(m0) for _ in range(nthread)]
    nstep = T * substeps + 1  # one extra step reads the sensors of the last state
    body = np.empty((S, T + 1, nb, DYN_NODE_SIZE), dtype=np.float32)
    qpos = np.empty((S, T + 1, m0.nq), dtype=np.float32)
    qvel = np.empty((S, T + 1, m0.nv), dtype=np.float32)
    body[:, :, 0] = world_state(1)
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
