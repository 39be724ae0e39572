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
    """Kernel ``(nodes_in [n, F], col, eps_in [n, 13], std, movable_in [n] int32, offsets_in [G+1]
    int32, node_graph_in [n] int32, noisy_out [n, 13], centred_out [n, 13])`` over n threads (one
    per node), dyn = nodes_in[:, col:col + 13] (the body states of the input graph): noisy = dyn +
    std * eps on moving bodies (quaternion divided by max(|q|, 1e-12)); centred = noisy with its
    graph's mean x, y over moving bodies subtracted on moving bodies (a copy when not
    ``recenter``). Each thread re-sums its graph's noisy x, y (a few nodes: two loads each) rather
    than wait on a reduction."""
    T = dtype
    NOISE = 1 if noise else 0
    CENTRE = 1 if recenter else 0

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def noisy_centred(
        # Data in:
        nodes_in: wp.array2d(dtype=T),
        col: int,
        eps_in: wp.array2d(dtype=T),
        std: T,
        movable_in: wp.array(dtype=wp.int32),
        offsets_in: wp.array(dtype=wp.int32),
        node_graph_in: wp.array(dtype=wp.int32),
        # Data out:
        noisy_out: wp.array2d(dtype=T),
        centred_out: wp.array2d(dtype=T),
    ):
        i = wp.tid()
        m = movable_in[i]
        q0 = nodes_in[i, col + 3]
        q1 = nodes_in[i, col + 4]
        q2 = nodes_in[i, col + 5]
        q3 = nodes_in[i, col + 6]
        if wp.static(NOISE == 1):
            if m != 0:
                q0 = q0 + eps_in[i, 3] * std
                q1 = q1 + eps_in[i, 4] * std
                q2 = q2 + eps_in[i, 5] * std
                q3 = q3 + eps_in[i, 6] * std
                r = wp.max(wp.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3), T(1e-12))
                q0 = q0 / r
                q1 = q1 / r
                q2 = q2 / r
                q3 = q3 / r
        for k in range(13):
            v = nodes_in[i, col + k]
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
                        v = v + eps_in[i, k] * std
            noisy_out[i, k] = v
            centred_out[i, k] = v
        if wp.static(CENTRE == 1):
            if m != 0:
                g = node_graph_in[i]
                sx = T(0.0)
                sy = T(0.0)
                c = T(0.0)
                for j in range(offsets_in[g], offsets_in[g + 1]):
                    if movable_in[j] != 0:
                        x = nodes_in[j, col]
                        y = nodes_in[j, col + 1]
                        if wp.static(NOISE == 1):
                            x = x + eps_in[j, 0] * std
                            y = y + eps_in[j, 1] * std
                        sx += x
                        sy += y
                        c += T(1.0)
                d = wp.max(c, T(1.0))
                centred_out[i, 0] = noisy_out[i, 0] - sx / d
                centred_out[i, 1] = noisy_out[i, 1] - sy / d

    return noisy_centred


@wp.func
def _term_start(g: int):
    """First column of squared-error term g: position 0, linear velocity 7, angular velocity 10."""
    if g == 0:
        return 0
    return 4 + 3 * g


@wp.func
def _error(
    # Data in:
    pred_in: wp.array2d(dtype=Any),
    delta_in: wp.array2d(dtype=Any),
    mean_in: wp.array(dtype=Any),
    std_in: wp.array(dtype=Any),
    i: int,
    j: int,
):
    """Normalized prediction minus normalized true change, row i, column j."""
    return pred_in[i, j] - (delta_in[i, j] - mean_in[j]) / std_in[j]


@functools.cache
def loss_terms_kernel(dtype):
    """Kernel ``(pred_in [n, 13], delta_in [n, 13], mean_in [13], std_in [13], movable_in [n] int32,
    terms_out [n, 5])`` over n threads: with t = (delta - mean) / std, terms_out[i] = w * (sum
    (pred - t)^2 over position,
    over linear velocity, over angular velocity; 1 - (delta_q . q)^2 with q = pred_q * std_q +
    mean_q divided by max(|q|, 1e-12); 1), w = movable_in[i]."""
    T = dtype

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def loss_terms(
        # Data in:
        pred_in: wp.array2d(dtype=T),
        delta_in: wp.array2d(dtype=T),
        mean_in: wp.array(dtype=T),
        std_in: wp.array(dtype=T),
        movable_in: wp.array(dtype=wp.int32),
        # Data out:
        terms_out: wp.array2d(dtype=T),
    ):
        i = wp.tid()
        if movable_in[i] == 0:
            for k in range(5):
                terms_out[i, k] = T(0.0)
            return
        for g in range(3):
            a = _term_start(g)
            acc = T(0.0)
            for j in range(a, a + 3):
                e = _error(pred_in, delta_in, mean_in, std_in, i, j)
                acc += e * e
            terms_out[i, g] = acc
        q0 = pred_in[i, 3] * std_in[3] + mean_in[3]
        q1 = pred_in[i, 4] * std_in[4] + mean_in[4]
        q2 = pred_in[i, 5] * std_in[5] + mean_in[5]
        q3 = pred_in[i, 6] * std_in[6] + mean_in[6]
        r = wp.max(wp.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3), T(1e-12))
        d = (delta_in[i, 3] * q0 + delta_in[i, 4] * q1 + delta_in[i, 5] * q2 + delta_in[i, 6] * q3) / r
        terms_out[i, 3] = T(1.0) - d * d
        terms_out[i, 4] = T(1.0)

    return loss_terms


