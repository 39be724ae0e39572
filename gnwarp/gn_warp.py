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
from dataclasses import dataclass
from typing import NamedTuple

import torch
import warp as wp

from gnwarp.gn import GNBlockConfig, column_slices, matmul_precision
from gnwarp.graphs import GraphsTuple
from gnwarp.kernels import gn_block as K

__all__ = ["GraphIndex", "graph_index", "gn_block_forward", "choose_path", "tile_feasible", "warp_stream",
           "cuda_graph"]

_WP_DTYPE = {torch.float32: wp.float32, torch.float64: wp.float64, torch.float16: wp.float16,
             torch.bfloat16: wp.bfloat16}


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

    @property
    def wp_dtype(self):
        return _WP_DTYPE[self.compute_dtype]

    @property
    def wp_acc(self):
        return _WP_DTYPE[self.acc_dtype]


def _split_mlp_params(plan: _Plan, params):
    a, b = plan.n_edge_params, plan.n_edge_params + plan.n_node_params
    return params[:a], params[a:b], params[b:]


def _mlp_tail_forward(launch, plan, h, ws, bs, keep: bool):
    """Hidden layers 1.. and output GEMM of an MLP whose first layer output is ``h``.

    Returns (hs, z): the hidden activations [h1, ..., hL] (inputs of layers 1..L; saved for
    backward) and the output layer's GEMM result without bias (or ``None`` when the MLP has a
    single layer: then ``h`` is the output, its bias already added, and ``hs`` is empty). Without
    ``keep`` (no gradient wanted) only the last activation is held, so memory stays flat."""
    T = plan.wp_dtype
    n_layers = len(ws)
    if n_layers == 1:
        return [], None
    hs = [h]
    for l in range(1, n_layers - 1):
        z = torch.mm(hs[-1], ws[l].t())
        launch(K.bias_act_kernel(z.shape[1], True, T), z.shape, z, bs[l], z)
        hs = hs + [z] if keep else [z]
    return hs, torch.mm(hs[-1], ws[-1].t())


def _mlp_tail_backward(launch, plan, g, hs, ws, need_w: bool):
    """Backward through layers L..1 of an MLP. ``g``: gradient of the output.

    Returns (g0, gws, gbs): gradient at the first layer's pre-activation, and the gradients of
    the weights / biases of layers 1..L (lists, None if not ``need_w``)."""
    T = plan.wp_dtype
    gws, gbs = [], []
    for l in range(len(ws) - 1, 0, -1):
        x = hs[l - 1]
        if need_w:
            gws.append(torch.mm(g.t(), x))
            gbs.append(g.sum(0, dtype=plan.acc_dtype))
        gh = torch.mm(g, ws[l])
        launch(K.relu_grad_kernel(gh.shape[1], T), gh.shape, x, gh, gh)
        g = gh
    return g, gws[::-1], gbs[::-1]


def _zeros(rows, cols, dtype, like):
    return torch.zeros(rows, cols, dtype=dtype, device=like.device)


