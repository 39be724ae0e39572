"""Parameters and gradients as views of one flat buffer: the layout ``FlatAdam`` keeps the
parameters in, the ``main_grad`` views the GN backward adds its gradients into, and the carving of
one allocation into many tensors (one memset, one launch, instead of one per tensor).

Views start ``ALIGN``-element aligned (256 bytes in fp32), as cuBLAS likes its operands.
"""
from __future__ import annotations

import math

import torch

from gnwarp.interop import WP_DTYPE
from gnwarp.kernels.gn.flat import accumulate_kernel

__all__ = ["ALIGN", "flatten_parameters", "has_main_grad", "accumulate_main_grads", "flat_span", "cast_params",
           "carve", "views"]

ALIGN = 64  # elements


def _aligned(n: int) -> int:
    return -(-n // ALIGN) * ALIGN


def flatten_parameters(params) -> tuple[torch.Tensor, list[int]]:
    """Move ``params`` (one dtype, one device) into one flat buffer: each ``p.data`` becomes a
    view of it, starting ``ALIGN``-element aligned, zeros in the gaps. Returns (buffer, offsets).

    Modules keep working unchanged. The Warp GN implementation then casts a block's parameters
    for fp16 / bf16 in one launch over their span instead of a cat and a cast (FlatAdam does this
    itself; call it on a model used for inference or with another optimizer). Call it after
    ``model.to(...)``, which would replace the views."""
    ps = list(params)
    if not ps:
        raise ValueError("flatten_parameters got no parameters")
    dt, dev = ps[0].dtype, ps[0].device
    for k, p in enumerate(ps):
        if p.dtype != dt or p.device != dev:
            raise ValueError(f"parameter {k} is {p.dtype} on {p.device}, parameter 0 {dt} on {dev}: "
                             "flatten_parameters needs one dtype and one device")
    if len({id(p) for p in ps}) != len(ps):
        raise ValueError("flatten_parameters got a parameter twice")
    offsets, total = [], 0
    for p in ps:
        offsets.append(total)
        total += _aligned(p.numel())
    with torch.no_grad():
        flat = torch.zeros(total, dtype=dt, device=dev)
        for p, o in zip(ps, offsets):
            view = flat[o:o + p.numel()].view_as(p)
            view.copy_(p)
            p.data = view
    return flat, offsets


def has_main_grad(params) -> bool:
    """Whether every parameter carries a ``main_grad`` of its own shape and dtype, all views of
    one contiguous buffer (FlatAdam's), so a block's gradients can be added in one launch."""
    base = None
    for p in params:
        mg = getattr(p, "main_grad", None)
        if mg is None or mg.shape != p.shape or mg.dtype != p.dtype or not mg.is_contiguous() or mg._base is None:
            return False
        if base is None:
            base = mg._base
        elif mg._base is not base:
            return False
    return base is not None and base.is_contiguous()


_TABLES: dict[tuple, tuple] = {}


def accumulate_main_grads(launch, src: torch.Tensor, segments, mains) -> None:
    """mains[k] += src[off_k : off_k + numel_k] (dtype cast) for (off_k, k) in ``segments``, in
    one launch: ``src`` a flat gradient buffer, ``mains`` views of one flat buffer
    (``has_main_grad``). The segment table is made once per layout and kept on the device (so
    run a step before capturing a CUDA graph)."""
    if not segments:
        return
    base = mains[segments[0][1]]._base
    item = base.element_size()
    rows, starts, t = [], [0], 0
    for off, k in segments:
        mg = mains[k]
        rows.append((off, (mg.data_ptr() - base.data_ptr()) // item))
        t += mg.numel()
        starts.append(t)
    key = (tuple(rows), tuple(starts), base.device)
    tabs = _TABLES.get(key)
    if tabs is None:
        tabs = _TABLES[key] = (torch.tensor(rows, dtype=torch.int32, device=base.device),
                               torch.tensor(starts, dtype=torch.int32, device=base.device))
    launch(accumulate_kernel(WP_DTYPE[src.dtype], WP_DTYPE[base.dtype]), t, src, tabs[0], tabs[1], len(rows), base)


def flat_span(params) -> tuple[int, int] | None:
    """(first, end) storage offsets when the parameters are contiguous, non-overlapping views of
    one storage in order, each starting ``ALIGN``-aligned (``FlatAdam``'s flat buffer), else None."""
    p0 = params[0]
    ptr = p0.untyped_storage().data_ptr()
    end = -1
    for p in params:
        o = p.storage_offset()
        if (p.untyped_storage().data_ptr() != ptr or p.dtype != p0.dtype or not p.is_contiguous()
                or o < end or o % ALIGN):
            return None
        end = o + p.numel()
    return params[0].storage_offset(), end


_PADS: dict[tuple, torch.Tensor] = {}


def cast_params(params, dtype: torch.dtype) -> list[torch.Tensor]:
    """The parameters in ``dtype``: themselves when they already are, else views of one flat
    copy, each starting aligned: one cast launch of their span when they are views of one flat
    buffer in order (FlatAdam), else one cat and one cast (not one cast per tensor)."""
    if all(p.dtype == dtype for p in params):
        return list(params)
    span = flat_span(params)
    if span is not None:
        a, b = span
        flat = torch.as_strided(params[0].detach(), (b - a,), (1,), a).to(dtype)
        return [flat[p.storage_offset() - a:p.storage_offset() - a + p.numel()].view(p.shape) for p in params]
    pieces, offsets, o = [], [], 0
    for p in params:
        pad = -o % ALIGN
        if pad:
            key = (p.device, p.dtype, pad)
            if key not in _PADS:
                _PADS[key] = torch.zeros(pad, dtype=p.dtype, device=p.device)
            pieces.append(_PADS[key])
            o += pad
        pieces.append(p.reshape(-1))
        offsets.append(o)
        o += p.numel()
    flat = torch.cat(pieces).to(dtype)
    return [flat[o:o + p.numel()].view(p.shape) for p, o in zip(params, offsets)]


def carve(shapes, dtype: torch.dtype, device, zero: bool):
    """Views of one allocation with the given shapes (None -> None), each ``ALIGN``-aligned: one
    memset when ``zero``, instead of one per tensor. Returns (views, buffer, offsets)."""
    offsets, total = [], 0
    for s in shapes:
        offsets.append(total)
        if s is not None:
            total += _aligned(math.prod(s))
    buf = (torch.zeros if zero else torch.empty)(max(total, 1), dtype=dtype, device=device)
    return views(buf, shapes, offsets), buf, offsets


def views(buf: torch.Tensor, shapes, offsets) -> list:
    """The views of ``buf`` that ``carve`` made (of another buffer of the same layout)."""
    return [None if s is None else buf[o:o + math.prod(s)].view(s) for s, o in zip(shapes, offsets)]
