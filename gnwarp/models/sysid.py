"""System identification (paper D.2, D.3, D.6.2, Algorithms D.2 and D.4): a recurrent GN reads a
window of dynamic graphs and outputs a latent static graph G_ID that replaces the true static
graph in a forward model.

::

    G_d^t  = dynamic graph of step t (13 body states per node, controls per edge; no static features)
    G_o, G_h = GN_p(Norm_in(G_d^t), G_h)   for t over the window (``RecurrentGNCore``), G_h = 0 first
    G_ID   = G_o of the last step          (per-node, per-edge and global latents; not normalized, D.3)
    x_t+1  = ForwardModel(concat(G_ID, G_d^t))   (the forward model's static columns are G_ID)

The forward model is a plain ``ForwardModel`` on a ``FeatureLayout`` whose static columns are
G_ID's (``gid_node_<i>``, ...); its input normalizers leave those columns as they are. ``Norm_in``
of the window is the forward model's, on the dynamic columns. In rollouts G_ID is identified
once and reused every step (``identify`` then ``rollout``); ``gnwarp.models.gid`` saves and loads it,
and holds it fixed for rollout engines and planners.
"""
from __future__ import annotations

import dataclasses
import weakref
from dataclasses import dataclass, field
from typing import Literal, NamedTuple

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from gnwarp.data.builder import GraphTemplate, graph_builder
from gnwarp.data.layout import FeatureLayout
from gnwarp.gn.options import RunOptions
from gnwarp.gn.reference import MLP
from gnwarp.gn.index import graph_index
from gnwarp.graphs import GraphsTuple, batch
from gnwarp.models.config import ModelConfig
from gnwarp.models.forward import ForwardModel
from gnwarp.models.gid import FixedGIDModel, GIDError
from gnwarp.models.normalizer import Normalizer
from gnwarp.models.recurrent import KINDS, RecurrentGNConfig, RecurrentGNCore
from gnwarp.models.rollout import (RolloutInputError, RolloutInputs, check_instance, float_tensor,
                                  source_info)
from gnwarp.state import ANGVEL, DYN_NODE_SIZE, LINVEL, state_delta
from gnwarp.validation import (MAX_WIDTH, ConfigError, Count, Flag, FloatRange, IntRange, PositiveFloat, PositiveInt,
                               check_fields, check_keys)

__all__ = ["SysIDConfig", "SysIDModel", "NominalGraph", "StackedWindow", "source_places", "nominal_graph",
           "instance_topologies"]


# the readouts that fit a linear model over the window (``SysIDConfig.readout``)
FITS = ("ridge", "dynamics")
# the "dynamics" readout's targets: the velocity columns of ``state_delta`` (6)
FIT_TARGETS = slice(LINVEL.start, ANGVEL.stop)


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


def _source_static(source) -> dict:
    """A Dataset's or a System's static arrays (``gnwarp.data.static_arrays``' layout)."""
    from gnwarp.data.convert import static_arrays
    from gnwarp.sim.systems import System
    return static_arrays([source])[0] if isinstance(source, System) else source.static


def _source_name(source) -> str:
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
        raise ValueError(f"nominal_static: the instances of {_source_name(dataset)} differ in topology (bodies or "
                         f"joints); a nominal static graph needs one")
    n, senders, receivers = topo[used[0]]
    mean = {k: np.asarray(static[k], dtype=np.float64)[used].mean(0) for k in KINDS}
    return NominalGraph(tuple(layout.global_names), tuple(layout.node_names), tuple(layout.edge_names),
                        tuple(float(v) for v in mean["globals"]),
                        tuple(tuple(float(v) for v in r) for r in mean["nodes"][:n]),
                        tuple(tuple(float(v) for v in r) for r in mean["edges"][:len(senders)]), senders, receivers)


def _identifier_default() -> RecurrentGNConfig:
    # D.2: abstract static graph of size 10 per node, edge and global; the hidden graph as wide
    return RecurrentGNConfig(hidden_edges=10, hidden_nodes=10, hidden_globals=10, out_edges=10, out_nodes=10,
                             out_globals=10)


