"""Warp kernels of the first-layer weight layout (launched by ``gnwarp/gn/first_layer.py``): a
block's parameters cast and its first-layer weights written as aligned, zero-padded GEMM blocks
(``prep``), and their gradient unpacked from those blocks (``unpack``)."""
# no `from __future__ import annotations`: Warp reads kernel annotations as objects of the factory scope
import functools

import warp as wp

from .common import OPTIONS

__all__ = ["unpack_kernel", "PREP_SLOTS", "PREP_VEC", "prep_threads", "prep_kernel"]


@functools.cache
def unpack_kernel(segments: tuple, cols: int, mat_dtype, flat_dtype, *, accumulate: bool):
    """The gradient of a first-layer weight from the aligned blocks its GEMM wrote (``prep_kernel``'s
    layout): ``mat_out[i, c] = flat_in[off + (row0 + i) * stride + (c - col0)]`` (``accumulate``:
    +=, into a gradient accumulator) for the columns c in [col0, col0 + width) of each segment (col0,
    width, off, stride, row0) of a row-major [rows, cols] matrix; four segments at most (edges,
    sender / receiver nodes stacked, globals). One thread per matrix element."""
    segs = list(segments) + [(0, 0, 0, 1, 0)] * (4 - len(segments))
    (C0, W0, O0, S0, R0), (C1, W1, O1, S1, R1), (C2, W2, O2, S2, R2), (C3, W3, O3, S3, R3) = segs
    M = mat_dtype
    F = flat_dtype

    @wp.kernel(module="unique", module_options=OPTIONS)
    def unpack(
        # Data in:
        flat_in: wp.array(dtype=F),
        # Data out:
        mat_out: wp.array2d(dtype=M),
    ):
        t = wp.tid()
        i = t // cols
        c = t - i * cols
        d = int(-1)
        if wp.static(W0 > 0):
            if c >= C0 and c < C0 + W0:
                d = O0 + (R0 + i) * S0 + (c - C0)
        if wp.static(W1 > 0):
            if c >= C1 and c < C1 + W1:
                d = O1 + (R1 + i) * S1 + (c - C1)
        if wp.static(W2 > 0):
            if c >= C2 and c < C2 + W2:
                d = O2 + (R2 + i) * S2 + (c - C2)
        if wp.static(W3 > 0):
            if c >= C3 and c < C3 + W3:
                d = O3 + (R3 + i) * S3 + (c - C3)
        if d >= 0:
            if wp.static(accumulate):
                mat_out[i, c] = mat_out[i, c] + M(flat_in[d])
            else:
                mat_out[i, c] = M(flat_in[d])

    return unpack


PREP_SLOTS = 6  # block segments of ``prep_kernel``: edge first layer 4 (edges, senders, receivers, globals) + node + global
PREP_VEC = 8    # elements per thread of ``prep_kernel``


