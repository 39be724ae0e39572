"""Warp backend of the GN block: torch autograd Functions around the kernels of ``gnwarp.kernels``.

Two paths, same parameters, same results (to rounding):

- "split" (``_SplitBlock``): the graph-structured work (split first layer with gathers, bias and
  activation epilogues, scatter-sums, their backward) runs in the Warp kernels of
  ``kernels/gn_block.py``; the dense layers run as BLAS GEMMs (torch.mm: cuBLAS / CPU BLAS). One
  autograd Function per block, with a hand-written backward (exact: it is the chain rule of the
  forward, checked with ``torch.autograd.gradcheck`` in float64).
- "tile" (``_TileBlock``): one fused Warp-tile kernel per update (gather, whole MLP with
  ``wp.tile_matmul``, scatter) from ``kernels/gn_tile.py``; backward by Warp's autodiff (adjoint
  launches of the same kernels).

Everything launches on torch's current stream, allocates through torch (so a
``torch.cuda.graph`` capture of a training step records it), and syncs with the host nowhere
except in input checks. Kernels are compiled on first use per configuration; run one step
before capturing a CUDA graph.
"""
from __future__ import annotations

import contextlib
import functools
import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
import warp as wp

from gnwarp.gn import GNBlockConfig, column_slices, matmul_precision
from gnwarp.graphs import GraphsTuple
from gnwarp.kernels import gn_block as K
from gnwarp.optim import ALIGN as _ALIGN
from gnwarp.optim import WP_DTYPE as _WP_DTYPE
from gnwarp.optim import accumulate_main_grads, has_main_grad

__all__ = ["GraphIndex", "graph_index", "gn_block_forward", "choose_path", "tile_feasible", "warp_stream",
           "cuda_graph"]



# -- graph index arrays -------------------------------------------------------------------------
class GraphIndex(NamedTuple):
    """Index arrays of a batch of graphs, int32 on the graph's device.

    ``senders``/``receivers`` [E], ``node_graph`` [N], ``edge_graph`` [E]: graph of each node /
    edge; ``node_offsets``/``edge_offsets`` [B+1]: first node / edge of each graph. Deterministic
    mode adds CSR layouts of the edges by receiver and by sender: ``recv_perm`` [E] (edge ids
    sorted by receiver, stable) with ``recv_offsets`` [N+1], and ``send_perm``/``send_offsets``.
    """
    n_nodes: int
    n_edges: int
    n_graphs: int
    senders: torch.Tensor
    receivers: torch.Tensor
    node_graph: torch.Tensor
    edge_graph: torch.Tensor
    node_offsets: torch.Tensor
    edge_offsets: torch.Tensor
    recv_perm: torch.Tensor | None = None
    recv_offsets: torch.Tensor | None = None
    send_perm: torch.Tensor | None = None
    send_offsets: torch.Tensor | None = None

    @property
    def deterministic(self) -> bool:
        return self.recv_perm is not None


def _csr(index: torch.Tensor, n_rows: int):
    """(perm, offsets): ids sorted by ``index`` (stable, so deterministic) and segment starts."""
    sorted_index, perm = torch.sort(index, stable=True)
    rows = torch.arange(n_rows + 1, device=index.device, dtype=sorted_index.dtype)
    offsets = torch.searchsorted(sorted_index, rows)  # no host sync (unlike bincount)
    return perm.to(torch.int32), offsets.to(torch.int32)


def graph_index(graph: GraphsTuple, deterministic: bool = False) -> GraphIndex:
    """Build the ``GraphIndex`` of a GraphsTuple of torch tensors (no host sync if nodes given)."""
    snd, rcv = graph.senders, graph.receivers
    dev = snd.device
    n_edges = int(snd.shape[0])
    n_nodes = int(graph.nodes.shape[0]) if graph.nodes is not None else graph.total_nodes
    n_graphs = int(graph.n_node.shape[0])
    graphs = torch.arange(n_graphs, device=dev)  # int64: torch's int32 repeat_interleave is slow on CPU
    n_node, n_edge = graph.n_node.long(), graph.n_edge.long()
    zero = torch.zeros(1, device=dev, dtype=torch.int64)
    gi = GraphIndex(
        n_nodes, n_edges, n_graphs,
        senders=snd.to(torch.int32).contiguous(), receivers=rcv.to(torch.int32).contiguous(),
        node_graph=torch.repeat_interleave(graphs, n_node, output_size=n_nodes).to(torch.int32),
        edge_graph=torch.repeat_interleave(graphs, n_edge, output_size=n_edges).to(torch.int32),
        node_offsets=torch.cat([zero, torch.cumsum(n_node, 0)]).to(torch.int32),
        edge_offsets=torch.cat([zero, torch.cumsum(n_edge, 0)]).to(torch.int32))
    if deterministic:
        rp, ro = _csr(gi.receivers, n_nodes)
        sp, so = _csr(gi.senders, n_nodes)
        gi = gi._replace(recv_perm=rp, recv_offsets=ro, send_perm=sp, send_offsets=so)
    return gi


# -- launching on torch's stream ----------------------------------------------------------------
_STREAMS: dict[int, wp.Stream] = {}
_PLACEHOLDERS: dict[tuple, torch.Tensor] = {}


def warp_stream(torch_stream: torch.cuda.Stream) -> wp.Stream:
    """The Warp stream wrapping a torch CUDA stream (made once per stream, then cached)."""
    key = torch_stream.cuda_stream
    s = _STREAMS.get(key)
    if s is None:
        wp.init()
        s = _STREAMS[key] = wp.stream_from_torch(torch_stream)
    return s


@contextlib.contextmanager
def cuda_graph(graph: torch.cuda.CUDAGraph, stream: torch.cuda.Stream | None = None, **kwargs):
    """``torch.cuda.graph(graph, stream)`` that Warp knows about: gnwarp launches inside are
    recorded into ``graph`` (Warp also keeps their modules loaded while the graph lives).

    Run the step once before (on ``stream``): kernels compile and load on first use, which must
    not happen during capture. Usage::

        s = torch.cuda.Stream(); s.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(s):
            step()                      # warm-up
        torch.cuda.current_stream().wait_stream(s)
        g = torch.cuda.CUDAGraph()
        with gn_warp.cuda_graph(g, s):
            step()
        g.replay()
    """
    stream = stream if stream is not None else torch.cuda.Stream()
    ws = warp_stream(stream)
    with wp.ScopedStream(ws), torch.cuda.graph(graph, stream=stream, **kwargs):
        wp.capture_begin(force_module_load=False, external=True)
        try:
            yield
        finally:
            wp.capture_end()


class _Launcher:
    """Launches Warp kernels on the device and current torch stream of ``like``."""

    def __init__(self, like: torch.Tensor):
        wp.init()  # no-op once initialized
        self.torch_device = like.device
        self.device = wp.device_from_torch(like.device)
        self.stream = None
        if like.device.type == "cuda":
            self.stream = warp_stream(torch.cuda.current_stream(like.device))

    def placeholder(self, dtype: torch.dtype, ndim: int) -> torch.Tensor:
        """Zero-size array for the argument of an input a kernel was built without."""
        key = (self.torch_device, dtype, ndim)
        t = _PLACEHOLDERS.get(key)
        if t is None:
            t = _PLACEHOLDERS[key] = torch.empty((0,) * ndim, dtype=dtype, device=self.torch_device)
        return t

    @staticmethod
    def array(a):
        """Zero-copy Warp view of a torch tensor (other arguments pass through)."""
        if isinstance(a, torch.Tensor):
            return wp.from_torch(a, dtype=_WP_DTYPE.get(a.dtype), requires_grad=False, return_ctype=True)
        return a

    def __call__(self, kernel, shape, *args):
        """Launch a ``gnwarp.kernels.gn_block`` kernel over ``shape`` = (rows, width) of its data."""
        dim = K.launch_dim(*shape)
        if dim == 0:
            return
        wp.launch(kernel, dim=dim, inputs=[self.array(a) for a in args], device=self.device, stream=self.stream)

    def n(self, kernel, dim: int, *args):
        """Launch ``kernel`` over ``dim`` threads."""
        if dim == 0:
            return
        wp.launch(kernel, dim=dim, inputs=[self.array(a) for a in args], device=self.device, stream=self.stream)

    def rows(self, kernel, rows: int, *args):
        """Launch a one-block-per-row kernel (``K.emu_split_kernel``): ``K.EMU_BLOCK`` threads a
        row on CUDA, one on the CPU."""
        if rows == 0:
            return
        wp.launch_tiled(kernel, dim=[rows], inputs=[self.array(a) for a in args], device=self.device,
                        stream=self.stream, block_dim=K.EMU_BLOCK if self.stream is not None else 1)


