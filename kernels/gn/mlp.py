"""Warp kernel of the MLP backward on the blas path (launched by ``gnwarp/gn/mlp.py``): ReLU
backward fused with the bias gradient; ReLU masks packed to bits and the ReLU backward from them
(the activation store of a rollout's adjoint loop, ``gnwarp/gn/replay.py``)."""
# no `from __future__ import annotations`: Warp reads kernel annotations as objects of the factory scope
import functools

import warp as wp

from .common import OPTIONS, ROW_BATCH, acc_dtype, vec

__all__ = ["relu_chunk_rows", "relu_grad_dim", "relu_grad_sum_kernel", "MASK_BITS", "mask_words",
           "relu_mask_pack_kernel", "relu_grad_bits_kernel"]


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
    activation's). Measured against a one-column kernel with a conditional load on an H200
    (bench/results/probes/relu_grad_probe_nvidia-h200.md, fp16): 3600 x 512 9.3 vs 11.9 us, 73728 x 512
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




# -- packed ReLU masks -----------------------------------------------------------------------------
# A mask of a [rows, width] activation is int32 [rows, words], words = ceil(width / 32): bit b of
# word w holds column w + b * words (so at each bit, the threads of a row read consecutive columns:
# coalesced loads). One thread per (row, word).
MASK_BITS = 32


def mask_words(width: int) -> int:
    """Words of one row's packed mask."""
    return (width + MASK_BITS - 1) // MASK_BITS


@functools.cache
def relu_mask_pack_kernel(width: int, dtype):
    """bits_out[r, w] bit b = act_in[r, w + b * words] > 0: the ReLU mask of a saved activation,
    1 bit per element (1/32 of an fp32 activation's bytes). Launch rows x ``mask_words(width)``."""
    NW = mask_words(width)
    FULL = width % MASK_BITS == 0
    T = dtype

    @wp.kernel(module="unique", module_options=OPTIONS)
    def relu_mask_pack(
        # Data in:
        act_in: wp.array2d(dtype=T),
        # Data out:
        bits_out: wp.array2d(dtype=wp.int32),
    ):
        i = wp.tid()
        r = i // NW
        w = i - r * NW
        m = wp.int32(0)
        for b in range(MASK_BITS):
            c = w + b * NW
            if wp.static(FULL) or c < width:
                if act_in[r, c] > T(0.0):
                    m = m | (wp.int32(1) << wp.int32(b))
        bits_out[r, w] = m

    return relu_mask_pack


@functools.cache
def relu_grad_bits_kernel(width: int, dtype):
    """grad_out[r, c] = grad_in[r, c] where the packed mask's bit of (r, c) is set, else 0: the
    ReLU backward from a packed mask (may run in place; each thread loads 8 elements, then stores
    them). Launch rows x ``mask_words(width)``."""
    NW = mask_words(width)
    FULL = width % MASK_BITS == 0
    G = 8
    T = dtype

    @wp.kernel(module="unique", module_options=OPTIONS)
    def relu_grad_bits(
        # Data in:
        bits_in: wp.array2d(dtype=wp.int32),
        grad_in: wp.array2d(dtype=T),
        # Data out:
        grad_out: wp.array2d(dtype=T),
    ):
        i = wp.tid()
        r = i // NW
        w = i - r * NW
        m = bits_in[r, w]
        for b0 in range(0, MASK_BITS, G):
            gs = wp.vector(length=G, dtype=T)
            for k in range(G):
                c = w + (b0 + k) * NW
                if wp.static(FULL) or c < width:
                    x = grad_in[r, c]
                    gs[k] = wp.where(((m >> wp.int32(b0 + k)) & wp.int32(1)) != wp.int32(0), x, T(0.0))
            for k in range(G):
                c = w + (b0 + k) * NW
                if wp.static(FULL) or c < width:
                    grad_out[r, c] = gs[k]

    return relu_grad_bits
