"""``GraphIndex``: the index arrays of a batch of graphs that the Warp kernels read, built once
per topology and shared by every block and step that runs on it."""
from __future__ import annotations

from typing import NamedTuple

import torch

from gnwarp.graphs import GraphsTuple, graph_of

__all__ = ["GraphIndex", "graph_index"]


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


def graph_index(graph: GraphsTuple, deterministic: bool = False) -> GraphIndex:
    """Build the ``GraphIndex`` of a GraphsTuple of torch tensors (no host sync if nodes given)."""
    snd, rcv = graph.senders, graph.receivers
    dev = snd.device
    n_edges = int(snd.shape[0])
    n_nodes = int(graph.nodes.shape[0]) if graph.nodes is not None else graph.total_nodes
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
