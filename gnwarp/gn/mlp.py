"""The dense layers of a GN block's MLPs on the blas path: GEMMs with their epilogues, forward and
backward (ReLU masks and bias gradients fused in one Warp pass per layer, ``kernels/gn/mlp.py``)."""
from __future__ import annotations

from typing import NamedTuple

import threading

import torch

from gnwarp.gn import fp16x3
from gnwarp.interop import WP_DTYPE
from gnwarp.kernels.gn import mlp as K

__all__ = ["gemm", "linear", "mlp_forward", "relu_grad", "gemm_accumulates", "wgrad", "mlp_backward", "PackedMask",
           "pack_mask", "prime_dense", "prime_dense_async"]

_ZERO_BIAS: dict[tuple, torch.Tensor] = {}


def _zero_bias(n: int, like: torch.Tensor) -> torch.Tensor:
    key = (n, like.dtype, like.device)
    if key not in _ZERO_BIAS:
        _ZERO_BIAS[key] = torch.zeros(n, dtype=like.dtype, device=like.device)
    return _ZERO_BIAS[key]


def gemm(a, b, out=None):
    """a @ b as cuBLASLt's matmul with a (zero) bias epilogue: torch.mm's plain cuBLAS path picks
    slow Ampere / Turing kernels for the narrow-K first-layer shapes, the Lt path its Hopper
    ones. Plain torch.mm off CUDA."""
    if a.device.type != "cuda":
        return torch.mm(a, b, out=out)
    return torch.addmm(_zero_bias(b.shape[1], a), a, b, out=out)


def linear(x, w, b, relu: bool):
    """x @ w.T + b, then ReLU if ``relu``: bias and ReLU run in the GEMM's epilogue (cuBLASLt on
    CUDA: no extra pass over the activations)."""
    if relu:
        return torch._addmm_activation(b, x, w.t())
    return torch.addmm(b, x, w.t())


def mlp_forward(h, ws, bs, keep: bool, launch=None, run=None):
    """Layers 1..L of an MLP whose first layer's output (after its ReLU) is ``h``.

    Returns (hs, out): the hidden activations [h0, h1, ...] (inputs of layers 1..L, saved for
    backward; without ``keep`` only the last one is held, so memory stays flat) and the MLP's
    output (bias included). A single-layer MLP returns ([], h). With ``launch`` and ``run``,
    layers 1..L run as fp16x3 GEMMs where ``fp16x3.mlp_emulates`` says so."""
    if len(ws) == 1:
        return [], h
    if run is not None and fp16x3.mlp_emulates(run, h.shape[0], ws):
        return fp16x3.mlp_forward(launch, h, ws[1:], bs[1:], keep, [h] if keep else [])
    hs = [h]
    for l in range(1, len(ws) - 1):
        h = linear(h, ws[l], bs[l], relu=True)
        hs = hs + [h] if keep else [h]
    return hs, linear(hs[-1], ws[-1], bs[-1], relu=False)


class PackedMask(NamedTuple):
    """The ReLU mask (act > 0) of a [rows, width] activation, 1 bit per element: int32 ``bits``
    [rows, ceil(width / 32)] (layout: ``kernels/gn/mlp.py``). Stands in for the activation in
    ``relu_grad`` when no weight gradient needs the activation itself."""
    bits: torch.Tensor
    width: int

    @property
    def nbytes(self) -> int:
        return self.bits.numel() * self.bits.element_size()


def pack_mask(launch, act: torch.Tensor, out: torch.Tensor | None = None) -> PackedMask:
    """The packed ReLU mask of ``act`` [rows, width] (written into ``out`` when given)."""
    rows, W = act.shape
    nw = K.mask_words(W)
    if out is None:
        out = torch.empty(rows, nw, dtype=torch.int32, device=act.device)
    elif tuple(out.shape) != (rows, nw) or out.dtype != torch.int32:
        raise ValueError(f"a packed mask of a {rows} x {W} activation is int32 {rows} x {nw}, got "
                         f"{out.dtype} {tuple(out.shape)}")
    if rows:
        launch(K.relu_mask_pack_kernel(W, WP_DTYPE[act.dtype]), rows * nw, act.contiguous(), out)
    return PackedMask(out, W)


def relu_grad(launch, run, act, g, gb) -> None:
    """In place: g = g where act > 0 else 0; ``gb`` (if given) = column sums of the result (the
    bias gradient), as atomics fused into the same pass, or a torch sum in deterministic mode.
    ``act`` may be a ``PackedMask`` (then no bias gradient: it is only kept when no parameter
    wants a gradient)."""
    rows, W = g.shape
    if isinstance(act, PackedMask):
        if gb is not None:
            raise ValueError("a packed ReLU mask gives no bias gradient: the parameters must not require grad")
        if act.width != W or act.bits.shape[0] != rows:
            raise ValueError(f"packed mask of {act.bits.shape[0]} x {act.width} for a gradient of {rows} x {W}")
        if rows:
            launch(K.relu_grad_bits_kernel(W, run.wp_dtype), rows * K.mask_words(W), act.bits, g, g)
        return
    fused = gb is not None and not run.deterministic
    chunk = K.relu_chunk_rows(rows, W)
    launch(K.relu_grad_sum_kernel(W, run.wp_dtype, bias_sum=fused), K.relu_grad_dim(rows, W, chunk),
           act, g, rows, chunk, g, gb if fused else launch.placeholder(run.acc_dtype, 1))
    if gb is not None and not fused:
        torch.sum(g, 0, dtype=run.acc_dtype, out=gb)


