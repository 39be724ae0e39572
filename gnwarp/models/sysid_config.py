"""The configuration of a system-identification model: ``SysIDConfig`` (GN_p's sizes, the
window, the readout and the options beyond the paper) and what validates it."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Literal

from gnwarp.models.config import ModelConfig
from gnwarp.models.recurrent import KINDS, RecurrentGNConfig
from gnwarp.models.sysid_graphs import NominalGraph
from gnwarp.state import ANGVEL, LINVEL
from gnwarp.validation import (MAX_WIDTH, ConfigError, Count, Flag, IntRange, PositiveFloat, PositiveInt, check_fields,
                               check_keys, described)

__all__ = ["SysIDConfig", "FITS", "FIT_TARGETS"]


# the readouts that fit a linear model over the window (``SysIDConfig.readout``)
FITS = ("ridge", "dynamics")
# the "dynamics" readout's targets: the velocity columns of ``state_delta`` (6)
FIT_TARGETS = slice(LINVEL.start, ANGVEL.stop)


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
    hold the parameters themselves (what ``SysIDTrainConfig.param_loss`` asks of it). The head
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
    parameters ``SysIDTrainConfig.param_loss`` supervises) are also handed to the forward model
    where each parameter lives, as a true static graph holds it: a body's length or mass as a
    column of its node, an actuator's gear as a column of its joint's edges (``param_places``,
    one ``(kind, rows)`` per parameter: ("nodes", (body,)), ("edges", (edge, ...)) with edge
    rows within a graph, ("globals", ()); filled from the training data's
    ``gnwarp.sim.param_places`` by ``gnwarp.models.build_sysid_model``). The forward model then reads the
    mass of a JACO link on that link's node rather than picking it out of 18 globals.

    ``nominal_static`` (beyond the paper; default off): the forward model also reads the training
    data's static graph with each element at its mean over the train split's instances
    (``nominal``, a ``NominalGraph`` filled by ``gnwarp.models.build_sysid_model``): the system as designed, its
    bodies' geometry and its joints' ranges, the same for every instance, so that it carries no
    parameter while G_ID says only how an instance differs from it. The paper's G_ID replaces the
    whole static graph, so the forward model must also learn from GN_p what is fixed (which JACO
    link is which). Needs every instance of one topology; binding a source of another is refused."""
    forward: ModelConfig = field(default_factory=ModelConfig)
    identifier: RecurrentGNConfig = field(default_factory=_identifier_default)
    window: PositiveInt = 20
    transitions: bool = described(False, "GN_p reads the window's transitions (states, controls and the change "
                                         "to the next state) instead of its states (beyond the paper)")
    stateless: Flag = described(False, "GN_p carries no state between the window's steps: it reads each step on its "
                                       "own and runs them all as one batch (needs readout mean, ridge or dynamics; "
                                       "beyond the paper)")
    readout: Literal["last", "mean", "ridge", "dynamics"] = described(
        "last", "G_ID is GN_p's last output (the paper's), the mean of its outputs over the window, a ridge fit over "
                "the window of some output columns on the others, or a ridge fit of the window's observed velocity "
                "changes on the outputs (beyond the paper)")
    ridge_features: PositiveInt = described(4, "with readout ridge: regressors per fit, the rest of GN_p's outputs "
                                               "being its targets")
    ridge: PositiveFloat = described(1e-3, "with readout ridge or dynamics: the fit's ridge weight, relative to the "
                                           "mean diagonal of its regressors' second moments")
    ridge_head: IntRange(0, MAX_WIDTH) = described(0, "with readout ridge or dynamics: the width of an MLP that maps "
                                                      "the fit's coefficients to G_ID (0: none, G_ID is the "
                                                      "coefficients; beyond the paper)")
    local_params: Flag = described(False, "with param_loss: the forward model also reads each supervised parameter "
                                          "on the node or edges it describes (a link's mass on its node, a gear on "
                                          "its joint's edges), as a true static graph holds it (beyond the paper)")
    param_places: tuple[tuple[Literal["nodes", "edges", "globals"], tuple[Count, ...]], ...] | None = None
    nominal_static: Flag = described(False, "the forward model also reads the training data's static graph at its "
                                            "mean over the instances (the system as designed; G_ID says how an "
                                            "instance differs; beyond the paper)")
    nominal: NominalGraph | None = None

    def __post_init__(self):
        check_fields(self)
        if self.nominal is not None and not self.nominal_static:
            raise ConfigError("nominal", "nominal is the static graph nominal_static reads: set nominal_static=True")
        if self.param_places is not None:
            if not self.local_params:
                raise ConfigError("param_places", "param_places places the parameters for local_params: set "
                                                  "local_params=True")
            for i, (kind, rows) in enumerate(self.param_places):
                if (kind == "globals") != (len(rows) == 0) or (kind == "nodes" and len(rows) != 1):
                    raise ConfigError("param_places", f"param_places[{i}] = {(kind, rows)}: a node parameter has one "
                                                      "row, an edge parameter one or more, a global one none")
        default = {f.name: f.default for f in dataclasses.fields(self)}
        if self.readout != "ridge" and self.ridge_features != default["ridge_features"]:
            raise ConfigError("ridge_features", f"ridge_features splits GN_p's outputs for readout 'ridge'; readout "
                                                f"{self.readout!r} does not read it")
        if self.readout not in FITS and self.ridge != default["ridge"]:
            raise ConfigError("ridge", f"ridge weights the fit of readout 'ridge' or 'dynamics'; readout "
                                       f"{self.readout!r} fits nothing")
        if self.stateless and self.readout == "last":
            raise ConfigError("stateless", "stateless reads each step of the window on its own, so G_ID must pool the "
                                           "steps: it needs readout 'mean', 'ridge' or 'dynamics', got 'last'")
        if self.ridge_head and self.readout not in FITS:
            raise ConfigError("ridge_head", f"ridge_head maps a fit's coefficients to G_ID: it needs readout 'ridge' "
                                            f"or 'dynamics', got {self.readout!r}")
        if self.readout == "dynamics":
            if self.transitions:
                raise ConfigError("transitions", "readout 'dynamics' fits the window's observed state changes on "
                                                 "GN_p's outputs, so GN_p must not read those changes: "
                                                 "transitions=True is refused with it")
            if self.window < 2:
                raise ConfigError("window", f"readout 'dynamics' fits state changes between steps: window must be at "
                                            f"least 2, got {self.window}")
        if self.readout == "ridge":
            small = [k for k in KINDS if 0 < self.identifier.out(k) <= self.ridge_features]
            if small:
                raise ConfigError("ridge_features", f"readout 'ridge' splits GN_p's outputs into "
                                                    f"{self.ridge_features} features and the targets; "
                                                    f"identifier.out_{small[0]} = {self.identifier.out(small[0])} "
                                                    "leaves no target")

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
