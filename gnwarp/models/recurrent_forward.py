"""The recurrent one-step model of the paper (D.7.3) on proprioceptive observations, and its
feed-forward baseline.

Per step, for observation graph G_t (``gnwarp.data.proprio``: nodes [static, cos q, sin q, qdot],
edges [static, controls]) and hidden graph H_{t-1}::

    O_t, H_t = RecurrentGNCore(Norm_in(G_t), H_{t-1})      O_t.nodes: normalized (dq, dqdot) per body
    (dq, dqdot) = Norm_out^-1(O_t.nodes)
    next = (cos(q + dq), sin(q + dq), qdot + dqdot)          rotated, so (cos, sin) stays on the circle;
                                                             bodies without a joint (the world) kept

The feed-forward baseline is the same model with ``recurrent=False``: its hidden graph is reset
to zeros before every step, so it sees the current observation only, with the same weights'
shapes and the same normalization: the comparison isolates memory.

The teacher-forcing loss (D.7.3, ``RecurrentForwardModel.loss``): windows of 21 observations;
the first 20 are the inputs, in order, carrying the hidden graph along; the last 20 are the
targets; the loss is the mean squared error of the normalized changes over all steps and bodies
with a joint.
"""
from __future__ import annotations

import copy
import dataclasses
import weakref
from dataclasses import dataclass, field

import torch
import torch.nn as nn

from gnwarp.gn.options import RunOptions
from gnwarp.graphs import GraphsTuple
from gnwarp.models.normalizer import Normalizer, normalize_graph
from gnwarp.models.recurrent import RecurrentGNConfig, RecurrentGNCore
from gnwarp.validation import ConfigError, check_keys

__all__ = ["RecurrentForwardConfig", "RecurrentForwardModel", "observation_delta", "apply_observation_delta"]

DELTA_SIZE = 2  # (dq, dqdot) per body


def observation_delta(obs: torch.Tensor, nxt: torch.Tensor) -> torch.Tensor:
    """The change [..., 2] = (angle change in (-pi, pi], velocity change) between observations
    [..., 3] = (cos q, sin q, qdot)."""
    c0, s0, c1, s1 = obs[..., 0], obs[..., 1], nxt[..., 0], nxt[..., 1]
    dq = torch.atan2(s1 * c0 - c1 * s0, c1 * c0 + s1 * s0)
    return torch.stack([dq, nxt[..., 2] - obs[..., 2]], -1)


