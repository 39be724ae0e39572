"""Warp kernel of the MLP backward on the blas path (launched by ``gnwarp/gn/mlp.py``): ReLU
backward fused with the bias gradient."""
# no `from __future__ import annotations`: Warp reads kernel annotations as objects of the factory scope
import functools

import warp as wp

from .common import OPTIONS, ROW_BATCH, acc_dtype, vec

__all__ = ["relu_chunk_rows", "relu_grad_dim", "relu_grad_sum_kernel"]


def relu_chunk_rows(rows: int, width: int) -> int:
    """Rows per thread of ``relu_grad_sum``: 8 for small layers, 16 from 1M elements (measured on
    an H200 with ``bench/probes/relu_grad_probe.py``: 16 rows won at 3600 x 512 and 73728 x 512, 8 at
    1600 x 256)."""
    return 8 if rows * width < (1 << 20) else 16


def relu_grad_dim(rows: int, width: int, chunk: int) -> int:
    """Launch size of ``relu_grad_sum``: one thread per (chunk of rows, ``vec(width)`` columns)."""
    return ((rows + chunk - 1) // chunk) * (width // vec(width)) if rows > 0 else 0


@functools.cache
def relu_grad_sum_kernel(width: int, dtype, *, bias_sum: bool):
    """grad_out[r, j] = grad_in[r, j] where act_in[r, j] > 0, else 0 (ReLU backward from the
    saved activation; may run in place), and sum_out[j] += that gradient summed over the rows
    (the bias gradient of the layer). Launch ``relu_grad_dim(rows, width, chunk)`` threads: each
    owns ``vec(width)`` columns (strided by width / vec, so a warp's accesses stay coalesced) of
    a chunk of rows; both loads are unconditional (a select, not a load that waits on the
    activation's). Measured against the one-column, conditional-load version on an H200
    (bench/results/relu_grad_probe_nvidia-h200.md, fp16): 3600 x 512 9.3 vs 11.9 us, 73728 x 512
    125 vs 157 us."""
    has_sum = bias_sum
    V = vec(width)
    Q = width // V
    RB = ROW_BATCH
    RBV = RB * V
    T = dtype
    A = acc_dtype(dtype)

    @wp.kernel(module="unique", module_options=OPTIONS)
    def relu_grad_sum(
        # Data in:
        act_in: wp.array2d(dtype=T),
        grad_in: wp.array2d(dtype=T),
        rows: int,
        chunk: int,
        # Data out:
        grad_out: wp.array2d(dtype=T),
        sum_out: wp.array(dtype=A),
    ):
        i = wp.tid()
        ci = i // Q
        j0 = i - ci * Q
        r0 = ci * chunk
        r1 = wp.min(r0 + chunk, rows)
        acc = wp.vector(length=V, dtype=A)
        for rb in range(r0, r1, RB):  # RB rows loaded, then stored (in place: read before written)
            gs = wp.vector(length=RBV, dtype=T)
            for k in range(RB):
                r = rb + k
                if r < r1:
                    for c in range(V):
                        a = act_in[r, j0 + c * Q]
                        x = grad_in[r, j0 + c * Q]
                        gs[k * V + c] = wp.where(a > T(0.0), x, T(0.0))
            for k in range(RB):
                r = rb + k
                if r < r1:
                    for c in range(V):
                        grad_out[r, j0 + c * Q] = gs[k * V + c]
                        acc[c] += A(gs[k * V + c])
        if wp.static(has_sum):
            for c in range(V):
                wp.atomic_add(sum_out, j0 + c * Q, acc[c])

    return relu_grad_sum