# How many side streams the backward spreads its weight-gradient GEMMs over (``_Side``; 0: all on
# the current stream); read when a backward runs (a captured graph keeps the choice it was
# captured with). Measured on an H200 (bench/gn_block.py --sections side;
# bench/results/gn_block_nvidia-h200_notes.md).
SIDE_STREAMS = 1
_SIDE_POOL: dict[int, list] = {}


class _Side:
    """The backward's weight-gradient GEMMs on side CUDA streams, off the critical path (the
    chain of input-gradient GEMMs, ReLU masks and scatters that each layer waits on): at batch
    200 each GEMM fills a fraction of the GPU, so the chains overlap. ``with side(*reads):``
    enqueues the body on the next side stream (round robin over ``SIDE_STREAMS``) after
    everything the current stream has enqueued; ``reads`` (the tensors the body reads) stay
    referenced until ``join``, so the caching allocator cannot hand their memory to later
    current-stream work while a side stream may still read it. ``after(fn)`` runs ``fn`` on the
    current stream at ``join``, which makes the current stream wait for the side streams (also
    inside a CUDA graph capture: forks and joins). Off CUDA (or with ``SIDE_STREAMS`` = 0) the
    bodies run in place."""

    def __init__(self, like: torch.Tensor):
        n = SIDE_STREAMS if like.device.type == "cuda" else 0
        self.streams, self.used, self.k = [], [], 0
        self.keep, self.pending = [], []
        if n > 0:
            self.main = torch.cuda.current_stream(like.device)
            pool = _SIDE_POOL.setdefault(self.main.cuda_stream, [])
            while len(pool) < n:
                pool.append(torch.cuda.Stream(like.device))
            self.streams = pool[:n]

    @contextlib.contextmanager
    def __call__(self, *reads):
        if not self.streams:
            yield
            return
        stream = self.streams[self.k % len(self.streams)]
        self.k += 1
        stream.wait_stream(self.main)
        self.keep.extend(r for r in reads if r is not None)
        if stream not in self.used:
            self.used.append(stream)
        with torch.cuda.stream(stream):
            yield

    def after(self, fn):
        self.pending.append(fn)

    def join(self):
        for stream in self.used:
            self.main.wait_stream(stream)
        self.used.clear()
        self.keep.clear()
        for fn in self.pending:
            fn()
        self.pending.clear()


# -- the split path -----------------------------------------------------------------------------
@dataclass(frozen=True)
class _Plan:
    """Static description of one block call: config, dtypes, modes."""
    config: GNBlockConfig
    compute_dtype: torch.dtype   # GEMM inputs and activations
    acc_dtype: torch.dtype       # scatter-sum accumulators
    precision: str
    deterministic: bool
    n_edge_params: int
    n_node_params: int
    edge_concat: bool = True     # edge first layer on concatenated gathered rows (else split)
    emulate_min: tuple = (0, 0)  # fp16x3: (rows, hidden width) from which an MLP emulates

    @property
    def wp_dtype(self):
        return _WP_DTYPE[self.compute_dtype]

    @property
    def wp_acc(self):
        return _WP_DTYPE[self.acc_dtype]


def _split_mlp_params(plan: _Plan, params):
    a, b = plan.n_edge_params, plan.n_edge_params + plan.n_node_params
    return params[:a], params[a:b], params[b:]




