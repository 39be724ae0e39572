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
from gnwarp.models.config import MLPCoreConfig, ModelConfig
from gnwarp.models.cores import GNCore, MLPCore
from gnwarp.models.normalizer import Normalizer
from gnwarp.models.rollout import RolloutEngine, rollout_with_adjoint
from gnwarp.state import (ANGVEL, DYN_NODE_SIZE, LINVEL, POS, QUAT, apply_delta, quat_normalize, rotation_loss,
                          state_delta)

__all__ = ["input_sizes", "StepContext", "ForwardModel", "MLPForwardModel"]


def input_sizes(layout: FeatureLayout) -> dict[str, int]:
    """Input feature widths of the full graph, read from the layout (one source of truth)."""
    if layout.n_global_ctrl:
        raise ValueError(f"the layout has {layout.n_global_ctrl} controls of actuators not on a joint; "
                         "GraphBuilder does not put them on the globals, so models cannot use this data")
    return dict(layout.sizes)


class StepContext(NamedTuple):
    """Per-topology bookkeeping of a batch of graphs, computed once and reused every step."""
    node_graph: torch.Tensor   # [n_nodes] graph of each node
    movable: torch.Tensor      # [n_nodes] bool: not a world body (node 0 of its graph)
    n_graph: int
    index: Any                 # the core's graph index (Warp GraphIndex or None)
    stats: dict                # normalizer (mean, std) by name, as of when the context was made


