"""The graphs of system identification (``SysIDModel``): the nominal static graph
(``NominalGraph``, ``nominal_graph``), where each instance parameter lives in a graph
(``source_places``, ``place_tables``), the forward model's layout of G_ID's columns
(``gid_layout``), the instances' graph topologies (``instance_topologies``) and an
identification window's graphs built as one batch (``StackedWindow``)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from gnwarp.data.layout import FeatureLayout
from gnwarp.graphs import GraphsTuple, batch
from gnwarp.models.recurrent import KINDS
from gnwarp.validation import ConfigError, Count, FloatRange, check_fields, check_keys

__all__ = ["NominalGraph", "StackedWindow", "gid_layout", "instance_topologies", "nominal_graph", "place_tables",
           "source_name", "source_places", "source_static"]


Finite = FloatRange()


@dataclass
class NominalGraph:
    """One graph's static features as ``SysIDConfig.nominal_static`` reads them: the kept static
    columns of the training data (``*_names``; the data's ``FeatureLayout``), each element at its
    mean over the train split's instances (``globals`` [F_g], ``nodes`` [n][F_v], ``edges``
    [e][F_e]), and the graph's topology (``senders``, ``receivers`` [e]). Built by
    ``nominal_graph``; validated when made, so a checkpoint's is checked as it loads."""
    global_names: tuple[str, ...]
    node_names: tuple[str, ...]
    edge_names: tuple[str, ...]
    globals: tuple[Finite, ...]
    nodes: tuple[tuple[Finite, ...], ...]
    edges: tuple[tuple[Finite, ...], ...]
    senders: tuple[Count, ...]
    receivers: tuple[Count, ...]

    def __post_init__(self):
        check_fields(self)
        rows = {"globals": [self.globals], "nodes": self.nodes, "edges": self.edges}
        for kind, names in (("globals", self.global_names), ("nodes", self.node_names), ("edges", self.edge_names)):
            bad = [i for i, r in enumerate(rows[kind]) if len(r) != len(names)]
            if bad:
                raise ConfigError(kind, f"row {bad[0]} has {len(rows[kind][bad[0]])} values for "
                                        f"{len(names)} {kind[:-1]} columns")
        if not self.nodes:
            raise ConfigError("nodes", "a nominal graph has at least one node")
        if not (len(self.senders) == len(self.receivers) == len(self.edges)):
            raise ConfigError("senders", f"{len(self.senders)} senders and {len(self.receivers)} receivers for "
                                         f"{len(self.edges)} edges")
        if any(i >= len(self.nodes) for i in (*self.senders, *self.receivers)):
            raise ConfigError("senders", f"an edge's node index is beyond the graph's {len(self.nodes)} nodes")

    def to_dict(self) -> dict:
        return {f.name: [list(r) for r in v] if f.name in ("nodes", "edges") else list(v)
                for f in dataclasses.fields(self) for v in [getattr(self, f.name)]}

    @classmethod
    def from_dict(cls, d: dict) -> "NominalGraph":
        return cls(**check_keys(cls, d, "nominal graph keys"))

    def tensors(self) -> dict[str, torch.Tensor]:
        """{"globals" [F_g], "nodes" [n, F_v], "edges" [e, F_e]} float64."""
        return {"globals": torch.tensor(self.globals, dtype=torch.float64),
                "nodes": torch.tensor(self.nodes, dtype=torch.float64).reshape(len(self.nodes), len(self.node_names)),
                "edges": torch.tensor(self.edges, dtype=torch.float64).reshape(len(self.edges), len(self.edge_names))}


def source_static(source) -> dict:
    """A Dataset's or a System's static arrays (``gnwarp.data.static_arrays``' layout)."""
    from gnwarp.data.convert import static_arrays
    from gnwarp.sim.systems import System
    return static_arrays([source])[0] if isinstance(source, System) else source.static


def source_name(source) -> str:
    return repr(getattr(source, "system", getattr(source, "name", type(source).__name__)))


