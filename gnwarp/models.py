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

A node's 13 dynamic features and their change use the layout of ``gnwarp.state``: position (0:3),
orientation w, x, y, z (3:7), linear (7:10) and angular (10:13) velocity in the world frame. The
change of orientation is the rotation ``dq`` with ``q_next = dq (x) q`` (Hamilton product, world
frame), sign-fixed so that ``dq.w >= 0``.

Everything below works on *flat* nodes ([sum(n_node), 13]) so batches may mix graphs of any size;
``rollout`` maps [N, B, 13] body states to and from them with a ``GraphTemplate`` built once.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import torch
import torch.nn as nn

from gnwarp.data.builder import GraphTemplate, graph_builder
from gnwarp.data.layout import FeatureLayout
from gnwarp.gn import MLP, EdgeBlockConfig, GlobalBlockConfig, GNBlockConfig, GraphNetwork, NodeBlockConfig
from gnwarp.graphs import GraphsTuple
from gnwarp.state import (ANGVEL, DYN_NODE_SIZE, LINVEL, POS, QUAT, apply_delta, quat_normalize, rotation_loss,
                          state_delta)

__all__ = [
    "Normalizer", "GNCoreConfig", "MLPCoreConfig", "ModelConfig", "MLP_SIZES", "GNCore", "MLPCore",
    "ForwardModel", "MLPForwardModel",
]


# -- normalization (D.3, D.7.1) ---------------------------------------------------------------

