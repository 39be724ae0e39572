"""End-to-end training of system identification (paper D.7.2, Algorithm D.4): ``SysIDTrainer``.

A ``Trainer`` whose model is a ``SysIDModel`` and whose seams change: ``sample`` draws, per
sequence of the train split, a random ``window``-step identification window and a different
random step t0 outside it; ``loss`` identifies G_ID from the window and applies the forward
model's loss (Algorithm D.3) at t0 with G_ID as the static graph; ``validate`` identifies from
the first ``window`` steps of each valid sequence and rolls out the next ``valid_horizon``
steps with that G_ID; checkpoints hold the whole model (``load_sysid`` reads them).

On CUDA the step is replayed from one CUDA graph as the ``Trainer``'s is (window sampling,
GN_p over the window, the forward model's loss, backward, update: no host synchronization
inside); ``capture=False`` runs it eagerly, as on the CPU.
"""
from __future__ import annotations

import dataclasses
import json
import math
from typing import NamedTuple

import numpy as np
import torch

from gnwarp.data.dataset import load
from gnwarp.data.layout import FeatureLayout, merge_layouts
from gnwarp.eval.metrics import movable_mask, normalized_errors
from gnwarp.graphs import GraphsTuple, batch
from gnwarp.interop import resolve_device
from gnwarp.models.sysid import (StackedWindow, SysIDConfig, SysIDModel, instance_topologies, nominal_graph,
                                 source_places)
from gnwarp.state import DYN_NODE_SIZE
from gnwarp.train.checkpoint import (CheckpointError, load_training, load_weights, model_config_changes,
                                     read_checkpoint)
from gnwarp.train.config import TrainConfig
from gnwarp.train.trainer import Trainer

__all__ = ["SysIDTrainer", "SysIDSample", "ParamStats", "build_sysid_model", "estimate_params", "load_sysid",
           "param_stats", "sysid_rollout_error", "sysid_rollout_predictions", "trained_param_stats", "window_spread",
           "with_params"]


class SysIDSample(NamedTuple):
    """One dataset's part of a batch: the identification window's dynamic graphs (built as one
    batch), the dynamic graph at t0 and the true next states [sum(n_node), 13]."""
    window: StackedWindow
    graph: GraphsTuple
    target: torch.Tensor
    params: tuple | None = None   # with param_loss: (standardized true parameters [n, P], their mask [n, P])


class ParamStats(NamedTuple):
    """A dataset's parameters as ``param_loss`` standardizes them: ``names`` [P], ``mean`` [P],
    ``std`` [P] over the train split's instances; ``used`` [P]: parameters that vary there."""
    names: list
    mean: np.ndarray
    std: np.ndarray
    used: np.ndarray

    def standardize(self, params) -> tuple[np.ndarray, np.ndarray]:
        """(z [..., P], ok [..., P]): ``params`` standardized, 0 where ``ok`` is False (a NaN, or a
        parameter that did not vary in training)."""
        raw = np.asarray(params, dtype=np.float64)
        ok = np.isfinite(raw) & self.used
        return np.where(ok, (np.nan_to_num(raw) - self.mean) / self.std, 0.0), ok

    def to_dict(self) -> dict:
        """As a checkpoint's config.json keeps it (``from_dict`` reads it back)."""
        return {"names": list(self.names), "mean": self.mean.tolist(), "std": self.std.tolist(),
                "used": self.used.tolist()}

    @classmethod
    def from_dict(cls, d) -> "ParamStats":
        """The statistics a checkpoint's config.json keeps (``param_stats`` per system), checked:
        P names, P finite means and standard deviations (positive where used), P flags."""
        if not isinstance(d, dict) or set(d) != {"names", "mean", "std", "used"}:
            raise ValueError(f"parameter statistics need names, mean, std and used, got {d!r:.80}")
        names = d["names"]
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise ValueError("parameter statistics: names must be a list of strings")
        try:
            mean, std = (np.asarray(d[k], dtype=np.float64) for k in ("mean", "std"))
            used = np.asarray(d["used"])
        except (TypeError, ValueError):
            raise ValueError("parameter statistics: mean and std must be lists of numbers") from None
        P = len(names)
        if any(a.shape != (P,) for a in (mean, std, used)) or used.dtype != np.bool_:
            raise ValueError(f"parameter statistics: mean, std and used must each hold {P} values (used: booleans)")
        if not (np.isfinite(mean).all() and np.isfinite(std).all() and (std[used] > 0).all()):
            raise ValueError("parameter statistics: mean and std must be finite, std positive for used parameters")
        return cls(list(names), mean, std, used)


