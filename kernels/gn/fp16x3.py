"""Warp kernel of fp16x3 (launched by ``gnwarp/gn/fp16x3.py``): float32-accurate GEMMs from three
fp16 tensor-core products; this kernel writes each float32 row's fp16 pieces, after the epilogue
of the GEMM before."""
# no `from __future__ import annotations`: Warp reads kernel annotations as objects of the factory scope
import functools

import warp as wp

from .common import OPTIONS

__all__ = ["BLOCK", "group", "pieces_kernel"]

# threads per row of ``pieces_kernel`` on CUDA (one warp, one block per row). Paper core's
# fp16x3 forward at batch 4096 on an H200, captured: 32 threads 3.44 ms, 64 3.57, 128 3.96
BLOCK = 32
VEC = 4     # column groups each thread loads before it computes and stores


def group(width: int) -> int:
    """Columns per vector load / store of ``pieces_kernel`` (16-byte float32 loads)."""
    return 4 if width % 4 == 0 else 2 if width % 2 == 0 else 1


@functools.cache
def pieces_kernel(width: int, *, epilogue: bool, relu: bool, write_f32: bool, write_pieces: bool, weights: bool):
    """One float32 row per block (``wp.launch_tiled``, dim = rows; any block size, 1 on the CPU):
    the operand pieces of the fp16x3 GEMM, optionally after the epilogue of the GEMM before.

    ``epilogue``: y = src_in * row_inv_in[r] * col_inv_in[c] + bias[c] (the previous fp16x3
    GEMM's output unscaled), ReLU if ``relu``, written to ``dst_out`` if ``write_f32`` (may be
    ``src_in``: each thread reads its elements before it writes them); else y = src_in.
    ``write_pieces``: the row's scale s = 2^k puts its largest |y| in [2^14, 2^15) (fp16's range holds
    y * s and its remainder; k from the exponent bits, no log), hi = fp16(y * s),
    lo = fp16(y * s - hi), written as pieces_out[r] = [hi | lo | hi] (activations) or
    [hi | hi | lo] (``weights``), so that one GEMM of pieces over 3 * width columns sums
    hi*Whi + lo*Whi + hi*Wlo; ``inv_out[r]`` = 1 / s (exact: a power of two). The row maximum
    is a block reduction (tile max). NaN stays NaN; an all-zero row gets any scale.

    Arrays are of ``group(width)``-vectors (row-major tensors viewed [rows, cols / g, g]):
    each thread loads 16 bytes at a time, consecutive threads consecutive groups."""
    g = group(width)
    G = width // g
    V = VEC
    F = wp.types.vector(g, wp.float32)
    H = wp.types.vector(g, wp.float16)
    R = wp.types.matrix(shape=(V, g), dtype=wp.float32)  # the V groups a thread holds

    @wp.func
    def unscale(y: F, ri: wp.float32, ci: F, b: F):
        out = F()
        for j in range(g):
            x = y[j] * ri * ci[j] + b[j]
            if wp.static(relu):
                x = wp.max(x, wp.float32(0.0))
            out[j] = x
        return out

    @wp.kernel(module="unique", module_options=OPTIONS)
    def pieces(
        # Data in:
        src_in: wp.array2d(dtype=F),
        row_inv_in: wp.array(dtype=wp.float32),
        col_inv_in: wp.array(dtype=F),
        # Parameters:
        bias: wp.array(dtype=F),
        # Data out:
        dst_out: wp.array2d(dtype=F),
        pieces_out: wp.array2d(dtype=H),
        inv_out: wp.array(dtype=wp.float32),
    ):
        r, lane = wp.tid()
        nb = wp.block_dim()
        ri = wp.float32(1.0)
        if wp.static(epilogue):
            ri = row_inv_in[r]
        m = wp.float32(0.0)
        for c0 in range(0, G, nb * V):
            ys = R()
            for k in range(V):
                c = c0 + k * nb + lane
                if c < G:
                    ys[k] = src_in[r, c]
            for k in range(V):
                c = c0 + k * nb + lane
                if c < G:
                    y = ys[k]
                    if wp.static(epilogue):
                        y = unscale(y, ri, col_inv_in[c], bias[c])
                        if wp.static(write_f32):
                            dst_out[r, c] = y
                    for j in range(g):
                        m = wp.max(m, wp.abs(y[j]))
        if wp.static(write_pieces):
            mx = wp.tile_extract(wp.tile_max(wp.tile(m)), 0)
            e = (wp.cast(mx, wp.int32) >> 23) & 255
            eb = wp.clamp(268 - e, 1, 253)  # 2^(eb - 127) * mx in [2^14, 2^15)
            s = wp.cast(eb << 23, wp.float32)
            if lane == 0:
                inv_out[r] = wp.cast((254 - eb) << 23, wp.float32)
            for c0 in range(0, G, nb * V):
                ys = R()
                for k in range(V):
                    c = c0 + k * nb + lane
                    if c < G:
                        if wp.static(epilogue and write_f32):
                            ys[k] = dst_out[r, c]
                        else:
                            ys[k] = src_in[r, c]
                for k in range(V):
                    c = c0 + k * nb + lane
                    if c < G:
                        y = ys[k]
                        if wp.static(epilogue and not write_f32):
                            y = unscale(y, ri, col_inv_in[c], bias[c])
                        hi = H()
                        lo = H()
                        for j in range(g):
                            x = y[j] * s
                            h = wp.float16(x)
                            hi[j] = h
                            lo[j] = wp.float16(x - wp.float32(h))
                        pieces_out[r, c] = hi
                        if wp.static(weights):
                            pieces_out[r, G + c] = hi
                            pieces_out[r, 2 * G + c] = lo
                        else:
                            pieces_out[r, G + c] = lo
                            pieces_out[r, 2 * G + c] = hi

    return pieces
