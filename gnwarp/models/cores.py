"""The cores of a forward model: normalized input graph -> normalized change of each body's state.

``GNCore`` is the paper's (D.1, D.2): two ``GraphNetwork`` blocks with a graph skip. ``MLPCore``
is the baseline of section E: an MLP on the flattened graph of a fixed topology.
"""
from __future__ import annotations

import contextlib
import contextvars

import torch
import torch.nn as nn

from gnwarp.gn.index import GraphIndex
from gnwarp.gn.module import GraphNetwork
from gnwarp.gn.options import RunOptions
from gnwarp.gn.reference import MLP
from gnwarp.graphs import GraphsTuple
from gnwarp.models.config import GNCoreConfig, MLPCoreConfig, core_blocks
from gnwarp.state import DYN_NODE_SIZE

__all__ = ["GNCore", "MLPCore", "gn2_listener"]

_GN2_LISTENER = contextvars.ContextVar("gn2_listener", default=None)


@contextlib.contextmanager
def gn2_listener(listener):
    """Within it, every ``GNCore`` forward that records gradients calls ``listener.gn2_forward()``,
    and its backward ``listener.gn2_backward()`` once GN2's backward is done (that call's GN2
    parameter gradients complete, its GN1's not begun): where a distributed trainer starts
    reducing GN2's gradients while GN1's backward runs (``gnwarp.train.overlap``)."""
    token = _GN2_LISTENER.set(listener)
    try:
        yield
    finally:
        _GN2_LISTENER.reset(token)


class _Signal(torch.autograd.Function):
    """Identity on GN2's inputs that need a gradient, whose backward calls ``listener.gn2_backward()``
    first (when their gradients are complete, i.e. GN2's backward has returned)."""

    @staticmethod
    def forward(ctx, listener, *xs):
        ctx.listener = listener
        return tuple(x.view_as(x) for x in xs)

    @staticmethod
    def backward(ctx, *grads):
        ctx.listener.gn2_backward()
        return (None, *grads)


class GNCore(nn.Module):
    """GN1 on the normalized input graph; GN2 on [input, GN1 output] (graph skip), with GN2's
    global update switched off since only its nodes are read: the normalized change of each
    body's dynamic state (D.1, D.2). ``config``'s wiring switches give Figure H.2's variants
    (one block; no skip; GN1's output keeping the input's edges, nodes or globals): see
    ``GNCoreConfig`` and ``core_blocks``.

    ``sizes``: input widths {"nodes", "edges", "globals"}; ``options``: how both blocks run (their
    input checks are off: a model's graphs come from its ``GraphBuilder``)."""

    def __init__(self, config: GNCoreConfig, sizes: dict[str, int], options: RunOptions | None = None):
        super().__init__()
        self.config = config
        blocks = core_blocks(config, sizes)
        self.gn1 = GraphNetwork(blocks[0])
        self.gn2 = GraphNetwork(blocks[1]) if len(blocks) > 1 else None
        self.set_options(options or RunOptions())

    @property
    def options(self) -> RunOptions:
        return self.gn1.options

    def set_options(self, options: RunOptions) -> None:
        """Run both blocks with ``options`` (their input checks off)."""
        for block in (self.gn1, self.gn2):
            if block is not None:
                block.options = options.replace(check_inputs=False)

    def graph_index(self, graph: GraphsTuple) -> GraphIndex | None:
        """Index of ``graph``'s topology, shared by both blocks (None for the torch implementation)."""
        return self.gn1.graph_index(graph) if self.options.impl == "warp" else None

    def replay_outputs(self) -> list[tuple[str, ...]]:
        """Per block call of ``forward``, the outputs read after it by anything but a later block
        (``gnwarp/gn/replay.py``): GN2's nodes (GN1's outputs feed only GN2), or GN1's nodes
        when it is the only block."""
        return [("nodes",)] if self.gn2 is None else [(), ("nodes",)]

    def forward(self, graph: GraphsTuple, index: GraphIndex | None = None) -> torch.Tensor:
        """Normalized input graph -> [sum(n_node), 13] normalized state changes."""
        g1 = self.gn1(graph, index)
        if self.gn2 is None:
            return g1.nodes
        c = self.config
        out = g1._replace(nodes=g1.nodes if c.gn1_nodes else graph.nodes,
                          edges=g1.edges if c.gn1_edges else graph.edges,
                          globals=g1.globals if c.gn1_globals else graph.globals)
        if c.skip:
            out = graph._replace(nodes=torch.cat([graph.nodes, out.nodes], -1),
                                 edges=torch.cat([graph.edges, out.edges], -1),
                                 globals=torch.cat([graph.globals, out.globals], -1))
        listener = _GN2_LISTENER.get()   # None outside a distributed trainer's overlapped step
        names = [] if listener is None or not torch.is_grad_enabled() else [
            k for k in ("nodes", "edges", "globals") if getattr(out, k) is not None and getattr(out, k).requires_grad]
        if names:
            listener.gn2_forward()
            out = out._replace(**dict(zip(names, _Signal.apply(listener, *(getattr(out, k) for k in names)))))
        return self.gn2(out, index).nodes


class MLPCore(nn.Module):
    """Section E: the GN core replaced by an MLP on the flattened graph [globals, all nodes, all
    edges] -> all nodes' normalized changes. Fixed topology: every graph has n_node nodes and
    n_edge edges in the order of the training data. ``options.precision`` applies to its GEMMs
    (torch's: tf32, or autocast for fp16 / bf16)."""

    def __init__(self, config: MLPCoreConfig, sizes: dict[str, int], options: RunOptions | None = None):
        super().__init__()
        if config.n_node <= 0 or config.n_edge < 0:
            raise ValueError("MLPCoreConfig needs the fixed topology (n_node, n_edge) of its data")
        self.n_node, self.n_edge = config.n_node, config.n_edge
        n_in = sizes["globals"] + self.n_node * sizes["nodes"] + self.n_edge * sizes["edges"]
        self.mlp = MLP(n_in, [config.width] * config.layers, self.n_node * DYN_NODE_SIZE)
        self.options = options or RunOptions()

    def set_options(self, options: RunOptions) -> None:
        self.options = options

    def graph_index(self, graph: GraphsTuple) -> None:
        return None

    def forward(self, graph: GraphsTuple, index=None) -> torch.Tensor:
        n = graph.n_node.shape[0]
        if graph.nodes.shape[0] != n * self.n_node or graph.edges.shape[0] != n * self.n_edge:
            raise ValueError(f"the MLP baseline has a fixed topology of {self.n_node} nodes and {self.n_edge} "
                             f"edges per graph; got {graph.nodes.shape[0]} nodes and {graph.edges.shape[0]} "
                             f"edges for {n} graphs")
        x = torch.cat([graph.globals.reshape(n, -1), graph.nodes.reshape(n, -1), graph.edges.reshape(n, -1)], -1)
        run = self.options.resolve(x.dtype, x.device)
        if run.autocast is not None:
            with torch.autocast(x.device.type, dtype=run.autocast):
                y = self.mlp(x)
            return y.to(x.dtype).reshape(n * self.n_node, DYN_NODE_SIZE)
        with run.matmul():
            return self.mlp(x).reshape(n * self.n_node, DYN_NODE_SIZE)
