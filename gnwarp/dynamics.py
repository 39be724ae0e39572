"""The dynamics that control and learning plan through, as two protocols every layer can name.

``Dynamics``: a learned one-step model of body states on graphs, what ``RolloutEngine``
(``gnwarp.models.rollout``) and ``GradientMPC`` (``gnwarp.control.gradient``) roll out and
differentiate: ``ForwardModel``, ``MLPForwardModel`` and ``FixedGIDModel`` implement it. Shapes:
N sequences, B bodies, T steps, U controls, n = sum of the graphs' nodes.

``RolloutDynamics``: what a sampling planner (``gnwarp.control.sampling``) rolls its candidates
through, ``rollout(obs, actions [M, T, U], samples) -> states [M, T+1, B, 13]``. The true
simulator (``EnvDynamics``, MuJoCo-Warp or MuJoCo C) and a learned model (``ModelDynamics``)
implement it, so any sampling planner runs on the true dynamics as an oracle beside the learned
model, through the same calls.

Both are ``runtime_checkable``: ``isinstance(model, Dynamics)`` checks that the members exist
(not their signatures).
"""
from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import torch

__all__ = ["Dynamics", "RolloutDynamics"]


@runtime_checkable
class Dynamics(Protocol):
    """A learned one-step model rolled out on graphs of a bound source (a Dataset or System).

    ``layout``: the ``FeatureLayout`` of its input graphs; ``builder``: the bound source's
    ``GraphBuilder`` (None before ``bind``); ``device`` / ``dtype``: where and in what it computes.
    """

    layout: Any
    builder: Any

    @property
    def device(self) -> torch.device: ...

    @property
    def dtype(self) -> torch.dtype: ...

    def bind(self, source, strict: bool = True) -> "Dynamics":
        """Read ``source``'s static graphs (a Dataset or System) in rollouts; returns self."""

    def template(self, instance, builder=None):
        """A ``GraphTemplate`` of system instances ``instance`` [N] of the bound source (or of
        ``builder``): maps body states [N, B, 13] and controls [N, U] to input graphs and back."""

    def context(self, graph, stats: bool = True):
        """Per-topology bookkeeping of a batch of input graphs, made once and reused every step."""

    def next_nodes(self, graph, ctx=None) -> torch.Tensor:
        """One step on a batch of input graphs: the next dynamic node states [n, 13]."""

    def rollout_inputs(self, template, n_ctrl: int | None, ctrl_policy: str = "clamp", check: bool = True,
                       builder=None):
        """The ``RolloutInputs`` (shape and value checks, control clamping) of rollouts over
        ``template``, made from ``builder`` (None: the bound source); ``n_ctrl``: the controls U."""

    def rollout_engine(self, instance, horizon: int, builder=None, ctrl_policy: str = "clamp", check: bool = True,
                       graphs: bool = True, store: bool | str = "auto", store_bytes: int | None = None,
                       fused: bool | None = None):
        """A ``RolloutEngine``: rollouts of ``horizon`` steps of instances ``instance`` [N],
        differentiable with respect to the initial states and the controls; ``fused``: whether
        its steps run fused (None: automatic; True raises where they cannot)."""


@runtime_checkable
class RolloutDynamics(Protocol):
    """What a sampling planner rolls its candidates through.

    ``rollout(obs, actions, samples)``: ``obs`` the N episodes' current true state (an
    ``Observation`` of qpos, qvel and body states, or body states [N, B, 13]); ``actions``
    [N * samples, T, U], episode n's candidates in rows n * samples ... (n + 1) * samples - 1;
    returns the states [N * samples, T+1, B, 13] from each episode's state (the first included).
    ``device``: where the returned states are.
    """

    device: torch.device

    def rollout(self, obs, actions: torch.Tensor, samples: int) -> torch.Tensor: ...