@functools.cache
def loss_finalize_kernel(dtype, normalized: bool):
    """Kernel ``(sums_in [5], std_in [13], terms_out [5])`` over 1 thread: terms_out = (pos, linvel,
    angvel, quat, loss) = sums[:4] / max(sums[4], 1), the rotation term divided by sum std[4:7]^2 when
    ``normalized``, and their total."""
    T = dtype
    NORM = 1 if normalized else 0

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def loss_finalize(
        # Data in:
        sums_in: wp.array(dtype=T),
        std_in: wp.array(dtype=T),
        # Data out:
        terms_out: wp.array(dtype=T),
    ):
        d = wp.max(sums_in[4], T(1.0))
        rs = T(1.0)
        if wp.static(NORM == 1):
            rs = T(1.0) / (std_in[4] * std_in[4] + std_in[5] * std_in[5] + std_in[6] * std_in[6])
        total = T(0.0)
        for k in range(4):
            v = sums_in[k] / d
            if k == 3:
                v = v * rs
            terms_out[k] = v
            total += v
        terms_out[4] = total

    return loss_finalize


@functools.cache
def loss_grad_kernel(dtype, normalized: bool):
    """Kernel ``(pred_in, delta_in, mean_in, std_in, movable_in, sums_in [5], g_terms_in [5],
    g_pred_out [n, 13])`` over n threads: the gradient of ``loss_finalize``'s terms (weighted by
    ``g_terms_in``) w.r.t. pred."""
    T = dtype
    NORM = 1 if normalized else 0

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def loss_grad(
        # Data in:
        pred_in: wp.array2d(dtype=T),
        delta_in: wp.array2d(dtype=T),
        mean_in: wp.array(dtype=T),
        std_in: wp.array(dtype=T),
        movable_in: wp.array(dtype=wp.int32),
        sums_in: wp.array(dtype=T),
        g_terms_in: wp.array(dtype=T),
        # Data out:
        g_pred_out: wp.array2d(dtype=T),
    ):
        i = wp.tid()
        if movable_in[i] == 0:
            for k in range(13):
                g_pred_out[i, k] = T(0.0)
            return
        d = wp.max(sums_in[4], T(1.0))
        for g in range(3):
            a = _term_start(g)
            c = T(2.0) * (g_terms_in[g] + g_terms_in[4]) / d
            for j in range(a, a + 3):
                g_pred_out[i, j] = c * _error(pred_in, delta_in, mean_in, std_in, i, j)
        rs = T(1.0)
        if wp.static(NORM == 1):
            rs = T(1.0) / (std_in[4] * std_in[4] + std_in[5] * std_in[5] + std_in[6] * std_in[6])
        cq = (g_terms_in[3] + g_terms_in[4]) * rs / d
        q0 = pred_in[i, 3] * std_in[3] + mean_in[3]
        q1 = pred_in[i, 4] * std_in[4] + mean_in[4]
        q2 = pred_in[i, 5] * std_in[5] + mean_in[5]
        q3 = pred_in[i, 6] * std_in[6] + mean_in[6]
        n = wp.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
        r = wp.max(n, T(1e-12))
        u0 = q0 / r
        u1 = q1 / r
        u2 = q2 / r
        u3 = q3 / r
        dot = delta_in[i, 3] * u0 + delta_in[i, 4] * u1 + delta_in[i, 5] * u2 + delta_in[i, 6] * u3
        # d(1 - dot^2)/du = -2 dot delta_q; through u = q / max(|q|, eps): (g - u (u . g)) / r
        h0 = T(-2.0) * dot * delta_in[i, 3] * cq
        h1 = T(-2.0) * dot * delta_in[i, 4] * cq
        h2 = T(-2.0) * dot * delta_in[i, 5] * cq
        h3 = T(-2.0) * dot * delta_in[i, 6] * cq
        p = T(0.0)
        if n >= T(1e-12):
            p = u0 * h0 + u1 * h1 + u2 * h2 + u3 * h3
        g_pred_out[i, 3] = (h0 - u0 * p) / r * std_in[3]
        g_pred_out[i, 4] = (h1 - u1 * p) / r * std_in[4]
        g_pred_out[i, 5] = (h2 - u2 * p) / r * std_in[5]
        g_pred_out[i, 6] = (h3 - u3 * p) / r * std_in[6]

    return loss_grad