def apply_observation_delta(obs: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """``obs`` [..., 3] advanced by ``delta`` [..., 2]: (cos, sin) rotated by dq, qdot + dqdot."""
    c, s = torch.cos(delta[..., 0]), torch.sin(delta[..., 0])
    return torch.stack([obs[..., 0] * c - obs[..., 1] * s, obs[..., 1] * c + obs[..., 0] * s,
                        obs[..., 2] + delta[..., 1]], -1)


@dataclass
class RecurrentForwardConfig:
    """``core``: the recurrent core's sizes (its output sizes are set by the model: 2 per node,
    none on edges and globals); ``recurrent``: False for the feed-forward baseline (hidden reset
    every step); ``run``: how the GN block runs; ``std_floor``: the normalizers' smallest std."""
    core: RecurrentGNConfig = field(default_factory=RecurrentGNConfig)
    recurrent: bool = True
    run: RunOptions = field(default_factory=RunOptions)
    std_floor: float = 1e-4

    def core_config(self) -> RecurrentGNConfig:
        return dataclasses.replace(self.core, out_nodes=DELTA_SIZE, out_edges=0, out_globals=0)

    def to_dict(self) -> dict:
        """As a checkpoint's config.json keeps it (``from_dict`` reads it back)."""
        return {"core": self.core.to_dict(), "recurrent": self.recurrent, "run": self.run.to_dict(),
                "std_floor": self.std_floor}

    @classmethod
    def from_dict(cls, d: dict) -> "RecurrentForwardConfig":
        """A config from ``to_dict``'s dict; unknown keys raise ``ConfigError``."""
        d = dict(check_keys(cls, d))
        if "core" in d:
            d["core"] = RecurrentGNConfig.from_dict(d["core"])
        if "run" in d:
            d["run"] = RunOptions.from_dict(d["run"])
        if not isinstance(d.get("recurrent", True), bool):
            raise ConfigError("recurrent", f"must be true or false, got {d['recurrent']!r}")
        if "std_floor" in d and not (isinstance(d["std_floor"], (int, float)) and not isinstance(d["std_floor"], bool)
                                     and d["std_floor"] > 0):
            raise ConfigError("std_floor", f"must be a number > 0, got {d['std_floor']!r}")
        return cls(**d)


class RecurrentForwardModel(nn.Module):
    """Recurrent (or, with ``config.recurrent=False``, feed-forward) one-step model of observation
    graphs (see the module docstring).

    ``sizes``: input widths {"nodes", "edges", "globals"} (``ProprioData.sizes``: the last 3 node
    columns are the observation). ``graphs``: a callable (instance [N], obs [N, B, 3],
    ctrl [N, U]) -> GraphsTuple (``ProprioData.graphs``). ``movable`` [B] bool: bodies with a joint,
    whose observations change (``ProprioData.movable``; default all but body 0, the world).
    Shapes: N sequences, B bodies, U controls.
    """

    def __init__(self, config: RecurrentForwardConfig, sizes: dict[str, int], graphs,
                 movable: torch.Tensor | None = None):
        super().__init__()
        self.config = copy.deepcopy(config)
        self.sizes = dict(sizes)
        self.graphs = graphs
        f = config.std_floor
        self.norm_nodes = Normalizer(sizes["nodes"], f)
        self.norm_edges = Normalizer(sizes["edges"], f)
        self.norm_globals = Normalizer(sizes["globals"], f) if sizes["globals"] else None
        self.norm_delta = Normalizer(DELTA_SIZE, f)
        self.core = RecurrentGNCore(config.core_config(), sizes, config.run)
        # a buffer (not saved): it follows the model to its device, so no step copies it there
        self.register_buffer("movable", None if movable is None else torch.as_tensor(movable, dtype=torch.bool),
                             persistent=False)

    @property
    def recurrent(self) -> bool:
        return self.config.recurrent

    # -- one step ---------------------------------------------------------------------------------
    def stats(self, dtype: torch.dtype) -> dict:
        out = {"nodes": self.norm_nodes.mean_std(dtype), "edges": self.norm_edges.mean_std(dtype),
               "delta": self.norm_delta.mean_std(dtype)}
        if self.norm_globals is not None:
            out["globals"] = self.norm_globals.mean_std(dtype)
        return out


    def initial_hidden(self, graph: GraphsTuple) -> GraphsTuple:
        return self.core.initial_hidden(graph)

    def step_delta(self, graph: GraphsTuple, hidden: GraphsTuple, stats: dict, index=None
                   ) -> tuple[torch.Tensor, GraphsTuple]:
        """Normalized predicted changes [sum(n_node), 2] of one input graph, and the next hidden
        graph (the feed-forward model ignores ``hidden`` and returns zeros)."""
        if not self.recurrent:
            hidden = self.core.initial_hidden(graph)
        out, hidden = self.core.step(normalize_graph(graph, stats), hidden, index)
        return out.nodes, hidden

    def step(self, instance: torch.Tensor, obs: torch.Tensor, ctrl: torch.Tensor, hidden: GraphsTuple | None,
             stats: dict | None = None, index=None) -> tuple[torch.Tensor, GraphsTuple]:
        """One step: ``obs`` [N, B, 3], ``ctrl`` [N, U], ``hidden`` (None: zeros) -> (next
        observation [N, B, 3], next hidden graph). Bodies without a joint keep their observation."""
        graph = self.graphs(instance, obs, ctrl)
        stats = stats if stats is not None else self.stats(graph.nodes.dtype)
        hidden = self.initial_hidden(graph) if hidden is None else hidden
        delta_n, hidden = self.step_delta(graph, hidden, stats, index)
        m, s = stats["delta"]
        nxt = apply_observation_delta(obs, (delta_n * s + m).reshape(*obs.shape[:2], DELTA_SIZE))
        return torch.where(self._movable(obs)[:, None], nxt, obs), hidden

    def _movable(self, obs: torch.Tensor) -> torch.Tensor:
        """[B] bool of observations [N, (T,) B, 3]: bodies with a joint."""
        if self.movable is not None:
            return self.movable.to(obs.device)
        movable = torch.ones(obs.shape[-2], dtype=torch.bool, device=obs.device)
        movable[0] = False
        return movable

    # -- training (D.7.3) -------------------------------------------------------------------------
    def loss(self, instance: torch.Tensor, obs: torch.Tensor, ctrl: torch.Tensor, accumulate: bool = False
             ) -> torch.Tensor:
        """Teacher-forcing loss of windows ``obs`` [N, T+1, B, 3] (T+1 = 21 in the paper) under
        ``ctrl`` [N, T, U]: inputs obs[:, :T] in order with the hidden graph carried along, targets
        obs[:, 1:]; mean squared error of the normalized (dq, dqdot) over steps and movable bodies.
        ``accumulate``: update the normalizers from this batch first."""
        N, T1, B, _ = obs.shape
        T = T1 - 1
        if ctrl.shape[:2] != (N, T):
            raise ValueError(f"ctrl must be [N, T, U] = [{N}, {T}, U] for obs of {T1} steps, got {tuple(ctrl.shape)}")
        graphs = [self.graphs(instance, obs[:, t], ctrl[:, t]) for t in range(T)]
        if graphs and graphs[0].nodes.device != obs.device:
            raise ValueError(f"the model's graphs are built on {graphs[0].nodes.device}, its observations are on "
                             f"{obs.device}: make the ProprioData (whose graphs the model reads) with device="
                             f"'{obs.device}'")
        delta = observation_delta(obs[:, :-1], obs[:, 1:])                       # [N, T, B, 2]
        w = self._movable(obs).to(obs.dtype).repeat(N)                           # [N*B], rows of a graph batch
        if accumulate:
            for g in graphs:
                self.norm_nodes.accumulate(g.nodes)
                self.norm_edges.accumulate(g.edges)
                if self.norm_globals is not None:
                    self.norm_globals.accumulate(g.globals)
            self.norm_delta.accumulate(delta.reshape(-1, DELTA_SIZE), w.repeat(T))  # w depends on the body only
        stats = self.stats(obs.dtype)
        m, s = stats["delta"]
        index = self.core.graph_index(graphs[0])
        hidden = self.initial_hidden(graphs[0])
        total = obs.new_zeros(())
        for t, g in enumerate(graphs):
            pred, hidden = self.step_delta(g, hidden, stats, index)
            target = ((delta[:, t] - m) / s).reshape(-1, DELTA_SIZE)
            total = total + ((pred - target).square().sum(-1) * w).sum()
        return total / (w.sum() * T * DELTA_SIZE)

    # -- rollouts ---------------------------------------------------------------------------------
    def rollout(self, instance: torch.Tensor, obs: torch.Tensor, ctrl: torch.Tensor, warmup: int = 20,
                capture: bool | None = None) -> torch.Tensor:
        """Warm up on true observations, then feed back predictions.

        ``obs`` [N, >= warmup+1, B, 3]: true observations (only the first warmup+1 are read);
        ``ctrl`` [N, T, U] with T > warmup. Inputs at steps t = 0..warmup are the true obs[:, t]
        (teacher forcing: the hidden graph takes them in), later inputs the model's previous
        prediction. Returns [N, T+1, B, 3]: obs[:, :warmup+1] and then the predictions of steps
        warmup+1..T (the free rollout, horizon h at index warmup+h).

        ``capture`` (default: on for CUDA tensors while gradients are off): the whole loop replays
        one CUDA graph, captured on the first call of each shape (N, warmup, T, U) and dtype and
        re-captured when the weights' storage moves (weights updated in place are read at each
        replay); the inputs are copied in and the result copied out."""
        N, T = ctrl.shape[:2]
        if not (0 <= warmup < T and obs.shape[1] >= warmup + 1):
            raise ValueError(f"rollout needs 0 <= warmup < T and warmup+1 true observations; got warmup {warmup}, "
                             f"T {T}, {obs.shape[1]} observations")
        instance = instance.to(obs.device)
        cuda = obs.is_cuda
        if capture is None:
            capture = cuda and not torch.is_grad_enabled()
        if capture:
            if not cuda:
                raise ValueError("capture=True needs CUDA observations")
            with torch.no_grad():
                return self._captured_rollout(instance, obs[:, :warmup + 1], ctrl, warmup)
        return self._rollout(instance, obs, ctrl, warmup)

    def _rollout(self, instance: torch.Tensor, obs: torch.Tensor, ctrl: torch.Tensor, warmup: int) -> torch.Tensor:
        T = ctrl.shape[1]
        g0 = self.graphs(instance, obs[:, 0], ctrl[:, 0])
        stats, index = self.stats(g0.nodes.dtype), self.core.graph_index(g0)
        hidden = self.initial_hidden(g0)
        out = [obs[:, t] for t in range(warmup + 1)]
        x = obs[:, 0]
        for t in range(T):
            x = obs[:, t] if t <= warmup else x
            x, hidden = self.step(instance, x, ctrl[:, t], hidden, stats, index)
            if t >= warmup:
                out.append(x)
        return torch.stack(out, 1)

    def _captured_rollout(self, instance, obs, ctrl, warmup: int) -> torch.Tensor:
        from gnwarp.interop import replay_cached
        storage = tuple(t.data_ptr() for t in (*self.parameters(), *self.buffers()) if t is not None)
        key = (tuple(instance.shape), tuple(obs.shape), tuple(ctrl.shape), obs.dtype, ctrl.dtype, instance.dtype,
               obs.device, warmup, self.core.options, self.recurrent, storage)
        return replay_cached(_ROLLOUT_GRAPHS.setdefault(self, {}), key, (instance, obs, ctrl),
                             lambda i, o, c: self._rollout(i, o, c, warmup)).clone()


# captured recurrent rollouts per model (``RecurrentForwardModel.rollout``), dropped with the model
_ROLLOUT_GRAPHS: "weakref.WeakKeyDictionary[RecurrentForwardModel, dict]" = weakref.WeakKeyDictionary()

