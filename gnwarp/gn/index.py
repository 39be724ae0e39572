"""``GraphIndex``: the index arrays of a batch of graphs that the Warp kernels read, built once
per topology and shared by every block and step that runs on it."""
from __future__ import annotations

from typing import NamedTuple

import torch

from gnwarp.graphs import GraphsTuple, graph_of

__all__ = ["GraphIndex", "graph_index", "check_index"]


class GraphIndex(NamedTuple):
    """Index arrays of a batch of graphs, int32 on the graph's device.

    ``senders``/``receivers`` [E], ``node_graph`` [N], ``edge_graph`` [E]: graph of each node /
    edge; ``node_offsets``/``edge_offsets`` [B+1]: first node / edge of each graph. Deterministic
    mode adds CSR layouts of the edges by receiver and by sender: ``recv_perm`` [E] (edge ids
    sorted by receiver, stable) with ``recv_offsets`` [N+1], and ``send_perm``/``send_offsets``.
    """
    n_nodes: int
    n_edges: int
    n_graphs: int
    senders: torch.Tensor
    receivers: torch.Tensor
    node_graph: torch.Tensor
    edge_graph: torch.Tensor
    node_offsets: torch.Tensor
    edge_offsets: torch.Tensor
    recv_perm: torch.Tensor | None = None
    recv_offsets: torch.Tensor | None = None
    send_perm: torch.Tensor | None = None
    send_offsets: torch.Tensor | None = None

    @property
    def deterministic(self) -> bool:
        return self.recv_perm is not None


def _csr(index: torch.Tensor, n_rows: int):
    """(perm, offsets): ids sorted by ``index`` (stable, so deterministic) and segment starts."""
    sorted_index, perm = torch.sort(index, stable=True)
    rows = torch.arange(n_rows + 1, device=index.device, dtype=sorted_index.dtype)
    offsets = torch.searchsorted(sorted_index, rows)  # no host sync (unlike bincount)
    return perm.to(torch.int32), offsets.to(torch.int32)


def _check_topology(graph: GraphsTuple, n_nodes: int, n_edges: int) -> None:
    """Raise ValueError naming the first problem of ``graph``'s counts and indices: shapes and
    dtypes from the host, values (counts against rows, negative counts, indices in range, edges
    inside their graph) on the device with one host sync. Skipped while a CUDA graph is being
    captured (nothing may sync then; the index of a captured step is built before capture)."""
    for name in ("senders", "receivers", "n_node", "n_edge"):
        a = getattr(graph, name)
        if not isinstance(a, torch.Tensor):
            raise TypeError(f"GraphsTuple.{name} must be a torch.Tensor, got {type(a).__name__}")
        if a.dtype not in (torch.int32, torch.int64):
            raise TypeError(f"GraphsTuple.{name} must be int32 or int64, got {a.dtype}")
        if a.ndim != 1:
            raise ValueError(f"GraphsTuple.{name} must be 1-D, got shape {tuple(a.shape)}")
    if graph.receivers.shape[0] != n_edges:
        raise ValueError(f"senders has {n_edges} entries but receivers {graph.receivers.shape[0]}")
    if graph.n_node.shape[0] != graph.n_edge.shape[0]:
        raise ValueError(f"n_node has {graph.n_node.shape[0]} graphs but n_edge has {graph.n_edge.shape[0]}")
    if graph.edges is not None and graph.edges.shape[0] != n_edges:
        raise ValueError(f"edges has {graph.edges.shape[0]} rows but senders {n_edges} entries")
    if max(n_nodes, n_edges) >= 2**31:
        raise ValueError(f"{n_nodes} nodes and {n_edges} edges: the index arrays are int32, at most 2**31 - 1 rows")
    if graph.senders.is_cuda and torch.cuda.is_current_stream_capturing():
        return
    n_node, n_edge = graph.n_node.long(), graph.n_edge.long()
    snd, rcv = graph.senders.long(), graph.receivers.long()
    zero = torch.zeros((), dtype=torch.int64, device=snd.device)
    amin = lambda a: a.min() if a.numel() else zero  # noqa: E731
    amax = lambda a: a.max() if a.numel() else zero - 1  # noqa: E731
    stats = [n_node.sum(), n_edge.sum(), amin(n_node), amin(n_edge), amin(snd), amax(snd), amin(rcv), amax(rcv)]
    vals = torch.stack([x.to(torch.int64) for x in stats]).tolist()   # the one host sync
    s_node, s_edge, min_node, min_edge, lo_s, hi_s, lo_r, hi_r = vals
    if min_node < 0 or min_edge < 0:
        raise ValueError(f"n_node and n_edge must be non-negative (smallest: {min_node}, {min_edge})")
    if s_node != n_nodes:
        raise ValueError(f"nodes has {n_nodes} rows but n_node sums to {s_node}")
    if s_edge != n_edges:
        raise ValueError(f"senders/receivers have {n_edges} entries but n_edge sums to {s_edge}")
    for name, lo, hi in (("senders", lo_s, hi_s), ("receivers", lo_r, hi_r)):
        if n_edges and (lo < 0 or hi >= n_nodes):
            raise ValueError(f"{name} index out of range: [{lo}, {hi}] for {n_nodes} nodes")
    if n_edges:  # an edge must stay inside its own graph
        node_g, edge_g = graph_of(n_node, n_nodes), graph_of(n_edge, n_edges)
        bad = (node_g[snd] != edge_g) | (node_g[rcv] != edge_g)
        if bool(bad.any()):
            k = int(bad.nonzero()[0, 0])
            raise ValueError(f"edge {k} connects nodes of a different graph than the one it belongs to")


