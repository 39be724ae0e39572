"""The first layer of each MLP as GEMM-ready weight blocks: its layout (aligned, zero-padded to
``config.pad`` columns, so cuBLAS takes its fast kernels), written once per forward by one kernel
(``prepare``: the parameter cast and every first-layer block), and its gradient unpacked back
(``FirstLayer.unpack``). Kernels: ``kernels/gn/first_layer.py``."""
from __future__ import annotations

import functools

import torch

from gnwarp.gn.config import column_slices, pad
from gnwarp.gn.flat import ALIGN, cast_params, flat_span
from gnwarp.gn.mlp import wgrad
from gnwarp.interop import WP_DTYPE, Launcher
from gnwarp.kernels.gn import first_layer as K

__all__ = ["padded", "first_layer_layout", "FirstLayer", "prepare"]


def padded(x, dtype):
    """``x`` in ``dtype``, rows zero-padded to ``pad`` columns (itself when already so)."""
    if x is None:
        return None
    cols = pad(x.shape[1])
    if x.dtype == dtype and x.is_contiguous() and cols == x.shape[1] and x.data_ptr() % 16 == 0:
        return x
    out = torch.empty(x.shape[0], cols, dtype=dtype, device=x.device)
    if cols > x.shape[1]:
        out[:, x.shape[1]:].zero_()
    out[:, :x.shape[1]].copy_(x)
    return out


