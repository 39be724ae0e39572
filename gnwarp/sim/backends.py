"""Batched simulation of many sequences under given controls, on three backends.

- ``mujoco_warp``: MuJoCo-Warp, many worlds at once (CUDA; Warp's CPU device works too, slowly).
  Per-world parameters through batched Model fields; one Model per topology. The sequences run
  on the persistent environment of ``gnwarp.sim.env`` (``MujocoWarpEnv``), whose data step is
  captured as a graph on CUDA (``gnwarp.sim.mujoco_warp``).
- ``mujoco``: MuJoCo C through ``mujoco.rollout`` on a thread pool, for CPU machines; body poses
  and velocities come from frame sensors added to a copy of the model (``gnwarp.sim.mujoco_c``).
- ``auto``: ``mujoco_warp`` when a CUDA device is present, else ``mujoco``.

All return the same ``Trajectories``: node states at every data step (the initial one included).
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from gnwarp.sim.common import Trajectories, resolve_backend
from gnwarp.sim.mujoco_c import simulate_mujoco, system_sensor_model
from gnwarp.sim.mujoco_warp import simulate_mujoco_warp

__all__ = ["simulate"]


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
    return simulate_mujoco_warp(systems, qpos0, qvel0, ctrl, device=device, progress=progress, **kw)
