"""The 13-number state of a body, and the quaternion algebra on it: one home for both.

Every body (graph node) carries, in world coordinates (paper, G.2)::

    pos      [0:3]    position of the body frame          (MuJoCo ``xpos``)
    quat     [3:7]    orientation, w, x, y, z              (``xquat``)
    linvel   [7:10]   linear velocity of the body frame    (``mj_objectVelocity(mjOBJ_XBODY, flg_local=0)``)
    angvel   [10:13]  angular velocity

Datasets store these per body and step, models predict their change (``state_delta`` /
``apply_delta``, D.5), evaluation compares them, rendering poses geoms from them. The functions
below take numpy arrays or torch tensors alike (``[..., 4]`` quaternions, ``[..., 3]`` vectors,
``[..., 13]`` states) and return the same kind; quaternion products are Hamilton products,
``quat_mul(a, b)`` = a (x) b, rotating by b first.
"""
from __future__ import annotations

import numpy as np
import torch

__all__ = [
    "DYN_NODE_NAMES", "DYN_NODE_SIZE", "POS", "QUAT", "LINVEL", "ANGVEL", "GROUPS",
    "quat_mul", "quat_conj", "quat_normalize", "quat_canonical", "quat_rotate", "quat_to_mat",
    "quat_axis_angle", "state_delta", "apply_delta", "rotation_loss", "world_state", "body_points",
    "geom_poses", "QUAT_MIN",
]

DYN_NODE_NAMES = ("pos_x", "pos_y", "pos_z", "quat_w", "quat_x", "quat_y", "quat_z",
                  "linvel_x", "linvel_y", "linvel_z", "angvel_x", "angvel_y", "angvel_z")
DYN_NODE_SIZE = 13
POS, QUAT, LINVEL, ANGVEL = slice(0, 3), slice(3, 7), slice(7, 10), slice(10, 13)
GROUPS = {"pos": POS, "quat": QUAT, "linvel": LINVEL, "angvel": ANGVEL}
# the least norm of a body state's orientation quaternion that still is one: below it, a state has
# no orientation at all (zeros where a state was never filled); rollouts and planners refuse it
QUAT_MIN = 0.1


def _torch(x) -> bool:
    return isinstance(x, torch.Tensor)


def _stack(xs, like):
    return torch.stack(xs, -1) if _torch(like) else np.stack(xs, -1)


def _cat(xs, like):
    return torch.cat(xs, -1) if _torch(like) else np.concatenate(xs, -1)


def _norm(x, eps: float):
    """|x| over the last axis (keepdims), at least ``eps``."""
    n = x.norm(dim=-1, keepdim=True) if _torch(x) else np.linalg.norm(x, axis=-1, keepdims=True)
    return _clamp_min(n, eps)


def _clamp_min(x, lo: float):
    return x.clamp_min(lo) if _torch(x) else np.maximum(x, lo)


def _cross(a, b):
    return torch.linalg.cross(a, b, dim=-1) if _torch(a) else np.cross(a, b)


# -- quaternions (w, x, y, z) -------------------------------------------------------------------

def quat_mul(a, b):
    """Hamilton product a (x) b of quaternions [..., 4] (w, x, y, z)."""
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return _stack([aw * bw - ax * bx - ay * by - az * bz,
                   aw * bx + ax * bw + ay * bz - az * by,
                   aw * by - ax * bz + ay * bw + az * bx,
                   aw * bz + ax * by - ay * bx + az * bw], a)


def quat_conj(q):
    """The conjugate (w, -x, -y, -z): the inverse rotation of a unit quaternion."""
    return _cat([q[..., :1], -q[..., 1:]], q)


def quat_normalize(q, eps: float = 1e-12):
    """q / |q| (a zero quaternion stays finite)."""
    return q / _norm(q, eps)


def quat_canonical(q):
    """The one of q, -q with w >= 0 (they are the same rotation)."""
    if _torch(q):
        return torch.where(q[..., :1] < 0, -q, q)
    return np.where(q[..., :1] < 0, -q, q)


def quat_rotate(q, v):
    """Vectors v [..., 3] rotated by unit quaternions q [..., 4]."""
    w, u = q[..., :1], q[..., 1:]
    t = 2.0 * _cross(u, v)
    return v + w * t + _cross(u, t)


def quat_to_mat(q):
    """[..., 4] quaternions (normalized here) -> [..., 3, 3] rotation matrices."""
    q = quat_normalize(q)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]
    if _torch(q):
        return torch.stack([torch.stack(r, -1) for r in rows], -2)
    return np.stack([np.stack(r, -1) for r in rows], -2)


