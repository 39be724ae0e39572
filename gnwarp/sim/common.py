"""What both simulation backends share: their names and the choice between them
(``resolve_backend``), their result (``Trajectories``), input checks, the topology signature that
groups models simulated together, and MuJoCo-Warp's batched Model fields (per-world parameters on
MuJoCo-Warp, ``put_batched_model``; the MuJoCo C backend copies the same fields)."""
from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from typing import Sequence

import mujoco
import numpy as np

from gnwarp.interop import cuda_available, warp

__all__ = ["BACKENDS", "resolve_backend", "Trajectories", "check_inputs", "topology_signature", "batchable_fields",
           "varying_model_fields", "put_batched_model"]

BACKENDS = ("auto", "mujoco", "mujoco_warp", "mujoco_warp_cpu")


def resolve_backend(backend: str) -> str:
    """The backend that ``backend`` names: "auto" made concrete; raises for an unknown name, or
    for "mujoco_warp" without a CUDA device."""
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend '{backend}'; choose one of {BACKENDS}")
    if backend == "auto":
        return "mujoco_warp" if cuda_available() else "mujoco"
    if backend == "mujoco_warp" and not cuda_available():
        raise RuntimeError("backend 'mujoco_warp' needs a CUDA device; use 'mujoco_warp_cpu' or 'mujoco'")
    return backend


@dataclass
class Trajectories:
    body: np.ndarray   # [S, T+1, nbody, 13] node states (float32)
    qpos: np.ndarray   # [S, T+1, nq] (float32)
    qvel: np.ndarray   # [S, T+1, nv] (float32)


def check_inputs(models: Sequence[mujoco.MjModel], qpos0: np.ndarray, qvel0: np.ndarray, ctrl: np.ndarray) -> None:
    """Raise ValueError unless ``qpos0`` [S, nq], ``qvel0`` [S, nv] and ``ctrl`` [S, T, nu] fit
    ``models`` (1 or S models of one topology) and are finite."""
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
    sig = topology_signature(m)
    for k, mk in enumerate(models):
        if topology_signature(mk) != sig:
            raise ValueError(f"model {k} has a different topology than model 0; simulate groups separately")


def topology_signature(m: mujoco.MjModel) -> tuple:
    """A hashable key equal for models that can be simulated in one batch (same sizes and tree)."""
    return (m.nq, m.nv, m.nu, m.nbody, m.njnt, m.ngeom, tuple(m.body_parentid), tuple(m.jnt_type))


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


def put_batched_model(models: Sequence[mujoco.MjModel], device):
    """One MuJoCo-Warp Model on ``device`` for ``models`` of one topology: the fields that differ
    between them batched with a leading world dimension [len(models), ...]."""
    import mujoco_warp as mjw
    wp = warp()
    varying = varying_model_fields(models)
    mw = mjw.put_model(models[0], batch_sizes={k: len(models) for k in varying})
    for name, vals in varying.items():
        arr = getattr(mw, name)
        setattr(mw, name, wp.array(vals, dtype=arr.dtype, device=device))
    return mw
