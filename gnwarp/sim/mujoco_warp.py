"""The MuJoCo-Warp simulation backend: many worlds at once (CUDA; Warp's CPU device works too, slowly).

Per-world parameters go through batched Model fields, one Model per topology; the step loop of
one data step is captured as a graph on CUDA. Its kernels are ``gnwarp.kernels.sim.mujoco_warp``.
"""
from __future__ import annotations

from typing import Callable, Sequence

import mujoco
import numpy as np

from gnwarp.interop import cuda_available, warp
from gnwarp.kernels.sim import mujoco_warp as K
from gnwarp.sim.common import Trajectories, check_inputs, varying_model_fields
from gnwarp.state import DYN_NODE_SIZE

__all__ = ["put_batched_model", "simulate_mujoco_warp"]


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


def simulate_mujoco_warp(models: Sequence[mujoco.MjModel], substeps: int, qpos0: np.ndarray,
                         qvel0: np.ndarray, ctrl: np.ndarray, device: str | None = None,
                         max_worlds: int = 32768, progress: Callable[[int], None] | None = None,
                         capture: bool | None = None) -> Trajectories:
    """MuJoCo-Warp with one world per sequence (chunks of ``max_worlds``)."""
    wp = warp()
    import mujoco_warp as mjw

    check_inputs(models, qpos0, qvel0, ctrl)
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
            mw = put_batched_model(models[s0:s1] if len(models) > 1 else [m0], dev)
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
                wp.launch(K.record_qstate, dim=(n, nq_nv), inputs=[step, d.qpos, d.qvel],
                          outputs=[qpos_out, qvel_out])
                if nu:
                    wp.launch(K.ctrl_feed, dim=(n, nu), inputs=[step, ctrl_seq], outputs=[d.ctrl])
                if rk4:  # RK4 leaves its last stage's kinematics behind: compute the state's own
                    mjw.kinematics(mw, d)
                    mjw.com_pos(mw, d)
                    mjw.com_vel(mw, d)
                else:
                    mjw.step(mw, d)
                wp.launch(K.record_body_state, dim=(n, m0.nbody),
                          inputs=[mw.body_rootid, step, d.xpos, d.xquat, d.cvel, d.subtree_com],
                          outputs=[body_out])
                for _ in range(substeps if rk4 else substeps - 1):
                    mjw.step(mw, d)
                wp.launch(K.advance, dim=1, outputs=[step])

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