@dataclass
class SysIDConfig:
    """A system-identification model: ``forward`` (the forward model's ``ModelConfig``; its run
    options are the whole model's), ``identifier`` (GN_p; its ``out_*`` sizes are G_ID's widths,
    except under a fitting readout without a head: ``gid_size``) and ``window`` (steps of the identification
    window, paper: 20).

    ``transitions`` (beyond the paper; default off, the paper's GN_p): GN_p reads the window's
    W - 1 transitions instead of its W states: at each step t < W - 1 the state, the controls and
    the state change to step t + 1 (``state_delta``, normalized by the forward model's output
    statistics), so the accelerations the parameters shape are inputs rather than something
    GN_p's recurrence must difference out of consecutive states.

    ``readout`` (beyond the paper): "last" (the paper's) takes G_ID as GN_p's output graph at
    the window's last step; "mean" averages its output graphs over every step, so that each
    step's evidence about the parameters counts alike (an estimate pooled over the window, as a
    least-squares fit pools its equations) instead of passing through 19 GRU updates; "ridge"
    reads each step's output of a node (edge, global) as regressors phi [F] (its first
    ``ridge_features`` columns) and targets psi (the rest, P of them), and G_ID is the ridge
    solution B [F, P] of psi ~ B^T phi over the window, flattened (F * P wide; with ``ridge_head``,
    the head's map of it): a least-squares fit
    whose features GN_p learns, the way a classical estimator identifies a system from a window.
    "dynamics" fixes the ridge fit's targets to what the window observed: each step's output of a
    node (edge, global) is the regressor phi [F] (all F of its columns) and the target is the
    body's velocity change to the next step (``state_delta``'s 6 velocity columns, normalized as
    the forward model's targets; an edge's is its receiver's, a global's the mean over the
    graph's moving bodies), so G_ID [F * 6] holds the coefficients of a linear model of the
    window's dynamics over learned features of the states and controls: the fit a classical
    identifier makes, with regressors GN_p learns. GN_p then reads states, not transitions (a
    regressor that saw the change it is fitted to would explain it away), and the window's last
    step is only a target.
    ``ridge``: the ridge weight, relative to the mean diagonal of the features' second moments.
    ``ridge_head`` (with a fitting readout; default 0, none): the width of a two-layer MLP (SiLU)
    per node, edge and global that maps the fit's coefficients to G_ID, which is then the
    identifier's ``out_*`` sizes wide. A fit's coefficients are the window's dynamics (for a
    pendulum, the velocity change per sin(angle) and per control), which the parameters shape
    nonlinearly (a length is a ratio of two of them); the head learns that map, so that G_ID can
    hold the parameters themselves (what ``SysIDTrainer(param_loss=...)`` asks of it). The head
    is plain torch layers in the parameter dtype, whatever ``RunOptions.impl``: a few small GEMMs
    once per window.

    ``stateless`` (beyond the paper; default off, the paper's recurrent GN_p): GN_p carries no
    hidden state from one step of the window to the next. Each step is read on its own, from the
    empty hidden graph (``RecurrentGNCore.first_steps``), and all of the window's steps run as
    one batch: one GN block instead of W - 1 in sequence, forward and backward. A pooling readout
    ("mean", "ridge", "dynamics") then combines the steps, as a least-squares fit combines its
    equations; needs one ("last" would read only the last step). With ``transitions`` each step
    holds what a fit needs (the state, the controls, the change they caused).

    ``local_params`` (beyond the paper; default off): G_ID's first P global columns (the
    parameters ``SysIDTrainer(param_loss=...)`` supervises) are also handed to the forward model
    where each parameter lives, as a true static graph holds it: a body's length or mass as a
    column of its node, an actuator's gear as a column of its joint's edges (``param_places``,
    one ``(kind, rows)`` per parameter: ("nodes", (body,)), ("edges", (edge, ...)) with edge
    rows within a graph, ("globals", ()); filled from the training data's
    ``gnwarp.sim.param_places`` by ``build_sysid_model``). The forward model then reads the
    mass of a JACO link on that link's node rather than picking it out of 18 globals.

    ``nominal_static`` (beyond the paper; default off): the forward model also reads the training
    data's static graph with each element at its mean over the train split's instances
    (``nominal``, a ``NominalGraph`` filled by ``build_sysid_model``): the system as designed, its
    bodies' geometry and its joints' ranges, the same for every instance, so that it carries no
    parameter while G_ID says only how an instance differs from it. The paper's G_ID replaces the
    whole static graph, so the forward model must also learn from GN_p what is fixed (which JACO
    link is which). Needs every instance of one topology; binding a source of another is refused."""
    forward: ModelConfig = field(default_factory=ModelConfig)
    identifier: RecurrentGNConfig = field(default_factory=_identifier_default)
    window: PositiveInt = 20
    transitions: bool = False
    stateless: Flag = False
    readout: Literal["last", "mean", "ridge", "dynamics"] = "last"
    ridge_features: PositiveInt = 4
    ridge: PositiveFloat = 1e-3
    ridge_head: IntRange(0, MAX_WIDTH) = 0
    local_params: Flag = False
    param_places: tuple[tuple[Literal["nodes", "edges", "globals"], tuple[Count, ...]], ...] | None = None
    nominal_static: Flag = False
    nominal: NominalGraph | None = None

    def __post_init__(self):
        check_fields(self)
        if self.nominal is not None and not self.nominal_static:
            raise ValueError("nominal is the static graph nominal_static reads: set nominal_static=True")
        if self.param_places is not None:
            if not self.local_params:
                raise ValueError("param_places places the parameters for local_params: set local_params=True")
            for i, (kind, rows) in enumerate(self.param_places):
                if (kind == "globals") != (len(rows) == 0) or (kind == "nodes" and len(rows) != 1):
                    raise ValueError(f"param_places[{i}] = {(kind, rows)}: a node parameter has one row, an edge "
                                     f"parameter one or more, a global one none")
        default = {f.name: f.default for f in dataclasses.fields(self)}
        if self.readout != "ridge" and self.ridge_features != default["ridge_features"]:
            raise ValueError(f"ridge_features splits GN_p's outputs for readout 'ridge'; readout {self.readout!r} "
                             f"does not read it")
        if self.readout not in FITS and self.ridge != default["ridge"]:
            raise ValueError(f"ridge weights the fit of readout 'ridge' or 'dynamics'; readout {self.readout!r} fits "
                             f"nothing")
        if self.stateless and self.readout == "last":
            raise ValueError("stateless reads each step of the window on its own, so G_ID must pool the steps: it "
                             "needs readout 'mean', 'ridge' or 'dynamics', got 'last'")
        if self.ridge_head and self.readout not in FITS:
            raise ValueError(f"ridge_head maps a fit's coefficients to G_ID: it needs readout 'ridge' or 'dynamics', "
                             f"got {self.readout!r}")
        if self.readout == "dynamics":
            if self.transitions:
                raise ValueError("readout 'dynamics' fits the window's observed state changes on GN_p's outputs, so "
                                 "GN_p must not read those changes: transitions=True is refused with it")
            if self.window < 2:
                raise ValueError(f"readout 'dynamics' fits state changes between steps: window must be at least 2, "
                                 f"got {self.window}")
        if self.readout == "ridge":
            small = [k for k in KINDS if 0 < self.identifier.out(k) <= self.ridge_features]
            if small:
                raise ValueError(f"readout 'ridge' splits GN_p's outputs into {self.ridge_features} features and "
                                 f"the targets; identifier.out_{small[0]} = {self.identifier.out(small[0])} "
                                 f"leaves no target")

    def gid_size(self, kind: str) -> int:
        """G_ID's width per node, edge or global."""
        w = self.identifier.out(kind)
        if self.ridge_head:
            return w
        return self.fit_size(kind)

    def fit_size(self, kind: str) -> int:
        """The width of the fit's flattened coefficients per node, edge or global (the identifier's
        output width when the readout fits nothing)."""
        w = self.identifier.out(kind)
        if self.readout == "dynamics":
            return w * (FIT_TARGETS.stop - FIT_TARGETS.start)
        return (w - self.ridge_features) * self.ridge_features if self.readout == "ridge" and w > 0 else w

    @property
    def core(self) -> str:
        return "sysid"   # what a run's progress bar and logs call the model

    def to_dict(self) -> dict:
        return {"forward": self.forward.to_dict(), "identifier": self.identifier.to_dict(), "window": self.window,
                "transitions": self.transitions, **({"stateless": True} if self.stateless else {}),
                "readout": self.readout,
                **({"ridge_features": self.ridge_features, "ridge": self.ridge} if self.readout == "ridge" else {}),
                **({"ridge": self.ridge} if self.readout == "dynamics" else {}),
                **({"ridge_head": self.ridge_head} if self.ridge_head else {}),
                **({"local_params": True, "param_places": [[k, list(r)] for k, r in self.param_places or ()]}
                   if self.local_params else {}),
                **({"nominal_static": True, "nominal": None if self.nominal is None else self.nominal.to_dict()}
                   if self.nominal_static else {})}

    @classmethod
    def from_dict(cls, d: dict) -> "SysIDConfig":
        return cls(**check_keys(cls, d, "sysid config keys"))


