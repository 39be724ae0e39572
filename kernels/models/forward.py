"""Warp kernel of ``gnwarp/models/forward.py``: a training batch's input states in one launch.

The loss of a batch (Algorithm D.3) perturbs the input body states with Gaussian noise (world
bodies excepted, orientations re-normalized, D.7.1) and re-centres each graph's x, y on its
moving bodies' mean position (D.4). Neither needs a gradient (they act on data), and in torch
they are ~20 small kernels. Here one thread per graph walks its nodes twice: first the noisy
states (written out, and their x, y summed over moving bodies), then the centred ones.
"""
# no `from __future__ import annotations`: Warp reads kernel annotations as objects of the factory scope
import functools

import warp as wp

__all__ = ["noisy_centred_kernel"]


@functools.cache
def noisy_centred_kernel(dtype, noise: bool, recenter: bool):
    """Kernel ``(nodes [n, F], col, eps [n, 13], std, movable [n] int32, offsets [G+1] int32,
    noisy [n, 13], centred [n, 13])`` over G threads, dyn = nodes[:, col:col + 13] (the body
    states of the input graph): noisy = dyn + std * eps on moving bodies
    (quaternion divided by max(|q|, 1e-12)); centred = noisy with each graph's mean x, y over its
    moving bodies subtracted from its moving bodies (a copy when not ``recenter``)."""
    T = dtype
    NOISE = 1 if noise else 0
    CENTRE = 1 if recenter else 0

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def noisy_centred(nodes: wp.array2d(dtype=T), col: int, eps: wp.array2d(dtype=T), std: T,
                      movable: wp.array(dtype=wp.int32),
                      offsets: wp.array(dtype=wp.int32), noisy: wp.array2d(dtype=T), centred: wp.array2d(dtype=T)):
        g = wp.tid()
        sx = T(0.0)
        sy = T(0.0)
        c = T(0.0)
        for i in range(offsets[g], offsets[g + 1]):
            m = movable[i]
            for k in range(13):
                v = nodes[i, col + k]
                if wp.static(NOISE == 1):
                    if m != 0:
                        v = v + eps[i, k] * std
                noisy[i, k] = v
            if wp.static(NOISE == 1):
                if m != 0:
                    n2 = noisy[i, 3] * noisy[i, 3] + noisy[i, 4] * noisy[i, 4] + noisy[i, 5] * noisy[i, 5] + noisy[i, 6] * noisy[i, 6]
                    r = wp.max(wp.sqrt(n2), T(1e-12))
                    for k in range(3, 7):
                        noisy[i, k] = noisy[i, k] / r
            if m != 0:
                sx += noisy[i, 0]
                sy += noisy[i, 1]
                c += T(1.0)
        mx = T(0.0)
        my = T(0.0)
        if wp.static(CENTRE == 1):
            d = wp.max(c, T(1.0))
            mx = sx / d
            my = sy / d
        for i in range(offsets[g], offsets[g + 1]):
            for k in range(13):
                centred[i, k] = noisy[i, k]
            if movable[i] != 0:
                centred[i, 0] = noisy[i, 0] - mx
                centred[i, 1] = noisy[i, 1] - my

    return noisy_centred
