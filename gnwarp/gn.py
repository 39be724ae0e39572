"""The graph-network block of the paper (Battaglia et al. 2018 GN block, sum aggregation).

For a batch of graphs (a ``GraphsTuple``):

1. edges:   e'_k = phi_e([e_k, v_sender(k), v_receiver(k), u_graph(k)])
2. aggregate: E_i = sum of e'_k over the edges k received by node i
3. nodes:   v'_i = phi_v([v_i, E_i, u_graph(i)])
4. globals: u'   = phi_u([u, sum_i v'_i, sum_k e'_k])   (per graph; skipped if ``update_globals=False``)

Each phi is an ``MLP`` (ReLU hidden layers, linear output). The ``use_*`` switches of each update
(graph_nets style) decide which of the bracketed pieces exist; the first-layer weight of each MLP
has one column block per piece, in the order written above (see ``GNBlockConfig.*_layout``).

``TorchGraphNetwork`` is the pure-torch reference (index_select, cat, nn.Linear, index_add_).
``GraphNetwork`` has the same parameters (state dicts are interchangeable) and runs either the
reference (``backend="torch"``) or the Warp kernels (``backend="warp"``, see ``gnwarp.gn_warp``).
"""
from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from typing import Sequence

import torch
import torch.nn as nn

from gnwarp.graphs import GraphsTuple, validate

__all__ = [
    "EdgeBlockConfig",
    "NodeBlockConfig",
    "GlobalBlockConfig",
    "GNBlockConfig",
    "MLP",
    "TorchGraphNetwork",
    "GraphNetwork",
    "PRECISIONS",
    "check_graph",
]

PRECISIONS = ("fp32", "tf32", "fp16", "bf16", "fp16x3")


# -- configuration ------------------------------------------------------------------------------
@dataclass(frozen=True)
class EdgeBlockConfig:
    """Inputs of the edge update phi_e."""
    use_edges: bool = True
    use_sender_nodes: bool = True
    use_receiver_nodes: bool = True
    use_globals: bool = True


@dataclass(frozen=True)
class NodeBlockConfig:
    """Inputs of the node update phi_v."""
    use_received_edges: bool = True
    use_nodes: bool = True
    use_globals: bool = True


@dataclass(frozen=True)
class GlobalBlockConfig:
    """Inputs of the global update phi_u."""
    use_edges: bool = True
    use_nodes: bool = True
    use_globals: bool = True


