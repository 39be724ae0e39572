"""One GN block on the blas path: Warp kernels for the graph work, BLAS GEMMs for the dense layers,
in one torch autograd Function with a hand-written backward (the chain rule of the forward,
checked with ``torch.autograd.gradcheck`` in float64).

Forward: the parameters in the compute dtype and the first-layer weights as aligned, padded
blocks in one launch (``first_layer.prepare``); the edge update's first layer on the
concatenated, gathered input rows (``graph_ops.concat``: one kernel, then one GEMM) or from
projections (node / global projections once per node / graph, gathered per edge by
``graph_ops.project``), as ``rules.edge_concat`` decides; the other layers as GEMMs with bias and
ReLU in cuBLASLt's epilogue (``mlp``); the output cast and the sum by receiver in one pass
(``graph_ops.scatter_out``), per-graph sums as ordered segment sums; node and global updates on
their concatenated input rows.

Backward, update by update (global, node, edge): one gather kernel that reads the incoming
gradient as autograd hands it over (any dtype and strides), adds the gradients of the sums it
fed and sums the output bias gradient (``graph_ops.gather_add``); GEMMs for weight gradients (on
a side stream; with FlatAdam added straight into ``main_grad``) and input gradients; ReLU masks
and bias gradients fused in one pass per layer; the gradient of each update's input rows handed
back to its inputs in one ``graph_ops.route`` pass (stored, or added by sender / receiver /
graph into input gradients summed in float32), or, for the projected first layer, one atomic
scatter (``graph_ops.project_grad``); ordered segment sums in deterministic mode.

Everything launches on torch's current stream and allocates through torch (so a
``torch.cuda.graph`` capture of a training step records it); nothing syncs with the host.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from gnwarp.gn import graph_ops
from gnwarp.gn.config import GNBlockConfig, column_slices
from gnwarp.gn.first_layer import padded, prepare
from gnwarp.gn.flat import accumulate_main_grads, carve, has_main_grad, views
from gnwarp.gn.fp16x3 import mlp_emulates
from gnwarp.gn.fp16x3 import mlp_forward as mlp_forward_emulated
from gnwarp.gn.index import GraphIndex
from gnwarp.gn.mlp import gemm, gemm_accumulates, linear, mlp_backward, mlp_forward
from gnwarp.gn.options import ResolvedRun
from gnwarp.gn.replay import active_store
from gnwarp.gn.rules import edge_concat
from gnwarp.gn.side import SideStreams
from gnwarp.interop import Launcher

__all__ = ["BlockPlan", "BlasBlock", "blas_block"]


@dataclass(frozen=True)
class BlockPlan:
    """Static description of one block call: config, resolved run options, parameter layout."""
    config: GNBlockConfig
    run: ResolvedRun
    n_edge_params: int           # 2 x layers of the edge MLP (weights and biases)
    n_node_params: int
    edge_concat: bool            # edge first layer on concatenated gathered rows (else projected)

    @property
    def offsets(self) -> tuple[int, int]:
        """First parameter index of the node and of the global MLP."""
        return self.n_edge_params, self.n_edge_params + self.n_node_params

    def mlps(self, params) -> tuple[list, list, list]:
        """``params`` (edge MLP [W0, b0, ...] + node MLP + global MLP) split per MLP."""
        a, b = self.offsets
        return params[:a], params[a:b], params[b:]

    def mlp_of(self, k: int) -> int:
        """The MLP (0 edge, 1 node, 2 global) of parameter ``k``."""
        a, b = self.offsets
        return 0 if k < a else 1 if k < b else 2


def _span(cols: dict, name: str) -> int:
    return cols[name].stop - cols[name].start


# -- forward, update by update --------------------------------------------------------------------
def _edge_forward(launch, plan: BlockPlan, gi: GraphIndex, v, e, u, pe, fl, keep: bool):
    """The edge update: (saved for backward, e' in the compute dtype)."""
    c, run = plan.config, plan.run
    we, be = pe[0::2], pe[1::2]
    saved = dict(x_e=None, v=None, e=None, u=None, hs_e=None, fl_e=fl)
    h = None
    if plan.edge_concat:
        x_e = saved["x_e"] = graph_ops.concat(launch, run, gi.n_edges, c.edge_layout,
                                              {"edges": (e, None), "sender_nodes": (v, gi.senders),
                                               "receiver_nodes": (v, gi.receivers), "globals": (u, gi.edge_graph)})
        if mlp_emulates(run, gi.n_edges, we):  # the first layer too: its K (the concatenated row) is wide
            saved["hs_e"], e_out = mlp_forward_emulated(launch, x_e, [fl.w["all"], *we[1:]], be, keep, [])
        else:
            h = linear(x_e, fl.w["all"], be[0], relu=len(we) > 1)
    else:
        # the inputs in the compute dtype, zero-padded, for the projection GEMMs (and their backward)
        cd = run.compute_dtype
        v_c, e_c, u_c = saved["v"], saved["e"], saved["u"] = padded(v, cd), padded(e, cd), padded(u, cd)
        cols = column_slices(c.edge_layout)
        direct = gemm(e_c, fl.w["edges"].t()) if "edges" in cols else None
        node_proj = gemm(v_c, fl.w["nodes"].t()) if "nodes" in fl.w else None
        glob_proj = gemm(u_c, fl.w["globals"].t()) if "globals" in cols else None
        h = graph_ops.project(launch, run, gi, direct, node_proj, glob_proj, "sender_nodes" in cols,
                              "receiver_nodes" in cols, be[0], relu=len(we) > 1)
        del direct, node_proj, glob_proj
    if h is not None:
        saved["hs_e"], e_out = mlp_forward(h, we, be, keep, launch, run)
    return saved, e_out


def _node_forward(launch, plan: BlockPlan, gi: GraphIndex, v, u, agg, pn, fl, keep: bool):
    """The node update: (saved for backward, v' in the compute dtype)."""
    c, run = plan.config, plan.run
    wn, bn = pn[0::2], pn[1::2]
    x_n = graph_ops.concat(launch, run, gi.n_nodes, c.node_layout,
                           {"nodes": (v, None), "received_edges": (agg, None), "globals": (u, gi.node_graph)})
    hs_n, v_out = mlp_forward(linear(x_n, fl.w["all"], bn[0], relu=len(wn) > 1), wn, bn, keep, launch, run)
    return dict(x_n=x_n, hs_n=hs_n, fl_n=fl), v_out


def _global_forward(launch, plan: BlockPlan, gi: GraphIndex, u, sum_v, sum_e, pg, fl, keep: bool):
    """The global update: (saved for backward, u' in the compute dtype)."""
    c, run = plan.config, plan.run
    wg, bg = pg[0::2], pg[1::2]
    x_g = graph_ops.concat(launch, run, gi.n_graphs, c.global_layout,
                           {"globals": (u, None), "nodes": (sum_v, None), "edges": (sum_e, None)})
    hs_g, u_out = mlp_forward(linear(x_g, fl.w["all"], bg[0], relu=len(wg) > 1), wg, bg, keep, launch, run)
    return dict(x_g=x_g, hs_g=hs_g, fl_g=fl), u_out


# -- backward: where the gradients go ------------------------------------------------------------
class _Grads:
    """The buffers the backward writes: the parameter gradients, and the input gradients summed
    in the accumulation dtype.

    With FlatAdam's ``main_grad`` (and every parameter wanted), the weight-gradient GEMMs add
    straight into it (cuBLAS's epilogue, float32 for fp16 / bf16 operands where torch offers it)
    and the bias sums' atomics target it: no gradient buffer and no accumulate launch. Otherwise
    weights go to one compute-dtype buffer and biases to one accumulation-dtype buffer (with the
    input-gradient sums: one memset), added into ``main_grad`` (or returned) by ``finish``."""

    def __init__(self, plan: BlockPlan, gi: GraphIndex, pc, need_p, main_params, in_widths, need_v: bool,
                 need_u: bool):
        run, c = plan.run, plan.config
        cd, ad, dev = run.compute_dtype, run.acc_dtype, pc[0].device
        N, B = gi.n_nodes, gi.n_graphs
        self.plan, self.need_p = plan, need_p
        self.need_w = any(need_p)
        self.mains = [p.main_grad for p in main_params] if (self.need_w and main_params is not None) else None
        every = all(need_p)
        self.w_main = self.mains is not None and every and gemm_accumulates(cd, self.mains[0].dtype, dev)
        self.b_main = self.mains is not None and every and not run.deterministic and self.mains[0].dtype == ad
        n = len(pc)
        self.w_shapes = [tuple(p.shape) if (self.need_w and k % 2 == 0 and not self.w_main) else None
                         for k, p in enumerate(pc)]
        b_shapes = [tuple(p.shape) if (self.need_w and k % 2 == 1 and not self.b_main) else None
                    for k, p in enumerate(pc)]
        # input gradients, summed in the accumulation dtype (the updates' pieces add into them);
        # the projected edge first layer's gradient summed by sender / receiver and by graph
        ecols = column_slices(c.edge_layout)
        H = pc[0].shape[0]
        node_pieces = [k for k in ("sender_nodes", "receiver_nodes") if k in ecols]
        acc_shapes = [(N, in_widths[0]) if need_v else None, (B, in_widths[2]) if need_u else None]
        if not plan.edge_concat:
            acc_shapes += [(N, H * len(node_pieces)) if node_pieces else None, (B, H) if "globals" in ecols else None]
        self.gws, self.w_buf, self.w_offs = carve(self.w_shapes, cd, dev, zero=False)
        vs, self.b_buf, self.b_offs = carve(b_shapes + acc_shapes, ad, dev, zero=True)
        self.gbs = vs[:n]
        self.gv, self.gu = vs[n], vs[n + 1]
        self.p_nodes, self.p_glob = vs[n + 2:] if not plan.edge_concat else (None, None)
        if self.w_main:
            self.gws = [self.mains[k] if k % 2 == 0 else None for k in range(n)]
        if self.b_main:
            self.gbs = [self.mains[k] if k % 2 == 1 else None for k in range(n)]
        self.done = [False, False, False]  # MLPs whose gradients were computed (the others get None)

    def mlp(self, k: int):
        """(weight-gradient views, bias-gradient views) of MLP k (0 edge, 1 node, 2 global)."""
        a, b = ((0,) + self.plan.offsets + (len(self.gbs),))[k:k + 2]
        return self.gws[a:b:2], self.gbs[a + 1:b:2]

    def finish(self, launch, param_dtypes) -> list:
        """The parameter gradients to return (None where ``main_grad`` received them)."""
        n = len(self.gbs)
        out = [None] * n
        got = [self.need_p[k] and self.done[self.plan.mlp_of(k)] for k in range(n)]
        if self.mains is not None:
            if not self.w_main:
                accumulate_main_grads(launch, self.w_buf, [(self.w_offs[k], k) for k in range(0, n, 2) if got[k]],
                                      self.mains)
            if not self.b_main:
                accumulate_main_grads(launch, self.b_buf, [(self.b_offs[k], k) for k in range(1, n, 2) if got[k]],
                                      self.mains)
        elif self.need_w:
            gws = self.gws
            if self.w_buf.dtype != param_dtypes[0]:  # reduced precision: one cast of all weight gradients
                gws = views(self.w_buf.to(param_dtypes[0]), self.w_shapes, self.w_offs)
            for k in range(n):
                if got[k]:
                    out[k] = (gws[k] if k % 2 == 0 else self.gbs[k]).to(param_dtypes[k])
        return out


# -- backward, update by update -----------------------------------------------------------------
def _global_backward(launch, side, plan: BlockPlan, gi, grads: _Grads, s: dict, pg, gu_out, need_u: bool):
    """Backward of the global update: the gradients of the per-graph node and edge sums it read."""
    c, run = plan.config, plan.run
    gws, gbs = grads.mlp(2)
    need_w = grads.need_w
    gu_tot, summed = graph_ops.gather_add(launch, run, gi.n_graphs, c.global_out, gu_out, (None, None), (None, None),
                                          gbs[-1] if need_w else None)
    g0 = mlp_backward(launch, run, side, gu_tot, s["hs_g"], pg[0::2], gws, gbs, need_w, summed, grads.w_main)
    g_x = s["fl_g"].backward_concat(side, g0, s["x_g"], gws[0] if need_w else None, grads.w_main)
    cols = column_slices(c.global_layout)
    if need_u and "globals" in cols:
        graph_ops.route(launch, run, g_x, c.global_layout, {"globals": (grads.gu, None, None)})
    grads.done[2] = True
    return (g_x[:, cols["nodes"]] if "nodes" in cols else None), (g_x[:, cols["edges"]] if "edges" in cols else None)


def _node_backward(launch, side, plan: BlockPlan, gi, grads: _Grads, s: dict, pn, gv_out, g_sum_v, need_v, need_u):
    """Backward of the node update: the gradient of the received-edge sums it read (or None)."""
    c, run = plan.config, plan.run
    gws, gbs = grads.mlp(1)
    need_w = grads.need_w
    gv_tot, summed = graph_ops.gather_add(launch, run, gi.n_nodes, c.node_out, gv_out, (g_sum_v, gi.node_graph),
                                          (None, None), gbs[-1] if need_w else None)
    if gv_tot is None:
        return None
    g0 = mlp_backward(launch, run, side, gv_tot, s["hs_n"], pn[0::2], gws, gbs, need_w, summed, grads.w_main)
    g_x = s["fl_n"].backward_concat(side, g0, s["x_n"], gws[0] if need_w else None, grads.w_main)
    cols = column_slices(c.node_layout)
    routes = {}
    if need_v and "nodes" in cols:
        routes["nodes"] = (grads.gv, None, None)
    if need_u and "globals" in cols:
        routes["globals"] = (grads.gu, gi.node_graph, (None, gi.node_offsets))
    graph_ops.route(launch, run, g_x, c.node_layout, routes)
    grads.done[1] = True
    return g_x[:, cols["received_edges"]] if "received_edges" in cols else None


def _edge_backward(launch, side, plan: BlockPlan, gi, grads: _Grads, s: dict, pe, ge_out, g_agg, g_sum_e,
                   need, in_dt, in_w):
    """Backward of the edge update; returns the gradient of the edge features (or None)."""
    c, run = plan.config, plan.run
    cd = run.compute_dtype
    need_v, need_e, need_u = need
    gws, gbs = grads.mlp(0)
    need_w = grads.need_w
    ge_tot, summed = graph_ops.gather_add(launch, run, gi.n_edges, c.edge_out, ge_out, (g_agg, gi.receivers),
                                          (g_sum_e, gi.edge_graph), gbs[-1] if need_w else None)
    if ge_tot is None:
        return None
    g0 = mlp_backward(launch, run, side, ge_tot, s["hs_e"], pe[0::2], gws, gbs, need_w, summed, grads.w_main)
    fl = s["fl_e"]
    cols = column_slices(c.edge_layout)
    node_pieces = [n for n in ("sender_nodes", "receiver_nodes") if n in cols]
    ge = None
    grads.done[0] = True
    if plan.edge_concat:
        if need_w:
            fl.weight_grad(side, g0, s["x_e"], gws[0], grads.w_main)
        if need_e or need_v or need_u:
            g_x = torch.mm(g0, fl.w["all"])
            routes = {}
            if need_e and "edges" in cols:
                ge = torch.empty(gi.n_edges, in_w[1], dtype=in_dt[1], device=g0.device)
                routes["edges"] = (ge, None, None)
            if need_v:
                for name in node_pieces:
                    snd = name == "sender_nodes"
                    routes[name] = (grads.gv, gi.senders if snd else gi.receivers,
                                    (gi.send_perm, gi.send_offsets) if snd else (gi.recv_perm, gi.recv_offsets))
            if need_u and "globals" in cols:
                routes["globals"] = (grads.gu, gi.edge_graph, (None, gi.edge_offsets))
            graph_ops.route(launch, run, g_x, c.edge_layout, routes, store=("edges",))
        return ge
    # projected first layer: each piece's weight block and input gradient from its own GEMMs
    H = g0.shape[1]
    blocks, buf = fl.grad_blocks(gws[0]) if need_w else (None, None)
    if "edges" in cols:
        if need_w:
            with side(g0, s["e"]):
                torch.mm(g0.t(), s["e"], out=blocks["edges"])
        if need_e:
            ge = torch.mm(g0, fl.w["edges"])[:, :_span(cols, "edges")]
    want_nodes = node_pieces and (need_w or need_v)
    want_glob = "globals" in cols and (need_w or need_u)
    if want_nodes or want_glob:
        # gradient of the node / global projections: g0 summed by sender, receiver, graph
        graph_ops.project_grad(launch, run, gi, g0, node_pieces, grads.p_nodes if want_nodes else None,
                               grads.p_glob if want_glob else None)
    if want_nodes:
        pn_c = grads.p_nodes.to(cd)
        if need_w:
            with side(pn_c, s["v"]):
                for k in range(len(node_pieces)):
                    torch.mm(pn_c[:, k * H:(k + 1) * H].t(), s["v"], out=blocks["nodes"][k * H:(k + 1) * H])
        if need_v:
            grads.gv.add_(torch.mm(pn_c, fl.w["nodes"])[:, :_span(cols, node_pieces[0])])
    if want_glob:
        pg_c = grads.p_glob.to(cd)
        if need_w:
            with side(pg_c, s["u"]):
                torch.mm(pg_c.t(), s["u"], out=blocks["globals"])
        if need_u:
            grads.gu.add_(torch.mm(pg_c, fl.w["globals"])[:, :_span(cols, "globals")])
    if need_w:  # the blocks' GEMMs may run on several side streams: unpack after they join
        side.after(lambda: fl.unpack(launch, buf, gws[0], grads.w_main))
    return ge


def _prepare(launch, plan: BlockPlan, params):
    """The parameters in the compute dtype and the first layers' weight blocks (``prepare``)."""
    c = plan.config
    n_e, n_n = plan.offsets
    first = [(0, c.edge_layout, not plan.edge_concat), (n_e, c.node_layout, False)]
    if c.update_globals:
        first.append((n_n, c.global_layout, False))
    return prepare(launch, plan.run, params, first)


def _save(ctx, plan: BlockPlan, gi: GraphIndex, saved, v, e, u, params) -> None:
    """What the backward reads besides ``saved`` (the intermediates, or None without a backward)."""
    ctx.plan, ctx.gi = plan, gi
    ctx.saved = saved
    ctx.in_dtypes = tuple(None if x is None else x.dtype for x in (v, e, u))
    ctx.in_widths = tuple(None if x is None else x.shape[1] for x in (v, e, u))
    ctx.param_dtypes = [p.dtype for p in params]
    # FlatAdam's parameters: the backward adds their gradients into ``main_grad`` and
    # returns None for them
    ctx.main_params = params if has_main_grad(params) else None
    ctx.set_materialize_grads(False)


def _replay(ctx, plan: BlockPlan, keep: bool, gi: GraphIndex, v, e, u, params, store, slot, k):
    """The forward of a block that replays (``gnwarp/gn/replay.py``): the stored outputs (zeros
    for those not kept) and, for the backward, the packed ReLU masks in place of the activations;
    no GEMM runs."""
    if any(p.requires_grad for p in params):
        raise RuntimeError("a replayed GN block computes no weight gradients: its parameters must not require grad "
                           "(RolloutEngine freezes them in its backward)")
    c = plan.config
    n_e, n_n = plan.offsets
    pc, fls = _prepare(Launcher(params[0]), plan, params)
    masks = slot.masks
    saved = dict(x_e=None, v=None, e=None, u=None, hs_e=masks.get("edge", []), fl_e=fls[0], x_n=None,
                 hs_n=masks.get("node", []), fl_n=fls[n_e], x_g=None, hs_g=masks.get("global", []),
                 fl_g=fls[n_n] if c.update_globals else None, pc=pc)
    like = params[0]
    outs = (store.output(slot, "nodes", (gi.n_nodes, c.node_out), like),
            store.output(slot, "edges", (gi.n_edges, c.edge_out), like))
    if c.update_globals:
        outs += (store.output(slot, "globals", (gi.n_graphs, c.global_out), like),)
    _save(ctx, plan, gi, saved if keep else None, v, e, u, params)
    return outs


class BlasBlock(torch.autograd.Function):
    """One GN block on the blas path (see the module docstring). Inputs: (plan, keep, GraphIndex,
    nodes, edges, globals, *params) with params = edge MLP [W0, b0, ...] + node MLP + global MLP;
    ``keep``: keep activations for a backward. Outputs: (nodes', edges'[, globals']) in the
    parameters' dtype."""

    @staticmethod
    def forward(ctx, plan: BlockPlan, keep: bool, gi: GraphIndex, v, e, u, *params):
        c, run = plan.config, plan.run
        out_dtype = params[0].dtype
        launch = Launcher(params[0])
        N, B = gi.n_nodes, gi.n_graphs
        n_e, n_n = plan.offsets
        store = active_store()
        taken = store.take() if store is not None else None
        if taken is not None and store.mode == "replay":
            return _replay(ctx, plan, keep, gi, v, e, u, params, store, *taken)
        record = taken is not None   # a rollout's forward: keep the masks (and outputs) in the store
        keep_acts = keep or record
        pc, fls = _prepare(launch, plan, params)
        pe, pn, pg = plan.mlps(pc)
        # scatter-sum destinations (accumulation dtype), one allocation: one memset
        (agg, sum_e, sum_v), _, _ = carve(
            [(N, c.edge_out) if c.aggregates_to_nodes else None, (B, c.edge_out) if c.edges_to_globals else None,
             (B, c.node_out) if c.nodes_to_globals else None], run.acc_dtype, params[0].device,
            zero=not run.deterministic)

        with run.matmul():
            saved, e_out = _edge_forward(launch, plan, gi, v, e, u, pe, fls[0], keep_acts)
            e_ret = graph_ops.scatter_out(launch, run, e_out, out_dtype,
                                          (agg, gi.receivers, gi.recv_perm, gi.recv_offsets))
            if sum_e is not None:
                # per-graph sums: ordered sums over each graph's contiguous rows (no atomics); the
                # receivers' sums when they exist (each edge's receiver is in the edge's graph)
                if agg is not None:
                    graph_ops.segment(launch, run, agg, None, gi.node_offsets, sum_e)
                else:
                    graph_ops.segment(launch, run, e_out, None, gi.edge_offsets, sum_e)
            del e_out
            s_n, v_out = _node_forward(launch, plan, gi, v, u, agg, pn, fls[n_e], keep_acts)
            saved.update(s_n)
            if sum_v is not None:
                graph_ops.segment(launch, run, v_out, None, gi.node_offsets, sum_v)
            v_ret = v_out.to(out_dtype)
            del v_out
            u_ret = None
            saved.update(x_g=None, hs_g=None, fl_g=None)
            if c.update_globals:
                s_g, u_out = _global_forward(launch, plan, gi, u, sum_v, sum_e, pg, fls[n_n], keep_acts)
                saved.update(s_g)
                u_ret = u_out.to(out_dtype)

        if record:
            store.record(launch, *taken, {"nodes": v_ret, "edges": e_ret, "globals": u_ret},
                         {"edge": saved["hs_e"] or [], "node": saved["hs_n"] or [], "global": saved["hs_g"] or []})
        # intermediates (not outputs: no reference cycle) for the hand-written backward
        _save(ctx, plan, gi, dict(saved, pc=pc) if keep else None, v, e, u, params)
        return (v_ret, e_ret) + ((u_ret,) if c.update_globals else ())

    @staticmethod
    def backward(ctx, gv_out, ge_out, gu_out=None):
        plan, gi, s = ctx.plan, ctx.gi, ctx.saved
        c, run = plan.config, plan.run
        pc = s["pc"]
        launch = Launcher(pc[0])
        side = SideStreams(pc[0])
        need = ctx.needs_input_grad  # (plan, keep, gi, v, e, u, *params)
        need_v, need_e, need_u = need[3], need[4], need[5]
        in_dt, in_w = ctx.in_dtypes, ctx.in_widths
        grads = _Grads(plan, gi, pc, need[6:], ctx.main_params, in_w, need_v, need_u)
        pe, pn, pg = plan.mlps(pc)
        # The incoming gradients (gv_out, ge_out, gu_out) are read as autograd hands them over (any
        # float dtype, any strides) by the gather kernels that start each update's backward.
        with run.matmul():
            g_sum_v = g_sum_e = None
            if c.update_globals and gu_out is not None:
                g_sum_v, g_sum_e = _global_backward(launch, side, plan, gi, grads, s, pg, gu_out, need_u)
            g_agg = _node_backward(launch, side, plan, gi, grads, s, pn, gv_out, g_sum_v, need_v, need_u)
            ge = _edge_backward(launch, side, plan, gi, grads, s, pe, ge_out, g_agg, g_sum_e,
                                (need_v, need_e, need_u), in_dt, in_w)
        side.join()  # the weight gradients are complete from here on
        out = [None if (g is None or not want) else g if g.dtype == dt else g.to(dt)
               for g, dt, want in ((grads.gv, in_dt[0], need_v), (ge, in_dt[1], need_e), (grads.gu, in_dt[2], need_u))]
        return (None, None, None, *out, *grads.finish(launch, ctx.param_dtypes))


def blas_block(config: GNBlockConfig, run: ResolvedRun, gi: GraphIndex, v, e, u, params, n_edge_layers: int,
               n_node_layers: int):
    """Run one GN block on the blas path; returns (nodes', edges'[, globals'])."""
    plan = BlockPlan(config, run, 2 * n_edge_layers, 2 * n_node_layers, edge_concat(config, run, gi.n_edges))
    # under no_grad (inference, rollouts) keep no activations for a backward that cannot come
    keep = torch.is_grad_enabled() and any(x is not None and x.requires_grad for x in (v, e, u, *params))
    return BlasBlock.apply(plan, keep, gi, v, e, u, *params)