def instance_topologies(static: dict) -> list[tuple]:
    """Per instance of static arrays (``gnwarp.data.static_arrays``' layout): its graph layout
    (n_node, senders, receivers), equal for instances whose graphs a G_ID fits alike."""
    ne, nn_ = np.asarray(static["n_edge"]), np.asarray(static["n_node"])
    s, r = np.asarray(static["senders"]), np.asarray(static["receivers"])
    return [(int(nn_[i]), tuple(int(x) for x in s[i, :ne[i]]), tuple(int(x) for x in r[i, :ne[i]]))
            for i in range(nn_.shape[0])]


def nominal_graph(dataset) -> NominalGraph:
    """``dataset``'s nominal static graph (``SysIDConfig.nominal_static``): its kept static
    columns, each element's mean over the instances of its train split. Raises ``ValueError``
    when the instances differ in topology (a swimmer with varied links)."""
    static, layout = dataset.static, dataset.layout
    used = np.unique(np.asarray(dataset["train"].instance[...]))
    topo = instance_topologies(static)
    if any(topo[i] != topo[used[0]] for i in range(len(topo))):
        raise ValueError(f"nominal_static: the instances of {source_name(dataset)} differ in topology (bodies or "
                         f"joints); a nominal static graph needs one")
    n, senders, receivers = topo[used[0]]
    mean = {k: np.asarray(static[k], dtype=np.float64)[used].mean(0) for k in KINDS}
    return NominalGraph(tuple(layout.global_names), tuple(layout.node_names), tuple(layout.edge_names),
                        tuple(float(v) for v in mean["globals"]),
                        tuple(tuple(float(v) for v in r) for r in mean["nodes"][:n]),
                        tuple(tuple(float(v) for v in r) for r in mean["edges"][:len(senders)]), senders, receivers)



def source_places(source) -> tuple:
    """``SysIDConfig.param_places`` of a parameterized Dataset or System: each parameter's node
    row, edge rows (its actuator's edges within a graph, the same in every instance) or none
    (a global), from the dataset's ``param_places`` metadata or ``gnwarp.sim.param_places``."""
    from gnwarp.sim.systems import System, param_places
    static = source_static(source)
    if isinstance(source, System):
        names, places = list(source.params), [list(p) for p in param_places(source)]
    else:
        names, places = source.meta.get("param_names", []), source.meta.get("param_places")
        if names and places is None:
            raise ValueError(f"dataset {source.system!r} does not say where its parameters live (no param_places in "
                             f"its metadata: generated before them); regenerate it for local_params")
    if not names:
        raise ValueError(f"{source_name(source)} has no instance parameters: "
                         f"local_params places the parameters of a parameterized system")
    ec = np.asarray(static["edge_ctrl"])[..., 0]
    ne = np.asarray(static["n_edge"])
    out = []
    for name, (kind, i) in zip(names, places):
        if kind != "edges":
            out.append((kind, (i,) if kind == "nodes" else ()))
            continue
        rows = [tuple(int(e) for e in np.flatnonzero(ec[j, :ne[j]] == i)) for j in range(ec.shape[0])]
        if not rows[0] or any(r != rows[0] for r in rows):
            raise ValueError(f"parameter {name!r} of actuator {i}: its edges differ between the instances (or it "
                             f"drives none); local_params needs them at the same rows in every graph")
        out.append(("edges", rows[0]))
    return tuple(out)


def gid_layout(sizes: dict[str, int], n_ctrl_slots: int, slots: dict[str, int] | None = None,
               nominal: NominalGraph | None = None) -> FeatureLayout:
    """The forward model's layout: G_ID's latents as its static columns, then ``slots`` columns
    of placed parameters per node and edge (``SysIDConfig.local_params``), then the nominal
    static graph's columns (``SysIDConfig.nominal_static``)."""
    slots = slots or {}
    names = {"globals": [f"gid_global_{i}" for i in range(sizes["globals"])],
             "nodes": [f"gid_node_{i}" for i in range(sizes["nodes"])]
             + [f"param_node_{i}" for i in range(slots.get("nodes", 0))],
             "edges": [f"gid_edge_{i}" for i in range(sizes["edges"])]
             + [f"param_edge_{i}" for i in range(slots.get("edges", 0))]}
    if nominal is not None:
        for k in KINDS:
            names[k] += [f"nominal_{n}" for n in getattr(nominal, f"{k[:-1]}_names")]   # global_names, ...
    return FeatureLayout(names["globals"], names["nodes"], names["edges"], n_ctrl_slots=n_ctrl_slots)