class ForwardModel(nn.Module):
    """One-step forward model (Algorithm D.1): ``x_{t+1} = M(static graph, x_t, a_t)``.

    Args:
        config: ``ModelConfig`` (core "gn" or "mlp", sizes, run options, re-centring).
        layout: the ``FeatureLayout`` of its input graphs (from the training dataset).

    The model is built in the dtype its run options ask for (float64 for precision "fp64", else
    float32); ``set_options`` changes how it runs without touching the weights.

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

    def context(self, graph: GraphsTuple) -> StepContext:
        """Bookkeeping of ``graph``'s topology and the current normalizer statistics (no host
        sync when graph.nodes is given)."""
        n_nodes = graph.nodes.shape[0]
        n_graph = graph.n_node.shape[0]
        n_node = graph.n_node.long()
        node_graph = graph_of(n_node, n_nodes)
        first = torch.cumsum(n_node, 0) - n_node
        movable = torch.arange(n_nodes, device=n_node.device) != first[node_graph]
        return StepContext(node_graph, movable, n_graph, self.core.graph_index(graph), self.stats(graph.nodes.dtype))

    # -- the pieces of Algorithm D.1 ------------------------------------------------------------
    def _recenter(self, dyn: torch.Tensor, ctx: StepContext) -> tuple[torch.Tensor, torch.Tensor | None]:
        """D.4: subtract each graph's mean (x, y) body position (world excluded); returns
        (centred states, per-node offset [n, 13] to add back) or (dyn, None)."""
        if not self.config.recenter:
            return dyn, None
        w = ctx.movable.to(dyn.dtype)[:, None]
        s = dyn.new_zeros(ctx.n_graph, 2).index_add_(0, ctx.node_graph, dyn[:, :2] * w)
        c = dyn.new_zeros(ctx.n_graph, 1).index_add_(0, ctx.node_graph, w)
        off = (s / c.clamp_min(1.0))[ctx.node_graph] * w
        off = torch.cat([off, off.new_zeros(off.shape[0], DYN_NODE_SIZE - 2)], -1)
        return dyn - off, off

    @staticmethod
    def _normalized_input(graph: GraphsTuple, stats: dict) -> GraphsTuple:
        def norm(kind, x):
            m, s = stats[kind]
            return (x - m) / s
        u = norm("globals", graph.globals) if "globals" in stats else graph.globals
        return graph._replace(nodes=norm("nodes", graph.nodes), edges=norm("edges", graph.edges), globals=u)

    def _accumulate_input(self, graph: GraphsTuple) -> None:
        if self.norm_globals is not None:
            self.norm_globals.accumulate(graph.globals)
        self.norm_nodes.accumulate(graph.nodes)
        self.norm_edges.accumulate(graph.edges)

    def _with_dynamic(self, graph: GraphsTuple, dyn: torch.Tensor) -> GraphsTuple:
        return graph._replace(nodes=torch.cat([graph.nodes[:, :-DYN_NODE_SIZE], dyn], -1))

    def predict_delta(self, graph: GraphsTuple, ctx: StepContext) -> torch.Tensor:
        """Normalized predicted changes [n, 13] of a (centred) input graph."""
        return self.core(self._normalized_input(graph, ctx.stats), ctx.index)

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

    def rollout(self, initial_body: torch.Tensor, ctrl: torch.Tensor, instance=None, builder=None,
                template: GraphTemplate | None = None, adjoint: bool = True) -> torch.Tensor:
        """Roll the model out from ``initial_body`` [N, B, 13] under ``ctrl`` [N, T, U] for system
        instances ``instance`` [N] (default: all 0) -> states [N, T+1, B, 13] (the initial included).

        Differentiable with respect to ``initial_body``, ``ctrl`` and the model's parameters. With
        ``adjoint`` (default) the backward recomputes one step at a time (``rollout_with_adjoint``):
        memory grows with the states, not with every step's activations; ``adjoint=False`` keeps
        the activations (plain autograd). The loop has no host synchronization (the template and
        graph index are built once before it).
        """
        N = initial_body.shape[0]
        if instance is None:
            instance = torch.zeros(N, dtype=torch.int64)
        tmpl = template if template is not None else self.template(instance, builder)
        dev = tmpl.static_nodes.device
        body = initial_body.to(dev, tmpl.dtype)
        ctrl = ctrl.to(dev, tmpl.dtype)
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

    def rollout_engine(self, instance, horizon: int, builder=None) -> RolloutEngine:
        """A ``RolloutEngine`` for rollouts of ``horizon`` steps of system instances ``instance``
        [N]: on CUDA its forward and backward (w.r.t. initial states and controls) replay CUDA
        graphs. Hold it and call ``engine.rollout(x0, ctrl)`` as often as needed."""
        return RolloutEngine(self, instance, horizon, builder)

    def predict(self, body: torch.Tensor, ctrl: torch.Tensor, instance=None, builder=None) -> torch.Tensor:
        """One step: body [N, B, 13], ctrl [N, U] -> next body [N, B, 13]."""
        return self.rollout(body, ctrl[:, None], instance, builder)[:, 1]

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
        ctx = self.context(graph)
        dyn = graph.nodes[:, -DYN_NODE_SIZE:]
        if noise_std > 0:
            eps = torch.randn(dyn.shape, generator=generator, device=dyn.device, dtype=dyn.dtype) * noise_std
            noisy = dyn + eps * ctx.movable[:, None]
            dyn = torch.cat([noisy[:, :3], quat_normalize(noisy[:, QUAT]), noisy[:, 7:]], -1)
        dyn_c, off = self._recenter(dyn, ctx)
        graph = self._with_dynamic(graph, dyn_c)
        delta = state_delta(dyn, target)  # translation does not change it
        w = ctx.movable.to(dyn.dtype)
        if accumulate:
            self._accumulate_input(graph)
            self.norm_delta.accumulate(delta, w)
            ctx = ctx._replace(stats=self.stats(dyn.dtype))
        pred_n = self.predict_delta(graph, ctx)
        m, s = ctx.stats["delta"]
        target_n = (delta - m) / s
        denom = w.sum().clamp_min(1.0)
        terms = {}
        for name, sl in (("pos", POS), ("linvel", LINVEL), ("angvel", ANGVEL)):
            terms[name] = (((pred_n[:, sl] - target_n[:, sl]) ** 2).sum(-1) * w).sum() / denom
        q_pred = quat_normalize(pred_n[:, QUAT] * s[QUAT] + m[QUAT])
        rot = rotation_loss(delta[:, QUAT], q_pred)
        if rotation_scale == "normalized":
            rot = rot / (s[4:7] ** 2).sum()
        elif rotation_scale != "paper":
            raise ValueError(f"rotation_scale must be 'normalized' or 'paper', got {rotation_scale!r}")
        terms["quat"] = (rot * w).sum() / denom
        terms["loss"] = terms["pos"] + terms["quat"] + terms["linvel"] + terms["angvel"]
        return terms

    def extra_repr(self) -> str:
        return f"core={self.config.core!r}, recenter={self.config.recenter}"


class MLPForwardModel(ForwardModel):
    """The MLP baseline of section E: a ``ForwardModel`` whose core is an MLP on the flattened
    graph (``size`` one of ``MLP_SIZES``), same normalization and state update."""

    def __init__(self, layout: FeatureLayout, n_node: int, n_edge: int, size: str = "5x256", **config):
        super().__init__(ModelConfig(core="mlp", mlp=MLPCoreConfig.preset(size, n_node, n_edge), **config), layout)
