"""Warp kernels of ``gnwarp/models/forward.py``: a training batch's input states in one launch,
and its loss terms (forward and backward) in a few.

The loss of a batch (Algorithm D.3) perturbs the input body states with Gaussian noise (world
bodies excepted, orientations re-normalized, D.7.1) and re-centres each graph's x, y on its
moving bodies' mean position (D.4). Neither needs a gradient (they act on data), and in torch
they are ~20 small kernels. Here one thread per node writes its noisy and centred
states, re-summing its graph's noisy x, y itself (graphs have a few bodies).

The loss (D.7.4) compares the normalized predicted change with the normalized true one per
moving node: squared errors of position, linear and angular velocity, and 1 - (q_e . q_p)^2 of
the de-normalized, re-normalized predicted rotation. In torch its forward and backward are ~50
small kernels; here ``loss_terms`` writes each node's four sums (and its weight), torch sums
them over nodes (a fixed-order reduction), ``loss_finalize`` divides by the moving nodes' count,
and ``loss_grad`` writes the gradient of the predicted change, one thread per node.
"""
# no `from __future__ import annotations`: Warp reads kernel annotations as objects of the factory scope
import functools
from typing import Any

import warp as wp

__all__ = ["noisy_centred_kernel", "loss_terms_kernel", "loss_finalize_kernel", "loss_grad_kernel"]


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


@wp.func
def _term_start(g: int):
    """First column of squared-error term g: position 0, linear velocity 7, angular velocity 10."""
    if g == 0:
        return 0
    return 4 + 3 * g


@wp.func
def _error(pred: wp.array2d(dtype=Any), delta: wp.array2d(dtype=Any), mean: wp.array(dtype=Any),
           std: wp.array(dtype=Any), i: int, j: int):
    """Normalized prediction minus normalized true change, row i, column j."""
    return pred[i, j] - (delta[i, j] - mean[j]) / std[j]


@functools.cache
def loss_terms_kernel(dtype):
    """Kernel ``(pred [n, 13], delta [n, 13], mean [13], std [13], movable [n] int32, out [n, 5])``
    over n threads: with t = (delta - mean) / std, out[i] = w * (sum (pred - t)^2 over position,
    over linear velocity, over angular velocity; 1 - (delta_q . q)^2 with q = pred_q * std_q +
    mean_q divided by max(|q|, 1e-12); 1), w = movable[i]."""
    T = dtype

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def loss_terms(pred: wp.array2d(dtype=T), delta: wp.array2d(dtype=T), mean: wp.array(dtype=T),
                   std: wp.array(dtype=T), movable: wp.array(dtype=wp.int32), out: wp.array2d(dtype=T)):
        i = wp.tid()
        if movable[i] == 0:
            for k in range(5):
                out[i, k] = T(0.0)
            return
        for g in range(3):
            a = _term_start(g)
            acc = T(0.0)
            for j in range(a, a + 3):
                e = _error(pred, delta, mean, std, i, j)
                acc += e * e
            out[i, g] = acc
        q0 = pred[i, 3] * std[3] + mean[3]
        q1 = pred[i, 4] * std[4] + mean[4]
        q2 = pred[i, 5] * std[5] + mean[5]
        q3 = pred[i, 6] * std[6] + mean[6]
        r = wp.max(wp.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3), T(1e-12))
        d = (delta[i, 3] * q0 + delta[i, 4] * q1 + delta[i, 5] * q2 + delta[i, 6] * q3) / r
        out[i, 3] = T(1.0) - d * d
        out[i, 4] = T(1.0)

    return loss_terms


@functools.cache
def loss_finalize_kernel(dtype, normalized: bool):
    """Kernel ``(sums [5], std [13], terms [5])`` over 1 thread: terms = (pos, linvel, angvel,
    quat, loss) = sums[:4] / max(sums[4], 1), the rotation term divided by sum std[4:7]^2 when
    ``normalized``, and their total."""
    T = dtype
    NORM = 1 if normalized else 0

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def loss_finalize(sums: wp.array(dtype=T), std: wp.array(dtype=T), terms: wp.array(dtype=T)):
        d = wp.max(sums[4], T(1.0))
        rs = T(1.0)
        if wp.static(NORM == 1):
            rs = T(1.0) / (std[4] * std[4] + std[5] * std[5] + std[6] * std[6])
        total = T(0.0)
        for k in range(4):
            v = sums[k] / d
            if k == 3:
                v = v * rs
            terms[k] = v
            total += v
        terms[4] = total

    return loss_finalize


@functools.cache
def loss_grad_kernel(dtype, normalized: bool):
    """Kernel ``(pred, delta, mean, std, movable, sums [5], g_terms [5], g_pred [n, 13])`` over
    n threads: the gradient of ``loss_finalize``'s terms (weighted by ``g_terms``) w.r.t. pred."""
    T = dtype
    NORM = 1 if normalized else 0

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def loss_grad(pred: wp.array2d(dtype=T), delta: wp.array2d(dtype=T), mean: wp.array(dtype=T),
                  std: wp.array(dtype=T), movable: wp.array(dtype=wp.int32), sums: wp.array(dtype=T),
                  g_terms: wp.array(dtype=T), g_pred: wp.array2d(dtype=T)):
        i = wp.tid()
        if movable[i] == 0:
            for k in range(13):
                g_pred[i, k] = T(0.0)
            return
        d = wp.max(sums[4], T(1.0))
        for g in range(3):
            a = _term_start(g)
            c = T(2.0) * (g_terms[g] + g_terms[4]) / d
            for j in range(a, a + 3):
                g_pred[i, j] = c * _error(pred, delta, mean, std, i, j)
        rs = T(1.0)
        if wp.static(NORM == 1):
            rs = T(1.0) / (std[4] * std[4] + std[5] * std[5] + std[6] * std[6])
        cq = (g_terms[3] + g_terms[4]) * rs / d
        q0 = pred[i, 3] * std[3] + mean[3]
        q1 = pred[i, 4] * std[4] + mean[4]
        q2 = pred[i, 5] * std[5] + mean[5]
        q3 = pred[i, 6] * std[6] + mean[6]
        n = wp.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
        r = wp.max(n, T(1e-12))
        u0 = q0 / r
        u1 = q1 / r
        u2 = q2 / r
        u3 = q3 / r
        dot = delta[i, 3] * u0 + delta[i, 4] * u1 + delta[i, 5] * u2 + delta[i, 6] * u3
        # d(1 - dot^2)/du = -2 dot delta_q; through u = q / max(|q|, eps): (g - u (u . g)) / r
        h0 = T(-2.0) * dot * delta[i, 3] * cq
        h1 = T(-2.0) * dot * delta[i, 4] * cq
        h2 = T(-2.0) * dot * delta[i, 5] * cq
        h3 = T(-2.0) * dot * delta[i, 6] * cq
        p = T(0.0)
        if n >= T(1e-12):
            p = u0 * h0 + u1 * h1 + u2 * h2 + u3 * h3
        g_pred[i, 3] = (h0 - u0 * p) / r * std[3]
        g_pred[i, 4] = (h1 - u1 * p) / r * std[4]
        g_pred[i, 5] = (h2 - u2 * p) / r * std[5]
        g_pred[i, 6] = (h3 - u3 * p) / r * std[6]

    return loss_grad