class _SplitBlock(torch.autograd.Function):
    """One GN block on the split path. Inputs: (plan, keep, GraphIndex, nodes, edges, globals, *params)
    with params = edge MLP [W0, b0, ...] + node MLP + global MLP. Outputs: (nodes', edges'[,
    globals']) in the parameters' dtype."""

    @staticmethod
    def forward(ctx, plan: _Plan, keep: bool, gi: GraphIndex, v, e, u, *params):
        c = plan.config
        cd, ad = plan.compute_dtype, plan.acc_dtype
        T = plan.wp_dtype
        out_dtype = params[0].dtype
        like = params[0]
        launch = _Launcher(like)
        ph = launch.placeholder
        det = plan.deterministic
        N, E, B = gi.n_nodes, gi.n_edges, gi.n_graphs
        cast = (lambda x: None if x is None else x.to(cd).contiguous())
        pc = [p.to(cd) for p in params]
        pe, pn, pg = _split_mlp_params(plan, pc)
        v_c, e_c, u_c = cast(v), cast(e), cast(u)

        with matmul_precision(plan.precision):
            # ---- edge update -----------------------------------------------------------------
            we, be = pe[0::2], pe[1::2]
            cols = column_slices(c.edge_layout)
            H = we[0].shape[0]
            direct = torch.mm(e_c, we[0][:, cols["edges"]].t()) if "edges" in cols else None
            node_blocks = [we[0][:, cols[n]] for n in ("sender_nodes", "receiver_nodes") if n in cols]
            w_nodes = torch.cat(node_blocks, 0) if node_blocks else None
            node_proj = torch.mm(v_c, w_nodes.t()) if node_blocks else None
            glob_proj = torch.mm(u_c, we[0][:, cols["globals"]].t()) if "globals" in cols else None
            h = torch.empty(E, H, dtype=cd, device=like.device)
            launch(K.first_layer_kernel(H, direct is not None, "sender_nodes" in cols, "receiver_nodes" in cols,
                                        glob_proj is not None, len(we) > 1, T), (E, H),
                   direct if direct is not None else ph(cd, 2), node_proj if node_proj is not None else ph(cd, 2),
                   glob_proj if glob_proj is not None else ph(cd, 2), gi.senders, gi.receivers, gi.edge_graph,
                   be[0], h)
            del direct, node_proj, glob_proj
            hs_e, z = _mlp_tail_forward(launch, plan, h, we, be, keep)
            e_out = z if z is not None else h
            agg = _zeros(N, c.edge_out, ad, like) if c.aggregates_to_nodes else None
            sum_e = _zeros(B, c.edge_out, ad, like) if c.edges_to_globals else None
            _output_epilogue(launch, plan, gi, z, be[-1], e_out, det,
                             (agg, gi.receivers, gi.recv_perm, gi.recv_offsets),
                             (sum_e, gi.edge_graph, None, gi.edge_offsets))

            # ---- node update -----------------------------------------------------------------
            wn, bn = pn[0::2], pn[1::2]
            cols = column_slices(c.node_layout)
            H = wn[0].shape[0]
            agg_c = cast(agg)
            direct = None
            for name, x in (("nodes", v_c), ("received_edges", agg_c)):
                if name in cols:
                    w = wn[0][:, cols[name]].t()
                    direct = torch.mm(x, w) if direct is None else direct.addmm_(x, w)
            glob_proj = torch.mm(u_c, wn[0][:, cols["globals"]].t()) if "globals" in cols else None
            h = torch.empty(N, H, dtype=cd, device=like.device)
            launch(K.first_layer_kernel(H, direct is not None, False, False, glob_proj is not None, len(wn) > 1, T),
                   (N, H), direct if direct is not None else ph(cd, 2), ph(cd, 2),
                   glob_proj if glob_proj is not None else ph(cd, 2), gi.senders, gi.receivers, gi.node_graph,
                   bn[0], h)
            del direct, glob_proj
            hs_n, z = _mlp_tail_forward(launch, plan, h, wn, bn, keep)
            v_out = z if z is not None else h
            sum_v = _zeros(B, c.node_out, ad, like) if c.nodes_to_globals else None
            _output_epilogue(launch, plan, gi, z, bn[-1], v_out, det,
                             (sum_v, gi.node_graph, None, gi.node_offsets), (None, None, None, None))

            # ---- global update ---------------------------------------------------------------
            hs_g, sum_v_c, sum_e_c = None, None, None
            u_out = None
            if c.update_globals:
                wg, bg = pg[0::2], pg[1::2]
                cols = column_slices(c.global_layout)
                H = wg[0].shape[0]
                sum_v_c, sum_e_c = cast(sum_v), cast(sum_e)
                direct = None
                for name, x in (("globals", u_c), ("nodes", sum_v_c), ("edges", sum_e_c)):
                    if name in cols:
                        w = wg[0][:, cols[name]].t()
                        direct = torch.mm(x, w) if direct is None else direct.addmm_(x, w)
                h = torch.empty(B, H, dtype=cd, device=like.device)
                launch(K.first_layer_kernel(H, True, False, False, False, len(wg) > 1, T), (B, H),
                       direct, ph(cd, 2), ph(cd, 2), gi.senders, gi.receivers, gi.node_graph, bg[0], h)
                del direct
                hs_g, z = _mlp_tail_forward(launch, plan, h, wg, bg, keep)
                u_out = z if z is not None else h
                _output_epilogue(launch, plan, gi, z, bg[-1], u_out, det, (None,) * 4, (None,) * 4)

        ctx.plan, ctx.gi = plan, gi
        # intermediates (not outputs: no reference cycle) for the hand-written backward
        ctx.saved = None if not keep else dict(v=v_c, e=e_c, u=u_c, agg=agg_c, sum_v=sum_v_c, sum_e=sum_e_c,
                                               hs_e=hs_e, hs_n=hs_n, hs_g=hs_g, pc=pc)
        ctx.in_dtypes = (None if v is None else v.dtype, None if e is None else e.dtype,
                         None if u is None else u.dtype)
        ctx.param_dtypes = [p.dtype for p in params]
        ctx.set_materialize_grads(False)
        outs = (v_out.to(out_dtype), e_out.to(out_dtype))
        if c.update_globals:
            outs = outs + (u_out.to(out_dtype),)
        return outs

    @staticmethod
    def backward(ctx, gv_out, ge_out, gu_out=None):
        plan, gi, s = ctx.plan, ctx.gi, ctx.saved
        c = plan.config
        cd, ad = plan.compute_dtype, plan.acc_dtype
        det = plan.deterministic
        pc = s["pc"]
        like = pc[0]
        launch = _Launcher(like)
        N, E, B = gi.n_nodes, gi.n_edges, gi.n_graphs
        need = ctx.needs_input_grad[1:]  # drop ``keep``: indices as in (plan, gi, v, e, u, *params)
        need_v, need_e, need_u = need[2], need[3], need[4]
        need_w = any(need[5:])
        pe, pn, pg = _split_mlp_params(plan, pc)
        # our own contiguous copies in the compute dtype: never hand torch's grad buffers to Warp
        grad_in = (lambda g: None if g is None else g.to(cd, copy=True).contiguous())
        gv_out, ge_out, gu_out = grad_in(gv_out), grad_in(ge_out), grad_in(gu_out)
        gv = gu = ge = None                      # input gradients (compute dtype)
        g_params = [None] * len(pc)

        def add(acc, x):
            return x if acc is None else acc.add_(x)

        def first_layer_weight_grad(w0, layout, g0, inputs):
            """Gradient of W0 (all column blocks) and of each input piece."""
            cols = column_slices(layout)
            gw0 = torch.zeros_like(w0, dtype=ad) if need_w else None
            g_inputs = {}
            for name, x in inputs.items():
                if name not in cols or x is None:
                    continue
                if need_w:
                    gw0[:, cols[name]] = torch.mm(g0.t(), x)
                g_inputs[name] = torch.mm(g0, w0[:, cols[name]])
            return gw0, g_inputs

        offsets = (0, plan.n_edge_params, plan.n_edge_params + plan.n_node_params)

        def store_mlp_grads(k, gw0, gb0, gws, gbs):
            if not need_w:
                return
            o = offsets[k]
            g_params[o], g_params[o + 1] = gw0, gb0
            for l, (gw, gb) in enumerate(zip(gws, gbs), start=1):
                g_params[o + 2 * l], g_params[o + 2 * l + 1] = gw, gb

        with matmul_precision(plan.precision):
            # ---- global update -----------------------------------------------------------------
            g_sum_v = g_sum_e = None
            if c.update_globals and gu_out is not None:
                wg = pg[0::2]
                g0, gws, gbs = _mlp_tail_backward(launch, plan, gu_out, s["hs_g"], wg, need_w)
                gw0, gin = first_layer_weight_grad(
                    wg[0], c.global_layout, g0, {"globals": s["u"], "nodes": s["sum_v"], "edges": s["sum_e"]})
                store_mlp_grads(2, gw0, g0.sum(0, dtype=ad) if need_w else None, gws, gbs)
                g_sum_v, g_sum_e = gin.get("nodes"), gin.get("edges")
                if need_u and "globals" in gin:
                    gu = add(gu, gin["globals"])

            # ---- node update -------------------------------------------------------------------
            g_agg = None
            gv_tot = _gather_add(launch, plan, N, c.node_out, gv_out, (g_sum_v, gi.node_graph), (None, None))
            if gv_tot is not None:
                wn = pn[0::2]
                g0, gws, gbs = _mlp_tail_backward(launch, plan, gv_tot, s["hs_n"], wn, need_w)
                gw0, gin = first_layer_weight_grad(wn[0], c.node_layout, g0, {"nodes": s["v"],
                                                                              "received_edges": s["agg"]})
                if "globals" in column_slices(c.node_layout):
                    g_proj = _segment_or_scatter(launch, plan, g0, B, (gi.node_graph, None, gi.node_offsets))
                    gs = column_slices(c.node_layout)["globals"]
                    if need_w:
                        gw0[:, gs] = torch.mm(g_proj.t(), s["u"])
                    if need_u:
                        gu = add(gu, torch.mm(g_proj, wn[0][:, gs]))
                store_mlp_grads(1, gw0, g0.sum(0, dtype=ad) if need_w else None, gws, gbs)
                g_agg = gin.get("received_edges")
                if need_v and "nodes" in gin:
                    gv = add(gv, gin["nodes"])

            # ---- edge update -------------------------------------------------------------------
            ge_tot = _gather_add(launch, plan, E, c.edge_out, ge_out, (g_agg, gi.receivers),
                                 (g_sum_e, gi.edge_graph))
            if ge_tot is not None:
                we = pe[0::2]
                g0, gws, gbs = _mlp_tail_backward(launch, plan, ge_tot, s["hs_e"], we, need_w)
                cols = column_slices(c.edge_layout)
                gw0, gin = first_layer_weight_grad(we[0], c.edge_layout, g0, {"edges": s["e"]})
                H = we[0].shape[0]
                node_pieces = [n for n in ("sender_nodes", "receiver_nodes") if n in cols]
                if node_pieces:
                    # gradient of the node projections: scatter of g0 by sender / receiver
                    g_proj = _zeros(N, H * len(node_pieces), cd if det else ad, like)
                    for k, name in enumerate(node_pieces):
                        idx = gi.senders if name == "sender_nodes" else gi.receivers
                        perm = gi.send_perm if name == "sender_nodes" else gi.recv_perm
                        offs = gi.send_offsets if name == "sender_nodes" else gi.recv_offsets
                        _segment_or_scatter(launch, plan, g0, N, (idx, perm, offs), out=g_proj, dst_col=k * H)
                    g_proj = g_proj.to(cd)
                    w_nodes = torch.cat([we[0][:, cols[n]] for n in node_pieces], 0)
                    if need_w:
                        gwn = torch.mm(g_proj.t(), s["v"])
                        for k, name in enumerate(node_pieces):
                            gw0[:, cols[name]] = gwn[k * H:(k + 1) * H]
                    if need_v:
                        gv = add(gv, torch.mm(g_proj, w_nodes))
                if "globals" in cols:
                    g_proj = _segment_or_scatter(launch, plan, g0, B, (gi.edge_graph, None, gi.edge_offsets))
                    if need_w:
                        gw0[:, cols["globals"]] = torch.mm(g_proj.t(), s["u"])
                    if need_u:
                        gu = add(gu, torch.mm(g_proj, we[0][:, cols["globals"]]))
                store_mlp_grads(0, gw0, g0.sum(0, dtype=ad) if need_w else None, gws, gbs)
                if need_e and "edges" in gin:
                    ge = gin["edges"]

        in_dt = ctx.in_dtypes
        out = [None if g is None else g.to(dt) for g, dt in ((gv, in_dt[0]), (ge, in_dt[1]), (gu, in_dt[2]))]
        params_out = [None if (g is None or not need[5 + k]) else g.to(ctx.param_dtypes[k])
                      for k, g in enumerate(g_params)]
        return (None, None, None, *out, *params_out)


