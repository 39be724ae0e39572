"""A recurrent GN core: a GN block over [input graph, hidden graph] and GRU updates of the hidden
graph's edges, nodes and globals (paper D.2, D.7.2, D.7.3).

One step, for input graph G_t and hidden graph H_{t-1} of the same topology::

    Z   = GN(concat(G_t, H_{t-1}))                  edges, nodes, globals of width ``latent``
    H_t = GRU_k(Z.k, H_{t-1}.k)   for k in edges, nodes, globals (one GRU cell per kind)
    O_t = Linear_k(concat(Z.k, H_t.k))  for each kind with an output size > 0

``first_steps`` runs the step from H = 0 on a batch that stacks many steps' graphs: the same
weights read as a feed-forward GN, each step on its own.

The GN block runs on the Warp kernels (``impl="warp"``) or the torch reference
(``impl="torch"``), as ``RunOptions`` say; the GRU cells and output layers are torch. Hidden
sizes: 20 for the paper's recurrent forward model, 10 for the inferred static graph (D.2). A step
has no host synchronization when given the graph's index (build it once with ``graph_index``).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable, Sequence

import torch
import torch.nn as nn

from gnwarp.gn.config import EdgeBlockConfig, GlobalBlockConfig, GNBlockConfig, NodeBlockConfig
from gnwarp.gn.index import GraphIndex
from gnwarp.gn.module import GraphNetwork
from gnwarp.gn.options import RunOptions
from gnwarp.graphs import GraphsTuple
from gnwarp.validation import Count, Width, Widths, check_fields, check_keys

__all__ = ["RecurrentGNConfig", "RecurrentGNCore", "KINDS"]

KINDS = ("edges", "nodes", "globals")


@dataclass
class RecurrentGNConfig:
    """Sizes of a ``RecurrentGNCore``.

    ``latent``: width of the GN block's updated edges, nodes and globals (the GRUs' input).
    ``hidden_edges`` / ``hidden_nodes`` / ``hidden_globals``: widths of the hidden (state) graph
    (paper: 20 for recurrent forward models, 10 for parameter inference).
    ``edge_mlp`` / ``node_mlp`` / ``global_mlp``: hidden layer widths of the GN block's MLPs.
    ``out_edges`` / ``out_nodes`` / ``out_globals``: widths of the output graph (0: the output
    graph has no such features, its field is None).
    """
    latent: Width = 128
    hidden_edges: Width = 20
    hidden_nodes: Width = 20
    hidden_globals: Width = 20
    edge_mlp: Widths = (256, 256)
    node_mlp: Widths = (128, 128)
    global_mlp: Widths = (128, 128)
    out_edges: Count = 0
    out_nodes: Count = 0
    out_globals: Count = 0

    def __post_init__(self):
        check_fields(self)  # types and ranges: one ConfigError naming the key

    def hidden(self, kind: str) -> int:
        return getattr(self, f"hidden_{kind}")

    def out(self, kind: str) -> int:
        return getattr(self, f"out_{kind}")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "RecurrentGNConfig":
        return cls(**check_keys(cls, d))


def block_config(c: RecurrentGNConfig, sizes: dict[str, int]) -> GNBlockConfig:
    """The GN block of a recurrent core on inputs of widths ``sizes``: it reads [input, hidden]
    (globals always present: the hidden graph has them) and updates all three kinds."""
    fv, fe, fg = (int(sizes[k]) + c.hidden(k) for k in ("nodes", "edges", "globals"))
    return GNBlockConfig(fv, fe, fg, node_out=c.latent, edge_out=c.latent, global_out=c.latent,
                         edge_hidden=c.edge_mlp, node_hidden=c.node_mlp, global_hidden=c.global_mlp,
                         edge_block=EdgeBlockConfig(use_globals=True), node_block=NodeBlockConfig(use_globals=True),
                         global_block=GlobalBlockConfig(use_globals=True), update_globals=True)


class RecurrentGNCore(nn.Module):
    """A GN core with a hidden graph state (see the module docstring).

    ``config``: ``RecurrentGNConfig``; ``sizes``: input widths {"nodes", "edges", "globals"}
    (globals may be 0); ``options``: how the GN block runs (its input checks off).

    Attributes: ``gn`` (the ``GraphNetwork``), ``gru`` (an ``nn.GRUCell`` per kind, keyed by
    "edges" / "nodes" / "globals"), ``out`` (an ``nn.Linear`` per kind with an output).
    """

    def __init__(self, config: RecurrentGNConfig, sizes: dict[str, int], options: RunOptions | None = None):
        super().__init__()
        self.config = config
        self.sizes = {k: int(sizes[k]) for k in KINDS}
        self.gn = GraphNetwork(block_config(config, self.sizes))
        self.gru = nn.ModuleDict({k: nn.GRUCell(config.latent, config.hidden(k)) for k in KINDS})
        self.out = nn.ModuleDict({k: nn.Linear(config.latent + config.hidden(k), config.out(k))
                                  for k in KINDS if config.out(k) > 0})
        self.set_options(options or RunOptions())

    @property
    def options(self) -> RunOptions:
        return self.gn.options

    def set_options(self, options: RunOptions) -> None:
        """Run the GN block with ``options`` (input checks off: a model's graphs are built by it)."""
        self.gn.options = options.replace(check_inputs=False)

    def graph_index(self, graph: GraphsTuple) -> GraphIndex | None:
        """Index of ``graph``'s topology (validated, one host sync; None for the torch impl)."""
        return self.gn.graph_index(graph) if self.options.impl == "warp" else None

    def initial_hidden(self, graph: GraphsTuple) -> GraphsTuple:
        """The empty hidden graph of ``graph``'s topology: zeros, [rows, hidden_<kind>] per kind."""
        ref = graph.nodes
        dtype = self.gn.edge_mlp.layers[0].weight.dtype
        rows = {"nodes": ref.shape[0], "edges": graph.senders.shape[0], "globals": graph.n_node.shape[0]}
        z = {k: torch.zeros(rows[k], self.config.hidden(k), dtype=dtype, device=ref.device) for k in KINDS}
        return graph._replace(**z)

    def _check(self, graph: GraphsTuple, hidden: GraphsTuple) -> None:
        rows = {"nodes": graph.nodes.shape[0], "edges": graph.senders.shape[0], "globals": graph.n_node.shape[0]}
        for k in KINDS:
            x, h = getattr(graph, k), getattr(hidden, k)
            width = 0 if x is None else x.shape[-1]
            if width != self.sizes[k]:
                raise ValueError(f"input graph {k} have width {width}, the core was built for {self.sizes[k]}")
            if h is None or tuple(h.shape) != (rows[k], self.config.hidden(k)):
                got = None if h is None else tuple(h.shape)
                raise ValueError(f"hidden graph {k} must be [{rows[k]}, {self.config.hidden(k)}] (the input "
                                 f"graph's topology), got {got}")

    def step(self, graph: GraphsTuple, hidden: GraphsTuple, index: GraphIndex | None = None,
             output: bool = True) -> tuple[GraphsTuple | None, GraphsTuple]:
        """One step: (output graph, next hidden graph), both of ``graph``'s topology. Output
        fields of kinds without an output size are None. ``index``: ``graph_index(graph)``,
        shared by all steps of a sequence (built here otherwise). ``output=False``: only the
        hidden graph (the output is None; its MLPs are not run)."""
        self._check(graph, hidden)

        def cat(k):
            x = getattr(graph, k)
            h = getattr(hidden, k).to(self.gn.edge_mlp.layers[0].weight.dtype)
            return h if x is None or x.shape[-1] == 0 else torch.cat([x.to(h.dtype), h], -1)
        z = self.gn(graph._replace(**{k: cat(k) for k in KINDS}), index)
        new_h = {k: self.gru[k](getattr(z, k), getattr(hidden, k)) for k in KINDS}
        if not output:
            return None, graph._replace(**new_h)
        out = {k: (self.out[k](torch.cat([getattr(z, k), new_h[k]], -1)) if k in self.out else None)
               for k in KINDS}
        return graph._replace(**out), graph._replace(**new_h)

    def first_steps(self, graph: GraphsTuple, index: GraphIndex | None = None) -> GraphsTuple:
        """The output graph of ``step`` from the empty hidden graph, for every graph of ``graph``:
        a batch that stacks the graphs of many steps (``gnwarp.graphs.batch``) runs them all in one
        block, with no state carried from one step to the next (``SysIDConfig.stateless``)."""
        out, _ = self.step(graph, self.initial_hidden(graph), index)
        return out

    def sequence(self, graphs: Sequence[GraphsTuple] | Callable[[int], GraphsTuple], hidden: GraphsTuple | None = None,
                 steps: int | None = None, index: GraphIndex | None = None,
                 last_only: bool = False) -> tuple[list[GraphsTuple], GraphsTuple]:
        """Run ``step`` over a sequence: ``graphs`` a list of graphs of one topology, or a callable
        ``t -> graph`` with ``steps`` steps. ``hidden``: the initial hidden graph (default zeros).
        Returns (the output graph of every step, the final hidden graph). ``index``: the graphs'
        ``graph_index`` (default: built once, from the first graph). ``last_only``: compute the
        output graph of the last step alone (the list holds just it)."""
        if callable(graphs):
            if steps is None:
                raise ValueError("sequence(callable) needs steps=")
            get, n = graphs, int(steps)
        else:
            graphs = list(graphs)
            get, n = graphs.__getitem__, len(graphs) if steps is None else int(steps)
        if n < 1:
            raise ValueError("sequence needs at least one step")
        g = get(0)
        index = self.graph_index(g) if index is None else index
        h = self.initial_hidden(g) if hidden is None else hidden
        outs = []
        for t in range(n):
            o, h = self.step(g if t == 0 else get(t), h, index, output=not last_only or t == n - 1)
            if o is not None:
                outs.append(o)
        return outs, h
