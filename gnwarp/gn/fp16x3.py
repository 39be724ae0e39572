"""precision="fp16x3": float32-accurate GEMMs from fp16 tensor cores.

Each float32 operand row is scaled by a power of two and split into fp16 hi + lo pieces
(``kernels/gn/fp16x3.py``); one GEMM over [hi | lo | hi] x [Whi | Whi | Wlo] (3x the K, float32
out) sums the three products that carry float32's 24 bits (lo * Wlo, ~2^-24 relative, is left
out), and the next pieces kernel unscales, adds the bias and applies the ReLU. Which MLPs emulate
is ``rules.emulates`` (measured); the backward runs IEEE fp32 GEMMs on the float32 activations
the epilogues also write when autograd needs them.
"""
from __future__ import annotations

import torch
import warp as wp

from gnwarp.gn.rules import emulates
from gnwarp.kernels.gn import fp16x3 as K

__all__ = ["mlp_emulates", "gemm", "pieces", "mlp_forward"]


def mlp_emulates(run, rows: int, ws) -> bool:
    """Whether layers 1..L of an MLP with weights ``ws`` run as fp16x3 GEMMs on ``rows`` rows."""
    return len(ws) > 1 and emulates(run, rows, ws[1].shape[1])


def gemm(a3: torch.Tensor, w3: torch.Tensor) -> torch.Tensor:
    """a3 @ w3.T in float32 from fp16 pieces: cuBLAS with float32 output on CUDA; on the CPU the
    pieces in float32 (their products are exact there too)."""
    if a3.is_cuda:
        return torch.mm(a3, w3.t(), out_dtype=torch.float32)
    return torch.mm(a3.float(), w3.float().t())


def pieces(launch, width: int, rows: int, src, epilogue=None, relu=False, dst=None, out=None, inv=None,
           weights=False) -> None:
    """``K.pieces_kernel`` over ``rows`` rows of ``width`` columns: ``src`` float32 rows (and
    ``dst`` when given: the epilogue's float32 output, may be ``src``); ``epilogue``: (row_inv,
    col_inv, bias) of the GEMM that made ``src``; ``out`` [rows, 3 * width] fp16 pieces and
    ``inv`` [rows] when writing pieces. Arrays go as Warp views of ``K.group``-vectors."""
    g = K.group(width)
    F, H = wp.types.vector(g, wp.float32), wp.types.vector(g, wp.float16)

    def vec(t, dtype):
        return wp.from_torch(t.view(*t.shape[:-1], t.shape[-1] // g, g), dtype=dtype, requires_grad=False,
                             return_ctype=True)
    ph = none = launch.placeholder
    kernel = K.pieces_kernel(width, epilogue=epilogue is not None, relu=relu, write_f32=dst is not None,
                             write_pieces=out is not None, weights=weights)
    launch.tiled(kernel, rows, K.BLOCK, vec(src, F), epilogue[0] if epilogue is not None else ph(torch.float32, 1),
                 vec(epilogue[1], F) if epilogue is not None else none(F, 1),
                 vec(epilogue[2], F) if epilogue is not None else none(F, 1),
                 vec(dst, F) if dst is not None else none(F, 2),
                 vec(out, H) if out is not None else none(H, 2),
                 inv if inv is not None else ph(torch.float32, 1))


def mlp_forward(launch, h, ws, bs, keep: bool, hs: list):
    """Layers ``ws`` (with biases ``bs``, ReLU after all but the last) on input rows ``h`` as
    fp16x3 GEMMs; ``hs``: the activations kept before them (``keep``). Returns (hs + the float32
    inputs of the later layers when ``keep``, output)."""
    M, k = h.shape
    dev = h.device

    def alloc(n, width):
        return (torch.empty(n, 3 * width, dtype=torch.float16, device=dev),
                torch.empty(n, dtype=torch.float32, device=dev))

    a3, a_inv = alloc(M, k)
    pieces(launch, k, M, h.contiguous(), out=a3, inv=a_inv)
    out = None
    for l in range(len(ws)):
        w = ws[l].contiguous()
        n = w.shape[0]
        w3, w_inv = alloc(n, k)
        pieces(launch, k, n, w, out=w3, inv=w_inv, weights=True)
        p = gemm(a3, w3)
        if l == len(ws) - 1:
            pieces(launch, n, M, p, epilogue=(a_inv, w_inv, bs[l].contiguous()), dst=p)
            out = p
        else:
            a3, a_next = alloc(M, n)
            pieces(launch, n, M, p, epilogue=(a_inv, w_inv, bs[l].contiguous()), relu=True,
                   dst=p if keep else None, out=a3, inv=a_next)
            a_inv, k = a_next, n
            if keep:
                hs.append(p)
    return hs, out