def _carve(shapes, dtype, device, zero: bool):
    """Views of one allocation with the given shapes (None -> None): one memset when ``zero``,
    instead of one per tensor. Returns (views, buffer, offsets)."""
    offsets, total = [], 0
    for s in shapes:
        offsets.append(total)
        if s is not None:
            total += -(-math.prod(s) // _ALIGN) * _ALIGN
    buf = (torch.zeros if zero else torch.empty)(max(total, 1), dtype=dtype, device=device)
    return _views(buf, shapes, offsets), buf, offsets


def _views(buf, shapes, offsets):
    return [None if s is None else buf[o:o + math.prod(s)].view(s) for s, o in zip(shapes, offsets)]


_PADS: dict[tuple, torch.Tensor] = {}


def _flat_span(params):
    """(first, end) storage offsets when the parameters are contiguous, non-overlapping views of
    one storage in order, each starting ``_ALIGN``-aligned (``gnwarp.optim.FlatAdam``'s flat
    buffer), else None."""
    p0 = params[0]
    ptr = p0.untyped_storage().data_ptr()
    end = -1
    for p in params:
        o = p.storage_offset()
        if (p.untyped_storage().data_ptr() != ptr or p.dtype != p0.dtype or not p.is_contiguous()
                or o < end or o % _ALIGN):
            return None
        end = o + p.numel()
    return params[0].storage_offset(), end


def _cast_params(params, dtype):
    """The parameters in the compute dtype: themselves when they already are, else views of one
    flat copy, each starting aligned: one cast launch of their span when they are views of one
    flat buffer in order (FlatAdam), else one cat and one cast (not one cast per tensor)."""
    if all(p.dtype == dtype for p in params):
        return list(params)
    span = _flat_span(params)
    if span is not None:
        a, b = span
        flat = torch.as_strided(params[0].detach(), (b - a,), (1,), a).to(dtype)
        return [flat[p.storage_offset() - a:p.storage_offset() - a + p.numel()].view(p.shape) for p in params]
    pieces, offsets, o = [], [], 0
    for p in params:
        pad = -o % _ALIGN
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


def _prepare(launch, plan, params, first):
    """The block's parameters for its GEMMs, in one ``prep_kernel`` launch: (pc, {k: _FirstLayer}).

    ``pc``: the parameters in the compute dtype (themselves when already so; else views of one
    cast copy of their flat span when they are views of one buffer in order, FlatAdam's; else
    ``_cast_params``'s copy, made before). ``first``: [(k, layout, split)] of the first-layer
    weights params[k] (edge, node, global update), each as the aligned, zero-padded blocks of
    ``_FirstLayer``, read from the parameter itself (cast in the kernel)."""
    cd = plan.compute_dtype
    p0 = params[0]
    n_cast, span = 0, None
    if p0.dtype == cd:
        pc = list(params)
    else:
        span = _flat_span(params)
        if span is None:
            pc = _cast_params(params, cd)
        else:
            n_cast = span[1] - span[0]
    fls, slots, mats = {}, [], []
    base = -(-n_cast // _ALIGN) * _ALIGN
    total = base
    for k, layout, split in first:
        fl = fls[k] = _FirstLayer(plan, pc[k] if span is None else params[k], layout, split, span is not None)
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
    launch.n(K.prep_kernel(tuple(slots), _WP_DTYPE[p0.dtype], plan.wp_dtype), threads, src, n_cast, n_cast_threads,
             base, *mats, dst)
    if span is not None:
        a = span[0]
        pc = [dst[p.storage_offset() - a:p.storage_offset() - a + p.numel()].view(p.shape) for p in params]
    for k, fl in fls.items():
        fl.w = {"all": pc[k]} if fl.as_is else fl._views(dst[base + fl.base:base + fl.base + fl.total])
    return pc, fls


def _pad(cols: int) -> int:
    """Padded width of a first-layer GEMM operand: a multiple of 8 elements (16 bytes in fp16 /
    bf16, 32 in fp32), which cuBLAS's fast (Hopper) kernels need for their K and leading
    dimensions; widths such as 31 or 159 otherwise fall back to Ampere / Turing kernels."""
    return -(-cols // 8) * 8


_ZERO_BIAS: dict[tuple, torch.Tensor] = {}


def _zero_bias(n: int, like: torch.Tensor) -> torch.Tensor:
    key = (n, like.dtype, like.device)
    if key not in _ZERO_BIAS:
        _ZERO_BIAS[key] = torch.zeros(n, dtype=like.dtype, device=like.device)
    return _ZERO_BIAS[key]


def _gemm(a, b, out=None):
    """a @ b as cuBLASLt's matmul with a (zero) bias epilogue: torch.mm's plain cuBLAS path picks
    slow Ampere / Turing kernels for the narrow-K first-layer shapes, the Lt path its Hopper
    ones. Plain torch.mm off CUDA."""
    if a.device.type != "cuda":
        return torch.mm(a, b, out=out)
    return torch.addmm(_zero_bias(b.shape[1], a), a, b, out=out)


def _padded(x, dtype):
    """``x`` in ``dtype``, rows zero-padded to ``_pad`` columns (itself when already so)."""
    if x is None:
        return None
    cols = _pad(x.shape[1])
    if x.dtype == dtype and x.is_contiguous() and cols == x.shape[1] and x.data_ptr() % 16 == 0:
        return x
    out = torch.empty(x.shape[0], cols, dtype=dtype, device=x.device)
    if cols > x.shape[1]:
        out[:, x.shape[1]:].zero_()
    out[:, :x.shape[1]].copy_(x)
    return out


@functools.cache
def _first_layer_layout(layout: tuple, split: bool, H: int, dtype: torch.dtype):
    """Padded block layout of a first-layer weight [H, sum of widths]: (segments of
    ``unpack_kernel``, {block: (offset, rows, width, stride)}, total elements); each block's rows
    are ``stride = _pad(width)`` long, zeros after ``width``. ``split`` (the edge update):
    blocks "edges", "nodes" (sender rows stacked over receiver rows) and "globals"; else one
    block "all"."""
    cols = column_slices(layout)
    segs, blocks, total = [], {}, 0

    def block(name, rows, width):
        nonlocal total
        stride = _pad(width)
        blocks[name] = (total, rows, width, stride)
        total += -(-rows * stride // _ALIGN) * _ALIGN
        return blocks[name][0], stride

    if split:
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


class _FirstLayer:
    """A first-layer weight [H, K] as GEMM-ready blocks (``w``: {block: [rows, _pad(width)]}, zero
    columns after the block's width, 16-byte-aligned rows), written by ``_prepare``'s one kernel
    (for the edge update it also stacks the sender and receiver blocks); a single block of a
    padded width in the compute dtype is used as is. Their GEMM partners are padded the same
    way (``_padded``, ``_concat``)."""

    def __init__(self, plan, w0, layout, split: bool, cast_copy: bool = False):
        """``cast_copy``: ``w0`` is the parameter, of which an aligned compute-dtype copy is made
        (``_prepare``'s flat cast); else ``w0`` is the weight in the dtype the GEMMs will read."""
        cd = self.dtype = plan.compute_dtype
        self.segs, self.blocks, self.total = _first_layer_layout(tuple(layout), split, w0.shape[0], cd)
        self.shape = tuple(w0.shape)
        self.as_is = (not split and (cast_copy or (w0.dtype == cd and w0.data_ptr() % 16 == 0))
                      and w0.is_contiguous() and _pad(w0.shape[1]) == w0.shape[1])
        self.w = {"all": w0} if self.as_is and not cast_copy else None
        self.base = 0  # offset of its blocks in ``_prepare``'s buffer

    def _views(self, buf):
        return {name: buf[o:o + rows * st].view(rows, st) for name, (o, rows, _, st) in self.blocks.items()}

    def grad_blocks(self, gw0):
        """(block views to write the weight gradient into, buffer to unpack into ``gw0`` or None)."""
        if self.as_is:
            return {"all": gw0}, None
        buf = torch.empty(max(self.total, 1), dtype=self.dtype, device=gw0.device)  # GEMM output: compute dtype
        return self._views(buf), buf

    def backward_concat(self, plan, side, g0, x, gw0, accumulate: bool):
        """Backward of the concatenated first layer y = x @ W.T: writes (``accumulate``: adds)
        dL/dW into ``gw0`` (when given; its GEMM and unpack on ``side``) and returns dL/dx."""
        if gw0 is not None:
            self.weight_grad(plan, side, g0, x, gw0, accumulate)
        return torch.mm(g0, self.w["all"])

    def weight_grad(self, plan, side, g0, x, gw0, accumulate: bool):
        """dL/dW = g0^T x written (``accumulate``: added) into ``gw0``: the GEMM, and the unpack of
        its padded blocks after it, on the same side stream (off the critical path)."""
        blocks, buf = self.grad_blocks(gw0)
        with side(g0, x, buf):
            _wgrad(g0.t(), x, blocks["all"], accumulate and buf is None)
            self.unpack(_Launcher(g0), plan, buf, gw0, accumulate)  # on the side stream

    def unpack(self, launch, plan, buf, gw0, accumulate: bool):
        """gw0 = (``accumulate``: +=) the weight-gradient blocks written into ``buf`` (padding
        columns dropped)."""
        if buf is not None:
            launch.n(K.unpack_kernel(self.segs, self.shape[1], _WP_DTYPE[gw0.dtype], _WP_DTYPE[buf.dtype],
                                     accumulate), gw0.numel(), gw0, buf)


def _linear(x, w, b, relu: bool):
    """x @ w.T + b, then ReLU if ``relu``: bias and ReLU run in the GEMM's epilogue (cuBLASLt on
    CUDA: no extra pass over the activations)."""
    if relu:
        return torch._addmm_activation(b, x, w.t())
    return torch.addmm(b, x, w.t())


# fp16x3 (precision="fp16x3"): float32-accurate GEMMs from fp16 tensor cores. Each float32
# operand row is scaled by a power of two and split into fp16 hi + lo (``K.emu_split_kernel``);
# one GEMM over [hi | lo | hi] x [Whi | Whi | Wlo] (3x the K, float32 out) sums the three
# products that carry float32's 24 bits (lo * Wlo, ~2^-24 relative, is left out), and the next
# split's kernel unscales, adds the bias and applies the ReLU. Measured on an H200 (torch.mm
# peers in the same run; bench/results/fp32_emulation_probe_nvidia-h200.md; errors against
# float64): at 73728 x 512 @ 512 x 512 IEEE fp32 takes 0.82-0.84 ms, the one GEMM of the three
# fp16 products 0.16-0.17 ms (bf16x6, range-safe without scales: 0.57 ms; tf32x3: 0.45 ms) and
# the split pass 0.17 ms. At 32768 x 256 @ 256 x 256 emulation loses (IEEE 0.12 ms); the node
# MLPs' width-256 layers emulated made the paper core's forward 2% slower. Hence the rule: an
# MLP emulates when its hidden width is >= ``_EMU_MIN_WIDTH`` on >= ``_EMU_MIN_ROWS`` rows:
# layers 1..L, and layer 0 too when it is one GEMM on the concatenated input rows (fp16x3 takes
# the edge update's concat mode above the rows; below them it is the fp32 path, bitwise). Paper
# core at batch 4096 (bench/results/gn_block_nvidia-h200.md): forward 5.70 -> 3.45-3.48 ms
# captured, error against float64 ~1.0e-6 (IEEE fp32: 4.1-4.3e-7). The backward runs IEEE fp32
# GEMMs on the float32 activations the epilogues also write when autograd needs them.
_EMU_MIN_ROWS = 16384
_EMU_MIN_WIDTH = 512


def _emulates(plan, rows: int, ws) -> bool:
    """Whether layers 1..L of this MLP run as fp16x3 GEMMs (the rule above)."""
    return (plan.precision == "fp16x3" and plan.compute_dtype == torch.float32 and len(ws) > 1
            and rows >= plan.emulate_min[0] and ws[1].shape[1] >= plan.emulate_min[1])


def _emu_gemm(a3, w3):
    """a3 @ w3.T in float32 from fp16 pieces: cuBLAS with float32 output on CUDA; on the CPU the
    pieces in float32 (their products are exact there too)."""
    if a3.is_cuda:
        return torch.mm(a3, w3.t(), out_dtype=torch.float32)
    return torch.mm(a3.float(), w3.float().t())


def _emu_split(launch, width: int, rows: int, src, epilogue=None, relu=False, dst=None, pieces=None,
               inv=None, weights=False):
    """``K.emu_split_kernel`` over ``rows`` rows of ``width`` columns: ``src`` float32 rows (and
    ``dst`` when given: the epilogue's float32 output, may be ``src``); ``epilogue``: (row_inv,
    col_inv, bias) of the GEMM that made ``src``; ``pieces`` [rows, 3 * width] fp16 and ``inv``
    [rows] when splitting. Arrays go as Warp views of ``K.emu_group``-vectors."""
    g = K.emu_group(width)
    F, H = wp.types.vector(g, wp.float32), wp.types.vector(g, wp.float16)

    def vec(t, dtype):
        return wp.from_torch(t.view(*t.shape[:-1], t.shape[-1] // g, g), dtype=dtype, requires_grad=False,
                             return_ctype=True)
    def none(dtype, ndim):  # zero-size Warp array for an argument the kernel was built without
        key = (str(launch.device), dtype, ndim)
        if key not in _EMU_PLACEHOLDERS:
            _EMU_PLACEHOLDERS[key] = wp.empty((0,) * ndim, dtype=dtype, device=launch.device)
        return _EMU_PLACEHOLDERS[key]
    ph = launch.placeholder
    ri = epilogue[0] if epilogue is not None else ph(torch.float32, 1)
    launch.rows(K.emu_split_kernel(width, epilogue is not None, relu, dst is not None, pieces is not None, weights),
                rows, vec(src, F), ri,
                vec(epilogue[1], F) if epilogue is not None else none(F, 1),
                vec(epilogue[2], F) if epilogue is not None else none(F, 1),
                vec(dst, F) if dst is not None else none(F, 2),
                vec(pieces, H) if pieces is not None else none(H, 2),
                inv if inv is not None else ph(torch.float32, 1))


_EMU_PLACEHOLDERS: dict[tuple, object] = {}


def _mlp_forward_emulated(launch, h, ws, bs, keep: bool, hs: list):
    """Layers ``ws`` (with biases ``bs``, ReLU after all but the last) on input rows ``h`` as
    fp16x3 GEMMs (``_emulates``); ``hs``: the activations kept before them (``keep``). Returns
    (hs + the float32 inputs of the later layers when ``keep``, output)."""
    M, k = h.shape
    dev = h.device

    def pieces(n, width):
        return (torch.empty(n, 3 * width, dtype=torch.float16, device=dev),
                torch.empty(n, dtype=torch.float32, device=dev))

    a3, a_inv = pieces(M, k)
    _emu_split(launch, k, M, h.contiguous(), pieces=a3, inv=a_inv)
    out = None
    for l in range(len(ws)):
        w = ws[l].contiguous()
        n = w.shape[0]
        w3, w_inv = pieces(n, k)
        _emu_split(launch, k, n, w, pieces=w3, inv=w_inv, weights=True)
        p = _emu_gemm(a3, w3)
        if l == len(ws) - 1:
            _emu_split(launch, n, M, p, epilogue=(a_inv, w_inv, bs[l].contiguous()), dst=p)
            out = p
        else:
            a3, a_next = pieces(M, n)
            _emu_split(launch, n, M, p, epilogue=(a_inv, w_inv, bs[l].contiguous()), relu=True,
                       dst=p if keep else None, pieces=a3, inv=a_next)
            a_inv, k = a_next, n
            if keep:
                hs.append(p)
    return hs, out


def _mlp_forward(h, ws, bs, keep: bool, emulated=None):
    """Layers 1..L of an MLP whose first layer's output (after its ReLU) is ``h``.

    Returns (hs, out): the hidden activations [h0, h1, ...] (inputs of layers 1..L, saved for
    backward; without ``keep`` only the last one is held, so memory stays flat) and the MLP's
    output (bias included). A single-layer MLP returns ([], h). ``emulated``: (launcher, plan)
    when layers 1..L may run as fp16x3 GEMMs (``_emulates`` decides)."""
    if len(ws) == 1:
        return [], h
    if emulated is not None and _emulates(emulated[1], h.shape[0], ws):
        return _mlp_forward_emulated(emulated[0], h, ws[1:], bs[1:], keep, [h] if keep else [])
    hs = [h]
    for l in range(1, len(ws) - 1):
        h = _linear(h, ws[l], bs[l], relu=True)
        hs = hs + [h] if keep else [h]
    return hs, _linear(hs[-1], ws[-1], bs[-1], relu=False)


def _relu_grad(launch, plan, act, g, gb):
    """In place: g = g where act > 0 else 0; ``gb`` (if given) = column sums of the result (the
    bias gradient), as atomics fused into the same pass, or a torch sum in deterministic mode."""
    rows, W = g.shape
    fused = gb is not None and not plan.deterministic
    chunk = K.relu_chunk_rows(rows, W)
    launch.n(K.relu_grad_sum_kernel(W, fused, plan.wp_dtype), K.relu_grad_dim(rows, W, chunk),
             act, g, rows, chunk, g, gb if fused else launch.placeholder(plan.acc_dtype, 1))
    if gb is not None and not fused:
        torch.sum(g, 0, dtype=plan.acc_dtype, out=gb)


def _gemm_accumulates(compute_dtype: torch.dtype, grad_dtype: torch.dtype, device: torch.device) -> bool:
    """Whether a weight-gradient GEMM of ``compute_dtype`` operands can add straight into a
    ``grad_dtype`` buffer (``_wgrad``): same dtype anywhere; fp16 / bf16 operands into float32 on
    CUDA through torch's ``addmm(..., out_dtype=)`` (not on the CPU)."""
    if compute_dtype == grad_dtype:
        return True
    return (device.type == "cuda" and grad_dtype == torch.float32 and compute_dtype in (torch.float16, torch.bfloat16)
            and hasattr(torch.ops.aten.addmm, "dtype_out"))


def _wgrad(a, b, out, accumulate: bool):
    """out = a @ b, or (``accumulate``) out += a @ b: the GEMM adds in its epilogue (beta = 1),
    in ``out``'s dtype (float32 accumulation of fp16 / bf16 operands, ``_gemm_accumulates``)."""
    if not accumulate:
        return torch.mm(a, b, out=out)
    if a.dtype == out.dtype:
        return torch.addmm(out, a, b, out=out)
    return torch.addmm(out, a, b, out_dtype=out.dtype, out=out)


def _mlp_backward(launch, plan, side, g, hs, ws, gws, gbs, need_w: bool, summed: bool, accumulate: bool = False):
    """Backward through layers L..1 of an MLP from ``g``, the gradient of its output.

    Writes (``accumulate``: adds) the weight gradients of layers 1..L into ``gws`` (GEMMs on
    ``side``, off the critical path) and the bias gradients of layers
    0..L into ``gbs`` (``summed``: the kernel that made ``g`` already added the output bias's
    gradient into gbs[-1]). Returns the gradient at the first layer's pre-activation."""
    if need_w and not summed:
        torch.sum(g, 0, dtype=plan.acc_dtype, out=gbs[-1])
    for l in range(len(ws) - 1, 0, -1):
        x = hs[l - 1]
        if need_w:
            with side(g, x):
                _wgrad(g.t(), x, gws[l], accumulate)
        gh = torch.mm(g, ws[l])
        _relu_grad(launch, plan, x, gh, gbs[l - 1] if need_w else None)
        g = gh
    return g


def _concat(launch, plan, rows, layout, pieces):
    """Input rows of an MLP whose first layer is one GEMM: the pieces of ``layout`` side by side
    in the compute dtype, zero-padded to ``_pad`` columns, in one kernel. ``pieces``: {name:
    (tensor, index or None)}; a piece with an index is read at row ``index[r]``. A lone piece
    read in place is only padded (``_padded``)."""
    cd = plan.compute_dtype
    items = [(pieces[name][0], pieces[name][1], w) for name, w in layout]
    if len(items) == 1 and items[0][1] is None:
        return _padded(items[0][0], cd)
    width = _pad(sum(w for _, _, w in items))
    widths = tuple(w for _, _, w in items) + (0,) * (4 - len(items))
    threads = K.concat_threads(rows, widths, width)
    if max(rows * width, threads) >= 2 ** 31:  # element offsets and thread ids are int32
        raise ValueError(f"batch too large for one GN block launch: {rows} rows x {width} input columns "
                         f"({threads} threads) exceeds 2**31; split the batch")
    for (name, w), (t, _, _) in zip(layout, items):
        if t.dim() != 2 or t.shape[1] != w:  # the kernel reads rows of exactly ``w`` elements
            raise ValueError(f"GN block input {name!r}: expected {w} columns, got shape {tuple(t.shape)}")
    out = torch.empty(rows, width, dtype=cd, device=items[0][0].device)
    flat = [t.contiguous().view(-1) for t, _, _ in items]
    items += [(launch.placeholder(cd, 1), None, 0)] * (4 - len(items))
    flat += [t for t, _, _ in items[len(flat):]]
    kernel = K.concat_kernel(widths, tuple(i is not None for _, i, _ in items),
                             tuple(_WP_DTYPE[t.dtype] for t, _, _ in items), plan.wp_dtype, width)
    launch.n(kernel, threads, *flat,
             *(i if i is not None else launch.placeholder(torch.int32, 1) for _, i, _ in items), rows, out.view(-1))
    return out


# The edge update's first layer runs on concatenated input rows [e, v_s, v_r, u] (one kernel
# writes them, then one GEMM with bias and ReLU in its epilogue, like the node update) or split
# (node / global projections as GEMMs over nodes / graphs, the edge rows' own projection as a
# GEMM, and ``first_layer`` adding the gathered projections per edge). Concat costs 2 * extra_K
# FLOPs per edge and hidden unit (extra_K = padded sender + receiver + global widths) plus the
# concatenated row written and read; split costs the direct projection written and read back
# plus two gathered hidden rows, in ``first_layer`` at ~1.3 TB/s, and four more launches
# (forward) / ~6 (backward). Measured (H200, paper core on cheetah graphs, captured; the
# second block has extra_K = 480; the v7 ablation in bench/results/gn_block_nvidia-h200_notes.md,
# concat vs split): with tensor cores (tf32, fp16, bf16) concat wins everywhere: forward at batch
# 4096 tf32 1.40 vs 1.52 ms, fp16 1.05 vs 1.21; training step at 200 tf32 0.89 vs 0.96, at 4096
# fp16 3.71 vs 4.25. In plain fp32 the extra FLOPs run at the SIMT rate (48 TFLOP/s): split wins
# at 4096 (forward 5.82 vs 6.16 ms, training step 17.8 vs 18.6) and loses narrowly at 200 (1.69
# vs 1.66), so fp32 / fp64 keep the extra_K rule (concat up to 256, as for the paper's first block).
_EDGE_CONCAT_MAX_K = 256
_TENSOR_CORE_PRECISIONS = ("tf32", "fp16", "bf16")


def edge_concat(config: GNBlockConfig, mode: str = "auto", precision: str = "fp32") -> bool:
    """Whether the edge update's first layer runs on concatenated rows: ``mode`` "concat" /
    "split" force it; "auto" applies the measured rule above for ``precision``."""
    if mode != "auto":
        return mode == "concat"
    if precision in _TENSOR_CORE_PRECISIONS or precision == "fp16x3":
        return True
    cols = column_slices(config.edge_layout)
    extra = sum(_pad(_width(cols, n)) for n in ("sender_nodes", "receiver_nodes", "globals") if n in cols)
    return extra <= _EDGE_CONCAT_MAX_K


def _scatter_out(launch, plan, x, out_dtype, target):
    """The block's output ``x`` in ``out_dtype`` and its sum by receiver in one pass: atomic adds
    (with the dtype cast in the same kernel), or (deterministic) ordered segment sums after it.

    ``target``: (sum array or None, row -> destination index, CSR perm or None, CSR offsets)."""
    det = plan.deterministic
    sums, idx, perm, offs = target
    scatter = sums is not None and not det
    copy = x.dtype != out_dtype
    if scatter:
        ph = launch.placeholder
        out = torch.empty(x.shape, dtype=out_dtype, device=x.device) if copy else x
        launch(K.scatter_out_kernel(x.shape[1], True, False, copy, plan.wp_dtype, _WP_DTYPE[out_dtype]),
               x.shape, x, idx, ph(torch.int32, 1), out if copy else ph(out_dtype, 2), sums, ph(plan.acc_dtype, 2))
    else:
        out = x.to(out_dtype)
    if det and sums is not None:
        _segment(launch, plan, x, perm, offs, sums)
    return out


class _SplitBlock(torch.autograd.Function):
    """One GN block on the split path. Inputs: (plan, keep, GraphIndex, nodes, edges, globals, *params)
    with params = edge MLP [W0, b0, ...] + node MLP + global MLP. Outputs: (nodes', edges'[,
    globals']) in the parameters' dtype.

    Forward: the parameters in the compute dtype and the first-layer weights as aligned, padded
    blocks in one launch (``_prepare``); edge update with its first layer on the concatenated,
    gathered input rows (``concat``: one kernel, then one GEMM) when the gathered pieces are
    narrow, else split (node / global projections once per node / graph, gathered per edge by
    ``first_layer``); the other layers as GEMMs with bias and ReLU in cuBLASLt's epilogue; the
    output cast and the sum by receiver in one pass (``scatter_out``), per-graph sums as ordered
    segment sums; node and global updates on their concatenated input rows. First-layer GEMMs
    run on operands zero-padded to 8-column multiples (cuBLAS's Hopper kernels). Backward: each
    update starts with one gather kernel that reads the incoming gradient as autograd hands it
    over (any dtype and strides), adds the gradients of the sums it fed, and sums the output
    bias gradient; GEMMs for weight gradients (on a side stream; with FlatAdam added straight
    into ``main_grad``) and input gradients; ReLU masks and bias gradients (column sums) fused in
    one pass per layer; the gradient of each update's concatenated input rows handed back to
    its inputs in one ``split`` pass (stored, or added by sender / receiver / graph into input
    gradients summed in float32), or, for the split first layer, one atomic scatter to senders,
    receivers and graphs; ordered segment sums in deterministic mode."""

    @staticmethod
    def forward(ctx, plan: _Plan, keep: bool, gi: GraphIndex, v, e, u, *params):
        c = plan.config
        cd, ad = plan.compute_dtype, plan.acc_dtype
        T = plan.wp_dtype
        out_dtype = params[0].dtype
        like = params[0]
        dev = like.device
        launch = _Launcher(like)
        ph = launch.placeholder
        det = plan.deterministic
        N, E, B = gi.n_nodes, gi.n_edges, gi.n_graphs
        n_e, n_n = plan.n_edge_params, plan.n_edge_params + plan.n_node_params
        first = [(0, c.edge_layout, not plan.edge_concat), (n_e, c.node_layout, False)]
        if c.update_globals:
            first.append((n_n, c.global_layout, False))
        pc, fls = _prepare(launch, plan, params, first)
        pe, pn, pg = _split_mlp_params(plan, pc)
        # inputs in the compute dtype, zero-padded, only for the split edge first layer's GEMMs:
        # the concat kernels read the inputs as they are (any float dtype, any width)
        v_c = e_c = u_c = None
        # scatter-sum destinations (accumulation dtype), one allocation: one memset
        (agg, sum_e, sum_v), _, _ = _carve(
            [(N, c.edge_out) if c.aggregates_to_nodes else None, (B, c.edge_out) if c.edges_to_globals else None,
             (B, c.node_out) if c.nodes_to_globals else None], ad, dev, zero=not det)

        with matmul_precision(plan.precision):
            # ---- edge update -----------------------------------------------------------------
            we, be = pe[0::2], pe[1::2]
            cols = column_slices(c.edge_layout)
            H = we[0].shape[0]
            fl_e = fls[0]
            x_e = h = None
            if plan.edge_concat:
                x_e = _concat(launch, plan, E, c.edge_layout,
                              {"edges": (e, None), "sender_nodes": (v, gi.senders),
                               "receiver_nodes": (v, gi.receivers), "globals": (u, gi.edge_graph)})
                if _emulates(plan, E, we):  # the first layer too: its K (the concatenated row) is wide
                    hs_e, e_out = _mlp_forward_emulated(launch, x_e, [fl_e.w["all"], *we[1:]], be, keep, [])
                else:
                    h = _linear(x_e, fl_e.w["all"], be[0], relu=len(we) > 1)
            else:
                v_c, e_c, u_c = _padded(v, cd), _padded(e, cd), _padded(u, cd)
                direct = _gemm(e_c, fl_e.w["edges"].t()) if "edges" in cols else None
                node_proj = _gemm(v_c, fl_e.w["nodes"].t()) if "nodes" in fl_e.w else None
                glob_proj = _gemm(u_c, fl_e.w["globals"].t()) if "globals" in cols else None
                h = torch.empty(E, H, dtype=cd, device=dev)
                launch(K.first_layer_kernel(H, direct is not None, "sender_nodes" in cols, "receiver_nodes" in cols,
                                            glob_proj is not None, len(we) > 1, T), (E, H),
                       direct if direct is not None else ph(cd, 2), node_proj if node_proj is not None else ph(cd, 2),
                       glob_proj if glob_proj is not None else ph(cd, 2), gi.senders, gi.receivers, gi.edge_graph,
                       be[0], h)
                del direct, node_proj, glob_proj
            if h is not None:
                hs_e, e_out = _mlp_forward(h, we, be, keep, (launch, plan))
            e_ret = _scatter_out(launch, plan, e_out, out_dtype, (agg, gi.receivers, gi.recv_perm, gi.recv_offsets))
            if sum_e is not None:
                # per-graph sums: ordered sums over each graph's contiguous rows (no atomics); the
                # receivers' sums when they exist (each edge's receiver is in the edge's graph)
                if agg is not None:
                    _segment(launch, plan, agg, None, gi.node_offsets, sum_e)
                else:
                    _segment(launch, plan, e_out, None, gi.edge_offsets, sum_e)
            del e_out

            # ---- node update -----------------------------------------------------------------
            wn, bn = pn[0::2], pn[1::2]
            x_n = _concat(launch, plan, N, c.node_layout,
                          {"nodes": (v, None), "received_edges": (agg, None), "globals": (u, gi.node_graph)})
            fl_n = fls[n_e]
            hs_n, v_out = _mlp_forward(_linear(x_n, fl_n.w["all"], bn[0], relu=len(wn) > 1), wn, bn, keep,
                                       (launch, plan))
            if sum_v is not None:
                _segment(launch, plan, v_out, None, gi.node_offsets, sum_v)
            v_ret = v_out.to(out_dtype)
            del v_out

            # ---- global update ---------------------------------------------------------------
            hs_g = x_g = u_ret = fl_g = None
            if c.update_globals:
                wg, bg = pg[0::2], pg[1::2]
                x_g = _concat(launch, plan, B, c.global_layout,
                              {"globals": (u, None), "nodes": (sum_v, None), "edges": (sum_e, None)})
                fl_g = fls[n_n]
                hs_g, u_out = _mlp_forward(_linear(x_g, fl_g.w["all"], bg[0], relu=len(wg) > 1), wg, bg, keep,
                                           (launch, plan))
                u_ret = u_out.to(out_dtype)

        ctx.plan, ctx.gi = plan, gi
        # intermediates (not outputs: no reference cycle) for the hand-written backward
        ctx.saved = None if not keep else dict(v=v_c, e=e_c, u=u_c, fl_e=fl_e, fl_n=fl_n, fl_g=fl_g, x_e=x_e,
                                               x_n=x_n, x_g=x_g, hs_e=hs_e, hs_n=hs_n, hs_g=hs_g, pc=pc)
        ctx.in_dtypes = tuple(None if x is None else x.dtype for x in (v, e, u))
        ctx.in_widths = tuple(None if x is None else x.shape[1] for x in (v, e, u))
        ctx.param_dtypes = [p.dtype for p in params]
        # FlatAdam's parameters: the backward adds their gradients into ``main_grad`` (one launch
        # for the weights, one for the biases) and returns None for them
        ctx.main_params = params if has_main_grad(params) else None
        ctx.set_materialize_grads(False)
        outs = (v_ret, e_ret)
        if c.update_globals:
            outs = outs + (u_ret,)
        return outs

    @staticmethod
    def backward(ctx, gv_out, ge_out, gu_out=None):
        plan, gi, s = ctx.plan, ctx.gi, ctx.saved
        c = plan.config
        cd, ad = plan.compute_dtype, plan.acc_dtype
        det = plan.deterministic
        pc = s["pc"]
        like = pc[0]
        dev = like.device
        launch = _Launcher(like)
        side = _Side(like)
        N, E, B = gi.n_nodes, gi.n_edges, gi.n_graphs
        need = ctx.needs_input_grad[1:]  # drop ``keep``: indices as in (plan, gi, v, e, u, *params)
        need_v, need_e, need_u = need[2], need[3], need[4]
        need_w = any(need[5:])
        pe, pn, pg = _split_mlp_params(plan, pc)
        in_dt, in_w = ctx.in_dtypes, ctx.in_widths
        # The incoming gradients (gv_out, ge_out, gu_out) are read as autograd hands them over (any
        # float dtype, any strides) by the gather kernels that start each update's backward.
        ge = None

        ecols, ncols = column_slices(c.edge_layout), column_slices(c.node_layout)
        H = pe[0].shape[0]
        node_pieces = [n for n in ("sender_nodes", "receiver_nodes") if n in ecols]
        edge_glob = "globals" in ecols
        edge_concat = s["x_e"] is not None
        # Parameter gradients. With FlatAdam's ``main_grad`` (and every parameter wanted), the
        # weight-gradient GEMMs add straight into it (cuBLAS's epilogue, float32 for fp16 / bf16
        # operands where torch offers it) and the bias sums' atomics target it: no gradient
        # buffer and no accumulate launch. Otherwise weights go to one compute-dtype buffer and
        # biases to one accumulation-dtype buffer, added into ``main_grad`` (or returned) at the end.
        mains = [p.main_grad for p in ctx.main_params] if (need_w and ctx.main_params is not None) else None
        every = all(need[5:])
        w_main = mains is not None and every and _gemm_accumulates(cd, mains[0].dtype, dev)
        b_main = mains is not None and every and not det and mains[0].dtype == ad
        w_shapes = [tuple(p.shape) if (need_w and k % 2 == 0 and not w_main) else None for k, p in enumerate(pc)]
        b_shapes = [tuple(p.shape) if (need_w and k % 2 == 1 and not b_main) else None for k, p in enumerate(pc)]
        # input gradients, summed in the accumulation dtype (the updates' pieces add into them);
        # the split edge first layer's gradient summed by sender / receiver and by graph
        acc_shapes = [(N, in_w[0]) if need_v else None, (B, in_w[2]) if need_u else None]
        if not edge_concat:
            acc_shapes += [(N, H * len(node_pieces)) if node_pieces else None, (B, H) if edge_glob else None]
        gws_all, gw_buf, w_offs = _carve(w_shapes, cd, dev, zero=False)
        views, b_buf, b_offs = _carve(b_shapes + acc_shapes, ad, dev, zero=True)
        gbs_all = views[:len(pc)]
        gv_acc, gu_acc = views[len(pc)], views[len(pc) + 1]
        p_nodes, p_glob = views[len(pc) + 2:] if not edge_concat else (None, None)
        if w_main:
            gws_all = [mains[k] if k % 2 == 0 else None for k in range(len(pc))]
        if b_main:
            gbs_all = [mains[k] if k % 2 == 1 else None for k in range(len(pc))]
        offsets = (0, plan.n_edge_params, plan.n_edge_params + plan.n_node_params, len(pc))

        def mlp_grads(k):
            """(weight-gradient views, bias-gradient views) of MLP k (0 edge, 1 node, 2 global)."""
            a, b = offsets[k], offsets[k + 1]
            return gws_all[a:b:2], gbs_all[a + 1:b:2]

        done = [False, False, False]  # MLPs whose gradients were computed (the others get None)

        with matmul_precision(plan.precision):
            # ---- global update -----------------------------------------------------------------
            g_sum_v = g_sum_e = None
            if c.update_globals and gu_out is not None:
                wg = pg[0::2]
                gws, gbs = mlp_grads(2)
                gu_tot, summed = _gather_add(launch, plan, B, c.global_out, gu_out, (None, None), (None, None),
                                             gbs[-1] if need_w else None)
                g0 = _mlp_backward(launch, plan, side, gu_tot, s["hs_g"], wg, gws, gbs, need_w, summed, w_main)
                fl = s["fl_g"]
                g_x = fl.backward_concat(plan, side, g0, s["x_g"], gws[0] if need_w else None, w_main)
                gcols = column_slices(c.global_layout)
                g_sum_v = g_x[:, gcols["nodes"]] if "nodes" in gcols else None
                g_sum_e = g_x[:, gcols["edges"]] if "edges" in gcols else None
                if need_u and "globals" in gcols:
                    _route(launch, plan, g_x, c.global_layout, {"globals": (gu_acc, None, None)})
                done[2] = True

            # ---- node update -------------------------------------------------------------------
            g_agg = None
            gws, gbs = mlp_grads(1)
            gv_tot, summed = _gather_add(launch, plan, N, c.node_out, gv_out, (g_sum_v, gi.node_graph), (None, None),
                                         gbs[-1] if need_w else None)
            if gv_tot is not None:
                wn = pn[0::2]
                g0 = _mlp_backward(launch, plan, side, gv_tot, s["hs_n"], wn, gws, gbs, need_w, summed, w_main)
                fl = s["fl_n"]
                g_x = fl.backward_concat(plan, side, g0, s["x_n"], gws[0] if need_w else None, w_main)
                g_agg = g_x[:, ncols["received_edges"]] if "received_edges" in ncols else None
                routes = {}
                if need_v and "nodes" in ncols:
                    routes["nodes"] = (gv_acc, None, None)
                if need_u and "globals" in ncols:
                    routes["globals"] = (gu_acc, gi.node_graph, (None, gi.node_offsets))
                _route(launch, plan, g_x, c.node_layout, routes)
                done[1] = True

            # ---- edge update -------------------------------------------------------------------
            gws, gbs = mlp_grads(0)
            ge_tot, summed = _gather_add(launch, plan, E, c.edge_out, ge_out, (g_agg, gi.receivers),
                                         (g_sum_e, gi.edge_graph), gbs[-1] if need_w else None)
            if ge_tot is not None:
                we = pe[0::2]
                g0 = _mlp_backward(launch, plan, side, ge_tot, s["hs_e"], we, gws, gbs, need_w, summed, w_main)
                fl = s["fl_e"]
                blocks, buf = fl.grad_blocks(gws[0]) if (need_w and not edge_concat) else (None, None)
                if edge_concat:
                    if need_w:
                        fl.weight_grad(plan, side, g0, s["x_e"], gws[0], w_main)
                    if need_e or need_v or need_u:
                        g_x = torch.mm(g0, fl.w["all"])
                        routes = {}
                        if need_e and "edges" in ecols:
                            ge = torch.empty(E, in_w[1], dtype=in_dt[1], device=dev)
                            routes["edges"] = (ge, None, None)
                        if need_v:
                            for name in node_pieces:
                                snd = name == "sender_nodes"
                                routes[name] = (gv_acc, gi.senders if snd else gi.receivers,
                                                (gi.send_perm, gi.send_offsets) if snd else (gi.recv_perm, gi.recv_offsets))
                        if need_u and edge_glob:
                            routes["globals"] = (gu_acc, gi.edge_graph, (None, gi.edge_offsets))
                        _route(launch, plan, g_x, c.edge_layout, routes, store=("edges",))
                    done[0] = True
                elif "edges" in ecols:
                    if need_w:
                        with side(g0, s["e"]):
                            torch.mm(g0.t(), s["e"], out=blocks["edges"])
                    if need_e:
                        ge = torch.mm(g0, fl.w["edges"])[:, :_width(ecols, "edges")]
                want_nodes = node_pieces and (need_w or need_v)
                want_glob = edge_glob and (need_w or need_u)
                if not edge_concat and (want_nodes or want_glob):
                    # gradient of the node / global projections: g0 summed by sender, receiver, graph
                    _scatter_first_layer(launch, plan, gi, g0, node_pieces, p_nodes if want_nodes else None,
                                         p_glob if want_glob else None)
                if not edge_concat and want_nodes:
                    pn_c = p_nodes.to(cd)
                    if need_w:
                        with side(pn_c, s["v"]):
                            for k in range(len(node_pieces)):
                                torch.mm(pn_c[:, k * H:(k + 1) * H].t(), s["v"], out=blocks["nodes"][k * H:(k + 1) * H])
                    if need_v:
                        gv_acc.add_(torch.mm(pn_c, fl.w["nodes"])[:, :_width(ecols, node_pieces[0])])
                if not edge_concat and want_glob:
                    pg_c = p_glob.to(cd)
                    if need_w:
                        with side(pg_c, s["u"]):
                            torch.mm(pg_c.t(), s["u"], out=blocks["globals"])
                    if need_u:
                        gu_acc.add_(torch.mm(pg_c, fl.w["globals"])[:, :_width(ecols, "globals")])
                if need_w and not edge_concat:  # the blocks' GEMMs may run on several side streams
                    side.after(lambda fl=fl, buf=buf, gw0=gws[0]: fl.unpack(launch, plan, buf, gw0, w_main))
                done[0] = True

        side.join()  # the weight gradients are complete from here on
        out = [None if (g is None or not want) else g if g.dtype == dt else g.to(dt)
               for g, dt, want in ((gv_acc, in_dt[0], need_v), (ge, in_dt[1], need_e), (gu_acc, in_dt[2], need_u))]
        params_out = [None] * len(pc)
        if mains is not None:
            got = [need[5 + k] and done[0 if k < offsets[1] else 1 if k < offsets[2] else 2] for k in range(len(pc))]
            if not w_main:
                accumulate_main_grads(launch, gw_buf, [(w_offs[k], k) for k in range(0, len(pc), 2) if got[k]], mains)
            if not b_main:
                accumulate_main_grads(launch, b_buf, [(b_offs[k], k) for k in range(1, len(pc), 2) if got[k]], mains)
        elif need_w:
            pdt = ctx.param_dtypes[0]
            if gw_buf.dtype != pdt:  # reduced precision: one cast of all weight gradients
                gws_all = _views(gw_buf.to(pdt), w_shapes, w_offs)
            for k in range(len(pc)):
                mlp = 0 if k < offsets[1] else 1 if k < offsets[2] else 2
                if need[5 + k] and done[mlp]:
                    g = gws_all[k] if k % 2 == 0 else gbs_all[k]
                    params_out[k] = g.to(ctx.param_dtypes[k])
        return (None, None, None, *out, *params_out)


def _route(launch, plan, g_x, layout, routes, store=()):
    """Backward of ``_concat``: the gradient ``g_x`` of an update's input rows handed back to its
    inputs, in one ``split_kernel`` pass. ``routes``: {piece: (out, index, segments)}: the
    piece's columns of row r are added into ``out`` at row ``index[r]`` (atomic), or at row r
    when ``index`` is None; pieces named in ``store`` are stored at row r instead (no other
    piece writes there). Pieces not in ``routes`` are left alone (read in place by their
    consumers). Deterministic mode adds the indexed pieces by ordered segment sums
    (``segments`` = (CSR perm or None, offsets)) after the pass, one launch each."""
    if not routes:
        return
    cols = column_slices(layout)
    ph = launch.placeholder
    pieces, later = [], []
    for name, (out, index, segments) in routes.items():
        sl = cols[name]
        if plan.deterministic and index is not None:
            later.append((sl, out, segments))
            continue
        mode = K.SPLIT_STORE if name in store else K.SPLIT_ADD
        pieces.append(((sl.start, sl.stop - sl.start, mode, index is not None, _WP_DTYPE[out.dtype]), index, out))
    if pieces:
        rows, cols_total = g_x.shape[0], sum(p[0][1] for p in pieces)
        if rows * cols_total >= 2 ** 31:  # thread ids are int32
            raise ValueError(f"batch too large for one GN block launch: {rows} rows x {cols_total} gradient "
                             "columns exceeds 2**31; split the batch")
        kernel = K.split_kernel(tuple(p[0] for p in pieces), plan.wp_dtype)
        pad = 4 - len(pieces)
        launch.n(kernel, rows * cols_total, g_x,
                 *[p[1] if p[1] is not None else ph(torch.int32, 1) for p in pieces], *[ph(torch.int32, 1)] * pad,
                 *[p[2] for p in pieces], *[ph(plan.compute_dtype, 2)] * pad)
    for sl, out, (perm, offsets) in later:
        _segment(launch, plan, g_x, perm, offsets, out, sl.start, 0, sl.stop - sl.start, accumulate=True)


def _scatter_first_layer(launch, plan, gi, g0, node_pieces, p_nodes, p_glob):
    """Backward of the split first layer of the edge update: sums of the rows of ``g0`` by sender
    (columns [0, H) of ``p_nodes``) and by receiver (the next H columns), in one atomic pass or
    (deterministic) ordered segment sums; and by graph (``p_glob``): ordered sums over each
    graph's rows, from the receivers' sums when they exist (N rows instead of E; each edge's
    receiver is in the edge's graph)."""
    H = g0.shape[1]
    if p_nodes is not None:
        if plan.deterministic:
            for k, name in enumerate(node_pieces):
                perm = gi.send_perm if name == "sender_nodes" else gi.recv_perm
                offs = gi.send_offsets if name == "sender_nodes" else gi.recv_offsets
                _segment(launch, plan, g0, perm, offs, p_nodes, 0, k * H, H)
        else:
            launch(K.scatter_edges_kernel(H, "sender_nodes" in node_pieces, "receiver_nodes" in node_pieces, False,
                                          plan.wp_dtype, plan.wp_acc), g0.shape, g0,
                   gi.senders, gi.receivers, gi.edge_graph, p_nodes, launch.placeholder(plan.acc_dtype, 2))
    if p_glob is not None:
        if p_nodes is not None and "receiver_nodes" in node_pieces:
            rcv_col = node_pieces.index("receiver_nodes") * H
            _segment(launch, plan, p_nodes, None, gi.node_offsets, p_glob, rcv_col, 0, H)
        else:
            _segment(launch, plan, g0, None, gi.edge_offsets, p_glob)


def _segment(launch, plan, src, perm, offsets, out, src_col=0, dst_col=0, width=None, accumulate=False):
    W = src.shape[1] if width is None else width
    k = K.segment_sum_kernel(W, perm is not None, _WP_DTYPE[src.dtype], _WP_DTYPE[out.dtype], accumulate)
    launch(k, (out.shape[0], W), src, perm if perm is not None else launch.placeholder(torch.int32, 1),
           offsets, src_col, dst_col, out)


def _width(cols, name):
    return cols[name].stop - cols[name].start


def _gather_add(launch, plan, rows, width, base, a, b, gb):
    """(base + src_a[index_a] + src_b[index_b] over ``rows`` rows in the compute dtype, contiguous;
    whether ``gb`` got its column sums): one kernel, which reads ``base`` (an incoming gradient)
    in its own dtype and strides and adds the column sums of its result into ``gb`` (atomics)
    when given and not deterministic. Returns (base, False) when there is nothing to gather,
    cast or sum, (None, False) when all are None."""
    (src_a, idx_a), (src_b, idx_b) = a, b
    ph = launch.placeholder
    cd = plan.compute_dtype
    fused = gb is not None and not plan.deterministic
    if src_a is None and src_b is None:
        if base is None:
            return None, False
        if not fused and base.dtype == cd and base.is_contiguous():
            return base, False
    if base is not None and (base.dim() != 2 or base.shape != (rows, width)):
        raise ValueError(f"gradient of a GN block output: expected shape {(rows, width)}, got {tuple(base.shape)}")
    if base is not None and min(base.stride()) <= 0:  # broadcast (expanded) gradients: one real row
        base = base.contiguous()
    out = torch.empty(rows, width, dtype=cd, device=(src_a if src_a is not None else src_b if src_b is not None
                                                     else base).device)
    chunk = K.chunk_rows(rows, width)
    launch.n(K.gather_add_sum_kernel(width, base is not None, src_a is not None, src_b is not None, fused,
                                     plan.wp_dtype, _WP_DTYPE[base.dtype] if base is not None and base.dtype != cd
                                     else None),
             K.chunk_dim(rows, width, chunk),
             base if base is not None else ph(cd, 2), src_a if src_a is not None else ph(cd, 2),
             idx_a if src_a is not None else ph(torch.int32, 1), src_b if src_b is not None else ph(cd, 2),
             idx_b if src_b is not None else ph(torch.int32, 1), rows, chunk, out,
             gb if fused else ph(plan.acc_dtype, 1))
    return out, fused


# -- path choice --------------------------------------------------------------------------------
# Shared-memory budget of a fused tile kernel on CUDA (bytes): all weights of one MLP plus a few
# row tiles must fit on one SM (H100/H200: 228 KB per SM, 227 KB per block).
_TILE_SMEM_BUDGET = 160 * 1024


def _mlp_weight_elems(in_size, hidden, out_size) -> int:
    sizes = [in_size, *hidden, out_size]
    return sum(a * b + b for a, b in zip(sizes[:-1], sizes[1:]))


def tile_feasible(config: GNBlockConfig, precision: str, deterministic: bool, device: torch.device) -> str | None:
    """None if the fused tile path can run this block, else the reason why not."""
    if deterministic:
        return "deterministic mode needs ordered segment sums (tile scatters are atomic)"
    if precision not in ("fp32",):
        return f"tile path runs fp32/fp64 only (precision={precision!r})"
    if device.type == "cuda":
        c = config
        from gnwarp.gn import _width  # noqa: PLC0415
        for name, layout, hid, out in (("edge", c.edge_layout, c.edge_hidden, c.edge_out),
                                       ("node", c.node_layout, c.node_hidden, c.node_out),
                                       ("global", c.global_layout, c.global_hidden, c.global_out)):
            if not layout:
                continue
            nbytes = 4 * _mlp_weight_elems(_width(layout), hid, out)
            if nbytes > _TILE_SMEM_BUDGET:
                return (f"{name} MLP weights take {nbytes // 1024} KB, over the {_TILE_SMEM_BUDGET // 1024} KB "
                        f"shared-memory budget of one fused tile kernel")
    return None


def choose_path(config: GNBlockConfig, precision: str, deterministic: bool, device: torch.device,
                n_edges: int) -> str:
    """The "auto" rule: the split path (Warp graph kernels + BLAS GEMMs) unless the fused tile
    path is feasible and was measured faster for such a block.

    Why the split path is the default: Warp's tile GEMM runs at 18 GFLOP/s on the 2-core CPU
    against 172 for CPU BLAS, and at 28-34 TFLOP/s on an H200 against cuBLAS's 48 (fp32) / 205
    (tf32) / 527 (fp16) (../shared/notes/warp-mujoco.md), and paper-size MLPs (3x512) do not fit
    a fused kernel's shared memory at all. The tile path can only pay where launches dominate:

    - CUDA (bench/gn_block.py crossover on an H200, paper core on cheetah graphs with every width
      w, fp32, both paths in one CUDA graph, as in a training loop): tile wins at w=16 from batch
      16 up to 200 (the largest measured: 3600 edges; fwd 0.13 vs 0.20 ms, fwd+bwd 0.54 vs 0.79 ms
      at 200), split wins at batch 1, and at w=32 (fwd+bwd 0.82 vs 1.27 ms at 200) and w=64
      (fwd 0.19 vs 0.43 ms; the w=64 backward does not fit shared memory). Uncaptured, the tile
      path's 3 launches per block beat the split path's ~10 at every w <= 64 measured, but
      captured loops are the fast way to run either.
    - CPU (same crossover on the 2-core CPU, one thread): tile within 10% at batch 1 with w=16
      (fwd 0.97 vs 1.06 ms) and slower everywhere else (w=16, batch 200: fwd 11.7 vs 6.0 ms,
      fwd+bwd 41 vs 17 ms): always split.

    Hence: tile on CUDA when every hidden / output width <= ``_TILE_MAX_WIDTH`` and the batch has
    ``_TILE_MIN_EDGES`` to ``_TILE_MAX_EDGES`` edges (outside that range: unmeasured or slower);
    else split. A tile kernel found too large for the device's shared memory when it is built
    falls back to the split path. Re-derive the constants from the "crossover" section of the
    benchmark when kernels or Warp change.
    """
    if tile_feasible(config, precision, deterministic, device) is not None:
        return "split"
    if device.type != "cuda":
        return "split"
    c = config
    widths = (*c.edge_hidden, *c.node_hidden, *c.global_hidden, c.edge_out, c.node_out, c.global_out)
    if max(widths) <= _TILE_MAX_WIDTH and _TILE_MIN_EDGES <= n_edges <= _TILE_MAX_EDGES:
        return "tile"
    return "split"


# Crossover of the "auto" rule on CUDA (H200, bench/results/gn_block_nvidia-h200.md): cheetah
# graphs have 18 edges, so 288 edges = batch 16 and 3600 = batch 200.
_TILE_MAX_WIDTH = 16
_TILE_MIN_EDGES = 288
_TILE_MAX_EDGES = 3600


# -- entry point --------------------------------------------------------------------------------
def _compute_dtype(precision: str, param_dtype: torch.dtype) -> torch.dtype:
    if precision == "fp16":
        return torch.float16
    if precision == "bf16":
        return torch.bfloat16
    return param_dtype


def gn_block_forward(module, graph: GraphsTuple, index: GraphIndex | None = None) -> GraphsTuple:
    """Run ``module`` (a GraphNetwork) on ``graph`` with the Warp backend."""
    c: GNBlockConfig = module.config
    params = module.flat_parameters()
    p0 = params[0]
    if index is None:
        index = graph_index(graph, deterministic=module.deterministic)
    elif module.deterministic and not index.deterministic:
        raise ValueError("deterministic GraphNetwork needs a GraphIndex built with deterministic=True")
    path = module.path
    auto = path == "auto"
    if auto:
        path = choose_path(c, module.precision, module.deterministic, p0.device, index.n_edges)
    v = graph.nodes if c.needs_nodes else None
    e = graph.edges if c.needs_edges else None
    u = graph.globals if c.needs_globals else None
    outs = None
    if path == "tile":
        why = tile_feasible(c, module.precision, module.deterministic, p0.device)
        if why is not None:
            raise ValueError(f"path='tile' cannot run this block: {why}")
        from gnwarp import gn_tile  # noqa: PLC0415
        try:
            outs = gn_tile.tile_block(c, index, v, e, u, params, module.edge_mlp.layers, module.node_mlp.layers,
                                      module.global_mlp.layers if module.global_mlp is not None else None)
        except gn_tile.TileSharedMemoryError:
            if not auto:
                raise
            outs = None  # checked before any launch: the split path runs instead
    if outs is None:
        cd = _compute_dtype(module.precision, p0.dtype)
        ad = torch.float64 if cd == torch.float64 else torch.float32
        emu = tuple(getattr(module, "emulate_min", None) or (_EMU_MIN_ROWS, _EMU_MIN_WIDTH))
        # fp16x3 below its rule's rows (or on float64 parameters) is the fp32 path, with fp32's
        # edge first-layer rule too
        rule = module.precision
        if rule == "fp16x3" and (index.n_edges < emu[0] or cd != torch.float32):
            rule = "fp32"
        plan = _Plan(c, cd, ad, module.precision, module.deterministic,
                     2 * len(module.edge_mlp.layers), 2 * len(module.node_mlp.layers),
                     edge_concat(c, getattr(module, "edge_first_layer", "auto"), rule), emu)
        # under no_grad (inference, rollouts) keep no activations for a backward that cannot come
        keep = torch.is_grad_enabled() and any(x is not None and x.requires_grad for x in (v, e, u, *params))
        outs = _SplitBlock.apply(plan, keep, index, v, e, u, *params)
    v_out, e_out = outs[0], outs[1]
    u_out = outs[2] if c.update_globals else graph.globals
    return graph._replace(nodes=v_out, edges=e_out, globals=u_out)