@functools.cache
def first_layer_layout(layout: tuple, projected: bool, H: int, dtype: torch.dtype):
    """Padded block layout of a first-layer weight [H, sum of widths]: (segments of
    ``unpack_kernel``, {block: (offset, rows, width, stride)}, total elements); each block's rows
    are ``stride = pad(width)`` long, zeros after ``width``. ``projected`` (the edge update in
    "project" mode):
    blocks "edges", "nodes" (sender rows stacked over receiver rows) and "globals"; else one
    block "all"."""
    cols = column_slices(layout)
    segs, blocks, total = [], {}, 0

    def block(name, rows, width):
        nonlocal total
        stride = pad(width)
        blocks[name] = (total, rows, width, stride)
        total += -(-rows * stride // ALIGN) * ALIGN
        return blocks[name][0], stride

    if projected:
        if "edges" in cols:
            sl = cols["edges"]
            off, st = block("edges", H, sl.stop - sl.start)
            segs.append((sl.start, sl.stop - sl.start, off, st, 0))
        node_pieces = [n for n in ("sender_nodes", "receiver_nodes") if n in cols]
        if node_pieces:
            w = cols[node_pieces[0]].stop - cols[node_pieces[0]].start
            off, st = block("nodes", H * len(node_pieces), w)
            for k, n in enumerate(node_pieces):
                segs.append((cols[n].start, w, off, st, k * H))
        if "globals" in cols:
            sl = cols["globals"]
            off, st = block("globals", H, sl.stop - sl.start)
            segs.append((sl.start, sl.stop - sl.start, off, st, 0))
    else:
        w = sum(wd for _, wd in layout)
        off, st = block("all", H, w)
        segs.append((0, w, off, st, 0))
    return tuple(segs), blocks, total


class FirstLayer:
    """A first-layer weight [H, K] as GEMM-ready blocks (``w``: {block: [rows, pad(width)]}, zero
    columns after the block's width, 16-byte-aligned rows), written by ``prepare``'s one kernel
    (for the edge update it also stacks the sender and receiver blocks); a single block of a
    padded width in the compute dtype is used as is. Their GEMM partners are padded the same
    way (``padded``, ``graph_ops.concat``)."""

    def __init__(self, run, w0, layout, projected: bool, cast_copy: bool = False):
        """``cast_copy``: ``w0`` is the parameter, of which an aligned compute-dtype copy is made
        (``prepare``'s flat cast); else ``w0`` is the weight in the dtype the GEMMs will read."""
        cd = self.dtype = run.compute_dtype
        self.segs, self.blocks, self.total = first_layer_layout(tuple(layout), projected, w0.shape[0], cd)
        self.shape = tuple(w0.shape)
        self.as_is = (not projected and (cast_copy or (w0.dtype == cd and w0.data_ptr() % 16 == 0))
                      and w0.is_contiguous() and pad(w0.shape[1]) == w0.shape[1])
        self.w = {"all": w0} if self.as_is and not cast_copy else None
        self.base = 0  # offset of its blocks in ``prepare``'s buffer

    def _views(self, buf):
        return {name: buf[o:o + rows * st].view(rows, st) for name, (o, rows, _, st) in self.blocks.items()}

    def grad_blocks(self, gw0):
        """(block views to write the weight gradient into, buffer to unpack into ``gw0`` or None)."""
        if self.as_is:
            return {"all": gw0}, None
        buf = torch.empty(max(self.total, 1), dtype=self.dtype, device=gw0.device)  # GEMM output: compute dtype
        return self._views(buf), buf

    def backward_concat(self, side, g0, x, gw0, accumulate: bool):
        """Backward of the concatenated first layer y = x @ W.T: writes (``accumulate``: adds)
        dL/dW into ``gw0`` (when given; its GEMM and unpack on ``side``) and returns dL/dx."""
        if gw0 is not None:
            self.weight_grad(side, g0, x, gw0, accumulate)
        return torch.mm(g0, self.w["all"])

    def weight_grad(self, side, g0, x, gw0, accumulate: bool):
        """dL/dW = g0^T x written (``accumulate``: added) into ``gw0``: the GEMM, and the unpack of
        its padded blocks after it, on the same side stream (off the critical path)."""
        blocks, buf = self.grad_blocks(gw0)
        with side(g0, x, buf):
            wgrad(g0.t(), x, blocks["all"], accumulate and buf is None)
            self.unpack(Launcher(g0), buf, gw0, accumulate)  # on the side stream

    def unpack(self, launch, buf, gw0, accumulate: bool):
        """gw0 = (``accumulate``: +=) the weight-gradient blocks written into ``buf`` (padding
        columns dropped)."""
        if buf is not None:
            launch(K.unpack_kernel(self.segs, self.shape[1], WP_DTYPE[gw0.dtype], WP_DTYPE[buf.dtype],
                                   accumulate=accumulate), gw0.numel(), buf, gw0)


def prepare(launch, run, params, first):
    """The block's parameters for its GEMMs, in one ``prep_kernel`` launch: (pc, {k: FirstLayer}).

    ``pc``: the parameters in the compute dtype (themselves when already so; else views of one
    cast copy of their flat span when they are views of one buffer in order, FlatAdam's; else
    ``cast_params``'s copy, made before). ``first``: [(k, layout, projected)] of the first-layer
    weights params[k] (edge, node, global update), each as the aligned, zero-padded blocks of
    ``FirstLayer``, read from the parameter itself (cast in the kernel)."""
    cd = run.compute_dtype
    p0 = params[0]
    n_cast, span = 0, None
    if p0.dtype == cd:
        pc = list(params)
    else:
        span = flat_span(params)
        if span is None:
            pc = cast_params(params, cd)
        else:
            n_cast = span[1] - span[0]
    fls, slots, mats = {}, [], []
    base = -(-n_cast // ALIGN) * ALIGN
    total = base
    for k, layout, projected in first:
        fl = fls[k] = FirstLayer(run, pc[k] if span is None else params[k], layout, projected, span is not None)
        if fl.as_is:
            continue
        fl.base = total - base
        for col0, width, off, stride, row0 in fl.segs:
            slots.append((fl.base + off + row0 * stride, fl.shape[0], width, stride, col0))
            mats.append(params[k])
        total += fl.total
    if len(slots) > K.PREP_SLOTS:
        raise ValueError(f"{len(slots)} first-layer weight blocks, over the {K.PREP_SLOTS} of one prep launch")
    if total == 0:
        return pc, fls
    dst = torch.empty(total, dtype=cd, device=p0.device)
    n_cast_threads, threads = K.prep_threads(n_cast, tuple(slots))
    if total >= 2 ** 31:
        raise ValueError(f"GN block parameters too large for one launch ({total} elements)")
    ph = launch.placeholder
    src = torch.as_strided(p0.detach(), (n_cast,), (1,), span[0]) if span is not None else ph(p0.dtype, 1)
    mats = [m.detach() for m in mats] + [ph(p0.dtype, 2)] * (K.PREP_SLOTS - len(mats))
    launch(K.prep_kernel(tuple(slots), WP_DTYPE[p0.dtype], run.wp_dtype), threads, src, n_cast, n_cast_threads,
           base, *mats, dst)
    if span is not None:
        a = span[0]
        pc = [dst[p.storage_offset() - a:p.storage_offset() - a + p.numel()].view(p.shape) for p in params]
    for k, fl in fls.items():
        fl.w = {"all": pc[k]} if fl.as_is else fl._views(dst[base + fl.base:base + fl.base + fl.total])
    return pc, fls