def prep_threads(n_cast: int, blocks: tuple, max_vec: int = PREP_VEC) -> tuple:
    """(threads of the cast region, total launch size) of ``prep_kernel``."""
    nc = -(-n_cast // max_vec)
    return nc, nc + sum(-(-rows * stride // max_vec) for _, rows, _, stride, _ in blocks)


def _prep_block(dst_off: int, n: int, stride: int, width: int, col0: int, mat_dtype, dtype, max_vec: int):
    """One block segment of ``prep_kernel``: dst_out[d0 + dst_off + i * stride + c] = mat_in[i, col0 + c]
    for c < width, 0 for width <= c < stride (the padding), for the ``max_vec`` elements
    j = j0 + k * NT (k < max_vec, j < n = rows * stride) of the thread j0 of NT."""
    O, S, W, C, M, T, V = dst_off, stride, width, col0, mat_dtype, dtype, max_vec
    NT = -(-n // V)

    @wp.func
    def block(
        # Data in:
        mat_in: wp.array2d(dtype=M),
        j0: int,
        d0: int,
        # Data out:
        dst_out: wp.array(dtype=T),
    ):
        xs = wp.vector(length=V, dtype=T)  # zero: the padding
        for k in range(V):  # every load first, then the stores
            j = j0 + k * NT
            if j < n:
                i = j // S
                c = j - i * S
                if c < W:
                    xs[k] = T(mat_in[i, C + c])
        for k in range(V):
            j = j0 + k * NT
            if j < n:
                dst_out[d0 + O + j] = xs[k]

    return block


@functools.cache
def prep_kernel(blocks: tuple, mat_dtype, dtype, *, max_vec: int = PREP_VEC):
    """A GN block's parameters made ready for its GEMMs, in one launch (every forward, since the
    optimizer changes them): the first ``n_cast_threads`` threads cast ``src_in`` (the block's
    parameters as one flat span, FlatAdam's buffer) to the compute dtype, ``dst_out[i] =
    src_in[i]`` for i < n_cast; the rest write the first-layer weights as aligned, zero-padded
    blocks from up to ``PREP_SLOTS`` block segments ``blocks`` = ((dst_off, rows, width, stride,
    col0), ...): rows x stride elements each at ``dst_out[d0 + dst_off ...]``, read from columns
    [col0, col0 + width) of the segment's matrix ``mat_k_in``. Each thread owns ``max_vec``
    elements strided by its region's thread count (coalesced; loads before stores). Launch
    ``prep_threads(n_cast, blocks)[1]`` threads. One launch where separate ones would take a cast
    and, per first layer, a zero fill and a pack."""
    V = max_vec
    bs = list(blocks) + [(0, 0, 0, 1, 0)] * (PREP_SLOTS - len(blocks))
    counts = [-(-rows * stride // V) for _, rows, _, stride, _ in bs]
    starts = [0]
    for n in counts:
        starts.append(starts[-1] + n)
    S0, S1, S2, S3, S4, S5, S6 = starts
    N0, N1, N2, N3, N4, N5 = counts
    f0, f1, f2, f3, f4, f5 = (_prep_block(b[0], b[1] * b[3], b[3], b[2], b[4], mat_dtype, dtype, V) for b in bs)
    M = mat_dtype
    T = dtype

    @wp.kernel(module="unique", module_options=OPTIONS)
    def prep(
        # Data in:
        src_in: wp.array(dtype=M),
        n_cast: int,
        n_cast_threads: int,
        d0: int,
        mat_0_in: wp.array2d(dtype=M),
        mat_1_in: wp.array2d(dtype=M),
        mat_2_in: wp.array2d(dtype=M),
        mat_3_in: wp.array2d(dtype=M),
        mat_4_in: wp.array2d(dtype=M),
        mat_5_in: wp.array2d(dtype=M),
        # Data out:
        dst_out: wp.array(dtype=T),
    ):
        t = wp.tid()
        if t < n_cast_threads:
            xs = wp.vector(length=V, dtype=T)
            for k in range(V):
                i = t + k * n_cast_threads
                if i < n_cast:
                    xs[k] = T(src_in[i])
            for k in range(V):
                i = t + k * n_cast_threads
                if i < n_cast:
                    dst_out[i] = xs[k]
        else:
            b = t - n_cast_threads
            if wp.static(N0 > 0):
                if b < S1:
                    f0(mat_0_in, b, d0, dst_out)
            if wp.static(N1 > 0):
                if b >= S1 and b < S2:
                    f1(mat_1_in, b - S1, d0, dst_out)
            if wp.static(N2 > 0):
                if b >= S2 and b < S3:
                    f2(mat_2_in, b - S2, d0, dst_out)
            if wp.static(N3 > 0):
                if b >= S3 and b < S4:
                    f3(mat_3_in, b - S3, d0, dst_out)
            if wp.static(N4 > 0):
                if b >= S4 and b < S5:
                    f4(mat_4_in, b - S4, d0, dst_out)
            if wp.static(N5 > 0):
                if b >= S5 and b < S6:
                    f5(mat_5_in, b - S5, d0, dst_out)

    return prep


