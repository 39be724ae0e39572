"""The learned forward model of the paper (supplementary D.1-D.5, D.7.1, D.7.4) and its MLP baseline (E).

One model, two cores::

    input graph G_i = concat(static graph, dynamic graph)           (``GraphBuilder``)
    G_n  = Norm_in(G_i)                                             (``Normalizer`` per globals/nodes/edges)
    dN_n = core(G_n)                                                (``GNCore``: GN2([G_n, GN1(G_n)]).nodes,
                                                                     or ``MLPCore`` on the flattened graph)
    dN   = Norm_out^-1(dN_n)                                        (per dynamic feature)
    next = update(N_d, dN)    pos, linvel, angvel: +;  quat: dq (x) q with |dq| = 1
    world body (node 0 of each graph) kept fixed; re-centred in x, y for translation-invariant
    single-system models (D.4).

A node's 13 dynamic features and their change: ``gnwarp.state`` (``state_delta``,
``apply_delta``). Everything below works on *flat* nodes ([sum(n_node), 13]) so batches may mix
graphs of any size; ``rollout`` maps [N, B, 13] body states to and from them with a
``GraphTemplate`` built once.
"""
from __future__ import annotations

import copy
from typing import Any, NamedTuple

import torch
import torch.nn as nn

from gnwarp.data.builder import GraphTemplate, graph_builder
from gnwarp.data.layout import FeatureLayout
from gnwarp.gn.options import RunOptions
from gnwarp.graphs import GraphsTuple, graph_of
from gnwarp.interop import WP_DTYPE, Launcher
from gnwarp.kernels.models import forward as K
from gnwarp.models.config import MLPCoreConfig, ModelConfig
from gnwarp.models.cores import GNCore, MLPCore
from gnwarp.models.normalizer import Normalizer, accumulate_over_ranks, normalize_graph
from gnwarp.models.rollout import (RolloutEngine, RolloutInputError, RolloutInputs, float_tensor, check_instance,
                                   rollout_with_adjoint, source_info)
from gnwarp.state import (ANGVEL, DYN_NODE_SIZE, LINVEL, POS, QUAT, apply_delta, quat_normalize, rotation_loss,
                          state_delta)

__all__ = ["input_sizes", "StepContext", "ForwardModel", "MLPForwardModel"]


def input_sizes(layout: FeatureLayout) -> dict[str, int]:
    """Input feature widths of the full graph, read from the layout (one source of truth)."""
    if layout.n_global_ctrl:
        raise ValueError(f"the layout has {layout.n_global_ctrl} controls of actuators not on a joint edge (a "
                         "site, body or slider-crank transmission, or a tendon) on the globals, which no model reads; "
                         "regenerate the data: gnwarp generate puts actuators on fixed tendons on their joints' edges "
                         "and refuses the transmissions the graph cannot carry, naming the actuator")
    return dict(layout.sizes)


class StepContext(NamedTuple):
    """Per-topology bookkeeping of a batch of graphs, computed once and reused every step."""
    node_graph: torch.Tensor   # [n_nodes] graph of each node
    movable: torch.Tensor      # [n_nodes] bool: not a world body (node 0 of its graph)
    n_graph: int
    index: Any                 # the core's graph index (Warp GraphIndex or None)
    stats: dict                # normalizer (mean, std) by name, as of when the context was made
    movable_i32: Any = None    # [n_nodes] int32 of movable, [n_graph + 1] int32 first node of
    node_offsets: Any = None   # each graph and [n_nodes] int32 node_graph: what the Warp kernel
    node_graph_i32: Any = None  # of a batch's inputs reads