@dataclass(frozen=True)
class GNBlockConfig:
    """Sizes and switches of one GN block.

    ``node_size``, ``edge_size``, ``global_size``: input feature widths (0: the graph carries no
    such features; then no switch may use them). ``*_out``: output widths of the three updates.
    ``*_hidden``: hidden layer widths of each MLP (may be empty: a single linear layer).
    Defaults are the paper's sizes (section D.2: edge MLP 3x512, node and global 2x256, latent 128).
    """
    node_size: int
    edge_size: int
    global_size: int
    node_out: int = 128
    edge_out: int = 128
    global_out: int = 128
    edge_hidden: tuple[int, ...] = (512, 512, 512)
    node_hidden: tuple[int, ...] = (256, 256)
    global_hidden: tuple[int, ...] = (256, 256)
    edge_block: EdgeBlockConfig = field(default_factory=EdgeBlockConfig)
    node_block: NodeBlockConfig = field(default_factory=NodeBlockConfig)
    global_block: GlobalBlockConfig = field(default_factory=GlobalBlockConfig)
    update_globals: bool = True

    def __post_init__(self):
        object.__setattr__(self, "edge_hidden", tuple(int(h) for h in self.edge_hidden))
        object.__setattr__(self, "node_hidden", tuple(int(h) for h in self.node_hidden))
        object.__setattr__(self, "global_hidden", tuple(int(h) for h in self.global_hidden))
        for name in ("node_size", "edge_size", "global_size"):
            if getattr(self, name) < 0:
                raise ValueError(f"GNBlockConfig.{name} must be >= 0, got {getattr(self, name)}")
        for name in ("node_out", "edge_out", "global_out"):
            if getattr(self, name) <= 0:
                raise ValueError(f"GNBlockConfig.{name} must be > 0, got {getattr(self, name)}")
        for name in ("edge_hidden", "node_hidden", "global_hidden"):
            if any(h <= 0 for h in getattr(self, name)):
                raise ValueError(f"GNBlockConfig.{name} widths must be > 0, got {getattr(self, name)}")
        eb, nb, gb = self.edge_block, self.node_block, self.global_block
        wants = {
            "node_size": [("edge_block.use_sender_nodes", eb.use_sender_nodes),
                          ("edge_block.use_receiver_nodes", eb.use_receiver_nodes),
                          ("node_block.use_nodes", nb.use_nodes)],
            "edge_size": [("edge_block.use_edges", eb.use_edges)],
            "global_size": [("edge_block.use_globals", eb.use_globals),
                            ("node_block.use_globals", nb.use_globals),
                            ("global_block.use_globals", gb.use_globals and self.update_globals)],
        }
        for size_name, uses in wants.items():
            if getattr(self, size_name) == 0:
                on = [n for n, u in uses if u]
                if on:
                    raise ValueError(f"{size_name}=0 but {', '.join(on)} is set: switch it off or give the size")
        for block, layout in (("edge", self.edge_layout), ("node", self.node_layout),
                              ("global", self.global_layout)):
            if block == "global" and not self.update_globals:
                continue
            if not layout:
                raise ValueError(f"the {block} update uses no input: set at least one of its use_* switches")

    # One source of truth for the column blocks of each MLP's first layer: [(piece, width)].
    @property
    def edge_layout(self) -> tuple[tuple[str, int], ...]:
        eb = self.edge_block
        return tuple((n, w) for n, w, on in (
            ("edges", self.edge_size, eb.use_edges),
            ("sender_nodes", self.node_size, eb.use_sender_nodes),
            ("receiver_nodes", self.node_size, eb.use_receiver_nodes),
            ("globals", self.global_size, eb.use_globals)) if on)

    @property
    def node_layout(self) -> tuple[tuple[str, int], ...]:
        nb = self.node_block
        return tuple((n, w) for n, w, on in (
            ("nodes", self.node_size, nb.use_nodes),
            ("received_edges", self.edge_out, nb.use_received_edges),
            ("globals", self.global_size, nb.use_globals)) if on)

    @property
    def global_layout(self) -> tuple[tuple[str, int], ...]:
        gb = self.global_block
        if not self.update_globals:
            return ()
        return tuple((n, w) for n, w, on in (
            ("globals", self.global_size, gb.use_globals),
            ("nodes", self.node_out, gb.use_nodes),
            ("edges", self.edge_out, gb.use_edges)) if on)

    @property
    def needs_nodes(self) -> bool:
        return self.edge_block.use_sender_nodes or self.edge_block.use_receiver_nodes or self.node_block.use_nodes

    @property
    def needs_edges(self) -> bool:
        return self.edge_block.use_edges

    @property
    def needs_globals(self) -> bool:
        return any(n == "globals" for n, _ in self.edge_layout + self.node_layout + self.global_layout)

    @property
    def aggregates_to_nodes(self) -> bool:
        """Whether edge outputs are summed per receiver (the node update reads them)."""
        return self.node_block.use_received_edges

    @property
    def edges_to_globals(self) -> bool:
        return self.update_globals and self.global_block.use_edges

    @property
    def nodes_to_globals(self) -> bool:
        return self.update_globals and self.global_block.use_nodes


def column_slices(layout: Sequence[tuple[str, int]]) -> dict[str, slice]:
    """{piece: slice of first-layer weight columns} for a layout."""
    out, c = {}, 0
    for name, w in layout:
        out[name] = slice(c, c + w)
        c += w
    return out


# -- modules ------------------------------------------------------------------------------------
class MLP(nn.Module):
    """ReLU hidden layers, linear output: ``layers`` is a list of nn.Linear."""

    def __init__(self, in_size: int, hidden: Sequence[int], out_size: int):
        super().__init__()
        sizes = [in_size, *hidden, out_size]
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(sizes[:-1], sizes[1:]))

    def forward(self, x):
        for k, layer in enumerate(self.layers):
            x = layer(x)
            if k < len(self.layers) - 1:
                x = torch.relu(x)
        return x

    def flat_parameters(self) -> list[torch.Tensor]:
        """[W0, b0, W1, b1, ...] (weights are [out, in], as nn.Linear stores them)."""
        return [p for layer in self.layers for p in (layer.weight, layer.bias)]