class Normalizer(nn.Module):
    """Online mean/std per feature, shared by every row (every node, edge or graph) (D.3).

    Accumulates count, sum and squared sum (float64 buffers, so they travel in the state dict and
    keep float64 when the model is cast). ``std = max(sqrt(var), std_floor)``; before any data the
    transform is the identity. No host synchronization anywhere.
    """

    def __init__(self, size: int, std_floor: float = 1e-4):
        super().__init__()
        self.size = int(size)
        self.std_floor = float(std_floor)
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))
        self.register_buffer("sum", torch.zeros(self.size, dtype=torch.float64))
        self.register_buffer("sumsq", torch.zeros(self.size, dtype=torch.float64))

    def _apply(self, fn, recurse=True):
        saved = {k: self._buffers[k] for k in ("count", "sum", "sumsq")}
        super()._apply(fn, recurse)
        for k, old in saved.items():  # keep the accumulators in float64 whatever the model's dtype
            if self._buffers[k].dtype != torch.float64:
                self._buffers[k] = old.to(self._buffers[k].device)
        return self

    @torch.no_grad()
    def accumulate(self, x: torch.Tensor, weight: torch.Tensor | None = None) -> None:
        """Add rows of x [n, size]; ``weight`` [n] (0/1) leaves rows out."""
        x = x.detach().to(torch.float64).reshape(-1, self.size)
        if weight is None:
            self.count += x.shape[0]
            self.sum += x.sum(0)
            self.sumsq += (x * x).sum(0)
        else:
            w = weight.detach().to(torch.float64).reshape(-1, 1)
            self.count += w.sum()
            self.sum += (x * w).sum(0)
            self.sumsq += (x * x * w).sum(0)

    def reset(self) -> None:
        for b in (self.count, self.sum, self.sumsq):
            b.zero_()

    def mean_std(self, dtype: torch.dtype | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(mean [size], std [size]) in ``dtype``."""
        n = self.count.clamp_min(1.0)
        mean = self.sum / n
        var = (self.sumsq / n - mean * mean).clamp_min(0.0)
        std = var.sqrt().clamp_min(self.std_floor)
        seen = self.count > 0
        mean = torch.where(seen, mean, torch.zeros_like(mean))
        std = torch.where(seen, std, torch.ones_like(std))
        dtype = dtype or torch.get_default_dtype()
        return mean.to(dtype), std.to(dtype)

    def extra_repr(self) -> str:
        return f"size={self.size}, std_floor={self.std_floor:g}"


# -- configs ------------------------------------------------------------------------------------

@dataclass
class GNCoreConfig:
    """The two-block GN core (D.2). Defaults are the paper's standard sizes: edge MLP 3x512, node
    and global MLPs 2x256, updated edge/node/global size 128."""
    latent: int = 128
    edge_hidden: tuple[int, ...] = (512, 512, 512)
    node_hidden: tuple[int, ...] = (256, 256)
    global_hidden: tuple[int, ...] = (256, 256)
    backend: str = "warp"          # GraphNetwork backend: "warp" or "torch" (the reference)
    path: str = "auto"             # Warp path: "auto", "split" or "tile"
    precision: str = "fp32"
    deterministic: bool = False

    def __post_init__(self):
        for k in ("edge_hidden", "node_hidden", "global_hidden"):
            setattr(self, k, tuple(int(h) for h in getattr(self, k)))


# Section E: the five MLP baselines, "<layers>x<width>".
MLP_SIZES = ("3x128", "3x512", "9x128", "9x512", "5x256")


@dataclass
class MLPCoreConfig:
    """MLP baseline core (E): ``layers`` hidden layers of ``width`` on the flattened graph of a
    fixed topology (``n_node`` bodies, ``n_edge`` edges; set from the training data)."""
    layers: int = 5
    width: int = 256
    n_node: int = 0
    n_edge: int = 0

    @classmethod
    def preset(cls, size: str, n_node: int = 0, n_edge: int = 0) -> "MLPCoreConfig":
        if size not in MLP_SIZES:
            raise ValueError(f"unknown MLP size {size!r}; the paper's are {MLP_SIZES}")
        layers, width = (int(s) for s in size.split("x"))
        return cls(layers, width, n_node, n_edge)


@dataclass
class ModelConfig:
    """What a forward model is made of; saved as JSON in checkpoints."""
    core: str = "gn"                                   # "gn" (D.2) or "mlp" (E)
    gn: GNCoreConfig = field(default_factory=GNCoreConfig)
    mlp: MLPCoreConfig = field(default_factory=MLPCoreConfig)
    recenter: bool | None = None  # D.4: re-centre x, y before prediction; None: decided by training
                                  # (True for a single translation-invariant system), False when used as is
    std_floor: float = 1e-4    # normalizers' smallest standard deviation

    def __post_init__(self):
        if isinstance(self.gn, dict):
            self.gn = GNCoreConfig(**self.gn)
        if isinstance(self.mlp, dict):
            self.mlp = MLPCoreConfig(**self.mlp)
        if self.core not in ("gn", "mlp"):
            raise ValueError(f"ModelConfig.core must be 'gn' or 'mlp', got {self.core!r}")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "ModelConfig":
        return cls(**d)


def input_sizes(layout: FeatureLayout) -> dict[str, int]:
    """Input feature widths of the full graph, read from the layout (one source of truth)."""
    if layout.n_global_ctrl:
        raise ValueError(f"the layout has {layout.n_global_ctrl} controls of actuators not on a joint; "
                         "GraphBuilder does not put them on the globals, so models cannot use this data")
    return dict(layout.sizes)


# -- cores --------------------------------------------------------------------------------------

class GNCore(nn.Module):
    """GN1 on the normalized input graph; GN2 on [input, GN1 output] (graph skip), with GN2's
    global update switched off since only its nodes are read: the normalized change of each
    body's dynamic state (D.1, D.2). Both are ``gnwarp.gn.GraphNetwork`` blocks."""

    def __init__(self, config: GNCoreConfig, sizes: dict[str, int]):
        super().__init__()
        fv, fe, fg = sizes["nodes"], sizes["edges"], sizes["globals"]
        L = config.latent
        hidden = dict(edge_hidden=config.edge_hidden, node_hidden=config.node_hidden,
                      global_hidden=config.global_hidden)
        # A graph without global features (a fixed system: no static global varies) gives GN1 no
        # global input at all; GN1 still makes globals from its nodes and edges for GN2.
        g = fg > 0
        gn1 = GNBlockConfig(fv, fe, fg, node_out=L, edge_out=L, global_out=L, **hidden,
                            edge_block=EdgeBlockConfig(use_globals=g), node_block=NodeBlockConfig(use_globals=g),
                            global_block=GlobalBlockConfig(use_globals=g))
        gn2 = GNBlockConfig(fv + L, fe + L, fg + L, node_out=DYN_NODE_SIZE, edge_out=L, global_out=L, **hidden,
                            update_globals=False)
        opts = dict(impl=config.backend, path={"split": "blas"}.get(config.path, config.path), precision=config.precision,
                    deterministic=config.deterministic, check_inputs=False)  # graphs come from GraphBuilder
        self.gn1 = GraphNetwork(gn1, **opts)
        self.gn2 = GraphNetwork(gn2, **opts)

    @property
    def backend(self) -> str:
        return self.gn1.impl

    @backend.setter
    def backend(self, value: str) -> None:
        self.gn1.impl = self.gn2.impl = value

    def graph_index(self, graph: GraphsTuple):
        """Index of ``graph``'s topology, shared by both blocks (None for the torch backend)."""
        return self.gn1.graph_index(graph) if self.backend == "warp" else None

    def forward(self, graph: GraphsTuple, index=None) -> torch.Tensor:
        """Normalized input graph -> [sum(n_node), 13] normalized state changes."""
        g1 = self.gn1(graph, index)
        skip = graph._replace(nodes=torch.cat([graph.nodes, g1.nodes], -1),
                              edges=torch.cat([graph.edges, g1.edges], -1),
                              globals=torch.cat([graph.globals, g1.globals], -1))
        return self.gn2(skip, index).nodes


class MLPCore(nn.Module):
    """Section E: the GN core replaced by an MLP on the flattened graph [globals, all nodes, all
    edges] -> all nodes' normalized changes. Fixed topology: every graph has n_node nodes and
    n_edge edges in the order of the training data."""

    def __init__(self, config: MLPCoreConfig, sizes: dict[str, int]):
        super().__init__()
        if config.n_node <= 0 or config.n_edge < 0:
            raise ValueError("MLPCoreConfig needs the fixed topology (n_node, n_edge) of its data")
        self.n_node, self.n_edge = config.n_node, config.n_edge
        n_in = sizes["globals"] + self.n_node * sizes["nodes"] + self.n_edge * sizes["edges"]
        self.mlp = MLP(n_in, [config.width] * config.layers, self.n_node * DYN_NODE_SIZE)

    def graph_index(self, graph: GraphsTuple):
        return None

    def forward(self, graph: GraphsTuple, index=None) -> torch.Tensor:
        n = graph.n_node.shape[0]
        if graph.nodes.shape[0] != n * self.n_node or graph.edges.shape[0] != n * self.n_edge:
            raise ValueError(f"the MLP baseline has a fixed topology of {self.n_node} nodes and {self.n_edge} "
                             f"edges per graph; got {graph.nodes.shape[0]} nodes and {graph.edges.shape[0]} "
                             f"edges for {n} graphs")
        x = torch.cat([graph.globals.reshape(n, -1), graph.nodes.reshape(n, -1), graph.edges.reshape(n, -1)], -1)
        return self.mlp(x).reshape(n * self.n_node, DYN_NODE_SIZE)


# -- the model ------------------------------------------------------------------------------------

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
        config: ``ModelConfig`` (core "gn" or "mlp", sizes, backend, re-centring).
        layout: the ``FeatureLayout`` of its input graphs (from the training dataset).

    Main methods (shapes: N graphs, B bodies, T steps, U controls):
        ``bind(source)``: use the static graphs of a Dataset or System for ``rollout``.
        ``rollout(initial_body [N, B, 13], ctrl [N, T, U], instance [N]) -> [N, T+1, B, 13]``.
        ``next_nodes(graph) -> [sum(n_node), 13]``: one step on a batch of input graphs.
        ``loss(graph, target [sum(n_node), 13], noise_std, accumulate) -> dict``: D.7 training loss.
    """

    def __init__(self, config: ModelConfig, layout: FeatureLayout):
        super().__init__()
        self.config = config
        self.layout = layout
        sizes = input_sizes(layout)
        f = config.std_floor
        self.norm_globals = Normalizer(sizes["globals"], f) if sizes["globals"] else None
        self.norm_nodes = Normalizer(sizes["nodes"], f)
        self.norm_edges = Normalizer(sizes["edges"], f)
        self.norm_delta = Normalizer(DYN_NODE_SIZE, f)
        self.core = GNCore(config.gn, sizes) if config.core == "gn" else MLPCore(config.mlp, sizes)
        self.builder = None

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
        node_graph = torch.repeat_interleave(torch.arange(n_graph, device=n_node.device), n_node, output_size=n_nodes)
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
                template: GraphTemplate | None = None) -> torch.Tensor:
        """Roll the model out from ``initial_body`` [N, B, 13] under ``ctrl`` [N, T, U] for system
        instances ``instance`` [N] (default: all 0) -> states [N, T+1, B, 13] (the initial included).

        Differentiable with respect to ``initial_body`` and ``ctrl``. The loop has no host
        synchronization (the template and graph index are built once before it).
        """
        N = initial_body.shape[0]
        if instance is None:
            instance = torch.zeros(N, dtype=torch.int64)
        tmpl = template if template is not None else self.template(instance, builder)
        dev = tmpl.static_nodes.device
        body = initial_body.to(dev, tmpl.dtype)
        ctrl = ctrl.to(dev, tmpl.dtype)
        ctx = self.context(tmpl.graph(body, ctrl[:, 0]))  # topology, graph index and statistics: once
        out = [body]
        for t in range(ctrl.shape[1]):
            nxt = self.next_nodes(tmpl.graph(body, ctrl[:, t]), ctx)
            body = tmpl.to_body(nxt, body)
            out.append(body)
        return torch.stack(out, 1)

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