class ForwardModel(nn.Module):
    """One-step forward model (Algorithm D.1): ``x_{t+1} = M(static graph, x_t, a_t)``.

    Args:
        config: ``ModelConfig`` (core "gn" or "mlp", sizes, run options, re-centring).
        layout: the ``FeatureLayout`` of its input graphs (from the training dataset).

    The model is built in the dtype its run options ask for (float64 for precision "fp64", else
    float32); ``set_options`` changes how it runs without touching the weights.

    A ``gnwarp.dynamics.Dynamics`` (what ``RolloutEngine`` and ``GradientMPC`` roll out).
    Main methods (shapes: N graphs, B bodies, T steps, U controls):
        ``bind(source)``: use the static graphs of a Dataset or System for ``rollout``.
        ``rollout(initial_body [N, B, 13], ctrl [N, T, U], instance [N]) -> [N, T+1, B, 13]``.
        ``next_nodes(graph) -> [sum(n_node), 13]``: one step on a batch of input graphs.
        ``loss(graph, target [sum(n_node), 13], noise_std, accumulate) -> dict``: D.7 training loss.
    """

    def __init__(self, config: ModelConfig, layout: FeatureLayout):
        super().__init__()
        self.config = copy.deepcopy(config)  # its own: set_options must not change another model's
        self.layout = layout
        sizes = input_sizes(layout)
        f = config.std_floor
        self.norm_globals = Normalizer(sizes["globals"], f) if sizes["globals"] else None
        self.norm_nodes = Normalizer(sizes["nodes"], f)
        self.norm_edges = Normalizer(sizes["edges"], f)
        self.norm_delta = Normalizer(DYN_NODE_SIZE, f)
        core = GNCore(config.gn, sizes, config.run) if config.core == "gn" else MLPCore(config.mlp, sizes, config.run)
        self.core = core.to(config.run.param_dtype)
        self.builder = None

    # -- how it runs ------------------------------------------------------------------------
    @property
    def options(self) -> RunOptions:
        """How the model runs (``config.run``): implementation, path, precision, ..."""
        return self.config.run

    def set_options(self, options: RunOptions | None = None, **changes) -> "ForwardModel":
        """Run with ``options`` (or the current ones with ``changes``, e.g. ``precision="tf32"``);
        the weights stay as they are, cast to float64 when "fp64" comes and to float32 when it
        goes (bind again then). Returns self."""
        old = self.config.run
        opts = (options if options is not None else old).replace(**changes)
        self.config.run = opts
        self.core.set_options(opts)
        if opts.param_dtype != old.param_dtype:
            self.to(opts.param_dtype)
        return self

    # -- data -------------------------------------------------------------------------------
    @property
    def device(self) -> torch.device:
        return self.norm_nodes.sum.device

    @property
    def dtype(self) -> torch.dtype:
        return next(self.core.parameters()).dtype

    def graph_builder(self, source, strict: bool = True):
        """A GraphBuilder of ``source`` (Dataset or System) mapped to this model's layout, on the
        model's device and dtype (see ``graph_builder``)."""
        return graph_builder(self.layout, source, self.device, self.dtype, strict)

    def bind(self, source, strict: bool = True) -> "ForwardModel":
        """Use ``source``'s static graphs (a Dataset or System) in ``rollout``; returns self.
        Call again after moving the model to another device or dtype."""
        self.builder = self.graph_builder(source, strict)
        return self

    def stats(self, dtype: torch.dtype) -> dict[str, tuple[torch.Tensor, torch.Tensor]]:
        """{"globals"|"nodes"|"edges"|"delta": (mean, std)} of the normalizers (globals absent
        when the graphs have no global features)."""
        out = {"nodes": self.norm_nodes.mean_std(dtype), "edges": self.norm_edges.mean_std(dtype),
               "delta": self.norm_delta.mean_std(dtype)}
        if self.norm_globals is not None:
            out["globals"] = self.norm_globals.mean_std(dtype)
        return out

    def context(self, graph: GraphsTuple, stats: bool = True) -> StepContext:
        """Bookkeeping of ``graph``'s topology and the current normalizer statistics (no host
        sync when graph.nodes is given; ``stats=False`` leaves them out). The topology part is
        kept for the graph's index tensors: a batch built on the same ones (a ``GraphBuilder`` of
        one topology makes them once per batch size) reuses it."""
        topo = self._topology_context(graph)
        return topo._replace(stats=self.stats(graph.nodes.dtype) if stats else {})

    def _topology_context(self, graph: GraphsTuple) -> StepContext:
        # kept on the senders tensor itself, so that it lives exactly as long as the batch's index
        # tensors do (a captured step that read it keeps working; nothing evicts it under one)
        snd, others = graph.senders, (graph.receivers, graph.n_node, graph.n_edge)
        sig = (tuple(t._version for t in (snd, *others)), graph.nodes.shape[0], self.options.impl,
               self.options.deterministic)
        entries = getattr(snd, "_gnwarp_contexts", None) or []
        for key, s, ctx in entries:
            if s == sig and all(a is b for a, b in zip(key, others)):
                return ctx
        n_nodes = graph.nodes.shape[0]
        n_graph = graph.n_node.shape[0]
        n_node = graph.n_node.long()
        node_graph = graph_of(n_node, n_nodes)
        first = torch.cumsum(n_node, 0) - n_node
        movable = torch.arange(n_nodes, device=n_node.device) != first[node_graph]
        offsets = torch.cat([first, first.new_full((1,), n_nodes)]).to(torch.int32)
        ctx = StepContext(node_graph, movable, n_graph, self.core.graph_index(graph), {}, movable.to(torch.int32),
                          offsets, node_graph.to(torch.int32))
        snd._gnwarp_contexts = (entries + [(others, sig, ctx)])[-4:]
        return ctx

    # -- the pieces of Algorithm D.1 ------------------------------------------------------------
    def _recenter(self, dyn: torch.Tensor, ctx: StepContext) -> tuple[torch.Tensor, torch.Tensor | None]:
        """D.4: subtract each graph's mean (x, y) body position (world excluded); returns
        (centred states, per-node offset [..., n, 13] to add back) or (dyn, None). ``dyn``
        [..., n, 13]: leading dimensions are further batches of ``ctx``'s topology (the steps of
        a window), each centred on its own."""
        if not self.config.recenter:
            return dyn, None
        w = ctx.movable.to(dyn.dtype)[:, None]
        lead, d = dyn.shape[:-2], dyn.dim() - 2
        s = dyn.new_zeros(*lead, ctx.n_graph, 2).index_add_(d, ctx.node_graph, dyn[..., :2] * w)
        c = dyn.new_zeros(ctx.n_graph, 1).index_add_(0, ctx.node_graph, w)
        off = (s / c.clamp_min(1.0))[..., ctx.node_graph, :] * w
        off = torch.cat([off, off.new_zeros(*off.shape[:-1], DYN_NODE_SIZE - 2)], -1)
        return dyn - off, off

    def _noisy_centred(self, nodes: torch.Tensor, noise_std: float, ctx: StepContext,
                       generator: torch.Generator | None) -> tuple[torch.Tensor, torch.Tensor]:
        """A training batch's input states [n, 13] (D.7.1: Gaussian noise of ``noise_std`` on the
        moving bodies, orientations re-normalized) and the same re-centred (D.4, when the model
        re-centres), in one Warp launch (``kernels/models/forward.py``); no gradient flows."""
        dyn = nodes[:, -DYN_NODE_SIZE:]
        noise = noise_std > 0
        eps = torch.randn(dyn.shape, generator=generator, device=dyn.device, dtype=dyn.dtype) if noise else dyn
        nodes = nodes.detach().contiguous()
        noisy, centred = torch.empty_like(dyn), torch.empty_like(dyn)
        kernel = K.noisy_centred_kernel(WP_DTYPE[dyn.dtype], noise, bool(self.config.recenter))
        Launcher(nodes)(kernel, dyn.shape[0], nodes, nodes.shape[1] - DYN_NODE_SIZE, eps.detach(), float(noise_std),
                        ctx.movable_i32, ctx.node_offsets, ctx.node_graph_i32, noisy, centred)
        return noisy, centred

    def _with_dynamic(self, graph: GraphsTuple, dyn: torch.Tensor) -> GraphsTuple:
        return graph._replace(nodes=torch.cat([graph.nodes[:, :-DYN_NODE_SIZE], dyn], -1))

    def predict_delta(self, graph: GraphsTuple, ctx: StepContext) -> torch.Tensor:
        """Normalized predicted changes [n, 13] of a (centred) input graph."""
        return self.core(normalize_graph(graph, ctx.stats), ctx.index)

    def next_nodes(self, graph: GraphsTuple, ctx: StepContext | None = None) -> torch.Tensor:
        """One step of Algorithm D.1 on a batch of input graphs: next dynamic states [n, 13]."""
        ctx = ctx if ctx is not None else self.context(graph)
        dyn = graph.nodes[:, -DYN_NODE_SIZE:]
        dyn_c, off = self._recenter(dyn, ctx)
        delta_n = self.predict_delta(self._with_dynamic(graph, dyn_c), ctx)
        m, s = ctx.stats["delta"]
        nxt = apply_delta(dyn_c, delta_n * s + m)
        if off is not None:
            nxt = nxt + off
        return torch.where(ctx.movable[:, None], nxt, dyn)  # the world body does not move

    # -- rollouts -------------------------------------------------------------------------------
    def template(self, instance: torch.Tensor, builder=None) -> GraphTemplate:
        builder = builder if builder is not None else self.builder
        if builder is None:
            raise ValueError("no static graphs: call model.bind(dataset_or_system) first, or pass builder=")
        return GraphTemplate(builder, torch.as_tensor(instance))

    def rollout_inputs(self, template: GraphTemplate, n_ctrl: int | None, ctrl_policy: str = "clamp",
                       check: bool = True, builder=None) -> RolloutInputs:
        """Checks and control clamping of rollouts over ``template`` (``RolloutInputs``): the
        actuators' ranges are the template's own static edge features, whichever ``builder``
        made it. ``n_ctrl``: the controls U (None: the template's largest control index + 1)."""
        return RolloutInputs(template, self.layout, n_ctrl, ctrl_policy, check)

    def rollout(self, initial_body: torch.Tensor, ctrl: torch.Tensor, instance=None, builder=None,
                template: GraphTemplate | None = None, adjoint: bool = True, ctrl_policy: str = "clamp",
                check: bool = True) -> torch.Tensor:
        """Roll the model out from ``initial_body`` [N, B, 13] under ``ctrl`` [N, T, U] for system
        instances ``instance`` [N] (default: all 0) -> states [N, T+1, B, 13] (the initial included).

        Differentiable with respect to ``initial_body``, ``ctrl`` and the model's parameters. With
        ``adjoint`` (default) the backward recomputes one step at a time (``rollout_with_adjoint``):
        memory grows with the states, not with every step's activations; ``adjoint=False`` keeps
        the activations (plain autograd). The loop has no host synchronization (the template and
        graph index are built once before it).

        Inputs are checked before any launch (``RolloutInputError``, a ValueError, naming the
        argument): shapes (B the bound source's bodies, U its controls, N alike, T >= 1), instances
        (integers in range of the bound source) and, with ``check`` (default), NaN / Inf in the
        initial states of real bodies and in the controls (one host sync). ``ctrl_policy``:
        "clamp" (default) clamps each control to its actuator's range where the actuator is
        ctrllimited, as MuJoCo does (the range is a static edge feature of the model's data);
        "error" refuses controls outside it; "none" uses them as they are.

        This runs the unfused step (``next_nodes``), which also differentiates the parameters;
        ``rollout_engine(..., fused=...)`` gives rollouts differentiable in the initial states and
        controls only, whose steps may run fused (``FusedStep``).
        """
        initial_body = float_tensor(initial_body, "initial_body")
        if initial_body.ndim != 3:
            raise RolloutInputError(f"initial_body must be [N, B, 13], got shape {tuple(initial_body.shape)}")
        N = initial_body.shape[0]
        source = builder if builder is not None else self.builder
        if template is None:
            if source is None:
                raise ValueError("no static graphs: call model.bind(dataset_or_system) first, or pass builder=")
            n_inst, n_ctrl = source_info(source)
            if N < 1:
                raise RolloutInputError("initial_body holds no sequences (N = 0)")
            instance = torch.zeros(N, dtype=torch.int64) if instance is None else check_instance(instance, n_inst, N)
            tmpl = self.template(instance, builder)
        else:
            tmpl, n_ctrl = template, (source_info(builder)[1] if builder is not None else None)
        inputs = self.rollout_inputs(tmpl, n_ctrl, ctrl_policy, check, builder)
        body, ctrl = inputs.shapes(initial_body, ctrl)
        dev = tmpl.static_nodes.device
        body = body.to(dev, tmpl.dtype)
        ctrl = inputs.values(body, ctrl.to(dev, tmpl.dtype))   # checked; clamped to the actuators' ranges
        ctx = self.context(tmpl.graph(body, ctrl[:, 0]))  # topology, graph index and statistics: once

        def step(b: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
            return tmpl.to_body(self.next_nodes(tmpl.graph(b, c), ctx), b)

        params = [p for p in self.parameters() if p.requires_grad]
        if adjoint and torch.is_grad_enabled() and (body.requires_grad or ctrl.requires_grad or params):
            return rollout_with_adjoint(step, body, ctrl, params)
        out = [body]
        for t in range(ctrl.shape[1]):
            body = step(body, ctrl[:, t])
            out.append(body)
        return torch.stack(out, 1)

    def rollout_engine(self, instance, horizon: int, builder=None, ctrl_policy: str = "clamp",
                       check: bool = True, graphs: bool = True, store: bool | str = "auto",
                       store_bytes: int | None = None, fused: bool | None = None) -> RolloutEngine:
        """A ``RolloutEngine`` for rollouts of ``horizon`` steps of system instances ``instance``
        [N]: on CUDA its forward and backward (w.r.t. initial states and controls) replay CUDA
        graphs (``graphs=False``: eager, for callers that capture a larger step around it).
        Hold it and call ``engine.rollout(x0, ctrl)`` as often as needed. ``ctrl_policy`` and
        ``check`` as in ``rollout`` (the checks run on the host once per call, before the replay);
        ``store`` / ``store_bytes``: whether its backward replays the forward's recorded GN blocks
        instead of recomputing them (``RolloutEngine``). ``fused``: run each step as a
        ``gnwarp.models.fused_step.FusedStep`` (input graph, normalization, core, state update and
        their backward in a few launches): None (default) where it runs and the measured rule
        (``gnwarp.gn.rules.choose_fused``: CUDA) picks it, True always (ValueError
        naming why it cannot run: an MLP core, graphs of several sizes, ...), False never;
        ``engine.fused`` says which runs."""
        return RolloutEngine(self, instance, horizon, builder, ctrl_policy=ctrl_policy, check=check, graphs=graphs,
                             store=store, store_bytes=store_bytes, fused=fused)

    def predict(self, body: torch.Tensor, ctrl: torch.Tensor, instance=None, builder=None,
                ctrl_policy: str = "clamp", check: bool = True) -> torch.Tensor:
        """One step: body [N, B, 13], ctrl [N, U] -> next body [N, B, 13] (checked as ``rollout``)."""
        ctrl = float_tensor(ctrl, "ctrl")
        if ctrl.ndim != 2:
            raise RolloutInputError(f"predict's ctrl must be [N, U] (one step), got shape {tuple(ctrl.shape)}")
        return self.rollout(body, ctrl[:, None], instance, builder, ctrl_policy=ctrl_policy, check=check)[:, 1]

    # -- training (D.7.1, D.7.4) --------------------------------------------------------------
    def loss(self, graph: GraphsTuple, target: torch.Tensor, noise_std: float = 0.0, accumulate: bool = False,
             rotation_scale: str = "normalized", generator: torch.Generator | None = None) -> dict[str, torch.Tensor]:
        """Training loss of one batch (Algorithm D.3).

        ``graph``: input graphs (static + true dynamic state); ``target`` [n, 13]: true next states.
        ``noise_std``: Gaussian noise added to the input dynamic nodes (world bodies excepted;
        orientations re-normalized); the target change is computed from the noisy input.
        ``accumulate``: update the normalizers from this batch first.
        ``rotation_scale``: "paper" for 1 - (q_e . q_p)^2 as is; "normalized" divides it by the
        output normalizer's variance of the rotation's vector part, so that it weighs like the
        normalized position and velocity terms (the paper's raw term is ~1e3 times smaller).
        Returns {"loss", "pos", "quat", "linvel", "angvel"} (each a mean over movable nodes).
        """
        ctx = self.context(graph, stats=not accumulate)
        dyn = graph.nodes[:, -DYN_NODE_SIZE:]
        if noise_std > 0 or self.config.recenter:
            dyn, dyn_c = self._noisy_centred(graph.nodes, noise_std, ctx, generator)
        else:
            dyn_c = dyn
        graph = self._with_dynamic(graph, dyn_c)
        delta = state_delta(dyn, target)  # translation does not change it
        w = ctx.movable.to(dyn.dtype)
        if accumulate:  # each normalizer's sums and new statistics in one launch
            items = {"nodes": (self.norm_nodes, graph.nodes, None), "edges": (self.norm_edges, graph.edges, None),
                     "delta": (self.norm_delta, delta, w)}
            if self.norm_globals is not None:
                items["globals"] = (self.norm_globals, graph.globals, None)
            ranks = self.norm_nodes.ranks
            if ranks is not None and ranks.distributed:   # the batches of every rank as one: one all-reduce
                stats = dict(zip(items, accumulate_over_ranks(list(items.values()), ranks)))
            else:
                stats = {k: n.accumulate_stats(x, wt) for k, (n, x, wt) in items.items()}
            ctx = ctx._replace(stats=stats)
        pred_n = self.predict_delta(graph, ctx)
        m, s = ctx.stats["delta"]
        if rotation_scale not in ("normalized", "paper"):
            raise ValueError(f"rotation_scale must be 'normalized' or 'paper', got {rotation_scale!r}")
        if _fused_loss_applies(pred_n, delta, m, s):
            parts = _FusedLoss.apply(pred_n, delta, m, s, ctx.movable_i32, rotation_scale == "normalized")
        else:
            parts = loss_terms(pred_n, delta, m, s, w, rotation_scale)
        return {name: parts[k] for k, name in enumerate(LOSS_TERMS)}

    def extra_repr(self) -> str:
        return f"core={self.config.core!r}, recenter={self.config.recenter}"


# the terms ``ForwardModel.loss`` returns, in the order of the fused loss's vector
LOSS_TERMS = ("pos", "linvel", "angvel", "quat", "loss")


def loss_terms(pred_n: torch.Tensor, delta: torch.Tensor, m: torch.Tensor, s: torch.Tensor, w: torch.Tensor,
               rotation_scale: str = "normalized") -> torch.Tensor:
    """The loss terms (``LOSS_TERMS``) of normalized predicted changes ``pred_n`` [n, 13] against
    true changes ``delta`` [n, 13] under the output normalizer's (mean ``m``, std ``s``), over nodes
    weighted by ``w`` [n] (1 on moving bodies): in torch (the reference of the fused kernels, and
    the path for dtypes or gradients they do not cover)."""
    target_n = (delta - m) / s
    denom = w.sum().clamp_min(1.0)
    # squared errors summed per column over movable nodes, then per term (few kernels)
    col = ((pred_n - target_n).square() * w[:, None]).sum(0)
    assert (POS, LINVEL, ANGVEL) == (slice(0, 3), slice(7, 10), slice(10, 13))
    q_pred = quat_normalize(pred_n[:, QUAT] * s[QUAT] + m[QUAT])
    rot = rotation_loss(delta[:, QUAT], q_pred)
    if rotation_scale == "normalized":
        rot = rot / (s[4:7] ** 2).sum()
    parts = torch.cat([col[POS].sum()[None], col[7:].view(2, 3).sum(1), (rot * w).sum()[None]]) / denom
    return torch.cat([parts, parts.sum()[None]])


def _fused_loss_applies(pred_n, delta, m, s) -> bool:
    """Whether the fused loss kernels compute this loss: the data and statistics in one of float32
    and float64 (a half-precision prediction is promoted to it, as torch's formulas would), and no
    gradient wanted but the prediction's (the normalizer statistics and the data need none)."""
    dt = delta.dtype
    return (dt in (torch.float32, torch.float64) and m.dtype == dt and s.dtype == dt
            and pred_n.dtype in (torch.float16, torch.bfloat16, torch.float32, torch.float64)
            and pred_n.dtype.itemsize <= dt.itemsize and not any(t.requires_grad for t in (delta, m, s)))


class _FusedLoss(torch.autograd.Function):
    """``loss_terms`` in three Warp launches and one torch reduction; backward in one launch
    (``kernels/models/forward.py``)."""

    @staticmethod
    def forward(ctx, pred, delta, m, s, movable, normalized: bool):
        ctx.pred_dtype = pred.dtype
        pred = pred.detach().to(delta.dtype)
        pred, delta, m, s = (t.detach().contiguous() for t in (pred, delta, m, s))
        T = WP_DTYPE[pred.dtype]
        run = Launcher(pred)
        per_node = torch.empty(pred.shape[0], 5, device=pred.device, dtype=pred.dtype)
        run(K.loss_terms_kernel(T), pred.shape[0], pred, delta, m, s, movable, per_node)
        sums = per_node.sum(0)
        terms = torch.empty(5, device=pred.device, dtype=pred.dtype)
        run(K.loss_finalize_kernel(T, normalized), 1, sums, s, terms)
        ctx.save_for_backward(pred, delta, m, s, movable, sums)
        ctx.normalized = normalized
        return terms

    @staticmethod
    def backward(ctx, g_terms):
        pred, delta, m, s, movable, sums = ctx.saved_tensors
        g = torch.empty_like(pred)
        Launcher(pred)(K.loss_grad_kernel(WP_DTYPE[pred.dtype], ctx.normalized), pred.shape[0], pred, delta, m, s,
                       movable, sums, g_terms.contiguous(), g)
        return g.to(ctx.pred_dtype), None, None, None, None, None


class MLPForwardModel(ForwardModel):
    """The MLP baseline of section E: a ``ForwardModel`` whose core is an MLP on the flattened
    graph (``size`` one of ``MLP_SIZES``), same normalization and state update."""

    def __init__(self, layout: FeatureLayout, n_node: int, n_edge: int, size: str = "5x256", **config):
        super().__init__(ModelConfig(core="mlp", mlp=MLPCoreConfig.preset(size, n_node, n_edge), **config), layout)
