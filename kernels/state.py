"""Warp kernel of ``gnwarp/state.py``: the change between two body states (D.5) in one launch.

``state_delta`` in torch is ~50 element-wise kernels (the Hamilton product alone is 28); a
training step computes it once per batch for its targets, where no gradient is needed. This
kernel computes the same formulas per row: position and velocity differences, and the rotation
dq = q_next (x) q^-1 (q^-1 = conj(q) / max(|q|^2, 1e-24)), normalized (|dq| at least 1e-12) with
dq.w >= 0.
"""
# no `from __future__ import annotations`: Warp reads kernel annotations as objects of the factory scope
import functools

import warp as wp

__all__ = ["state_delta_kernel"]


@functools.cache
def state_delta_kernel(dtype):
    """Kernel ``(x [n, 13], x_next [n, 13], out [n, 13])`` over n threads, in ``dtype``."""
    T = dtype

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def state_delta(x: wp.array2d(dtype=T), y: wp.array2d(dtype=T), out: wp.array2d(dtype=T)):
        i = wp.tid()
        for k in range(3):
            out[i, k] = y[i, k] - x[i, k]
        for k in range(7, 13):
            out[i, k] = y[i, k] - x[i, k]
        aw = y[i, 3]
        ax = y[i, 4]
        ay = y[i, 5]
        az = y[i, 6]
        n2 = wp.max(x[i, 3] * x[i, 3] + x[i, 4] * x[i, 4] + x[i, 5] * x[i, 5] + x[i, 6] * x[i, 6], T(1e-24))
        bw = x[i, 3] / n2
        bx = -x[i, 4] / n2
        by = -x[i, 5] / n2
        bz = -x[i, 6] / n2
        w = aw * bw - ax * bx - ay * by - az * bz
        qx = aw * bx + ax * bw + ay * bz - az * by
        qy = aw * by - ax * bz + ay * bw + az * bx
        qz = aw * bz + ax * by - ay * bx + az * bw
        r = wp.max(wp.sqrt(w * w + qx * qx + qy * qy + qz * qz), T(1e-12))
        if w < T(0.0):
            r = -r
        out[i, 3] = w / r
        out[i, 4] = qx / r
        out[i, 5] = qy / r
        out[i, 6] = qz / r

    return state_delta