def _ridge_solution(phi: torch.Tensor, psi: torch.Tensor, ridge: float) -> torch.Tensor:
    """Per row of the regressors ``phi`` [T, n, F] and targets ``psi`` [T, n, P] (T steps): the
    ridge solution B [F, P] of psi ~ B^T phi over the T steps, flattened to [n, F * P], in
    ``phi``'s dtype. Solved in float64, so that a small ``ridge`` stays exact: a Cholesky solve
    without error checks (no host synchronization, so it can be captured)."""
    dtype, phi, psi = phi.dtype, phi.double(), psi.double()
    features, T = phi.shape[-1], phi.shape[0]
    S = torch.einsum("tnf,tng->nfg", phi, phi) / T
    R = torch.einsum("tnf,tnp->nfp", phi, psi) / T
    eye = torch.eye(features, dtype=phi.dtype, device=phi.device)
    lam = ridge * S.diagonal(dim1=-2, dim2=-1).mean(-1)[:, None, None] + 1e-6
    L, _ = torch.linalg.cholesky_ex(S + lam * eye)
    y = torch.linalg.solve_triangular(L, R, upper=False)
    B = torch.linalg.solve_triangular(L.transpose(-1, -2), y, upper=True)
    return B.reshape(B.shape[0], -1).to(dtype)