def _width(layout) -> int:
    return sum(w for _, w in layout)


class TorchGraphNetwork(nn.Module):
    """The pure-torch reference GN block (index_select, cat, nn.Linear, index_add_).

    ``forward(graph)`` takes a GraphsTuple of torch tensors and returns one with new nodes,
    edges and (if ``config.update_globals``) globals; senders, receivers and counts are kept.
    """

    def __init__(self, config: GNBlockConfig | None = None, **kwargs):
        super().__init__()
        if config is None:
            config = GNBlockConfig(**kwargs)
        elif kwargs:
            raise TypeError("give either a GNBlockConfig or keyword sizes, not both")
        self.config = config
        c = config
        self.edge_mlp = MLP(_width(c.edge_layout), c.edge_hidden, c.edge_out)
        self.node_mlp = MLP(_width(c.node_layout), c.node_hidden, c.node_out)
        self.global_mlp = MLP(_width(c.global_layout), c.global_hidden, c.global_out) if c.update_globals else None

    def flat_parameters(self) -> list[torch.Tensor]:
        ps = self.edge_mlp.flat_parameters() + self.node_mlp.flat_parameters()
        if self.global_mlp is not None:
            ps += self.global_mlp.flat_parameters()
        return ps

    def reference_forward(self, graph: GraphsTuple) -> GraphsTuple:
        c = self.config
        v, e, u = graph.nodes, graph.edges, graph.globals
        snd, rcv = graph.senders.long(), graph.receivers.long()
        n_graph = graph.n_node.shape[0]
        n_nodes = v.shape[0] if v is not None else graph.total_nodes
        node_g = torch.repeat_interleave(torch.arange(n_graph, device=snd.device), graph.n_node.long(),
                                         output_size=n_nodes)
        edge_g = torch.repeat_interleave(torch.arange(n_graph, device=snd.device), graph.n_edge.long(),
                                         output_size=snd.shape[0])
        pieces = {"edges": lambda: e, "sender_nodes": lambda: v.index_select(0, snd),
                  "receiver_nodes": lambda: v.index_select(0, rcv), "globals": lambda: u.index_select(0, edge_g)}
        e_new = self.edge_mlp(torch.cat([pieces[n]() for n, _ in c.edge_layout], -1))
        dtype, dev = e_new.dtype, e_new.device
        pieces = {"nodes": lambda: v, "globals": lambda: u.index_select(0, node_g),
                  "received_edges": lambda: torch.zeros(n_nodes, c.edge_out, dtype=dtype, device=dev)
                  .index_add_(0, rcv, e_new)}
        v_new = self.node_mlp(torch.cat([pieces[n]() for n, _ in c.node_layout], -1))
        u_new = u
        if c.update_globals:
            pieces = {"globals": lambda: u,
                      "nodes": lambda: torch.zeros(n_graph, c.node_out, dtype=v_new.dtype, device=dev)
                      .index_add_(0, node_g, v_new),
                      "edges": lambda: torch.zeros(n_graph, c.edge_out, dtype=dtype, device=dev)
                      .index_add_(0, edge_g, e_new)}
            u_new = self.global_mlp(torch.cat([pieces[n]() for n, _ in c.global_layout], -1))
        return graph._replace(nodes=v_new, edges=e_new, globals=u_new)

    def forward(self, graph: GraphsTuple) -> GraphsTuple:
        return self.reference_forward(graph)


# -- input checks -------------------------------------------------------------------------------
_FLOATS = (torch.float32, torch.float64)


