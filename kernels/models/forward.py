"""Warp kernel of ``gnwarp/models/forward.py``: a training batch's input states in one launch.

The loss of a batch (Algorithm D.3) perturbs the input body states with Gaussian noise (world
bodies excepted, orientations re-normalized, D.7.1) and re-centres each graph's x, y on its
moving bodies' mean position (D.4). Neither needs a gradient (they act on data), and in torch
they are ~20 small kernels. Here one thread per node writes its noisy and centred
states, re-summing its graph's noisy x, y itself (graphs have a few bodies).
"""
# no `from __future__ import annotations`: Warp reads kernel annotations as objects of the factory scope
import functools

import warp as wp

__all__ = ["noisy_centred_kernel"]


@functools.cache
def noisy_centred_kernel(dtype, noise: bool, recenter: bool):
    """Kernel ``(nodes [n, F], col, eps [n, 13], std, movable [n] int32, offsets [G+1] int32,
    node_graph [n] int32, noisy [n, 13], centred [n, 13])`` over n threads (one per node), dyn =
    nodes[:, col:col + 13] (the body states of the input graph): noisy = dyn + std * eps on
    moving bodies (quaternion divided by max(|q|, 1e-12)); centred = noisy with its graph's mean
    x, y over moving bodies subtracted on moving bodies (a copy when not ``recenter``). Each thread
    re-sums its graph's noisy x, y (a few nodes: two loads each) rather than wait on a reduction."""
    T = dtype
    NOISE = 1 if noise else 0
    CENTRE = 1 if recenter else 0

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def noisy_centred(nodes: wp.array2d(dtype=T), col: int, eps: wp.array2d(dtype=T), std: T,
                      movable: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.int32),
                      node_graph: wp.array(dtype=wp.int32), noisy: wp.array2d(dtype=T), centred: wp.array2d(dtype=T)):
        i = wp.tid()
        m = movable[i]
        q0 = nodes[i, col + 3]
        q1 = nodes[i, col + 4]
        q2 = nodes[i, col + 5]
        q3 = nodes[i, col + 6]
        if wp.static(NOISE == 1):
            if m != 0:
                q0 = q0 + eps[i, 3] * std
                q1 = q1 + eps[i, 4] * std
                q2 = q2 + eps[i, 5] * std
                q3 = q3 + eps[i, 6] * std
                r = wp.max(wp.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3), T(1e-12))
                q0 = q0 / r
                q1 = q1 / r
                q2 = q2 / r
                q3 = q3 / r
        for k in range(13):
            v = nodes[i, col + k]
            if k >= 3 and k < 7:
                if k == 3:
                    v = q0
                elif k == 4:
                    v = q1
                elif k == 5:
                    v = q2
                else:
                    v = q3
            else:
                if wp.static(NOISE == 1):
                    if m != 0:
                        v = v + eps[i, k] * std
            noisy[i, k] = v
            centred[i, k] = v
        if wp.static(CENTRE == 1):
            if m != 0:
                g = node_graph[i]
                sx = T(0.0)
                sy = T(0.0)
                c = T(0.0)
                for j in range(offsets[g], offsets[g + 1]):
                    if movable[j] != 0:
                        x = nodes[j, col]
                        y = nodes[j, col + 1]
                        if wp.static(NOISE == 1):
                            x = x + eps[j, 0] * std
                            y = y + eps[j, 1] * std
                        sx += x
                        sy += y
                        c += T(1.0)
                d = wp.max(c, T(1.0))
                centred[i, 0] = noisy[i, 0] - sx / d
                centred[i, 1] = noisy[i, 1] - sy / d

    return noisy_centred