def gemm_accumulates(compute_dtype: torch.dtype, grad_dtype: torch.dtype, device: torch.device) -> bool:
    """Whether a weight-gradient GEMM of ``compute_dtype`` operands can add straight into a
    ``grad_dtype`` buffer (``wgrad``): same dtype anywhere; fp16 / bf16 operands into float32 on
    CUDA through torch's ``addmm(..., out_dtype=)`` (not on the CPU)."""
    if compute_dtype == grad_dtype:
        return True
    return (device.type == "cuda" and grad_dtype == torch.float32 and compute_dtype in (torch.float16, torch.bfloat16)
            and hasattr(torch.ops.aten.addmm, "dtype_out"))


def wgrad(a, b, out, accumulate: bool):
    """out = a @ b, or (``accumulate``) out += a @ b: the GEMM adds in its epilogue (beta = 1),
    in ``out``'s dtype (float32 accumulation of fp16 / bf16 operands, ``gemm_accumulates``)."""
    if not accumulate:
        return torch.mm(a, b, out=out)
    if a.dtype == out.dtype:
        return torch.addmm(out, a, b, out=out)
    return torch.addmm(out, a, b, out_dtype=out.dtype, out=out)


def mlp_backward(launch, run, side, g, hs, ws, gws, gbs, need_w: bool, summed: bool, accumulate: bool = False):
    """Backward through layers L..1 of an MLP from ``g``, the gradient of its output.

    Writes (``accumulate``: adds) the weight gradients of layers 1..L into ``gws`` (GEMMs on
    ``side``, off the critical path) and the bias gradients of layers 0..L into ``gbs``
    (``summed``: the kernel that made ``g`` already added the output bias's gradient into
    gbs[-1]). Returns the gradient at the first layer's pre-activation."""
    if need_w and not summed:
        torch.sum(g, 0, dtype=run.acc_dtype, out=gbs[-1])
    for l in range(len(ws) - 1, 0, -1):
        x = hs[l - 1]
        if need_w:
            with side(g, x):
                wgrad(g.t(), x, gws[l], accumulate)
        gh = torch.mm(g, ws[l])
        relu_grad(launch, run, x, gh, gbs[l - 1] if need_w else None)
        g = gh
    return g


def prime_dense(params, rows: int = 8, shapes: int = 8) -> int:
    """Run once, on constant stand-ins, the dense-layer GEMMs of every distinct 2-D weight shape
    in ``params`` (at most ``shapes`` of them; ``rows`` rows of input): forward with and without
    the ReLU epilogue (``linear``), the zero-bias ``gemm`` of the first layers, the input- and
    weight-gradient GEMMs of ``mlp_backward``. A process's first cuBLAS / cuBLASLt use
    (libraries, handle, workspace, kernels) then happens here. Nothing of ``params`` is written
    and no random generator is drawn from. Returns the shapes run."""
    seen = {}
    for p in params:
        if p.dim() == 2 and p.is_floating_point() and tuple(p.shape) not in seen:
            seen[tuple(p.shape)] = p
        if len(seen) >= shapes:
            break
    for (out_f, in_f), ref in seen.items():
        with torch.no_grad():
            like = dict(device=ref.device, dtype=ref.dtype)
            w = torch.full((out_f, in_f), 0.01, **like)
            b = torch.zeros(out_f, **like)
            x = torch.ones(rows, in_f, **like)
            h = linear(x, w, b, relu=True)
            linear(x, w, b, relu=False)
            gemm(x, w.t())
            wgrad(h.t(), x, torch.empty_like(w), accumulate=False)
            torch.mm(h, w)
    return len(seen)


def prime_dense_async(model) -> threading.Thread | None:
    """``prime_dense`` of ``model``'s parameters on a daemon thread and a CUDA stream of its own,
    started here, when they are on CUDA (None elsewhere: the CPU's GEMMs have no first-use cost
    worth hiding). The caller joins it before anything records a CUDA graph (a capture forbids
    other threads' CUDA work); an error in it is kept in the thread's ``error`` (the real GEMMs
    meet the same problem and report it)."""
    params = [p.detach() for p in model.parameters()]
    if not params or params[0].device.type != "cuda":
        return None
    device = params[0].device

    def run():
        try:
            with torch.cuda.device(device):
                stream = torch.cuda.Stream(device)
                with torch.cuda.stream(stream):
                    prime_dense(params)
                stream.synchronize()
        except Exception as e:   # an optimization only
            t.error = e
    t = threading.Thread(target=run, name="gnwarp-prime-dense", daemon=True)
    t.error = None
    t.start()
    return t
