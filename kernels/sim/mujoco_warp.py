"""Warp kernels that feed controls into, and read graph node states out of, batched MuJoCo-Warp data.

Launched by ``gnwarp.sim.mujoco_warp``. They run inside a captured step loop, so the data step
they act on comes from a device-side counter (``step_in``, advanced by ``advance``) instead of a
launch argument.
"""
import warp as wp


@wp.kernel
def ctrl_feed(
    # Data in:
    step_in: wp.array(dtype=int),
    ctrl_seq_in: wp.array3d(dtype=float),   # [nworld, T, nu]
    # Data out:
    ctrl_out: wp.array2d(dtype=float),      # [nworld, nu]
):
    w, u = wp.tid()
    t = wp.min(step_in[0], ctrl_seq_in.shape[1] - 1)
    ctrl_out[w, u] = ctrl_seq_in[w, t, u]


@wp.kernel
def record_qstate(
    # Data in:
    step_in: wp.array(dtype=int),
    qpos_in: wp.array2d(dtype=float),
    qvel_in: wp.array2d(dtype=float),
    # Data out:
    qpos_out: wp.array3d(dtype=float),      # [nworld, T+1, nq]
    qvel_out: wp.array3d(dtype=float),      # [nworld, T+1, nv]
):
    w, i = wp.tid()
    t = step_in[0]
    if i < qpos_in.shape[1]:
        qpos_out[w, t, i] = qpos_in[w, i]
    if i < qvel_in.shape[1]:
        qvel_out[w, t, i] = qvel_in[w, i]


@wp.kernel
def record_body_state(
    # Model:
    body_rootid: wp.array(dtype=int),
    # Data in:
    step_in: wp.array(dtype=int),
    xpos_in: wp.array2d(dtype=wp.vec3),
    xquat_in: wp.array2d(dtype=wp.quat),
    cvel_in: wp.array2d(dtype=wp.spatial_vector),
    subtree_com_in: wp.array2d(dtype=wp.vec3),
    # Data out:
    state_out: wp.array(dtype=float, ndim=4),   # [nworld, T+1, nbody, 13]
):
    """Node state of each body: xpos, xquat (w,x,y,z), world-frame linear and angular velocity
    of the body frame, i.e. mj_objectVelocity(mjOBJ_XBODY, flg_local=0)."""
    w, b = wp.tid()
    t = step_in[0]
    p = xpos_in[w, b]
    q = xquat_in[w, b]
    c = cvel_in[w, b]
    ang = wp.spatial_top(c)
    # cvel is about the subtree com of the body's root; shift the linear part to the body frame
    lin = wp.spatial_bottom(c) + wp.cross(ang, p - subtree_com_in[w, body_rootid[b]])
    state_out[w, t, b, 0] = p[0]
    state_out[w, t, b, 1] = p[1]
    state_out[w, t, b, 2] = p[2]
    # MuJoCo-Warp keeps MuJoCo's (w, x, y, z) order in its quaternion storage
    state_out[w, t, b, 3] = q[0]
    state_out[w, t, b, 4] = q[1]
    state_out[w, t, b, 5] = q[2]
    state_out[w, t, b, 6] = q[3]
    state_out[w, t, b, 7] = lin[0]
    state_out[w, t, b, 8] = lin[1]
    state_out[w, t, b, 9] = lin[2]
    state_out[w, t, b, 10] = ang[0]
    state_out[w, t, b, 11] = ang[1]
    state_out[w, t, b, 12] = ang[2]


@wp.kernel
def advance(
    # Data out:
    step_out: wp.array(dtype=int),
):
    step_out[0] = step_out[0] + 1
