"""The body states of one MuJoCo C ``MjData``: the reference every batched producer agrees with.

A body state is the 13 numbers of ``gnwarp.state`` (pos, quat (w, x, y, z), world-frame linear
and angular velocity of the body frame). The datasets' simulators (``gnwarp.sim.mujoco_c``'s frame
sensors, ``kernels/sim/mujoco_warp.record_body_state``) and the environments (``gnwarp.sim.env``)
write the same numbers; iLQG's costs and the control tasks' targets read them from here.
"""
from __future__ import annotations

import mujoco
import numpy as np

from gnwarp.state import ANGVEL, DYN_NODE_SIZE, LINVEL, POS, QUAT

__all__ = ["body_states"]


def body_states(model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
    """[nbody, 13] body states of one MjData (after mj_forward, or kinematics and velocities).

    Reference implementation on MuJoCo C; batched producers (the simulators) must agree with it.
    """
    out = np.zeros((model.nbody, DYN_NODE_SIZE))
    out[:, POS] = data.xpos
    out[:, QUAT] = data.xquat
    vel = np.zeros(6)
    for b in range(model.nbody):
        mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_XBODY, b, vel, 0)
        out[b, LINVEL] = vel[3:]
        out[b, ANGVEL] = vel[:3]
    return out