def place_tables(places) -> dict[str, torch.Tensor]:
    """Per kind ("nodes", "edges"): a table [rows + 1, slots] (int64) of the parameter in each
    slot of each node (edge) row within a graph, -1 where none; its last row is all -1 (for rows
    beyond the placed ones)."""
    out = {}
    for kind in ("nodes", "edges"):
        per_row: dict[int, list[int]] = {}
        for p, (k, rows) in enumerate(places):
            if k == kind:
                for r in rows:
                    per_row.setdefault(r, []).append(p)
        n = max(per_row, default=-1) + 1
        width = max((len(v) for v in per_row.values()), default=0)
        t = torch.full((n + 1, width), -1, dtype=torch.int64)
        for r, ps in per_row.items():
            t[r, :len(ps)] = torch.tensor(ps)
        out[kind] = t
    return out


class StackedWindow(NamedTuple):
    """An identification window's ``steps`` dynamic graphs, built as one batch: ``graph`` holds
    steps x N graphs, step by step (step t's N graphs are the t-th block of rows, as
    ``gnwarp.graphs.batch`` of the steps lays them out), and ``topology`` one step's senders,
    receivers and counts, which every step shares (no features). ``window[t]`` is step t's graph
    (views), ``len(window)`` the steps, ``head(k)`` the first k steps as one batch."""
    graph: GraphsTuple
    steps: int
    topology: GraphsTuple

    @classmethod
    def of(cls, graphs: list) -> "StackedWindow":
        """The window of ``graphs`` (one step each, of one topology)."""
        g0 = graphs[0]
        return cls(batch(graphs), len(graphs), g0._replace(nodes=None, edges=None, globals=None))

    @classmethod
    def build(cls, builder, instance: torch.Tensor, body: torch.Tensor, ctrl: torch.Tensor) -> "StackedWindow":
        """The window of N ``instance``s of ``builder``'s source from ``body`` [W, N, B, 13] and
        ``ctrl`` [W, N, U] (step first), in one call of the builder."""
        W, N = body.shape[:2]
        graph = builder(instance.repeat(W), body.reshape(W * N, *body.shape[2:]), ctrl.reshape(W * N, ctrl.shape[-1]))
        topology = builder.shared_topology(N, ctrl.shape[-1])
        return cls(graph, W, topology if topology is not None else cls._first(graph, W))

    @classmethod
    def _first(cls, graph: GraphsTuple, steps: int) -> GraphsTuple:
        """The first step's topology of a stacked ``graph`` (views)."""
        return cls(graph, steps, None).head(1)._replace(nodes=None, edges=None, globals=None)

    def __len__(self) -> int:
        return self.steps

    def __getitem__(self, t: int) -> GraphsTuple:
        if not -self.steps <= t < self.steps:
            raise IndexError(f"step {t} of a {self.steps}-step window")
        t %= self.steps
        return self.topology._replace(**{k: self._rows(k, t, t + 1) for k in KINDS})

    def head(self, k: int) -> GraphsTuple:
        """The first ``k`` steps as one batch of k x N graphs (views)."""
        return GraphsTuple(**{f: self._rows(f, 0, k) for f in GraphsTuple._fields})

    def _rows(self, field: str, a: int, b: int):
        """The rows of ``graph``'s ``field`` that steps [a, b) hold (every field has the same
        number of rows per step)."""
        x = getattr(self.graph, field)
        return None if x is None else x[x.shape[0] // self.steps * a:x.shape[0] // self.steps * b]
