"""The MuJoCo-Warp simulation backend: many worlds at once (CUDA; Warp's CPU device works too, slowly).

The sequences of a dataset run on the persistent environment ``gnwarp.sim.env.MujocoWarpEnv``, one
world per sequence: per-world parameters through batched Model fields (one Model per topology),
one data step captured as a graph on CUDA and replayed. Its kernels are
``gnwarp.kernels.sim.mujoco_warp``.
"""
from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from gnwarp.sim.common import Trajectories, check_inputs
from gnwarp.sim.env import MujocoWarpEnv
from gnwarp.state import DYN_NODE_SIZE

__all__ = ["simulate_mujoco_warp"]


def simulate_mujoco_warp(systems: Sequence, qpos0: np.ndarray, qvel0: np.ndarray, ctrl: np.ndarray,
                         device: str | None = None, max_worlds: int = 32768,
                         progress: Callable[[int], None] | None = None,
                         capture: bool | None = None) -> Trajectories:
    """MuJoCo-Warp with one world per sequence, in chunks of ``max_worlds`` worlds.

    ``systems``: one ``System`` for all sequences or one per sequence (one topology, one data
    timestep and sub-steps); ``qpos0`` [S, nq], ``qvel0`` [S, nv], ``ctrl`` [S, T, nu] ->
    ``Trajectories`` of T+1 states (float32). ``device``: the Warp device (default CUDA when
    present); ``capture``: replay a captured data step (default on CUDA)."""
    systems = list(systems)
    check_inputs([s.model for s in systems], qpos0, qvel0, ctrl)
    S, T, _ = ctrl.shape
    m0 = systems[0].model
    body = np.empty((S, T + 1, m0.nbody, DYN_NODE_SIZE), dtype=np.float32)
    qpos = np.empty((S, T + 1, m0.nq), dtype=np.float32)
    qvel = np.empty((S, T + 1, m0.nv), dtype=np.float32)
    for s0 in range(0, S, max_worlds):
        s1 = min(S, s0 + max_worlds)
        n = s1 - s0
        env = MujocoWarpEnv(systems[s0:s1] if len(systems) > 1 else systems, n, device=device, capture=capture)
        env.reset(qpos0[s0:s1], qvel0[s0:s1])
        if T > 0:
            obs = env.rollout(ctrl[s0:s1], states=True)
        else:
            obs = env.observe()
            obs = type(obs)(*(x[:, None] for x in obs))
        body[s0:s1] = obs.body.cpu().numpy()
        qpos[s0:s1] = obs.qpos.cpu().numpy()
        qvel[s0:s1] = obs.qvel.cpu().numpy()
        env.close()
        if progress:
            progress(n)
    return Trajectories(body, qpos, qvel)
