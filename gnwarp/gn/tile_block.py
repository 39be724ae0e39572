"""The fused Warp-tile path of the GN block: three launches forward (edge, node, global update,
each gather + MLP + scatter in one kernel, ``kernels/gn/tile_block.py``), their adjoint launches
backward (Warp's autodiff).

``GraphNetwork`` runs it when ``path="tile"`` (or "auto" picks it, ``rules.choose_path``). fp32 /
fp64 only.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from gnwarp.gn.config import GNBlockConfig
from gnwarp.gn.index import GraphIndex
from gnwarp.gn.rules import TUNABLES
from gnwarp.interop import WP_DTYPE, Launcher
from gnwarp.kernels.gn import tile_block as KT

__all__ = ["tile_block", "TILE_ROWS", "TileSharedMemoryError"]

TILE_ROWS = 16     # rows (edges / nodes / graphs) per thread block
BLOCK_DIM = 64     # threads per block on CUDA (the CPU runs a block as one thread)


def pack_mlp(layers) -> tuple[torch.Tensor, torch.Tensor]:
    """(W, b): every layer's W^T stacked by rows, padded to the widest layer, and one bias per
    row. Differentiable torch ops, so gradients of the pack flow back to the nn.Linear layers."""
    ws = [layer.weight.t() for layer in layers]
    n = max(w.shape[1] for w in ws)
    w = torch.cat([F.pad(x, (0, n - x.shape[1])) for x in ws], 0).contiguous()
    b = torch.stack([F.pad(layer.bias, (0, n - layer.bias.shape[0])) for layer in layers], 0).contiguous()
    return w, b


def _pad_index(x: torch.Tensor, tm: int) -> torch.Tensor:
    pad = (-x.shape[0]) % tm
    return F.pad(x, (0, pad), value=-1) if pad else x


# Warp's CPU tile kernels run in a fixed shared-memory arena; going past it aborts the process
# (an assertion in warp/native/tile.h), so it is checked before launching.
CPU_TILE_ARENA = 256 * 1024


class TileSharedMemoryError(ValueError):
    """A fused tile kernel would not fit the device's shared memory (raised before any launch)."""


class _Update:
    """One update's kernel and its argument slots."""

    def __init__(self, name, slots, hidden, out_size, n_scatter, dtype):
        self.name = name
        self.slots = tuple(slots) + ((KT.ABSENT, 0),) * (4 - len(slots))
        self.kernel = KT.update_tile_kernel(TILE_ROWS, self.slots, tuple(hidden), out_size, n_scatter, dtype,
                                            mathdx=TUNABLES.tile_mathdx)

    def check_shared_memory(self, device, backward: bool):
        """Compile / load the kernel and raise ValueError if its tiles exceed the shared memory
        of ``device`` (forward, and backward when it will run)."""
        block_dim = BLOCK_DIM if device.is_cuda else 1
        meta = self.kernel.module.load(device, block_dim).meta
        limit = device.max_shared_memory_per_block if device.is_cuda else CPU_TILE_ARENA
        for direction in ("forward",) + (("backward",) if backward else ()):
            need = max((v for k, v in meta.items() if k.endswith(f"_{direction}_smem_bytes")), default=0)
            if limit and need > limit:
                raise TileSharedMemoryError(f"path='tile': the fused {self.name} kernel needs {need // 1024} KiB of "
                                            f"shared memory ({direction}), over the {limit // 1024} KiB of {device}; "
                                            f"use path='blas' or smaller MLPs")


