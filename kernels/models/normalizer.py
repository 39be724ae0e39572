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

Over several ranks the batch sums are reduced first: ``sums_kernel`` adds each normalizer's batch
(count included) into one packed float64 buffer, the buffer is all-reduced, and one
``pack_stats_kernel`` launch writes every normalizer's mean and std from it.
"""
# no `from __future__ import annotations`: Warp reads kernel annotations as objects of the factory scope
import functools

import warp as wp

__all__ = ["BLOCK", "accumulate_kernel", "sums_kernel", "pack_stats_kernel"]

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
def _column_sums(dtype, weighted: bool):
    """Function ``(x_in [n, F], w_in [n], n, bd, col, lane) -> (sum w x, sum w x^2, sum w)`` of column
    ``col`` over the block's lanes (each lane a strided range of rows, then one tile reduction: a
    fixed order, so deterministic); w = 1 when not ``weighted``."""
    T = dtype
    W = 1 if weighted else 0

    @wp.func
    def column_sums(
        # Data in:
        x_in: wp.array2d(dtype=T),
        w_in: wp.array(dtype=T),
        n: int,
        bd: int,
        col: int,
        lane: int,
    ):
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
                c += wp.float64(1.0)
            i += bd
        sa = wp.tile_sum(wp.tile(a))
        sb = wp.tile_sum(wp.tile(b))
        sc = wp.tile_sum(wp.tile(c))
        return wp.vec3d(sa[0], sb[0], sc[0])

    return column_sums


@functools.cache
def accumulate_kernel(dtype, weighted: bool):
    """Kernel ``(x_in [n, F], w_in [n], n, bd, count_in [1], floor, sum_out [F], sumsq_out [F],
    mean_out [F], std_out [F])`` launched tiled over F blocks of ``bd`` threads: sum_out[j] +=
    sum_i w_i x_ij, sumsq_out[j] += sum_i w_i x_ij^2 (w = 1 when not ``weighted``), then
    mean_out[j], std_out[j] of the updated sums with the count ``count_in + sum_i w_i``: std =
    max(sqrt(max(var, 0)), floor); mean 0 and std 1 while the count is 0. ``x_in``, ``w_in``,
    ``mean_out``, ``std_out`` in ``dtype``; the sums in float64."""
    T = dtype
    sums = _column_sums(dtype, weighted)

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
        abc = sums(x_in, w_in, n, bd, col, lane)
        if lane == 0:
            s = sum_out[col] + abc[0]
            q = sumsq_out[col] + abc[1]
            cnt = count_in[0] + abc[2]
            sum_out[col] = s
            sumsq_out[col] = q
            ms = column_stats(s, q, cnt, floor)
            mean_out[col] = T(ms[0])
            std_out[col] = T(ms[1])

    return accumulate


@functools.cache
def sums_kernel(dtype, weighted: bool):
    """Kernel ``(x_in [n, F], w_in [n], n, bd, count_out [1], sum_out [F], sumsq_out [F])`` launched
    tiled over F blocks of ``bd`` threads: adds a batch's count (sum_i w_i), column sums and column
    squared sums to the float64 outputs (column 0's block adds the count), as ``accumulate_kernel``
    sums them; no statistics (a packed buffer of several normalizers' sums, before ``pack_stats_kernel``)."""
    T = dtype
    sums = _column_sums(dtype, weighted)

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def batch_sums(
        # Data in:
        x_in: wp.array2d(dtype=T),
        w_in: wp.array(dtype=T),
        n: int,
        bd: int,
        # Data out:
        count_out: wp.array(dtype=wp.float64),
        sum_out: wp.array(dtype=wp.float64),
        sumsq_out: wp.array(dtype=wp.float64),
    ):
        col, lane = wp.tid()
        abc = sums(x_in, w_in, n, bd, col, lane)
        if lane == 0:
            sum_out[col] = sum_out[col] + abc[0]
            sumsq_out[col] = sumsq_out[col] + abc[1]
            if col == 0:
                count_out[0] = count_out[0] + abc[2]

    return batch_sums


@functools.cache
def pack_stats_kernel(dtype):
    """Kernel ``(pack_in [*], where_in [C, 3], floor_in [C], mean_out [C], std_out [C])`` launched over
    C threads, the columns of several normalizers: column c's mean and std, as ``accumulate_kernel``
    writes them, from the float64 totals in ``pack_in`` at the indices ``where_in[c]`` = (its sum,
    its squared sum, its normalizer's count), with its normalizer's std floor."""
    T = dtype

    @wp.kernel(module="unique", module_options={"enable_backward": False})
    def pack_stats(
        # Data in:
        pack_in: wp.array(dtype=wp.float64),
        where_in: wp.array2d(dtype=int),
        floor_in: wp.array(dtype=wp.float64),
        # Data out:
        mean_out: wp.array(dtype=T),
        std_out: wp.array(dtype=T),
    ):
        c = wp.tid()
        ms = column_stats(pack_in[where_in[c, 0]], pack_in[where_in[c, 1]], pack_in[where_in[c, 2]], floor_in[c])
        mean_out[c] = T(ms[0])
        std_out[c] = T(ms[1])

    return pack_stats