def source_places(source) -> tuple:
    """``SysIDConfig.param_places`` of a parameterized Dataset or System: each parameter's node
    row, edge rows (its actuator's edges within a graph, the same in every instance) or none
    (a global), from the dataset's ``param_places`` metadata or ``gnwarp.sim.param_places``."""
    from gnwarp.sim.systems import System, param_places
    static = _source_static(source)
    if isinstance(source, System):
        names, places = list(source.params), [list(p) for p in param_places(source)]
    else:
        names, places = source.meta.get("param_names", []), source.meta.get("param_places")
        if names and places is None:
            raise ValueError(f"dataset {source.system!r} does not say where its parameters live (no param_places in "
                             f"its metadata: generated before them); regenerate it for local_params")
    if not names:
        raise ValueError(f"{_source_name(source)} has no instance parameters: "
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


class LatentColumnsNormalizer(Normalizer):
    """A ``Normalizer`` whose first ``skip`` columns (G_ID's latents) stay as they are (D.3)."""

    def __init__(self, size: int, skip: int, std_floor: float = 1e-4):
        super().__init__(size, std_floor)
        self.skip = int(skip)
        self.register_buffer("latent", torch.arange(self.size) < self.skip, persistent=False)

    def _masked(self, mean, std):
        m = self.latent.to(mean.device)
        return torch.where(m, torch.zeros_like(mean), mean), torch.where(m, torch.ones_like(std), std)

    def accumulate_stats(self, x, weight=None):
        return self._masked(*super().accumulate_stats(x, weight))

    def mean_std(self, dtype=None):
        return self._masked(*super().mean_std(dtype))



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


# the static edge features of an actuator's range (read from the bound source for clamping)
RANGE_COLUMNS = ("act_ctrllimited", "act_ctrlrange_0", "act_ctrlrange_1")


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


class SysIDModel(nn.Module):
    """GN_p (``identifier``, a ``RecurrentGNCore``) + a ``ForwardModel`` (``forward_model``) on G_ID.

    ``config``: ``SysIDConfig``; ``layout``: the data's ``FeatureLayout`` (only its control slots
    are read: GN_p and the forward model see no static feature of the data).

    Main methods (N graphs, W window steps, B bodies, U controls, T steps):
        ``bind(source)``: the Dataset or System whose graphs it reads.
        ``identify(window_body [N, W, B, 13], window_ctrl [N, W, U], instance [N]) -> G_ID``.
        ``rollout(initial_body [N, B, 13], ctrl [N, T, U], g_id, instance) -> [N, T+1, B, 13]``.
    """

    def __init__(self, config: SysIDConfig, layout: FeatureLayout):
        super().__init__()
        if layout.n_global_ctrl:
            raise ValueError("system identification needs every actuator on a joint edge")
        self.sysid = dataclasses.replace(config)
        c = config.identifier
        self.gid_sizes = {k: config.gid_size(k) for k in KINDS}
        K = int(layout.n_ctrl_slots)
        # what the model reads of the data: its dynamic graph only
        self.layout = FeatureLayout([], [], [], n_ctrl_slots=K)
        if config.local_params and config.param_places is None:
            raise ValueError("local_params needs param_places (where each parameter lives): build the model with "
                             "gnwarp.train.build_sysid_model from a parameterized dataset")
        # local_params: per node (edge) row of a graph, the parameter of each slot; buffers, so that they live on
        # the model's device (a captured step copies nothing from the host)
        tables = place_tables(config.param_places or ())
        for kind, t in tables.items():
            self.register_buffer(f"place_{kind}", t, persistent=False)
        slots = {k: t.shape[1] for k, t in tables.items()}
        if config.param_places and len(config.param_places) > self.gid_sizes["globals"]:
            raise ValueError(f"local_params places {len(config.param_places)} parameters from G_ID's first global "
                             f"columns, but G_ID has {self.gid_sizes['globals']} (widen identifier.out_globals; "
                             f"gnwarp train: --gid-globals)")
        if config.nominal_static and config.nominal is None:
            raise ValueError("nominal_static needs the nominal static graph (nominal): build the model with "
                             "gnwarp.train.build_sysid_model from a dataset")
        # nominal_static: the nominal graph's columns per kind (None: none), float64 buffers on the model's device
        for kind, t in (config.nominal.tensors() if config.nominal else {}).items():
            self.register_buffer(f"nominal_{kind}", t if t.shape[-1] else None, persistent=False)
        self.forward_model = ForwardModel(config.forward, gid_layout(self.gid_sizes, K, slots, config.nominal))
        fm, f = self.forward_model, config.forward.std_floor
        fm.norm_nodes = LatentColumnsNormalizer(fm.norm_nodes.size, self.gid_sizes["nodes"] + slots["nodes"], f)
        fm.norm_edges = LatentColumnsNormalizer(fm.norm_edges.size, self.gid_sizes["edges"] + slots["edges"], f)
        if fm.norm_globals is not None:
            fm.norm_globals = LatentColumnsNormalizer(fm.norm_globals.size, self.gid_sizes["globals"], f)
        sizes = {"nodes": DYN_NODE_SIZE * (2 if config.transitions else 1), "edges": K, "globals": 0}
        self.identifier = RecurrentGNCore(c, sizes, config.forward.run).to(config.forward.run.param_dtype)
        h = config.ridge_head   # the fit's coefficients -> G_ID (SysIDConfig.ridge_head)
        self.heads = nn.ModuleDict({k: MLP(config.fit_size(k), (h, h), self.gid_sizes[k], activation=F.silu)
                                    for k in KINDS if h and self.gid_sizes[k]}).to(config.forward.run.param_dtype)
        self.builder = None
        # the bound source's actuator ranges (``bind``): a builder of just those static columns
        self._range_layout = FeatureLayout([], [], list(RANGE_COLUMNS), n_ctrl_slots=K)
        self._range_builder = None

    # -- what the Trainer and users read --------------------------------------------------------
    @property
    def config(self) -> SysIDConfig:
        return dataclasses.replace(self.sysid, forward=self.forward_model.config)

    @property
    def window(self) -> int:
        return self.sysid.window

    @property
    def options(self) -> RunOptions:
        return self.forward_model.options

    @property
    def norm_nodes(self) -> Normalizer:
        return self.forward_model.norm_nodes

    @property
    def device(self) -> torch.device:
        return self.forward_model.device

    @property
    def dtype(self) -> torch.dtype:
        return self.forward_model.dtype

    def set_options(self, options: RunOptions | None = None, **changes) -> "SysIDModel":
        """Run both parts with ``options`` (or the current ones with ``changes``); returns self."""
        self.forward_model.set_options(options, **changes)
        self.identifier.set_options(self.options)
        self.identifier.to(self.options.param_dtype)
        self.heads.to(self.options.param_dtype)
        return self

    def graph_builder(self, source, strict: bool = True):
        """A ``GraphBuilder`` of ``source``'s dynamic graphs (no static columns), on the model's
        device and dtype. Data with more control slots per edge raises ``LayoutMismatchError``."""
        return graph_builder(self.layout, source, self.device, self.dtype, strict)

    def bind(self, source, strict: bool = True) -> "SysIDModel":
        """Read ``source``'s graphs (a Dataset or System) in ``identify`` and ``rollout``, and its
        actuators' control ranges (static edge features the model itself does not read) for
        clamping controls."""
        if self.sysid.local_params and source_places(source) != self.sysid.param_places:
            raise ValueError(f"this model places its parameters as {self.sysid.param_places!r:.120}, and "
                             f"{_source_name(source)} holds them elsewhere (another system, or other parameters)")
        nom = self.sysid.nominal
        if nom is not None:
            want = (len(nom.nodes), nom.senders, nom.receivers)
            other = [t for t in instance_topologies(_source_static(source)) if t != want]
            if other:
                raise ValueError(f"this model reads a nominal static graph of {want[0]} bodies and "
                                 f"{len(nom.senders)} edges; {_source_name(source)} has instances of another "
                                 f"topology ({other[0][0]} bodies, {len(other[0][1])} edges, or other joints)")
        self.builder = self.graph_builder(source, strict)
        try:
            self._range_builder = graph_builder(self._range_layout, source, self.device, self.dtype, strict)
        except ValueError:   # data without actuator ranges (LayoutMismatchError is one): nothing to clamp to
            self._range_builder = None
        return self

    def rollout_inputs(self, instance, n_ctrl: int, ctrl_policy: str = "clamp", check: bool = True) -> RolloutInputs:
        """Input checks and control clamping of rollouts of the bound source's ``instance`` [N]:
        the actuators' ranges come from the source's static edge features (``ctrl_policy`` as
        ``ForwardModel.rollout``'s; no ranges in the source: nothing is clamped)."""
        if self.builder is None:
            raise ValueError("no graphs to read: call model.bind(dataset_or_system) first")
        rb = self._range_builder
        if rb is None:
            return RolloutInputs(GraphTemplate(self.builder, torch.as_tensor(instance)), None, n_ctrl, ctrl_policy,
                                 check)
        return RolloutInputs(GraphTemplate(rb, torch.as_tensor(instance)), self._range_layout, n_ctrl, ctrl_policy,
                             check)

    # -- Algorithm D.2 ------------------------------------------------------------------------
    def with_gid(self, graph: GraphsTuple, g_id: GraphsTuple) -> GraphsTuple:
        """The forward model's input graph: G_ID's columns (``gid_columns``) concatenated with a
        dynamic graph."""
        return self.with_columns(graph, self.gid_columns(graph, g_id))

    @staticmethod
    def with_columns(graph: GraphsTuple, columns: dict) -> GraphsTuple:
        """``graph`` with ``columns`` (``gid_columns``' of its topology) before its own features."""
        def cat(k):
            x, z = getattr(graph, k), columns[k]
            return x if z is None else torch.cat([z.to(x.dtype), x], -1)
        return graph._replace(**{k: cat(k) for k in KINDS})

    def gid_columns(self, graph: GraphsTuple, g_id: GraphsTuple) -> dict:
        """The static columns the forward model reads per kind (None: none) on ``graph``'s
        topology: G_ID's latents; with ``local_params`` the parameters in G_ID's first global
        columns also at the nodes and edges they describe (``SysIDConfig.param_places``; 0 in
        slots no parameter fills); with ``nominal_static`` the nominal static graph's columns.
        A rollout computes them once and reuses them every step. Device gathers only: no host
        synchronization."""
        gl, dev = g_id.globals, graph.nodes.device
        dt = next((x.dtype for x in (g_id.nodes, g_id.edges, gl) if x is not None), graph.nodes.dtype)
        out = {k: [] if getattr(g_id, k) is None else [getattr(g_id, k)] for k in KINDS}
        for kind, count in (("nodes", graph.n_node), ("edges", graph.n_edge)):
            table, nominal = getattr(self, f"place_{kind}"), getattr(self, f"nominal_{kind}", None)
            if table.shape[1] == 0 and nominal is None:
                continue
            rows, count = getattr(graph, kind).shape[0], count.to(dev)
            of_graph = torch.repeat_interleave(torch.arange(count.shape[0], device=dev), count, output_size=rows)
            local = (torch.arange(rows, device=dev) - (torch.cumsum(count, 0) - count)[of_graph])   # row in its graph
            if table.shape[1]:
                which = table[local.clamp(max=table.shape[0] - 1)]     # [rows, slots] parameter index or -1
                vals = gl[of_graph[:, None], which.clamp(min=0)]
                out[kind].append(torch.where(which >= 0, vals, torch.zeros_like(vals)).to(dt))
            if nominal is not None:   # bind checked that every graph has the nominal's rows
                out[kind].append(nominal[local].to(dt))
        nominal = getattr(self, "nominal_globals", None)
        if nominal is not None:
            out["globals"].append(nominal.to(dt).expand(graph.n_node.shape[0], -1))
        return {k: None if not v else v[0] if len(v) == 1 else torch.cat(v, -1) for k, v in out.items()}

    def identify_graphs(self, window, steps: int, stats: dict | None = None) -> GraphsTuple:
        """G_ID from ``steps`` dynamic graphs of one topology: ``window`` a ``StackedWindow`` (the
        steps built as one batch), a list, or a callable t -> graph. They are normalized with the
        forward model's input statistics (``stats``: as ``ForwardModel.stats``; default its
        current ones) and re-centred as it re-centres (D.4), all steps at once; with
        ``config.transitions``, the ``steps - 1`` transitions between them; with
        ``config.readout`` "mean", the mean of GN_p's output graphs over the steps, "ridge" or
        "dynamics" their fits (through ``config.ridge_head``'s MLP where it has one;
        ``SysIDConfig``). No host synchronization once the topology's index exists."""
        fm, c = self.forward_model, self.sysid
        if not isinstance(window, StackedWindow):
            get = window if callable(window) else window.__getitem__
            window = StackedWindow.of([get(t) for t in range(steps)])
        g0, W = window[0], window.steps
        ctx = fm.context(g0, stats=False)      # the topology's index, shared with the forward model
        stats = stats if stats is not None else fm.stats(g0.nodes.dtype)
        (mn, sn), (me, se) = stats["nodes"], stats["edges"]
        K = g0.edges.shape[-1]
        transitions, readout = c.transitions, c.readout
        if (transitions or readout == "dynamics") and W < 2:
            raise ValueError("identifying from transitions or state changes needs a window of at least 2 steps")
        n = W - 1 if transitions or readout == "dynamics" else W      # GN_p's steps
        x = window.graph.nodes.reshape(W, -1, DYN_NODE_SIZE)          # [W, rows, 13]: every step at once
        dyn, _ = fm._recenter(x[:n], ctx)
        nodes = (dyn - mn[-DYN_NODE_SIZE:]) / sn[-DYN_NODE_SIZE:]
        psi = None
        if n < W:   # the change to the next step, normalized as the targets
            md, sd = stats["delta"]
            delta = (state_delta(x[:-1], x[1:]) - md) / sd
            if transitions:
                nodes = torch.cat([nodes, delta], -1)
            else:   # "dynamics": its targets; bodies that cannot move have no dynamics to fit
                psi = self._observed_targets(delta[..., FIT_TARGETS] * ctx.movable.to(delta.dtype)[:, None], g0, ctx)
        inputs = window.head(n)
        inputs = inputs._replace(nodes=nodes.reshape(-1, nodes.shape[-1]),
                                 edges=(inputs.edges - me[me.shape[0] - K:]) / se[se.shape[0] - K:])
        warp = self.options.impl == "warp" and ctx.index is not None
        if c.stateless:   # every step at once: the window's n graphs as one batch
            index = graph_index(inputs, self.options.deterministic, validate=False) if warp else None  # ctx validated
            out, last = self.identifier.first_steps(inputs, index), g0   # g0: the topology of G_ID
            per_step = {k: None if v is None else v.reshape(n, v.shape[0] // n, v.shape[-1])
                        for k, v in ((k, getattr(out, k)) for k in KINDS)}
        else:
            step = StackedWindow(inputs, n, window.topology)
            outs, _ = self.identifier.sequence(step.__getitem__, steps=n, index=ctx.index if warp else None,
                                               last_only=readout == "last")
            if readout == "last":
                return outs[-1]
            last = outs[-1]
            per_step = {k: None if getattr(last, k) is None else torch.stack([getattr(o, k) for o in outs])
                        for k in KINDS}

        def pool(k, x):   # x [T, rows, width]: GN_p's outputs of kind k over the steps
            if readout == "mean":
                return x.mean(0)
            if readout == "ridge":   # regressors and targets both GN_p's
                b = _ridge_solution(x[..., :c.ridge_features], x[..., c.ridge_features:], c.ridge)
            else:    # "dynamics": observed targets
                b = _ridge_solution(x, psi[k].to(x.dtype), c.ridge)
            return self.heads[k](b.to(self.options.param_dtype)).to(b.dtype) if k in self.heads else b
        return last._replace(**{k: None if per_step[k] is None else pool(k, per_step[k]) for k in KINDS})

    @staticmethod
    def _observed_targets(node: torch.Tensor, graph: GraphsTuple, ctx) -> dict[str, torch.Tensor]:
        """The "dynamics" readout's targets [T, rows, 6] per kind from the nodes' [T, n, 6]: an
        edge's are its receiver's, a graph's the mean over its moving bodies."""
        w = ctx.movable.to(node.dtype)
        count = node.new_zeros(ctx.n_graph).index_add_(0, ctx.node_graph, w).clamp_min(1.0)
        glob = node.new_zeros(node.shape[0], ctx.n_graph, node.shape[2]).index_add_(1, ctx.node_graph, node)
        return {"nodes": node, "edges": node[:, graph.receivers.long()], "globals": glob / count[:, None]}

    def _template(self, instance, N: int) -> tuple[GraphTemplate, int]:
        if self.builder is None:
            raise ValueError("no graphs to read: call model.bind(dataset_or_system) first")
        n_inst, n_ctrl = source_info(self.builder)
        instance = torch.zeros(N, dtype=torch.int64) if instance is None else check_instance(instance, n_inst, N)
        return GraphTemplate(self.builder, instance), n_ctrl

    def identify(self, window_body, window_ctrl, instance=None, check: bool = True,
                 capture: bool | None = None) -> GraphsTuple:
        """G_ID (a GraphsTuple: nodes [n, G], edges [e, G], globals [N, G] and the topology) of N
        system instances from an identification window: ``window_body`` [N, W, B, 13] (body
        states) and ``window_ctrl`` [N, W, U] (the controls applied at those steps); a longer
        window is cut to its last W = ``config.window`` steps. ``instance`` [N]: the bound
        source's instances (their topology; default 0). Raises ``RolloutInputError`` for a
        shorter window, shapes of another system's graph layout, and (``check``) NaN or Inf.

        ``capture`` (default: on for a CUDA model while gradients are off): GN_p's loop over the
        window replays one CUDA graph, captured on the first call of each shape, instances and
        dtype and re-captured when the weights' storage moves (weights updated in place are read
        at each replay); the window is copied in and G_ID copied out. A captured G_ID carries no
        gradient: differentiate through ``capture=False``."""
        body, ctrl = float_tensor(window_body, "window_body"), float_tensor(window_ctrl, "window_ctrl")
        W = self.window
        if body.ndim != 4 or ctrl.ndim != 3:
            raise RolloutInputError(f"window_body must be [N, W, B, {DYN_NODE_SIZE}] and window_ctrl [N, W, U], got "
                                    f"shapes {tuple(body.shape)} and {tuple(ctrl.shape)}")
        if body.shape[1] < W or ctrl.shape[1] < W:
            raise RolloutInputError(f"the identification window has {min(body.shape[1], ctrl.shape[1])} steps; this "
                                    f"model identifies systems from {W} (window_body [N, {W}, B, 13], window_ctrl "
                                    f"[N, {W}, U])")
        N = body.shape[0]
        tmpl, n_ctrl = self._template(instance, N)
        if tuple(body.shape[2:]) != (tmpl.B, DYN_NODE_SIZE) or ctrl.shape[0] != N or ctrl.shape[2] != n_ctrl:
            raise RolloutInputError(
                f"the window's graphs do not fit the bound system's graph layout: window_body {tuple(body.shape)} "
                f"and window_ctrl {tuple(ctrl.shape)}, expected [N, W, {tmpl.B}, {DYN_NODE_SIZE}] and [{N}, W, "
                f"{n_ctrl}] ({tmpl.B} bodies, {n_ctrl} controls): a window from a system with another graph layout")
        dev, dt = tmpl.static_nodes.device, tmpl.dtype
        body, ctrl = body[:, -W:].to(dev, dt), ctrl[:, -W:].to(dev, dt)
        if check:
            for name, x in (("window_body", body), ("window_ctrl", ctrl)):
                bad = ~torch.isfinite(x)
                if bool(bad.any()):
                    raise RolloutInputError(f"{name} contains NaN or Inf (first at {name}"
                                            f"{[int(i) for i in bad.nonzero()[0]]} of its last {W} steps)")
        if capture is None:
            capture = body.is_cuda and not torch.is_grad_enabled()
        if capture:
            if not body.is_cuda:
                raise ValueError("capture=True needs a model on a CUDA device")
            with torch.no_grad():
                return self._captured_identify(tmpl, body, ctrl)
        return self.identify_graphs(self._window(tmpl, {}, body, ctrl), W)

    def _window(self, tmpl: GraphTemplate, made: dict, body: torch.Tensor, ctrl: torch.Tensor) -> StackedWindow:
        """The ``StackedWindow`` of ``body`` [N, W, B, 13] and ``ctrl`` [N, W, U] on one step's
        template (``tmpl``) and one of all W steps, kept in ``made`` (made on the first call:
        outside any capture, as a template syncs with the host)."""
        W = body.shape[1]
        if W not in made:
            made[W] = GraphTemplate(self.builder, tmpl.instance.repeat(W))
        b, c = body.transpose(0, 1).reshape(-1, *body.shape[2:]), ctrl.transpose(0, 1).reshape(-1, ctrl.shape[-1])
        return StackedWindow(made[W].graph(b, c), W, tmpl.topology)

    def _captured_identify(self, tmpl: GraphTemplate, body: torch.Tensor, ctrl: torch.Tensor) -> GraphsTuple:
        from gnwarp.interop import replay_cached
        storage = tuple(t.data_ptr() for t in (*self.parameters(), *self.buffers()) if t is not None)
        key = (tmpl.instance.cpu().numpy().tobytes(), tuple(body.shape), tuple(ctrl.shape), body.dtype, ctrl.dtype,
               body.device, id(self.builder), self.options, self.sysid.readout, self.sysid.transitions, storage)
        W = body.shape[1]

        made = {}

        def run(b, c):   # the templates of the first call with these instances (its warm-up), kept by the graph
            return self.identify_graphs(self._window(tmpl, made, b, c), W)
        result = replay_cached(_IDENTIFY_GRAPHS.setdefault(self, {}), key, (body, ctrl), run, keep=self.builder)
        return result._replace(**{k: None if getattr(result, k) is None else getattr(result, k).clone() for k in KINDS})

    def rollout(self, initial_body, ctrl, g_id: GraphsTuple, instance=None, check: bool = True,
                ctrl_policy: str = "clamp") -> torch.Tensor:
        """Roll the forward model out from ``initial_body`` [N, B, 13] under ``ctrl`` [N, T, U]
        with G_ID reused at every step (D.6.2) -> states [N, T+1, B, 13]. ``g_id``: from
        ``identify`` (or ``load_gid``) on the same N graphs' topology; ``instance`` as there.
        ``ctrl_policy`` as ``ForwardModel.rollout``'s: "clamp" (default) clamps controls to the
        bound source's actuator ranges, "error" refuses controls outside them, "none" uses them
        as given. Differentiable (plain autograd) in ``initial_body``, ``ctrl``, G_ID and the
        weights."""
        initial_body = float_tensor(initial_body, "initial_body")
        if initial_body.ndim != 3:
            raise RolloutInputError(f"initial_body must be [N, B, 13], got shape {tuple(initial_body.shape)}")
        tmpl, n_ctrl = self._template(instance, initial_body.shape[0])
        inputs = self.rollout_inputs(tmpl.instance, n_ctrl, ctrl_policy, check)
        body, ctrl = inputs.shapes(initial_body, ctrl)
        dev, dt = tmpl.static_nodes.device, tmpl.dtype
        body = body.to(dev, dt)
        ctrl = inputs.values(body, ctrl.to(dev, dt))
        self.check_gid(g_id, tmpl.topology)
        g_id = g_id._replace(**{k: None if getattr(g_id, k) is None else getattr(g_id, k).to(dev, dt) for k in KINDS})
        fm = self.forward_model
        first = tmpl.graph(body, ctrl[:, 0])
        columns = self.gid_columns(first, g_id)      # the same every step: G_ID and the topology are fixed
        ctx = fm.context(self.with_columns(first, columns))
        out = [body]
        for t in range(ctrl.shape[1]):
            body = tmpl.to_body(fm.next_nodes(self.with_columns(tmpl.graph(body, ctrl[:, t]), columns), ctx), body)
            out.append(body)
        return torch.stack(out, 1)

    def with_fixed_gid(self, g_id: GraphsTuple) -> "FixedGIDModel":
        """This model with ``g_id`` as every rollout's static graph, behind the interface of a
        ``ForwardModel`` that ``RolloutEngine`` and the planners read (``gnwarp.control``): plan
        through an identified system (Figure 10's system-ID variant)."""
        return FixedGIDModel(self, g_id)

    def check_gid(self, g_id: GraphsTuple, topology: GraphsTuple) -> None:
        """``GIDError`` unless ``g_id`` has this model's widths and ``topology``'s graphs."""
        if not isinstance(g_id, GraphsTuple):
            raise GIDError(f"g_id must be a GraphsTuple (from identify or load_gid), got {type(g_id).__name__}")
        for k in KINDS:
            x, want = getattr(g_id, k), self.gid_sizes[k]
            if (0 if x is None else x.shape[-1]) != want:
                raise GIDError(f"G_ID's {k} have width {0 if x is None else x.shape[-1]}, this model's {want}")
        same = (g_id.n_node.shape == topology.n_node.shape and g_id.senders.shape == topology.senders.shape
                and all(bool(torch.equal(getattr(g_id, a).cpu(), getattr(topology, a).cpu()))
                        for a in ("n_node", "n_edge", "senders", "receivers")))
        if not same:
            raise GIDError(f"G_ID was identified on graphs of another layout ({g_id.n_node.shape[0]} graphs, nodes "
                           f"{g_id.n_node.tolist()[:4]}, {g_id.senders.shape[0]} edges) than the rollout's "
                           f"({topology.n_node.shape[0]} graphs, nodes {topology.n_node.tolist()[:4]}, "
                           f"{topology.senders.shape[0]} edges)")


# captured identifications per model (``SysIDModel.identify``), dropped with the model
_IDENTIFY_GRAPHS: "weakref.WeakKeyDictionary[SysIDModel, dict]" = weakref.WeakKeyDictionary()