def check_graph(config: GNBlockConfig, graph: GraphsTuple, param: torch.Tensor, finite: bool = True) -> None:
    """Raise a clear error if ``graph`` does not fit ``config`` or the parameters (like ``param``).

    TypeError: not a GraphsTuple of torch tensors, wrong dtype (features must have the parameters'
    dtype, float32 or float64; indices integers). ValueError: wrong device, missing or mis-sized
    features, inconsistent counts, indices out of range, non-finite features (``finite``).
    """
    if not isinstance(graph, GraphsTuple):
        raise TypeError(f"GraphNetwork expects a GraphsTuple, got {type(graph).__name__}")
    for name in ("nodes", "edges", "globals", "senders", "receivers", "n_node", "n_edge"):
        a = getattr(graph, name)
        if a is not None and not isinstance(a, torch.Tensor):
            raise TypeError(f"GraphsTuple.{name} must be a torch.Tensor (use graph.to_torch()), "
                            f"got {type(a).__name__}")
    for name, needed, width in (("nodes", config.needs_nodes, config.node_size),
                                ("edges", config.needs_edges, config.edge_size),
                                ("globals", config.needs_globals, config.global_size)):
        a = getattr(graph, name)
        if needed and a is None:
            raise ValueError(f"this GN block reads {name} (size {width}) but GraphsTuple.{name} is None")
        if a is None or not needed:
            continue
        if a.dtype != param.dtype:
            raise TypeError(f"GraphsTuple.{name} has dtype {a.dtype} but the block's parameters are "
                            f"{param.dtype}: convert one of them")
        if a.device != param.device:
            raise ValueError(f"GraphsTuple.{name} is on {a.device} but the block's parameters are on "
                             f"{param.device}")
        if a.ndim != 2 or a.shape[1] != width:
            raise ValueError(f"GraphsTuple.{name} has shape {tuple(a.shape)}, expected [rows, {width}] "
                             f"({name[:-1] if name != 'globals' else 'global'} feature size of the config)")
    for name in ("senders", "receivers", "n_node", "n_edge"):
        a = getattr(graph, name)
        if a is None:
            raise ValueError(f"GraphsTuple.{name} is None")
        if a.dtype not in (torch.int32, torch.int64):
            raise TypeError(f"GraphsTuple.{name} must be int32 or int64, got {a.dtype}")
        if a.device != param.device:
            raise ValueError(f"GraphsTuple.{name} is on {a.device} but the block's parameters are on "
                             f"{param.device}")
    if param.dtype not in _FLOATS:
        raise TypeError(f"parameters must be float32 or float64, got {param.dtype}")
    validate(graph)  # counts vs arrays, index ranges, edges inside their graph
    if finite:
        feats = [(n, getattr(graph, n)) for n in ("nodes", "edges", "globals") if getattr(graph, n) is not None]
        if feats:
            ok = torch.stack([torch.isfinite(a).all() for _, a in feats]).tolist()  # one sync
            bad = [n for (n, _), good in zip(feats, ok) if not good]
            if bad:
                raise ValueError(f"GraphsTuple.{bad[0]} contains NaN or Inf")


@contextlib.contextmanager
def matmul_precision(precision: str):
    """Scoped TF32 for float32 GEMMs (new torch API only: mixing it with the legacy
    ``allow_tf32`` flag makes torch raise)."""
    if precision != "tf32":
        yield
        return
    m = torch.backends.cuda.matmul
    old = m.fp32_precision
    m.fp32_precision = "tf32"
    try:
        yield
    finally:
        m.fp32_precision = old