def _output_epilogue(launch, plan, gi, z, bias, out, det, target_a, target_b):
    """Bias of the output GEMM (when ``z`` is given) fused with the scatter-sums of the result:
    atomic adds, or (deterministic) ordered segment sums after it.

    ``target_*``: (sum array or None, row -> destination index, perm or None, segment offsets)."""
    T = plan.wp_dtype
    ph = launch.placeholder
    sum_a, idx_a, perm_a, offs_a = target_a
    sum_b, idx_b, _, offs_b = target_b
    scatter_a = sum_a is not None and not det
    scatter_b = sum_b is not None and not det
    if z is not None or scatter_a or scatter_b:
        H = out.shape[1]
        launch(K.output_epilogue_kernel(H, z is not None, scatter_a, scatter_b, T), out.shape,
               out, idx_a if scatter_a else ph(torch.int32, 1), idx_b if scatter_b else ph(torch.int32, 1),
               bias, out, sum_a if scatter_a else ph(plan.acc_dtype, 2), sum_b if scatter_b else ph(plan.acc_dtype, 2))
    if det:
        if sum_a is not None:
            _segment(launch, plan, out, perm_a, offs_a, sum_a)
        if sum_b is not None:
            _segment(launch, plan, out, None, offs_b, sum_b)


def _segment(launch, plan, src, perm, offsets, out, src_col=0, dst_col=0, width=None):
    W = src.shape[1] if width is None else width
    k = K.segment_sum_kernel(W, perm is not None, _WP_DTYPE[src.dtype], _WP_DTYPE[out.dtype])
    launch(k, (out.shape[0], W), src, perm if perm is not None else launch.placeholder(torch.int32, 1),
           offsets, src_col, dst_col, out)


