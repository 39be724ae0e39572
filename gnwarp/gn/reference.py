"""The pure-torch reference of the GN block (index_select, cat, nn.Linear, index_add_), the MLP
its updates use, and the input checks every implementation runs first.

``GraphNetwork`` (``gnwarp.gn.module``) is this module with the Warp kernels beside it: the same
parameters, so state dicts are interchangeable and the tests compare one against the other.
"""
from __future__ import annotations

from typing import Sequence

import torch
import torch.nn as nn

from gnwarp.gn.config import GNBlockConfig, layout_width
from gnwarp.graphs import GraphsTuple, graph_of, validate

__all__ = ["MLP", "TorchGraphNetwork", "check_graph"]


class MLP(nn.Module):
    """Hidden layers with ``activation`` (ReLU, the GN kernels' and the paper's), linear output:
    ``layers`` is a list of nn.Linear."""

    def __init__(self, in_size: int, hidden: Sequence[int], out_size: int, activation=torch.relu):
        super().__init__()
        sizes = [in_size, *hidden, out_size]
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(sizes[:-1], sizes[1:]))
        self.activation = activation

    def forward(self, x):
        for k, layer in enumerate(self.layers):
            x = layer(x)
            if k < len(self.layers) - 1:
                x = self.activation(x)
        return x

    def flat_parameters(self) -> list[torch.Tensor]:
        """[W0, b0, W1, b1, ...] (weights are [out, in], as nn.Linear stores them)."""
        return [p for layer in self.layers for p in (layer.weight, layer.bias)]


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
        self.edge_mlp = MLP(layout_width(c.edge_layout), c.edge_hidden, c.edge_out)
        self.node_mlp = MLP(layout_width(c.node_layout), c.node_hidden, c.node_out)
        self.global_mlp = MLP(layout_width(c.global_layout), c.global_hidden, c.global_out) if c.update_globals else None

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
        node_g = graph_of(graph.n_node, n_nodes)
        edge_g = graph_of(graph.n_edge, snd.shape[0])
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