def graph_index(graph: GraphsTuple, deterministic: bool = False, validate: bool = True) -> GraphIndex:
    """Build the ``GraphIndex`` of a GraphsTuple of torch tensors.

    ``validate`` (default): first check what the kernels will read, with one host sync (an index
    is built once per topology): counts against rows, no negative counts, senders and receivers
    in range, each edge inside its graph; ValueError / TypeError name the problem, so bad indices
    never reach a kernel, also for blocks that run with ``check_inputs=False``. Off (or while a
    CUDA graph is captured) there is no host sync when ``graph.nodes`` is given.
    """
    snd, rcv = graph.senders, graph.receivers
    n_edges = int(snd.shape[0])
    n_nodes = int(graph.nodes.shape[0]) if graph.nodes is not None else graph.total_nodes
    if validate:
        _check_topology(graph, n_nodes, n_edges)
    dev = snd.device
    n_graphs = int(graph.n_node.shape[0])
    n_node, n_edge = graph.n_node.long(), graph.n_edge.long()
    zero = torch.zeros(1, device=dev, dtype=torch.int64)
    gi = GraphIndex(
        n_nodes, n_edges, n_graphs,
        senders=snd.to(torch.int32).contiguous(), receivers=rcv.to(torch.int32).contiguous(),
        node_graph=graph_of(n_node, n_nodes).to(torch.int32),
        edge_graph=graph_of(n_edge, n_edges).to(torch.int32),
        node_offsets=torch.cat([zero, torch.cumsum(n_node, 0)]).to(torch.int32),
        edge_offsets=torch.cat([zero, torch.cumsum(n_edge, 0)]).to(torch.int32))
    if deterministic:
        rp, ro = _csr(gi.receivers, n_nodes)
        sp, so = _csr(gi.senders, n_nodes)
        gi = gi._replace(recv_perm=rp, recv_offsets=ro, send_perm=sp, send_offsets=so)
    return gi


def check_index(index: GraphIndex, graph: GraphsTuple, values: bool = False) -> None:
    """Raise ValueError if ``index`` was built for another topology than ``graph``'s: node, edge
    and graph counts compared from shapes (no host sync); ``values`` also compares the senders,
    receivers and per-graph counts themselves (one host sync)."""
    if not isinstance(index, GraphIndex):
        raise TypeError(f"index must be a GraphIndex (gn.graph_index(graph)), got {type(index).__name__}")
    n_nodes = graph.nodes.shape[0] if graph.nodes is not None else None
    have = {"nodes": n_nodes, "edges": graph.senders.shape[0], "graphs": graph.n_node.shape[0]}
    built = {"nodes": index.n_nodes, "edges": index.n_edges, "graphs": index.n_graphs}
    for k, n in have.items():
        if n is not None and int(n) != built[k]:
            raise ValueError(f"the GraphIndex was built for another topology: {built['nodes']} nodes, "
                             f"{built['edges']} edges, {built['graphs']} graphs; this graph has {int(n)} {k}")
    if graph.edges is not None and graph.edges.shape[0] != index.n_edges:
        raise ValueError(f"the GraphIndex was built for {index.n_edges} edges; GraphsTuple.edges has "
                         f"{graph.edges.shape[0]} rows")
    if values and index.n_edges + index.n_graphs:
        dev = index.senders.device
        n_node = torch.diff(index.node_offsets.long())
        n_edge = torch.diff(index.edge_offsets.long())
        same = torch.stack([
            (index.senders.long() == graph.senders.to(dev).long()).all(),
            (index.receivers.long() == graph.receivers.to(dev).long()).all(),
            (n_node == graph.n_node.to(dev).long()).all(), (n_edge == graph.n_edge.to(dev).long()).all()])
        ok = same.tolist()
        if not all(ok):
            what = [n for n, good in zip(("senders", "receivers", "n_node", "n_edge"), ok) if not good]
            raise ValueError(f"the GraphIndex was built for another topology: its {', '.join(what)} differ "
                             "from the graph's (build one per topology with gn.graph_index(graph))")
