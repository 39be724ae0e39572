"""Input graphs of a model from static graphs and dynamic states, built on the device.

``GraphBuilder`` makes batches of input graphs (static features concatenated with body states
and controls) for any system instances of a dataset; ``GraphTemplate`` fixes the instances of a
rollout once so that every step only fills in states and controls; ``graph_builder`` binds a
Dataset or a System to a model's ``FeatureLayout``. Everything is torch, vectorized over the batch.
"""
from __future__ import annotations

import numpy as np
import torch

from gnwarp.data.convert import static_arrays
from gnwarp.data.layout import FeatureLayout, LayoutMismatchError, map_static
from gnwarp.graphs import GraphsTuple, graph_of
from gnwarp.interop import WP_DTYPE, Launcher
from gnwarp.kernels.data import builder as K
from gnwarp.sim.systems import System
from gnwarp.state import DYN_NODE_NAMES, DYN_NODE_SIZE

__all__ = ["edge_control_index", "edge_control_values", "GraphBuilder", "GraphTemplate", "graph_builder"]


def edge_control_index(index: torch.Tensor, graph: torch.Tensor, n_ctrl: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(flat, has): where each edge slot's control sits in the flat [N * n_ctrl] controls, and
    whether it has one. ``index`` [..., K]: the control index of each of an edge's K slots (-1: no
    actuator); ``graph``: the graph of each edge, broadcastable to index.shape[:-1]."""
    return graph[..., None] * n_ctrl + index.clamp(min=0), index >= 0


def edge_control_values(ctrl: torch.Tensor, index: torch.Tensor, graph: torch.Tensor,
                        gain: torch.Tensor | None = None) -> torch.Tensor:
    """Controls on edges (torch; ``gnwarp.data.convert.edge_controls`` is the numpy reference).

    ``ctrl`` [N, U]: the controls of N graphs; ``index``, ``graph`` as ``edge_control_index``;
    ``gain`` (shaped as index, or None for all 1): each slot's weight (a tendon's coefficient).
    Returns [..., K] in ctrl's dtype, 0 where no actuator; no host sync.
    """
    flat, has = edge_control_index(index, graph, ctrl.shape[-1])
    c = ctrl.reshape(-1)[flat.reshape(-1)].reshape(flat.shape)
    if gain is not None:
        c = c * gain.to(c.dtype)
    return torch.where(has, c, torch.zeros((), dtype=ctrl.dtype, device=ctrl.device))


class GraphBuilder:
    """Builds batched input graphs from per-instance static graphs and dynamic states.

    Vectorized over the batch (no Python loop over bodies or states); works on torch tensors on
    any device so rollouts can rebuild graphs every step without leaving the device.
    ``static``: the arrays of a dataset's ``/static`` group (``Dataset.static``, or
    ``gnwarp.data.convert.static_arrays``), numpy or h5py.
    ``__call__(instance [N], body [N, B, 13], ctrl [N, U]) -> GraphsTuple`` with
    nodes = [static node features, 13 dynamic], edges = [static edge features, controls],
    globals = static global features. Where ``static`` holds ``edge_ctrl_gain`` (actuators on
    tendons), each slot's control is multiplied by its gain (``edge_gain``, else None).
    """

    def __init__(self, static: dict, device=None, dtype=None):
        self.dtype = dtype or torch.float32
        t = lambda k, dt=None: torch.as_tensor(np.asarray(static[k][...]), device=device, dtype=dt)  # noqa: E731
        self.s_globals = t("globals", self.dtype)
        self.s_nodes = t("nodes", self.dtype)
        self.s_edges = t("edges", self.dtype)
        self.senders = t("senders", torch.int64)
        self.receivers = t("receivers", torch.int64)
        self.n_node = t("n_node", torch.int64)
        self.n_edge = t("n_edge", torch.int64)
        self.edge_ctrl = t("edge_ctrl", torch.int64)
        self.edge_gain = t("edge_ctrl_gain", self.dtype) if "edge_ctrl_gain" in static else None   # [I, E, K]
        B, E = self.s_nodes.shape[1], self.s_edges.shape[1]
        self.node_mask = torch.arange(B, device=device)[None] < self.n_node[:, None]   # [I, B]
        self.edge_mask = torch.arange(E, device=device)[None] < self.n_edge[:, None]   # [I, E]
        self.uniform = bool((self.n_node == B).all() and (self.n_edge == E).all())
        # one topology for every instance (a system's instances differ in parameters only): then
        # a batch's index arrays depend on its size alone, and are made once per size
        same = lambda a: bool((a == a[:1]).all()) if a.shape[0] else True  # noqa: E731
        self.fixed_topology = (self.uniform and same(self.senders) and same(self.receivers) and same(self.edge_ctrl)
                               and (self.edge_gain is None or same(self.edge_gain)))
        self.n_ctrl_read = int(self.edge_ctrl.max()) + 1 if self.edge_ctrl.numel() else 0  # controls the edges read
        # per instance, the System's actuator record (``graph_builder`` of Systems); None for a dataset
        self.actuators: list | None = None
        self._topologies: dict[tuple[int, int], tuple] = {}
        self._kernel_gain: torch.Tensor | None = None   # [I, E, K] the fused batch's weights, made once

    def topology(self, N: int, U: int) -> tuple:
        """(senders, receivers, n_node, n_edge, control index, has control) of N graphs of the one
        topology with U controls each, made once per (N, U) (the same tensors every call: steps
        and caches keyed on them see one topology)."""
        topo = self._topologies.get((N, U))
        if topo is None:
            dev = self.s_nodes.device
            B, E = self.s_nodes.shape[1], self.s_edges.shape[1]
            off = torch.arange(N, device=dev)[:, None] * B
            flat, has = edge_control_index(self.edge_ctrl[:1].expand(N, -1, -1), torch.arange(N, device=dev)[:, None], U)
            topo = ((self.senders[:1] + off).reshape(-1), (self.receivers[:1] + off).reshape(-1),
                    torch.full((N,), B, device=dev, dtype=torch.int64), torch.full((N,), E, device=dev, dtype=torch.int64),
                    flat.reshape(-1), has.reshape(-1))
            if len(self._topologies) >= 16:  # bounded; whoever captured a step on them holds them
                self._topologies.pop(next(iter(self._topologies)))
            self._topologies[(N, U)] = topo
        return topo

    def shared_topology(self, N: int, U: int) -> GraphsTuple | None:
        """The senders, receivers and counts (no features) that every call on N instances with U
        controls returns, when they are made once per size (one topology for every instance:
        ``topology``); None when each call makes its own."""
        if not (self.fixed_topology and U >= self.n_ctrl_read):
            return None
        snd, rcv, n_node, n_edge, _, _ = self.topology(N, U)
        return GraphsTuple(nodes=None, edges=None, receivers=rcv, senders=snd, globals=None, n_node=n_node,
                           n_edge=n_edge)

    def fuses(self, body: torch.Tensor, ctrl: torch.Tensor) -> bool:
        """Whether ``sequence_batch`` of these sequences runs as one Warp launch: one topology,
        every actuator slot's control present, float32 or float64 states in the builder's dtype."""
        return (self.fixed_topology and ctrl.shape[-1] >= self.n_ctrl_read and body.dtype in (torch.float32, torch.float64)
                and self.dtype == body.dtype == ctrl.dtype and body.shape[-1] == DYN_NODE_SIZE)

    def sequence_batch(self, instance: torch.Tensor, body: torch.Tensor, ctrl: torch.Tensor, seq: torch.Tensor,
                       t: torch.Tensor, fused: bool | None = None) -> tuple[GraphsTuple, torch.Tensor]:
        """(input graphs of the states at steps ``t`` [n] of sequences ``seq`` [n], their true next
        states [sum(n_node), 13]) of stored sequences: ``instance`` [S], ``body`` [S, T+1, B, 13],
        ``ctrl`` [S, T, U], on the builder's device. ``fused`` (default ``fuses(body, ctrl)``):
        written by one Warp launch (``kernels/data/builder.py``) instead of ~12 torch kernels."""
        if fused if fused is not None else self.fuses(body, ctrl):
            return self._fused_batch(instance, body, ctrl, seq, t)
        inst = instance[seq]
        g = self(inst, body[seq, t], ctrl[seq, t])
        nxt = body[seq, t + 1]
        target = nxt.reshape(-1, DYN_NODE_SIZE) if self.uniform else nxt[self.node_mask[inst]]
        return g, target

    def _fused_batch(self, instance, body, ctrl, seq, t) -> tuple[GraphsTuple, torch.Tensor]:
        n = seq.shape[0]
        snd, rcv, n_node, n_edge, _, _ = self.topology(n, ctrl.shape[-1])
        B, E = self.s_nodes.shape[1], self.s_edges.shape[1]
        new = lambda *shape: torch.empty(shape, device=body.device, dtype=body.dtype)  # noqa: E731
        nodes = new(n * B, self.s_nodes.shape[2] + DYN_NODE_SIZE)
        edges = new(n * E, self.s_edges.shape[2] + self.edge_ctrl.shape[2])
        glob, target = new(n, self.s_globals.shape[1]), new(n * B, DYN_NODE_SIZE)
        if self._kernel_gain is None:   # weights 1 where none are stored: the controls stay bit-identical
            self._kernel_gain = (self.edge_gain if self.edge_gain is not None
                                 else torch.ones(self.edge_ctrl.shape, device=self.edge_ctrl.device, dtype=self.dtype))
        gain = self._kernel_gain
        Launcher(nodes)(K.sample_batch_kernel(WP_DTYPE[nodes.dtype]), n * (B + E + 1), seq, t, instance, body, ctrl,
                        self.s_nodes, self.s_edges, self.s_globals, self.edge_ctrl, gain, nodes, edges, glob, target)
        g = GraphsTuple(nodes=nodes, edges=edges, receivers=rcv, senders=snd, globals=glob, n_node=n_node, n_edge=n_edge)
        return g, target

    def __call__(self, instance, body, ctrl) -> GraphsTuple:
        dev = self.s_nodes.device
        instance = instance.to(dev)
        body = body.to(dev, self.dtype)
        ctrl = ctrl.to(dev, self.dtype)
        N = instance.shape[0]
        if self.fixed_topology and ctrl.shape[-1] >= self.n_ctrl_read:
            snd, rcv, n_node, n_edge, cidx, has = self.topology(N, ctrl.shape[-1])
            c = ctrl.reshape(-1)[cidx]
            if self.edge_gain is not None:   # one gain for every instance (fixed_topology)
                c = c * self.edge_gain[:1].expand(N, -1, -1).reshape(-1)
            c = torch.where(has, c, 0.0)
            K = self.edge_ctrl.shape[-1]
            nodes = torch.cat([self.s_nodes[instance], body], -1)
            edges = torch.cat([self.s_edges[instance], c.reshape(N, -1, K)], -1)
            return GraphsTuple(nodes=nodes.reshape(-1, nodes.shape[-1]), edges=edges.reshape(-1, edges.shape[-1]),
                               receivers=rcv, senders=snd, globals=self.s_globals[instance],
                               n_node=n_node, n_edge=n_edge)
        graph = torch.arange(N, device=dev)[:, None]
        gain = self.edge_gain[instance] if self.edge_gain is not None else None
        c = edge_control_values(ctrl, self.edge_ctrl[instance], graph, gain)  # [N, E, K]
        nodes = torch.cat([self.s_nodes[instance], body], -1)           # [N, B, Fv+13]
        edges = torch.cat([self.s_edges[instance], c], -1)              # [N, E, Fe+K]
        n_node, n_edge = self.n_node[instance], self.n_edge[instance]
        off = torch.cumsum(n_node, 0) - n_node
        snd = self.senders[instance] + off[:, None]
        rcv = self.receivers[instance] + off[:, None]
        if self.uniform:
            return GraphsTuple(nodes=nodes.reshape(-1, nodes.shape[-1]), edges=edges.reshape(-1, edges.shape[-1]),
                               receivers=rcv.reshape(-1), senders=snd.reshape(-1), globals=self.s_globals[instance],
                               n_node=n_node, n_edge=n_edge)
        nm, em = self.node_mask[instance], self.edge_mask[instance]
        return GraphsTuple(nodes=nodes[nm], edges=edges[em], receivers=rcv[em], senders=snd[em],
                           globals=self.s_globals[instance], n_node=n_node, n_edge=n_edge)


class GraphTemplate:
    """The static part of a batch of input graphs (given system instances), built once, so that
    each rollout step only fills in body states and controls: ``graph(body [N, B, 13], ctrl [N, U])``
    runs without host synchronization. ``to_body(nodes, like)`` maps flat node rows back to [N, B, 13]."""

    def __init__(self, builder: GraphBuilder, instance: torch.Tensor):
        dev = builder.s_nodes.device
        instance = instance.to(dev)
        self.instance = instance                                                  # [N] the source's instances
        N, B = int(instance.shape[0]), int(builder.s_nodes.shape[1])
        self.N, self.B = N, B
        self.dtype = builder.dtype
        K = builder.edge_ctrl.shape[-1]
        U = max(int(builder.edge_ctrl.max()) + 1, 1)  # host sync, here only
        g = builder(instance, torch.zeros(N, B, DYN_NODE_SIZE, device=dev), torch.zeros(N, U, device=dev))
        self.static_nodes = g.nodes[:, :-DYN_NODE_SIZE]
        self.static_edges = g.edges[:, :-K]
        self.topology = g._replace(nodes=None, edges=None)
        nm = builder.node_mask[instance].reshape(-1)
        em = builder.edge_mask[instance].reshape(-1)
        self.rows = None if builder.uniform else nm.nonzero().squeeze(1)       # one sync, here only
        ec = builder.edge_ctrl[instance]                                          # [N, E, K]
        self.ctrl_index = ec.reshape(-1, K) if builder.uniform else ec.reshape(-1, K)[em.nonzero().squeeze(1)]
        # [n_edges, K] each slot's control weight (actuators on tendons), None where all are 1
        gain = None if builder.edge_gain is None else builder.edge_gain[instance].reshape(-1, K)
        self.ctrl_gain = gain if gain is None or builder.uniform else gain[em.nonzero().squeeze(1)]
        self.edge_of = graph_of(self.topology.n_edge, int(self.static_edges.shape[0]))  # graph of each edge
        self.n_nodes = int(self.static_nodes.shape[0])
        self._ctrl_map: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}
        acts = getattr(builder, "actuators", None)   # [N] the instances' actuator records, or None
        self.actuators = None if acts is None else [acts[i] for i in instance.tolist()]

    def graph(self, body: torch.Tensor, ctrl: torch.Tensor) -> GraphsTuple:
        """Input graphs of the N instances from ``body`` [N, B, 13] and ``ctrl`` [N, U]."""
        dyn = self.nodes(body)
        ctrl = ctrl.to(self.dtype)
        U = ctrl.shape[-1]
        if U not in self._ctrl_map:  # where each edge slot reads its control: once per control width
            self._ctrl_map[U] = edge_control_index(self.ctrl_index, self.edge_of, U)
        flat, has = self._ctrl_map[U]
        c = ctrl.reshape(-1)[flat]
        if self.ctrl_gain is not None:
            c = c * self.ctrl_gain
        c = torch.where(has, c, 0.0)
        return self.topology._replace(nodes=torch.cat([self.static_nodes, dyn], -1),
                                      edges=torch.cat([self.static_edges, c], -1))

    def nodes(self, body: torch.Tensor) -> torch.Tensor:
        """[N, B, 13] -> [sum(n_node), 13]."""
        flat = body.to(self.dtype).reshape(self.N * self.B, DYN_NODE_SIZE)
        return flat if self.rows is None else flat.index_select(0, self.rows)

    def to_body(self, nodes: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        """[sum(n_node), 13] -> [N, B, 13], padding rows taken from ``like``."""
        if self.rows is None:
            return nodes.reshape(self.N, self.B, DYN_NODE_SIZE)
        flat = like.to(nodes.dtype).reshape(self.N * self.B, DYN_NODE_SIZE)
        return flat.index_copy(0, self.rows, nodes).reshape(self.N, self.B, DYN_NODE_SIZE)


def graph_builder(layout: FeatureLayout, source, device=None, dtype=None, strict: bool = True) -> GraphBuilder:
    """A ``GraphBuilder`` of ``source``'s graphs in ``layout``: source is a ``Dataset``, a
    ``gnwarp.sim.systems.System`` (its static graph, for planning without a dataset) or a list of
    Systems of one family (instance i is the i-th: per-episode parameters)."""
    systems = None
    if isinstance(source, System):
        systems = [source]
    elif isinstance(source, (list, tuple)) and source and all(isinstance(s, System) for s in source):
        systems = list(source)
    if systems is not None:
        static, data_layout, _ = static_arrays(systems)
    elif all(hasattr(source, a) for a in ("static", "layout", "meta")):  # a Dataset: its module imports this one
        names = tuple(source.meta.get("dynamic_node_names", DYN_NODE_NAMES))
        if names != DYN_NODE_NAMES:
            raise LayoutMismatchError(f"the data's dynamic node features {names} are not {DYN_NODE_NAMES}")
        static, data_layout = source.static, source.layout
    else:
        raise TypeError(f"expected a gnwarp Dataset or System, got {type(source).__name__}")
    builder = GraphBuilder(map_static(layout, data_layout, static, strict), device=device, dtype=dtype)
    if systems is not None:   # the rollout clamp reads each instance's actuator record
        builder.actuators = [s.actuators for s in systems]
    return builder
