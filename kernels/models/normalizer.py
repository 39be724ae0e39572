"""Warp kernel of ``gnwarp/models/normalizer.py``: a normalizer's accumulation and statistics in
one launch.

In torch, accumulating a batch into the float64 sums (cast, weight, square, two column sums,
adds) and reading mean and std back (count clamp, divisions, variance, clamps, square root, the
"no data yet" selects, casts) are ~20 kernels per normalizer; a training step has four. Here one
block per feature column sums its column's weighted values, squares and weights over the rows
(each lane a strided range, then one tile reduction: a fixed order, so deterministic), adds them
to the column's float64 sums and writes the column's new mean and std in the model's dtype.
The row count is added by the caller afterwards (every block reads the count without this batch;
none writes it).
"""
# no `from __future__ import annotations`: Warp reads kernel annotations as objects of the factory scope
import functools

import warp as wp

__all__ = ["BLOCK", "accumulate_kernel", "apply_kernel"]

BLOCK = 128  # threads per column block on CUDA (Warp's CPU device runs one thread a block)


@wp.func
def column_stats(s: wp.float64, q: wp.float64, cnt: wp.float64, floor: wp.float64):
    """(mean, std) of a column from its sum ``s``, squared sum ``q`` and count: std = max(sqrt(max(var,
    0)), floor); (0, 1) while the count is 0."""
    if cnt > wp.float64(0.0):
        d = wp.max(cnt, wp.float64(1.0))
        m = s / d
        var = wp.max(q / d - m * m, wp.float64(0.0))
        return wp.vec2d(m, wp.max(wp.sqrt(var), floor))
    return wp.vec2d(wp.float64(0.0), wp.float64(1.0))


@functools.cache
def accumulate_kernel(dtype, weighted: bool):
    """Kernel ``(x_in [n, F], w_in [n], n, bd, count_in [1], floor, sum_out [F], sumsq_out [F],
    mean_out [F], std_out [F])`` launched tiled over F blocks of ``bd`` threads: sum_out[j] +=
    sum_i w_i x_ij, sumsq_out[j] += sum_i w_i x_ij^2 (w = 1 when not ``weighted``), then
    mean_out[j], std_out[j] of the updated sums with the count ``count_in + sum_i w_i``: std =
    max(sqrt(max(var, 0)), floor); mean 0 and std 1 while the count is 0. ``x_in``, ``w_in``,
    ``mean_out``, ``std_out`` in ``dtype``; the sums in float64."""
    T = dtype
    W = 1 if weighted else 0

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def accumulate(
        # Data in:
        x_in: wp.array2d(dtype=T),
        w_in: wp.array(dtype=T),
        n: int,
        bd: int,
        count_in: wp.array(dtype=wp.float64),
        floor: wp.float64,
        # Data out:
        sum_out: wp.array(dtype=wp.float64),
        sumsq_out: wp.array(dtype=wp.float64),
        mean_out: wp.array(dtype=T),
        std_out: wp.array(dtype=T),
    ):
        col, lane = wp.tid()
        a = wp.float64(0.0)
        b = wp.float64(0.0)
        c = wp.float64(0.0)
        i = lane
        while i < n:
            v = wp.float64(x_in[i, col])
            if wp.static(W == 1):
                wi = wp.float64(w_in[i])
                a += wi * v
                b += wi * v * v
                c += wi
            else:
                a += v
                b += v * v
            i += bd
        sa = wp.tile_sum(wp.tile(a))
        sb = wp.tile_sum(wp.tile(b))
        sc = wp.tile_sum(wp.tile(c))
        if lane == 0:
            s = sum_out[col] + sa[0]
            q = sumsq_out[col] + sb[0]
            cnt = count_in[0] + wp.float64(n)
            if wp.static(W == 1):
                cnt = count_in[0] + sc[0]
            sum_out[col] = s
            sumsq_out[col] = q
            ms = column_stats(s, q, cnt, floor)
            mean_out[col] = T(ms[0])
            std_out[col] = T(ms[1])

    return accumulate


@functools.cache
def apply_kernel(dtype):
    """Kernel ``(inc_in [1 + 2F], size, count_in [1], floor, sum_out [F], sumsq_out [F],
    mean_out [F], std_out [F])`` launched over F threads: adds a batch's sums ``inc_in`` (its
    count, column sums, column squared sums: several ranks' batches summed) to the column sums
    and writes the new mean and std as ``accumulate_kernel`` does, with the count ``count_in +
    inc_in[0]`` (the caller adds the count afterwards)."""
    T = dtype

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def apply(
        # Data in:
        inc_in: wp.array(dtype=wp.float64),
        size: int,
        count_in: wp.array(dtype=wp.float64),
        floor: wp.float64,
        # Data out:
        sum_out: wp.array(dtype=wp.float64),
        sumsq_out: wp.array(dtype=wp.float64),
        mean_out: wp.array(dtype=T),
        std_out: wp.array(dtype=T),
    ):
        col = wp.tid()
        s = sum_out[col] + inc_in[1 + col]
        q = sumsq_out[col] + inc_in[1 + size + col]
        cnt = count_in[0] + inc_in[0]
        sum_out[col] = s
        sumsq_out[col] = q
        ms = column_stats(s, q, cnt, floor)
        mean_out[col] = T(ms[0])
        std_out[col] = T(ms[1])

    return apply