def trained_param_stats(model: SysIDModel, system: str) -> ParamStats | None:
    """The parameter statistics a model loaded with ``load_sysid`` was trained with for
    ``system`` (``SysIDTrainer(param_loss=...)``); None if it was trained without them.
    ``CheckpointError`` if its config.json holds malformed ones."""
    kept = (getattr(model, "checkpoint_info", None) or {}).get("param_stats")
    stats = kept.get(system) if isinstance(kept, dict) else None
    if stats is None:
        return None
    try:
        return ParamStats.from_dict(stats)
    except ValueError as e:
        raise CheckpointError(f"config.json's param_stats[{system!r}]: {e}") from None


def with_params(g_id: GraphsTuple, z, ok) -> GraphsTuple:
    """G_ID with its first P global columns replaced by standardized parameters ``z`` [N, P]
    where ``ok`` [N, P] is nonzero (``ParamStats.standardize``'s; arrays or tensors), GN_p's
    estimate elsewhere."""
    gl = g_id.globals
    z, ok = (torch.as_tensor(a, device=gl.device, dtype=gl.dtype) for a in (z, ok))
    P = z.shape[1]
    return g_id._replace(globals=torch.cat([torch.where(ok > 0, z, gl[:, :P]), gl[:, P:]], 1))


def param_stats(dataset) -> ParamStats:
    """The statistics of ``dataset``'s instance parameters (``static["params"]``, a parameterized
    dataset's) over the instances of its train split, NaN (a parameter an instance lacks) left
    out; a clear error if it has none."""
    names = list(dataset.meta.get("param_names", []))
    params = np.asarray(dataset.static["params"], dtype=np.float64)
    if not names or params.ndim != 2 or params.shape[1] != len(names):
        raise ValueError(f"dataset {dataset.system!r} has no instance parameters (param_loss needs a parameterized "
                         f"dataset: gnwarp generate --parameterized)")
    rows = np.ma.masked_invalid(params[np.unique(np.asarray(dataset["train"].instance[...]))])
    mean, std = rows.mean(0).filled(0.0), rows.std(0).filled(0.0)
    used = (rows.count(0) > 1) & (std > 1e-12 * np.maximum(1.0, np.abs(mean)))
    return ParamStats(names, mean, np.where(used, std, 1.0), used)


def estimate_params(g_id: GraphsTuple, stats: ParamStats) -> np.ndarray:
    """The physical parameters [N, P] that G_ID of a model trained with ``param_loss`` carries in
    its first P global columns (``stats``: ``param_stats`` of its training data); NaN for
    parameters that did not vary in training."""
    P = len(stats.names)
    if g_id.globals is None or g_id.globals.shape[-1] < P:
        raise ValueError(f"G_ID has {0 if g_id.globals is None else g_id.globals.shape[-1]} global columns; "
                         f"the {P} parameters need as many")
    z = g_id.globals[:, :P].detach().double().cpu().numpy()
    return np.where(stats.used, z * stats.std + stats.mean, np.nan)