# -- public module ------------------------------------------------------------------------------
class GraphNetwork(TorchGraphNetwork):
    """A GN block with Warp kernels (``backend="warp"``) or the torch reference (``"torch"``).

    Args:
        config: a ``GNBlockConfig`` (or give its fields as keyword arguments).
        backend: "warp" (default) or "torch"; may be changed at any time (``gn.backend = ...``).
        path: Warp path: "split" (Warp kernels for the graph work + BLAS GEMMs), "tile" (one
            fused Warp-tile kernel per update) or "auto" (the rule in ``gn_warp.choose_path``).
        precision: "fp32" (default: the parameters' dtype, float32 or float64), "tf32" (float32
            GEMMs on TF32 tensor cores), "fp16" or "bf16" (GEMM inputs and activations in that
            dtype, sums accumulated in float32; outputs returned in the parameters' dtype), or
            "fp16x3" (float32 parameters: float32-accurate GEMMs as three fp16 tensor-core
            products of row-scaled hi / lo pieces, for the MLPs ``emulate_min`` selects; IEEE
            fp32 elsewhere, in the backward, and on the torch backend).
        emulate_min: fp16x3's rule, (rows, hidden width): an MLP emulates from that many input
            rows and that hidden width; None (default) takes ``gn_warp``'s measured rule.
        deterministic: aggregate with ordered segment sums (edges sorted by receiver) instead of
            atomics: bitwise identical results run to run, forward and backward.
        edge_first_layer: how the split path computes the edge MLP's first layer: "concat" (the
            gathered rows [e, v_s, v_r, u] side by side, then one GEMM), "split" (node and global
            projections once per node / graph, gathered and added per edge by a Warp kernel) or
            "auto" (the measured rule in ``gn_warp.edge_concat``). Same numbers up to rounding.
        check_inputs: validate the graph before any launch (shapes, dtypes, devices, index
            ranges, finiteness). Costs a few host syncs; set False inside captured loops.

    ``forward(graph, index=None)``: ``graph`` is a GraphsTuple of torch tensors on the
    parameters' device; ``index`` an optional ``gn_warp.GraphIndex`` of that graph (build it once
    with ``gn.graph_index(graph)`` to share it across blocks and steps). Returns a GraphsTuple.
    """

    def __init__(self, config: GNBlockConfig | None = None, *, backend: str = "warp", path: str = "auto",
                 precision: str = "fp32", deterministic: bool = False, edge_first_layer: str = "auto",
                 check_inputs: bool = True, emulate_min: tuple[int, int] | None = None, **kwargs):
        super().__init__(config, **kwargs)
        self.backend = backend
        self.path = path
        self.edge_first_layer = edge_first_layer
        self.precision = precision
        self.deterministic = deterministic
        self.check_inputs = check_inputs
        self.emulate_min = emulate_min
        self._check_options()

    def _check_options(self):
        if self.backend not in ("warp", "torch"):
            raise ValueError(f"backend must be 'warp' or 'torch', got {self.backend!r}")
        if self.path not in ("auto", "split", "tile"):
            raise ValueError(f"path must be 'auto', 'split' or 'tile', got {self.path!r}")
        if self.edge_first_layer not in ("auto", "concat", "split"):
            raise ValueError(f"edge_first_layer must be 'auto', 'concat' or 'split', got {self.edge_first_layer!r}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS}, got {self.precision!r}")
        em = self.emulate_min
        if em is not None and not (isinstance(em, (tuple, list)) and len(em) == 2
                                   and all(isinstance(x, int) and x >= 0 for x in em)):
            raise ValueError(f"emulate_min must be None or (rows, width), two ints >= 0, got {em!r}")

    def extra_repr(self) -> str:
        return (f"backend={self.backend!r}, path={self.path!r}, precision={self.precision!r}, "
                f"deterministic={self.deterministic}")

    def graph_index(self, graph: GraphsTuple):
        """Index arrays of ``graph`` for the Warp backend (reusable across blocks and steps)."""
        from gnwarp import gn_warp
        return gn_warp.graph_index(graph, deterministic=self.deterministic)

    def forward(self, graph: GraphsTuple, index=None) -> GraphsTuple:
        self._check_options()
        param = self.edge_mlp.layers[0].weight
        if self.check_inputs:
            check_graph(self.config, graph, param)
        if self.backend == "torch":
            return self._torch_forward(graph)
        from gnwarp import gn_warp
        return gn_warp.gn_block_forward(self, graph, index)

    def _torch_forward(self, graph: GraphsTuple) -> GraphsTuple:
        if self.precision in ("fp16", "bf16"):
            dt = torch.float16 if self.precision == "fp16" else torch.bfloat16
            dev_type = graph.senders.device.type
            with torch.autocast(dev_type, dtype=dt):
                out = self.reference_forward(graph)
            in_dtype = self.edge_mlp.layers[0].weight.dtype
            cast = (lambda x: None if x is None else x.to(in_dtype))
            return out._replace(nodes=cast(out.nodes), edges=cast(out.edges), globals=cast(out.globals))
        with matmul_precision(self.precision):
            return self.reference_forward(graph)