def _segment_or_scatter(launch, plan, src, n_rows, index, out=None, dst_col=0):
    """Sum rows of ``src`` into ``n_rows`` destinations given by ``index`` = (row -> destination,
    CSR perm or None, CSR offsets): ordered segment sums in deterministic mode, else atomics."""
    idx, perm, offs = index
    W = src.shape[1]
    if out is None:
        out = _zeros(n_rows, W, plan.compute_dtype if plan.deterministic else plan.acc_dtype, src)
    if plan.deterministic:
        _segment(launch, plan, src, perm, offs, out, 0, dst_col, W)
    else:
        launch(K.scatter_add_kernel(W, _WP_DTYPE[src.dtype], _WP_DTYPE[out.dtype]), src.shape,
               src, idx, 0, dst_col, out)
    return out.to(plan.compute_dtype)


def _gather_add(launch, plan, rows, width, base, a, b):
    """base + src_a[index_a] + src_b[index_b] over ``rows`` rows; None if all terms are None."""
    (src_a, idx_a), (src_b, idx_b) = a, b
    if base is None and src_a is None and src_b is None:
        return None
    if src_a is None and src_b is None:
        return base
    ph = launch.placeholder
    cd = plan.compute_dtype
    out = torch.empty(rows, width, dtype=cd, device=(base if base is not None else (src_a if src_a is not None
                                                                                       else src_b)).device)
    launch(K.gather_add_kernel(width, base is not None, src_a is not None, src_b is not None, plan.wp_dtype),
           (rows, width), base if base is not None else ph(cd, 2),
           src_a.contiguous() if src_a is not None else ph(cd, 2), idx_a if src_a is not None else ph(torch.int32, 1),
           src_b.contiguous() if src_b is not None else ph(cd, 2), idx_b if src_b is not None else ph(torch.int32, 1),
           out)
    return out


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
        plan = _Plan(c, cd, ad, module.precision, module.deterministic,
                     2 * len(module.edge_mlp.layers), 2 * len(module.node_mlp.layers))
        # under no_grad (inference, rollouts) keep no activations for a backward that cannot come
        keep = torch.is_grad_enabled() and any(x is not None and x.requires_grad for x in (v, e, u, *params))
        outs = _SplitBlock.apply(plan, keep, index, v, e, u, *params)
    v_out, e_out = outs[0], outs[1]
    u_out = outs[2] if c.update_globals else graph.globals
    return graph._replace(nodes=v_out, edges=e_out, globals=u_out)