def build_sysid_model(config: TrainConfig, datasets, sysid: SysIDConfig | None = None) -> SysIDModel:
    """A new ``SysIDModel`` for ``datasets``: the forward model from ``config.model`` (re-centring
    decided as ``build_model`` does, D.4), GN_p and the window from ``sysid``."""
    sysid = sysid or SysIDConfig()
    mcfg = dataclasses.replace(config.model)
    if mcfg.recenter is None:
        mcfg.recenter = len(datasets) == 1 and bool(datasets[0].meta.get("translation_invariant", False))
    if mcfg.core != "gn":
        raise ValueError("system identification trains the GN forward model (model.core = 'gn')")
    if sysid.local_params and sysid.param_places is None:   # where the data's parameters live
        places = {source_places(d) for d in datasets}
        if len(places) > 1:
            raise ValueError("local_params: the datasets place their parameters differently (train one system)")
        sysid = dataclasses.replace(sysid, param_places=places.pop())
    if sysid.nominal_static and sysid.nominal is None:   # the training data's system as designed
        if len(datasets) != 1:
            raise ValueError(f"nominal_static reads one dataset's nominal static graph; got {len(datasets)} datasets "
                             f"(train on one)")
        sysid = dataclasses.replace(sysid, nominal=nominal_graph(datasets[0]))
    return SysIDModel(dataclasses.replace(sysid, forward=mcfg), merge_layouts([d.layout for d in datasets]))


