"""``GraphNetwork``: the paper's GN block as a torch module, on hand-written Warp kernels.

For a batch of graphs (a ``GraphsTuple``):

1. edges:   e'_k = phi_e([e_k, v_sender(k), v_receiver(k), u_graph(k)])
2. aggregate: E_i = sum of e'_k over the edges k received by node i
3. nodes:   v'_i = phi_v([v_i, E_i, u_graph(i)])
4. globals: u'   = phi_u([u, sum_i v'_i, sum_k e'_k])   (per graph; skipped if ``update_globals=False``)

Each phi is an MLP (ReLU hidden layers, linear output); the ``use_*`` switches of each update
(``GNBlockConfig``) decide which bracketed pieces exist. ``RunOptions`` decide how it runs: the
Warp kernels (the "blas" path: Warp graph kernels + BLAS GEMMs, ``blas_block``; or the fused
"tile" path, ``tile_block``) or the torch reference, at a precision.
"""
from __future__ import annotations

import torch

from gnwarp.gn import blas_block, replay, rules, tile_block
from gnwarp.gn.config import GNBlockConfig
from gnwarp.gn.index import GraphIndex, check_index, graph_index
from gnwarp.gn.options import ResolvedRun, RunOptions
from gnwarp.gn.reference import TorchGraphNetwork, check_graph
from gnwarp.graphs import GraphsTuple

__all__ = ["GraphNetwork"]


def _option(name: str) -> property:
    """A module attribute that reads and writes ``options.<name>`` (validated on write)."""
    def get(self):
        return getattr(self.options, name)

    def set_(self, value):
        self.options = self.options.replace(**{name: value})
    return property(get, set_, doc=f"``options.{name}`` (see ``RunOptions``).")


class GraphNetwork(TorchGraphNetwork):
    """A GN block on Warp kernels (``impl="warp"``) or the torch reference (``impl="torch"``).

    Args:
        config: a ``GNBlockConfig`` (or give its fields as keyword arguments).
        options: a ``RunOptions``; or give its fields as keyword arguments (``impl``, ``path``,
            ``precision``, ``deterministic``, ``edge_first_layer``, ``emulate_min``,
            ``check_inputs``). Each is also an attribute that may be changed at any time
            (``gn.precision = "tf32"``), as is ``gn.options`` as a whole.

    ``forward(graph, index=None)``: ``graph`` is a GraphsTuple of torch tensors on the
    parameters' device; ``index`` an optional ``GraphIndex`` of that graph (build it once with
    ``gn.graph_index(graph)`` to share it across blocks and steps; building it validates the
    counts and indices). Returns a GraphsTuple with new nodes, edges and (with ``update_globals``)
    globals. An index of another topology raises: its node, edge and graph counts are compared with
    the graph's shapes on every call (no host sync), its arrays with the graph's values too when
    ``check_inputs`` is on.
    """
    impl = _option("impl")
    path = _option("path")
    precision = _option("precision")
    deterministic = _option("deterministic")
    edge_first_layer = _option("edge_first_layer")
    emulate_min = _option("emulate_min")
    check_inputs = _option("check_inputs")

    def __init__(self, config: GNBlockConfig | None = None, *, options: RunOptions | None = None, **kwargs):
        fields = set(RunOptions.__dataclass_fields__)
        run_kw = {k: kwargs.pop(k) for k in list(kwargs) if k in fields}
        super().__init__(config, **kwargs)
        if options is not None and run_kw:
            raise TypeError("give either options= or their fields as keyword arguments, not both")
        self.options = options if options is not None else RunOptions(**run_kw)

    def extra_repr(self) -> str:
        o = self.options
        return f"impl={o.impl!r}, path={o.path!r}, precision={o.precision!r}, deterministic={o.deterministic}"

    def graph_index(self, graph: GraphsTuple) -> GraphIndex:
        """Index arrays of ``graph`` for the Warp kernels (reusable across blocks and steps),
        validated once here (one host sync): counts, index ranges, edges inside their graph."""
        return graph_index(graph, deterministic=self.options.deterministic)

    def forward(self, graph: GraphsTuple, index: GraphIndex | None = None) -> GraphsTuple:
        param = self.edge_mlp.layers[0].weight
        run = self.options.resolve(param.dtype, param.device)
        if run.options.check_inputs:
            check_graph(self.config, graph, param)
        if index is not None:  # from shapes; the arrays too (a host sync) when inputs are checked
            check_index(index, graph, values=run.options.check_inputs)
        if run.impl == "torch":
            return self._torch_forward(graph, run)
        return self._warp_forward(graph, index, run)

    def _torch_forward(self, graph: GraphsTuple, run: ResolvedRun) -> GraphsTuple:
        if run.autocast is not None:
            with torch.autocast(graph.senders.device.type, dtype=run.autocast):
                out = self.reference_forward(graph)
            cast = (lambda x: None if x is None else x.to(run.param_dtype))
            return out._replace(nodes=cast(out.nodes), edges=cast(out.edges), globals=cast(out.globals))
        with run.matmul():
            return self.reference_forward(graph)

    def _warp_forward(self, graph: GraphsTuple, index: GraphIndex | None, run: ResolvedRun) -> GraphsTuple:
        c = self.config
        params = self.flat_parameters()
        device = params[0].device
        if index is None:  # validated here unless check_graph just did
            index = graph_index(graph, deterministic=run.deterministic, validate=not run.options.check_inputs)
        elif run.deterministic and not index.deterministic:
            raise ValueError("deterministic GraphNetwork needs a GraphIndex built with deterministic=True")
        auto = run.path == "auto"
        path = rules.choose_path(c, run, device, index.n_edges) if auto else run.path
        if replay.active_store() is not None:
            path = "blas"   # a rollout recording or replaying its blocks: every block replays (gn/replay.py)
        v = graph.nodes if c.needs_nodes else None
        e = graph.edges if c.needs_edges else None
        u = graph.globals if c.needs_globals else None
        outs = None
        if path == "tile":
            why = rules.tile_feasible(c, run, device)
            if why is not None:
                raise ValueError(f"path='tile' cannot run this block: {why}")
            try:
                outs = tile_block.tile_block(c, index, v, e, u, self.edge_mlp.layers, self.node_mlp.layers,
                                             self.global_mlp.layers if self.global_mlp is not None else None)
            except tile_block.TileSharedMemoryError:
                if not auto:
                    raise
                outs = None  # checked before any launch: the blas path runs instead
        if outs is None:
            outs = blas_block.blas_block(c, run, index, v, e, u, params, len(self.edge_mlp.layers),
                                         len(self.node_mlp.layers))
        u_out = outs[2] if c.update_globals else graph.globals
        return graph._replace(nodes=outs[0], edges=outs[1], globals=u_out)
