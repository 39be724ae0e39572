"""The one graph structure of gnwarp, in the style of jraph / graph_nets.

A ``GraphsTuple`` holds a batch of directed graphs concatenated into flat arrays:

- ``nodes``: [sum(n_node), F_v] node features (or None)
- ``edges``: [sum(n_edge), F_e] edge features (or None)
- ``receivers``, ``senders``: [sum(n_edge)] int node indices into the *batched* node array
- ``globals``: [n_graph, F_u] per-graph features (or None)
- ``n_node``, ``n_edge``: [n_graph] int counts per graph

The fields are in jraph's order (``jraph.GraphsTuple``), so code written against jraph reads the
same; construct with keywords all the same.

Batching concatenates graphs and offsets each graph's sender/receiver indices by the number of
nodes before it; ``unbatch`` undoes that. Arrays may be numpy arrays or torch tensors (on any
device); functions here keep whatever array type they are given.
"""
from __future__ import annotations

from typing import Any, NamedTuple, Sequence

import numpy as np

try:  # torch is a dependency, but keep the structure importable without it
    import torch
except ImportError:  # pragma: no cover
    torch = None


class GraphsTuple(NamedTuple):
    nodes: Any
    edges: Any
    receivers: Any
    senders: Any
    globals: Any
    n_node: Any
    n_edge: Any

    # -- sizes -------------------------------------------------------------------------------
    @property
    def n_graph(self) -> int:
        return int(self.n_node.shape[0])

    @property
    def total_nodes(self) -> int:
        return int(self.n_node.sum().item()) if _is_torch(self.n_node) else int(np.sum(self.n_node))

    @property
    def total_edges(self) -> int:
        return int(self.n_edge.sum().item()) if _is_torch(self.n_edge) else int(np.sum(self.n_edge))

    # -- index helpers -------------------------------------------------------------------------
    def node_graph_index(self):
        """[sum(n_node)] index of the graph each node belongs to."""
        return graph_of(self.n_node, self.total_nodes)

    def edge_graph_index(self):
        """[sum(n_edge)] index of the graph each edge belongs to."""
        return graph_of(self.n_edge, self.total_edges)

    # -- conversions ---------------------------------------------------------------------------
    def to_torch(self, device=None, dtype=None) -> "GraphsTuple":
        """Torch tensors on ``device``; float features cast to ``dtype`` when given, indices int64."""
        def f(x):
            if x is None:
                return None
            t = torch.as_tensor(x)
            return t.to(device=device, dtype=dtype if dtype is not None else t.dtype)

        def i(x):
            return None if x is None else torch.as_tensor(x).to(device=device, dtype=torch.int64)

        return GraphsTuple(nodes=f(self.nodes), edges=f(self.edges), receivers=i(self.receivers),
                           senders=i(self.senders), globals=f(self.globals), n_node=i(self.n_node),
                           n_edge=i(self.n_edge))

    def to_numpy(self) -> "GraphsTuple":
        def f(x):
            if x is None:
                return None
            return x.detach().cpu().numpy() if _is_torch(x) else np.asarray(x)
        return GraphsTuple(*(f(x) for x in self))

    def replace(self, **kw) -> "GraphsTuple":
        return self._replace(**kw)

    def validate(self) -> "GraphsTuple":
        """Raise ValueError naming the first inconsistency; return self when all is well."""
        validate(self)
        return self


def _is_torch(x) -> bool:
    return torch is not None and isinstance(x, torch.Tensor)


def graph_of(counts, total: int):
    """[total] index of the graph each row belongs to, for per-graph row ``counts`` [n_graph]
    (n_node or n_edge): 0 repeated counts[0] times, then 1, ... . ``total`` = sum(counts), given
    so that torch needs no host sync. Torch tensors give int64 on their device, numpy arrays numpy."""
    if _is_torch(counts):
        # int64 arange: torch's int32 repeat_interleave is slow on the CPU
        return torch.repeat_interleave(torch.arange(counts.shape[0], device=counts.device), counts.long(),
                                       output_size=total)
    return np.repeat(np.arange(len(counts)), counts)


def _rows(x) -> int | None:
    return None if x is None else int(x.shape[0])


