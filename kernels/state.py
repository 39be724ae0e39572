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
    """Kernel ``(x_in [n, 13], x_next_in [n, 13], delta_out [n, 13])`` over n threads, in ``dtype``."""
    T = dtype

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def state_delta(
        # Data in:
        x_in: wp.array2d(dtype=T),
        x_next_in: wp.array2d(dtype=T),
        # Data out:
        delta_out: wp.array2d(dtype=T),
    ):
        i = wp.tid()
        for k in range(3):
            delta_out[i, k] = x_next_in[i, k] - x_in[i, k]
        for k in range(7, 13):
            delta_out[i, k] = x_next_in[i, k] - x_in[i, k]
        aw = x_next_in[i, 3]
        ax = x_next_in[i, 4]
        ay = x_next_in[i, 5]
        az = x_next_in[i, 6]
        n2 = wp.max(x_in[i, 3] * x_in[i, 3] + x_in[i, 4] * x_in[i, 4] + x_in[i, 5] * x_in[i, 5]
                    + x_in[i, 6] * x_in[i, 6], T(1e-24))
        bw = x_in[i, 3] / n2
        bx = -x_in[i, 4] / n2
        by = -x_in[i, 5] / n2
        bz = -x_in[i, 6] / n2
        w = aw * bw - ax * bx - ay * by - az * bz
        qx = aw * bx + ax * bw + ay * bz - az * by
        qy = aw * by - ax * bz + ay * bw + az * bx
        qz = aw * bz + ax * by - ay * bx + az * bw
        r = wp.max(wp.sqrt(w * w + qx * qx + qy * qy + qz * qz), T(1e-12))
        if w < T(0.0):
            r = -r
        delta_out[i, 3] = w / r
        delta_out[i, 4] = qx / r
        delta_out[i, 5] = qy / r
        delta_out[i, 6] = qz / r

    return state_delta