class SysIDTrainer(Trainer):
    """Trains a ``SysIDModel`` end to end (Algorithm D.4); see the module docstring.

    ``sysid``: sizes of GN_p and the window (default ``SysIDConfig()``); the forward model's
    sizes and run options are ``config.model``'s. Other arguments as ``Trainer``'s. A rerun into
    the same ``out`` resumes from ``<out>/last`` (model, optimizer, sampler and run state), as
    the ``Trainer``'s do; a checkpoint of another model is refused. ``targets`` (beyond the
    paper's 1): one-step losses per identification window, at K different steps outside it, so
    that each identification (GN_p's whole window, most of a step's work) gets K times the signal.
    ``start_windows`` (beyond the paper's 0): the fraction of identification windows drawn at
    their sequence's start (s0 = 0) rather than uniformly: identification in use (``gnwarp
    evaluate``, Figure 8, ``control.identify_on_env``) reads an episode's first steps, from the
    initial-state distribution, which uniform windows reach once in T - W + 1 draws.
    ``consistency`` (beyond the paper's 0): the weight of a window-consistency term. Each
    batch's sequences come in pairs, two independent windows (and one-step targets) of one
    sequence, and the loss adds ``consistency`` times the share of G_ID's variance over the
    batch that lies between the two windows of a pair (``window_spread``: 0 when G_ID depends
    only on the sequence's system, ~1 when a pair's windows differ as much as any two). Its aim:
    G_ID that varies from window to window acts on the forward model as noise on its static
    inputs, which training answers by weakening the parameters' effect. No parameter labels are
    read; scale-free, so shrinking G_ID does not lower it.
    ``param_loss`` (beyond the paper's 0, which reads no labels): the weight of a parameter
    supervision term. Generated parameterized data know each instance's parameters
    (``static["params"]``); the loss adds ``param_loss`` times the mean squared error between G_ID's
    first P global columns and the instance's P parameters, standardized over the train split
    (``param_stats``). G_ID stays the forward model's latent static graph; the term tells GN_p
    what to identify, at a precision the one-step loss alone rewards too weakly (a 1% error in a
    pendulum's length changes one step's prediction by ~1e-4 of its noise, a 100-step rollout by
    far more). ``estimate_params`` reads the parameters back from G_ID.
    ``param_teacher`` (with ``param_loss``; default 0): the fraction of windows whose forward
    model reads the instance's true standardized parameters in those columns instead of GN_p's
    estimate (teacher forcing), so that it learns the parameters' exact effect; GN_p's columns
    then learn from ``param_loss`` alone on those windows."""

    def __init__(self, config: TrainConfig, sysid: SysIDConfig | None = None, datasets=None,
                 model: SysIDModel | None = None, callbacks=(), targets: int = 1, start_windows: float = 0.0,
                 consistency: float = 0.0, param_loss: float = 0.0, param_teacher: float = 0.0):
        if isinstance(targets, bool) or not isinstance(targets, int) or targets < 1:
            raise ValueError(f"targets must be a positive int (one-step losses per identification window), "
                             f"got {targets!r}")
        start_windows = _number("start_windows", start_windows, "the fraction of identification windows at a "
                                "sequence's start", most=1.0)
        consistency = _number("consistency", consistency, "the weight of the window-consistency term")
        param_loss = _number("param_loss", param_loss, "the weight of the parameter supervision term")
        param_teacher = _number("param_teacher", param_teacher, "the fraction of windows whose true parameters the "
                                "forward model reads", most=1.0)
        local = (sysid if sysid is not None else model.sysid if model is not None else SysIDConfig()).local_params
        if local and param_loss == 0:
            raise ValueError("local_params hands the forward model the parameters param_loss teaches G_ID: it needs "
                             "param_loss > 0")
        if param_teacher > 0 and param_loss == 0:
            raise ValueError("param_teacher hands the forward model the parameters param_loss supervises: it needs "
                             "param_loss > 0")
        self.targets = targets
        self.param_loss, self.param_teacher = param_loss, param_teacher
        self.start_windows, self.consistency = start_windows, consistency
        if datasets is None:
            if not config.data:
                raise ValueError("no training data: set `data` to one or more dataset files")
            datasets = [load(p, lazy=True) for p in config.data]
        datasets = list(datasets)
        torch.manual_seed(config.seed)
        model = model if model is not None else build_sysid_model(config, datasets, sysid)
        W = model.window
        for d in datasets:
            T = int(d["train"].num_steps)
            if T < W + 1:
                raise ValueError(f"dataset {d.system!r} has sequences of {T} steps; system identification needs "
                                 f"more than the {W}-step window (a window and a different step t0)")
        if self.consistency > 0:
            shares = _shares(config.batch_size, len(datasets))
            if any(n % 2 for n in shares):
                raise ValueError(f"consistency pairs each batch's sequences: batch_size {config.batch_size} gives "
                                 f"{len(datasets)} dataset(s) the shares {shares}; each must be even")
        if self.param_loss > 0:
            self.param_stats = [param_stats(d) for d in datasets]
            width = model.gid_sizes["globals"]
            for d, st in zip(datasets, self.param_stats):
                if len(st.names) > width:
                    raise ValueError(f"param_loss: dataset {d.system!r} has {len(st.names)} parameters but G_ID "
                                     f"has {width} global columns (widen identifier.out_globals; gnwarp train: "
                                     f"--gid-globals)")
        super().__init__(config, datasets, model, callbacks)
        if self.param_loss > 0:   # per sampler part: standardized parameters [I, P] and their mask
            dt = self.model.dtype
            self._param_z = []
            for d, st in zip(self.datasets, self.param_stats):
                z, ok = st.standardize(d.static["params"])
                self._param_z.append((torch.as_tensor(z, device=self.device, dtype=dt),
                                      torch.as_tensor(ok, device=self.device, dtype=dt)))
            self.info["param_stats"] = {d.system: st.to_dict() for d, st in zip(self.datasets, self.param_stats)}
        self.info["kind"] = "sysid"   # in config.json: load_sysid reads it, load_model refuses it
        self.info["train"]["targets"] = targets
        self.info["train"]["start_windows"] = self.start_windows
        self.info["train"]["consistency"] = self.consistency
        self.info["train"]["param_loss"] = self.param_loss
        self.info["train"]["param_teacher"] = self.param_teacher

    @property
    def log_fields(self) -> tuple[str, ...]:
        extra = (("window_spread",) if self.consistency > 0 else ()) + (("param_error",) if self.param_loss > 0 else ())
        return (*super().log_fields, *extra)

    def _load_last(self):
        """Resuming: the SysIDModel of ``<out>/last`` and its training state."""
        last = self.out / "last"
        return load_sysid(last, self.device), load_training(last)

    def _config_changes(self, saved: dict, wanted: SysIDConfig) -> list[str]:
        if not isinstance(saved, dict) or "forward" not in saved:
            return ["model: a forward-model checkpoint, not a system-identification one"]
        changes = model_config_changes(saved["forward"], wanted.forward)
        want = json.loads(json.dumps(wanted.to_dict()))   # tuples as the JSON lists saved
        before = {k: saved.get(k) for k in ("identifier", "window")}
        before["transitions"] = saved.get("transitions", False)   # checkpoints from before the options
        before["readout"] = saved.get("readout", "last")
        for k in ("ridge_features", "ridge"):   # the fitting readouts' own settings
            if k in want or k in saved:
                before[k] = saved.get(k)
        before["ridge_head"] = saved.get("ridge_head", 0)
        want.setdefault("ridge_head", 0)
        for k, none in (("stateless", False), ("local_params", False), ("param_places", None), ("nominal_static", False),
                        ("nominal", None)):
            before[k] = saved.get(k, none)
            want.setdefault(k, none)
        changes += [f"model.{k}: {v!r} -> {want.get(k)!r}" if k != "nominal" else
                    "model.nominal: another nominal static graph (the training data's system differs)"
                    for k, v in before.items() if v != want.get(k)]
        return changes

    # -- seams ------------------------------------------------------------------------------
    def sample(self) -> tuple[list[SysIDSample]]:
        """Per dataset, its share of ``batch_size`` sequences: a random window [s0, s0 + W) and a
        random step t0 outside it (Algorithm D.4); with ``targets`` K > 1, K steps t0 outside the
        window, drawn independently (the graphs and targets of the K draws one after another); a
        ``start_windows`` fraction of the windows at s0 = 0; with ``consistency``, the second half
        of each share the first half's sequences again (in order: a pair's graphs lie half a
        batch apart). On the device, no host sync."""
        W, K = self.model.window, self.targets
        parts = self.sampler.parts
        out = []
        for i, (p, n) in enumerate(zip(parts, _shares(self.config.batch_size, len(parts)))):
            if n == 0:
                continue
            dev, gen = p.body.device, self.generator
            if self.consistency > 0:
                seq = torch.randint(p.S, (n // 2,), generator=gen, device=dev).repeat(2)
            else:
                seq = torch.randint(p.S, (n,), generator=gen, device=dev)
            s0 = torch.randint(p.T - W + 1, (n,), generator=gen, device=dev)
            if self.start_windows > 0:
                at_start = torch.rand(n, generator=gen, device=dev) < self.start_windows
                s0 = torch.where(at_start, torch.zeros_like(s0), s0)
            r = torch.randint(p.T - W, (K * n,), generator=gen, device=dev)
            inst = p.instance[seq]
            steps = s0[None] + torch.arange(W, device=dev)[:, None]          # [W, n]: the window, step by step
            body_w, ctrl_w = p.body[seq[None], steps], p.ctrl[seq[None], steps]
            window = StackedWindow.build(p.builder, inst, body_w, ctrl_w)
            seq_k, inst_k, s0_k = (seq, inst, s0) if K == 1 else (seq.repeat(K), inst.repeat(K), s0.repeat(K))
            t0 = torch.where(r < s0_k, r, r + W)    # uniform over the steps outside the window
            graph = p.builder(inst_k, p.body[seq_k, t0], p.ctrl[seq_k, t0])
            nxt = p.body[seq_k, t0 + 1]
            target = nxt.reshape(-1, DYN_NODE_SIZE) if p.builder.uniform else nxt[p.builder.node_mask[inst_k]]
            params = None if self.param_loss == 0 else tuple(x[inst] for x in self._param_z[i])
            out.append(SysIDSample(window, graph, target, params))
        return (out,)

    def loss(self, parts: list[SysIDSample], accumulate: bool = True) -> dict[str, torch.Tensor]:
        """G_ID of each window, then the forward model's loss at t0 with G_ID as its static graph."""
        m, c = self.model, self.config
        fm = m.forward_model
        graphs, spread, perr = [], [], []
        for p in parts:
            g_id = m.identify_graphs(p.window, len(p.window), fm.stats(p.graph.nodes.dtype))
            if self.consistency > 0:
                spread.append(window_spread(g_id))
            if p.params is not None:
                z, ok = p.params
                est = g_id.globals[:, :z.shape[1]].to(z.dtype)
                perr.append(((est - z).square() * ok).sum() / ok.sum().clamp_min(1.0))
                if self.param_teacher > 0:   # these windows hand the forward model the true parameters
                    u = torch.rand(z.shape[0], 1, generator=self.generator, device=z.device, dtype=z.dtype)
                    g_id = with_params(g_id, z, ok * (u < self.param_teacher))
            if self.targets > 1:   # the same G_ID for each of the window's K one-step targets
                K = self.targets
                g_id = g_id._replace(**{k: None if getattr(g_id, k) is None else getattr(g_id, k).repeat(K, 1)
                                        for k in ("nodes", "edges", "globals")})
            graphs.append(m.with_gid(p.graph, g_id))
        graph = graphs[0] if len(graphs) == 1 else batch(graphs)
        target = parts[0].target if len(parts) == 1 else torch.cat([p.target for p in parts], 0)
        terms = fm.loss(graph, target, noise_std=c.noise_std, accumulate=accumulate, rotation_scale=c.rotation_loss,
                        generator=self.generator)
        if spread:
            terms["window_spread"] = torch.stack(spread).mean()
            terms["loss"] = terms["loss"] + self.consistency * terms["window_spread"]
        if perr:
            terms["param_error"] = torch.stack(perr).mean()
            terms["loss"] = terms["loss"] + self.param_loss * terms["param_error"]
        return terms

    def validate(self) -> float:
        c = self.config
        self.model.eval()
        errs = [sysid_rollout_error(self.model, d, "valid", c.valid_horizon, c.valid_sequences) for d in self.valid]
        self.model.train()
        return float(np.mean(errs)) if errs else math.nan


def _number(name: str, value, what: str, most: float | None = None) -> float:
    """``value`` as a float if it is a finite number >= 0 (and <= ``most``); ValueError naming
    ``name`` and ``what`` it is otherwise (a bool or a string is not a number here)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0 \
            or (most is not None and value > most):
        allowed = f"a number from 0 to {most:g}" if most is not None else "a finite number >= 0"
        raise ValueError(f"{name} must be {allowed} ({what}), got {value!r}")
    return float(value)


def _shares(batch_size: int, k: int) -> list[int]:
    """Each of k datasets' number of sequences in a batch (the first ones take the remainder)."""
    return [batch_size // k + (1 if i < batch_size % k else 0) for i in range(k)]


def window_spread(g_id: GraphsTuple, other: GraphsTuple | None = None) -> torch.Tensor:
    """The share of G_ID's variance that lies within pairs of windows of one sequence.

    ``g_id``: G_ID of a batch whose second half repeats its first half's sequences in order (so
    element j of the first half's nodes, edges and globals pairs with element j of the second
    half); or, with ``other``, G_ID of the same sequences from other windows (``g_id``'s element
    j pairs with ``other``'s). Within-pair variance E[(a - b)^2] / 2 over the total variance,
    summed over every G_ID column: a scalar in [0, ~2], 0 when each pair's G_IDs agree."""
    within, total = 0.0, 0.0
    for k in ("nodes", "edges", "globals"):
        x = getattr(g_id, k)
        if x is None or x.numel() == 0:
            continue
        if other is not None:
            y = getattr(other, k)
            if y is None or y.shape != x.shape:
                raise ValueError(f"window_spread: the two G_IDs' {k} differ in shape")
            x = torch.cat([x, y])
        h = x.shape[0] // 2
        within = within + (x[:h] - x[h:2 * h]).square().mean(0).sum() / 2
        total = total + x.var(0, unbiased=False).sum()
    return within / (total + 1e-12)


def other_instance_windows(dataset, split: str, n: int) -> np.ndarray:
    """For each of the first ``n`` sequences of ``split``, the sequence whose window identifies it
    in the paper's "another instance" test (``sysid_rollout_error(window_from=...)``): the previous
    one among the sequences whose instances share its graph topology (a G_ID has rows per node and
    edge, so it applies only to graphs of its own layout), cyclically. With one topology, as every
    system but the parameterized swimmer has, that is sequence i - 1. A sequence whose topology no
    other shares keeps its own window."""
    topology = instance_topologies(dataset.static)
    groups: dict[tuple, list[int]] = {}
    for i, k in enumerate(np.asarray(dataset[split].instance[:n])):
        groups.setdefault(topology[k], []).append(i)
    src = np.arange(n)
    for rows in groups.values():
        src[rows] = np.roll(rows, 1)
    return src


@torch.no_grad()
def sysid_rollout_predictions(model: SysIDModel, dataset, split: str = "valid", horizon: int = 20,
                              sequences: int | None = None, window_from=None, oracle: ParamStats | None = None
                              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(predicted [S, H+1, B, 13], true [S, H+1, B, 13], instance [S]) of rollouts from step W of
    each of the first ``sequences`` sequences of ``split``, G_ID identified from its steps
    [0, W) (``window_from`` [S]: the sequences whose windows to use instead, e.g. another
    instance's, for the paper's Figure 8). ``oracle`` (the ``param_stats`` of a model trained
    with ``param_loss``): G_ID's first P global columns are replaced by the instances' true
    standardized parameters, the forward model's predictions when those columns are identified
    perfectly."""
    sp = dataset[split]
    n = len(sp) if sequences is None else min(int(sequences), len(sp))
    W = model.window
    body = torch.as_tensor(np.asarray(sp.body[:n], dtype=np.float32))
    ctrl = torch.as_tensor(np.asarray(sp.ctrl[:n], dtype=np.float32))
    inst = np.asarray(sp.instance[:n])
    H = min(int(horizon), ctrl.shape[1] - W)
    if H < 1:
        raise ValueError(f"the {split} split's sequences are too short for a {W}-step window and a rollout")
    src = np.arange(n) if window_from is None else np.asarray(window_from)
    builder = model.graph_builder(dataset)
    old, model.builder = model.builder, builder
    try:
        g_id = model.identify(body[src, :W], ctrl[src, :W], torch.as_tensor(inst[src]))
        if oracle is not None:
            params = dataset.static.get("params")
            if params is None or np.asarray(params).shape[-1:] != oracle.mean.shape:
                raise ValueError(f"oracle: dataset {dataset.system!r} has no instance parameters of the "
                                 f"{len(oracle.names)} the statistics describe ({', '.join(oracle.names)})")
            g_id = with_params(g_id, *oracle.standardize(np.asarray(params)[inst[src]]))
        pred = model.rollout(body[:, W], ctrl[:, W:W + H], g_id, torch.as_tensor(inst)).float().cpu().numpy()
    finally:
        model.builder = old
    return pred, body[:, W:W + H + 1].numpy(), inst


def sysid_rollout_error(model: SysIDModel, dataset, split: str = "valid", horizon: int = 20,
                        sequences: int | None = None, window_from=None, oracle: ParamStats | None = None) -> float:
    """Mean normalized rollout error (as ``gnwarp.eval.rollout_error``) of the rollouts of
    ``sysid_rollout_predictions`` (same arguments); Inf where they are not finite."""
    pred, true, inst = sysid_rollout_predictions(model, dataset, split, horizon, sequences, window_from, oracle)
    const = np.broadcast_to(true[:, :1], true.shape)
    r = normalized_errors(pred[:, 1:], true[:, 1:], const[:, 1:], movable_mask(dataset, inst))["mean"]
    return r if math.isfinite(r) else math.inf


def load_sysid(path, device=None) -> SysIDModel:
    """A ``SysIDModel`` from a checkpoint folder a ``SysIDTrainer`` wrote (manifest and checksums
    checked, weights read with ``weights_only=True`` and checked finite); unbound."""
    path, cfg = read_checkpoint(path)
    if cfg.get("kind") != "sysid":
        raise CheckpointError(f"{path} is not a system-identification checkpoint (load it with gnwarp.load_model)")
    try:
        config = SysIDConfig.from_dict(cfg["model"])
        layout = FeatureLayout.from_dict(cfg["layout"])
    except (KeyError, TypeError, ValueError) as e:
        raise CheckpointError(f"{path}: config.json does not describe a system-identification model ({e})") from None
    model = SysIDModel(config, layout)
    model.checkpoint_info = cfg
    try:
        model.load_state_dict(load_weights(path))
    except Exception as e:  # noqa: BLE001 - weights of another architecture
        raise CheckpointError(f"{path}: cannot load the weights ({type(e).__name__}: {e})") from None
    return model.to(resolve_device(device))