def quat_axis_angle(axis, angle: float) -> np.ndarray:
    """Unit quaternion (numpy) of a rotation by ``angle`` radians about ``axis``."""
    axis = np.asarray(axis, dtype=float)
    axis = axis / np.linalg.norm(axis)
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis])


# -- states ----------------------------------------------------------------------------------------

def state_delta(x, x_next):
    """Change [..., 13] from states x to x_next [..., 13] (D.5): differences of position and
    velocities, and the rotation dq = q_next (x) q^-1 with dq.w >= 0. Torch tensors that need no
    gradient run one Warp kernel (``gnwarp.kernels.state``; the same formulas)."""
    if (_torch(x) and _torch(x_next) and x.shape == x_next.shape and x.shape[-1:] == (DYN_NODE_SIZE,)
            and x.dtype == x_next.dtype
            and x.dtype in (torch.float32, torch.float64) and x.device == x_next.device
            and not (torch.is_grad_enabled() and (x.requires_grad or x_next.requires_grad))):
        return _state_delta_warp(x, x_next)
    q, qn = x[..., QUAT], x_next[..., QUAT]
    inv = quat_conj(q) / _clamp_min((q * q).sum(-1)[..., None], 1e-24)
    dq = quat_canonical(quat_normalize(quat_mul(qn, inv)))
    return _cat([x_next[..., POS] - x[..., POS], dq, x_next[..., LINVEL] - x[..., LINVEL],
                 x_next[..., ANGVEL] - x[..., ANGVEL]], x)


def _state_delta_warp(x, x_next):
    from gnwarp.interop import WP_DTYPE, Launcher
    from gnwarp.kernels.state import state_delta_kernel
    a = x.detach().reshape(-1, DYN_NODE_SIZE).contiguous()
    b = x_next.detach().reshape(-1, DYN_NODE_SIZE).contiguous()
    out = torch.empty_like(a)
    Launcher(a)(state_delta_kernel(WP_DTYPE[a.dtype]), a.shape[0], a, b, out)
    return out.reshape(x.shape)


def apply_delta(x, delta):
    """Next states [..., 13] (D.5): position and velocities by addition, orientation by the
    Hamilton product with the change's rotation forced to unit norm (the product is
    re-normalized too, so rounding does not drift over long rollouts)."""
    q = quat_normalize(quat_mul(quat_normalize(delta[..., QUAT]), x[..., QUAT]))
    return _cat([x[..., POS] + delta[..., POS], q, x[..., LINVEL] + delta[..., LINVEL],
                 x[..., ANGVEL] + delta[..., ANGVEL]], x)


def rotation_loss(q_expected, q_predicted):
    """[...] 1 - (q_e . q_p)^2 for unit quaternions (D.7.4): sin^2 of half the angle between the
    rotations; zero for q_p = +-q_e. (The paper writes 1 - cos^2(q_e . q_p); with q_e . q_p =
    cos(angle / 2) this is the same loss read as the angle distance it is said to minimize.)"""
    d = (q_expected * q_predicted).sum(-1)
    return 1.0 - d * d


def world_state(n: int, dtype=np.float32) -> np.ndarray:
    """[n, 13] states of the world body: at the origin, unrotated, at rest."""
    w = np.zeros((n, DYN_NODE_SIZE), dtype=dtype)
    w[:, 3] = 1.0
    return w


# -- poses of what bodies carry ------------------------------------------------------------------

def body_points(body, bodies, local):
    """World positions [..., n, 3] of points fixed in bodies: ``body`` [..., B, 13] states,
    ``bodies`` [n] the body of each point, ``local`` [n, 3] its position in that body's frame."""
    p, q = body[..., bodies, POS], quat_normalize(body[..., bodies, QUAT])
    return p + quat_rotate(q, local)


def geom_poses(model, body: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World poses of every geom of a ``mujoco.MjModel`` from its body states ``body`` [nbody, 13]:
    (geom_xpos [ngeom, 3], geom_xmat [ngeom, 9]), each geom's local pose composed with its body's."""
    gb = np.asarray(model.geom_bodyid)
    R = quat_to_mat(body[:, QUAT])[gb]                                    # [G, 3, 3]
    xpos = body[gb, POS] + np.einsum("gij,gj->gi", R, np.asarray(model.geom_pos))
    xmat = R @ quat_to_mat(np.asarray(model.geom_quat))
    return xpos, xmat.reshape(-1, 9)