def validate(g: GraphsTuple) -> None:
    """Check shapes, counts and index ranges of a GraphsTuple; raise ValueError naming the problem."""
    if g.n_node is None or g.n_edge is None or g.senders is None or g.receivers is None:
        raise ValueError("GraphsTuple needs n_node, n_edge, senders and receivers (got None)")
    for name in ("n_node", "n_edge", "senders", "receivers"):
        a = getattr(g, name)
        if a.ndim != 1:
            raise ValueError(f"GraphsTuple.{name} must be 1-D, got shape {tuple(a.shape)}")
        kind = str(a.dtype)
        if "int" not in kind:
            raise ValueError(f"GraphsTuple.{name} must be an integer array, got dtype {kind}")
    if g.n_node.shape[0] != g.n_edge.shape[0]:
        raise ValueError(f"n_node has {g.n_node.shape[0]} graphs but n_edge has {g.n_edge.shape[0]}")
    n_nodes, n_edges = g.total_nodes, g.total_edges
    if (g.n_node < 0).any() or (g.n_edge < 0).any():
        raise ValueError("n_node and n_edge must be non-negative")
    if g.senders.shape[0] != n_edges or g.receivers.shape[0] != n_edges:
        raise ValueError(f"senders/receivers have {g.senders.shape[0]}/{g.receivers.shape[0]} entries but "
                         f"n_edge sums to {n_edges}")
    if g.nodes is not None and _rows(g.nodes) != n_nodes:
        raise ValueError(f"nodes has {_rows(g.nodes)} rows but n_node sums to {n_nodes}")
    if g.edges is not None and _rows(g.edges) != n_edges:
        raise ValueError(f"edges has {_rows(g.edges)} rows but n_edge sums to {n_edges}")
    if g.globals is not None and _rows(g.globals) != g.n_graph:
        raise ValueError(f"globals has {_rows(g.globals)} rows but there are {g.n_graph} graphs")
    for name in ("nodes", "edges", "globals"):
        a = getattr(g, name)
        if a is not None and a.ndim != 2:
            raise ValueError(f"GraphsTuple.{name} must be 2-D [rows, features], got shape {tuple(a.shape)}")
    if n_edges:
        for name in ("senders", "receivers"):
            a = getattr(g, name)
            lo, hi = int(a.min()), int(a.max())
            if lo < 0 or hi >= n_nodes:
                raise ValueError(f"{name} index out of range: [{lo}, {hi}] for {n_nodes} nodes")
        # an edge must stay inside its own graph
        eg = g.edge_graph_index()
        ng = g.node_graph_index()
        if _is_torch(eg):
            bad = (ng[g.senders] != eg) | (ng[g.receivers] != eg)
        else:
            bad = (ng[np.asarray(g.senders)] != eg) | (ng[np.asarray(g.receivers)] != eg)
        if bad.any():
            k = int(np.flatnonzero(np.asarray(bad.cpu() if _is_torch(bad) else bad))[0])
            raise ValueError(f"edge {k} connects nodes of a different graph than the one it belongs to")


def _cat(xs, like):
    if all(x is None for x in xs):
        return None
    if any(x is None for x in xs):
        raise ValueError("cannot batch graphs where some have features and others have None")
    if _is_torch(like):
        return torch.cat(list(xs), 0)
    return np.concatenate(xs, 0)


def batch(graphs: Sequence[GraphsTuple]) -> GraphsTuple:
    """Concatenate graphs (each may itself be a batch) into one GraphsTuple, offsetting indices.
    A graph's node offset is its node rows (a shape, known on the host) when it has node
    features, so batching reads nothing back from the device (it may run inside a CUDA graph
    capture); ``n_node``'s sum otherwise."""
    if len(graphs) == 0:
        raise ValueError("batch() needs at least one graph")
    like = graphs[0].n_node
    offsets, off = [], 0
    for g in graphs:
        offsets.append(off)
        off += int(g.nodes.shape[0]) if g.nodes is not None else g.total_nodes
    snd = [g.senders + o for g, o in zip(graphs, offsets)]
    rcv = [g.receivers + o for g, o in zip(graphs, offsets)]
    return GraphsTuple(
        nodes=_cat([g.nodes for g in graphs], like),
        edges=_cat([g.edges for g in graphs], like),
        globals=_cat([g.globals for g in graphs], like),
        senders=_cat(snd, like), receivers=_cat(rcv, like),
        n_node=_cat([g.n_node for g in graphs], like), n_edge=_cat([g.n_edge for g in graphs], like))


def unbatch(g: GraphsTuple) -> list[GraphsTuple]:
    """Split a batch into single graphs (indices made local again)."""
    n_node = g.n_node.tolist()
    n_edge = g.n_edge.tolist()
    out, v0, e0 = [], 0, 0
    for k, (nv, ne) in enumerate(zip(n_node, n_edge)):
        def sl(x, a, b):
            return None if x is None else x[a:b]
        out.append(GraphsTuple(
            nodes=sl(g.nodes, v0, v0 + nv), edges=sl(g.edges, e0, e0 + ne),
            globals=sl(g.globals, k, k + 1),
            senders=g.senders[e0:e0 + ne] - v0, receivers=g.receivers[e0:e0 + ne] - v0,
            n_node=g.n_node[k:k + 1], n_edge=g.n_edge[k:k + 1]))
        v0 += nv
        e0 += ne
    return out


def tile(template: GraphsTuple, n_graph: int, nodes=None, edges=None, globals=None) -> GraphsTuple:
    """A batch of ``n_graph`` copies of one graph's topology, with per-copy features.

    ``template`` holds a single graph's senders/receivers/n_node/n_edge (local indices);
    ``nodes`` is [n_graph * n_node, F] (or [n_graph, n_node, F]), likewise ``edges``;
    ``globals`` is [n_graph, F]. Vectorized: no Python loop over graphs.
    """
    nv, ne = int(template.n_node[0]), int(template.n_edge[0])
    t = _is_torch(template.senders)
    if t:
        dev = template.senders.device
        off = torch.arange(n_graph, device=dev)[:, None] * nv
        snd = (template.senders[None, :] + off).reshape(-1)
        rcv = (template.receivers[None, :] + off).reshape(-1)
        n_node = torch.full((n_graph,), nv, dtype=torch.int64, device=dev)
        n_edge = torch.full((n_graph,), ne, dtype=torch.int64, device=dev)
    else:
        off = np.arange(n_graph)[:, None] * nv
        snd = (np.asarray(template.senders)[None, :] + off).reshape(-1)
        rcv = (np.asarray(template.receivers)[None, :] + off).reshape(-1)
        n_node = np.full((n_graph,), nv, dtype=np.int64)
        n_edge = np.full((n_graph,), ne, dtype=np.int64)

    def flat(x):
        return None if x is None else x.reshape(-1, x.shape[-1])
    return GraphsTuple(nodes=flat(nodes), edges=flat(edges), receivers=rcv, senders=snd, globals=globals,
                       n_node=n_node, n_edge=n_edge)