def _launch_update(launch, upd, rows, xs, idx, scat, w, b, out, sums, adj=None):
    """Launch (or, with ``adj``, launch the adjoint of) one update kernel over ``rows`` rows."""
    launch.tiled(upd.kernel, -(-rows // TILE_ROWS), BLOCK_DIM, *xs, *idx, *scat, w, b, out, *sums, adjoint=adj)


class _TileBlock(torch.autograd.Function):
    @staticmethod
    def forward(ctx, spec, gi: GraphIndex, v, e, u, we, be, wn, bn, wg, bg):
        """Builds the three updates, checks their shared memory, then launches them in order."""
        c: GNBlockConfig = spec["config"]
        like = we
        dt = like.dtype
        T = WP_DTYPE[dt]
        launch = Launcher(like)
        ph2 = launch.placeholder(dt, 2)
        ph1 = launch.placeholder(torch.int32, 1)
        N, E, B = gi.n_nodes, gi.n_edges, gi.n_graphs
        v = v.contiguous() if v is not None else None
        e = e.contiguous() if e is not None else None
        u = u.contiguous() if u is not None else None
        tm = TILE_ROWS
        snd, rcv = _pad_index(gi.senders, tm), _pad_index(gi.receivers, tm)
        eg, ng = _pad_index(gi.edge_graph, tm), _pad_index(gi.node_graph, tm)

        # edge update
        eb = c.edge_block
        slots = [(KT.ROWS if eb.use_edges else KT.ABSENT, c.edge_size),
                 (KT.GATHER if eb.use_sender_nodes else KT.ABSENT, c.node_size),
                 (KT.GATHER if eb.use_receiver_nodes else KT.ABSENT, c.node_size),
                 (KT.GATHER if eb.use_globals else KT.ABSENT, c.global_size)]
        e_scat = [(rcv, "agg")] if c.aggregates_to_nodes else []
        e_scat += [(eg, "sum_e")] if c.edges_to_globals else []
        up_e = _Update("edge", slots, c.edge_hidden, c.edge_out, len(e_scat), T)
        e_out = torch.empty(E, c.edge_out, dtype=dt, device=like.device)
        agg = torch.zeros(N, c.edge_out, dtype=dt, device=like.device) if c.aggregates_to_nodes else None
        sum_e = torch.zeros(B, c.edge_out, dtype=dt, device=like.device) if c.edges_to_globals else None
        sums = {"agg": agg, "sum_e": sum_e}
        e_args = dict(
            xs=[e if eb.use_edges else ph2, v if eb.use_sender_nodes else ph2,
                v if eb.use_receiver_nodes else ph2, u if eb.use_globals else ph2],
            idx=[ph1, snd, rcv, eg],
            scat=[x for x, _ in e_scat] + [ph1] * (2 - len(e_scat)),
            out=e_out, sums=[sums[n] for _, n in e_scat] + [ph2] * (2 - len(e_scat)))
        todo = [(up_e, E, we, be, e_args)]

        # node update
        nb = c.node_block
        slots = [(KT.ROWS if nb.use_nodes else KT.ABSENT, c.node_size),
                 (KT.ROWS if nb.use_received_edges else KT.ABSENT, c.edge_out),
                 (KT.GATHER if nb.use_globals else KT.ABSENT, c.global_size)]
        n_scat = 1 if c.nodes_to_globals else 0
        up_n = _Update("node", slots, c.node_hidden, c.node_out, n_scat, T)
        v_out = torch.empty(N, c.node_out, dtype=dt, device=like.device)
        sum_v = torch.zeros(B, c.node_out, dtype=dt, device=like.device) if n_scat else None
        n_args = dict(
            xs=[v if nb.use_nodes else ph2, agg if nb.use_received_edges else ph2, u if nb.use_globals else ph2,
                ph2],
            idx=[ph1, ph1, ng, ph1], scat=[ng if n_scat else ph1, ph1], out=v_out,
            sums=[sum_v if n_scat else ph2, ph2])
        todo.append((up_n, N, wn, bn, n_args))

        # global update
        u_out, up_g, g_args = None, None, None
        if c.update_globals:
            gb = c.global_block
            slots = [(KT.ROWS if gb.use_globals else KT.ABSENT, c.global_size),
                     (KT.ROWS if gb.use_nodes else KT.ABSENT, c.node_out),
                     (KT.ROWS if gb.use_edges else KT.ABSENT, c.edge_out)]
            up_g = _Update("global", slots, c.global_hidden, c.global_out, 0, T)
            u_out = torch.empty(B, c.global_out, dtype=dt, device=like.device)
            g_args = dict(
                xs=[u if gb.use_globals else ph2, sum_v if gb.use_nodes else ph2,
                    sum_e if gb.use_edges else ph2, ph2],
                idx=[ph1] * 4, scat=[ph1, ph1], out=u_out, sums=[ph2, ph2])
            todo.append((up_g, B, wg, bg, g_args))

        for up, *_ in todo:
            up.check_shared_memory(launch.device, spec["backward"])
        for up, rows, w, b, args in todo:
            _launch_update(launch, up, rows, w=w, b=b, **args)

        ctx.spec, ctx.gi = spec, gi
        # the adjoint replays the forward into a scratch output: keep no reference to the outputs
        for a in (e_args, n_args, g_args):
            if a is not None:
                a["out"] = (a["out"].shape, a["out"].dtype)
        ctx.state = dict(updates=(up_e, up_n, up_g), args=(e_args, n_args, g_args),
                         params=(we, be, wn, bn, wg, bg), inputs=(v, e, u), sums=(agg, sum_e, sum_v))
        ctx.set_materialize_grads(False)
        outs = (v_out, e_out) + ((u_out,) if c.update_globals else ())
        return outs

    @staticmethod
    def backward(ctx, gv_out, ge_out, gu_out=None):
        st = ctx.state
        gi = ctx.gi
        up_e, up_n, up_g = st["updates"]
        e_args, n_args, g_args = st["args"]
        we, be, wn, bn, wg, bg = st["params"]
        v, e, u = st["inputs"]
        agg, sum_e, sum_v = st["sums"]
        launch = Launcher(we)
        N, E, B = gi.n_nodes, gi.n_edges, gi.n_graphs

        def zeros(x):
            return None if x is None else torch.zeros_like(x)

        e_args, n_args, g_args = (None if a is None else dict(a, out=torch.empty(a["out"][0], dtype=a["out"][1],
                                                                             device=we.device))
                                  for a in (e_args, n_args, g_args))

        def grad_buf(g, out):
            # our own buffer: the adjoint launch consumes its output gradient
            return torch.zeros_like(out) if g is None else g.to(out.dtype, copy=True).contiguous()

        ph = (lambda a: torch.zeros_like(a) if a is not None and a.numel() == 0 else a)
        gv, ge, gu = zeros(v), zeros(e), zeros(u)
        g_agg, g_sum_e, g_sum_v = zeros(agg), zeros(sum_e), zeros(sum_v)
        gwe, gbe, gwn, gbn = zeros(we), zeros(be), zeros(wn), zeros(bn)
        gwg, gbg = zeros(wg), zeros(bg)
        grad_of = {}
        for x, g in ((v, gv), (e, ge), (u, gu), (agg, g_agg), (sum_e, g_sum_e), (sum_v, g_sum_v)):
            if x is not None:
                grad_of[id(x)] = g

        def adj_list(args, w_grad, b_grad, out_grad, sum_grads):
            xs = [grad_of.get(id(x), ph(x)) for x in args["xs"]]
            return [*xs, None, None, None, None, None, None, w_grad, b_grad, out_grad, *sum_grads]

        def sum_grad(s):
            return grad_of.get(id(s), ph(s))

        if up_g is not None and gu_out is not None:
            _launch_update(launch, up_g, B, w=wg, b=bg, **g_args,
                           adj=adj_list(g_args, gwg, gbg, grad_buf(gu_out, g_args["out"]),
                                        [ph(s) for s in g_args["sums"]]))
        _launch_update(launch, up_n, N, w=wn, b=bn, **n_args,
                       adj=adj_list(n_args, gwn, gbn, grad_buf(gv_out, n_args["out"]),
                                    [sum_grad(s) for s in n_args["sums"]]))
        _launch_update(launch, up_e, E, w=we, b=be, **e_args,
                       adj=adj_list(e_args, gwe, gbe, grad_buf(ge_out, e_args["out"]),
                                    [sum_grad(s) for s in e_args["sums"]]))
        need = ctx.needs_input_grad
        grads = [gv, ge, gu, gwe, gbe, gwn, gbn, gwg, gbg]
        grads = [g if (g is not None and need[2 + k]) else None for k, g in enumerate(grads)]
        return (None, None, *grads)


def tile_block(config: GNBlockConfig, gi: GraphIndex, v, e, u, edge_layers, node_layers, global_layers):
    """Run one GN block on the fused tile path; returns (nodes', edges'[, globals'])."""
    we, be = pack_mlp(edge_layers)
    wn, bn = pack_mlp(node_layers)
    if global_layers is not None:
        wg, bg = pack_mlp(global_layers)
    else:
        wg, bg = None, None
    backward = torch.is_grad_enabled() and any(
        x is not None and x.requires_grad for x in (v, e, u, we, be, wn, bn, wg, bg))
    return _TileBlock.apply({"config": config, "backward": backward}, gi, v, e, u, we, be, wn, bn, wg, bg)
