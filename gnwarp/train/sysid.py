"""End-to-end training of system identification (paper D.7.2, Algorithm D.4): ``SysIDTrainer``.

A ``Trainer`` whose model is a ``SysIDModel`` and whose seams change: ``sample`` draws, per
sequence of the train split, a random ``window``-step identification window and a different
random step t0 outside it; ``loss`` identifies G_ID from the window and applies the forward
model's loss (Algorithm D.3) at t0 with G_ID as the static graph; ``validate`` identifies from
the first ``window`` steps of each valid sequence and rolls out the next ``valid_horizon``
steps with that G_ID; checkpoints hold the whole model (``load_sysid`` reads them) and the
training options (``SysIDTrainConfig``, ``trained_options`` reads them back).

On CUDA the step is replayed from one CUDA graph as the ``Trainer``'s is (window sampling,
GN_p over the window, the forward model's loss, backward, update: no host synchronization
inside); ``capture=False`` runs it eagerly, as on the CPU.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from gnwarp.data.dataset import load
from gnwarp.data.layout import FeatureLayout
from gnwarp.eval.sysid import sysid_rollout_error
from gnwarp.graphs import GraphsTuple, batch
from gnwarp.interop import resolve_device
from gnwarp.models.factory import build_sysid_model
from gnwarp.models.sysid import SysIDModel
from gnwarp.models.sysid_config import SysIDConfig
from gnwarp.models.sysid_graphs import StackedWindow
from gnwarp.models.sysid_params import ParamStats, param_stats, with_params
from gnwarp.state import DYN_NODE_SIZE
from gnwarp.train.checkpoint import (CheckpointError, checkpoint_config, load_training, load_weights,
                                     model_config_changes, read_checkpoint, recover_checkpoint)
from gnwarp.train.config import TrainConfig
from gnwarp.train.sysid_config import SysIDTrainConfig
from gnwarp.train.trainer import Trainer

__all__ = ["SysIDTrainer", "SysIDSample", "load_sysid", "trained_options", "trained_param_stats", "window_spread"]


class SysIDSample(NamedTuple):
    """One dataset's part of a batch: the identification window's dynamic graphs (built as one
    batch), the dynamic graph at t0 and the true next states [sum(n_node), 13]."""
    window: StackedWindow
    graph: GraphsTuple
    target: torch.Tensor
    params: tuple | None = None   # with param_loss: (standardized true parameters [n, P], their mask [n, P])


def trained_param_stats(model: SysIDModel, system: str) -> ParamStats | None:
    """The parameter statistics a model loaded with ``load_sysid`` was trained with for
    ``system`` (``SysIDTrainConfig.param_loss``); None if it was trained without them.
    ``CheckpointError`` if its config.json holds malformed ones."""
    kept = (getattr(model, "checkpoint_info", None) or {}).get("param_stats")
    stats = kept.get(system) if isinstance(kept, dict) else None
    if stats is None:
        return None
    try:
        return ParamStats.from_dict(stats)
    except ValueError as e:
        raise CheckpointError(f"config.json's param_stats[{system!r}]: {e}") from None


def trained_options(model: SysIDModel) -> SysIDTrainConfig:
    """The ``SysIDTrainConfig`` that trained a model loaded with ``load_sysid`` (its
    config.json's; a checkpoint from before the options were recorded gives the defaults, the
    paper's training, for the options it lacks). ``CheckpointError`` for malformed ones."""
    return _saved_options(getattr(model, "checkpoint_info", None) or {})


def _saved_options(cfg: dict) -> SysIDTrainConfig:
    try:
        return SysIDTrainConfig.from_checkpoint(cfg)
    except (TypeError, ValueError) as e:
        raise CheckpointError(f"config.json's system-identification training options: {e} (fix or remove its "
                              f"\"sysid_train\" table; the defaults are the paper's training)") from None


def _resumable(config: TrainConfig) -> dict | None:
    """The config.json of the system-identification checkpoint ``config`` resumes from
    (``<out>/last``, after putting back what a killed save left, as the ``Trainer`` does), else
    None (no resume, no checkpoint, another kind, or one that does not read: the ``Trainer``'s
    resume check reports it)."""
    if not config.resume:
        return None
    out = Path(config.out)
    recover_checkpoint(out / "best")
    recover_checkpoint(out / "last", fallbacks=[out / "best"])
    try:
        cfg = checkpoint_config(out / "last") if (out / "last").is_dir() else None
    except (CheckpointError, OSError):
        return None
    return cfg if isinstance(cfg, dict) and cfg.get("kind") == "sysid" else None


class SysIDTrainer(Trainer):
    """Trains a ``SysIDModel`` end to end (Algorithm D.4); see the module docstring.

    ``sysid``: sizes of GN_p and the window (default ``SysIDConfig()``); the forward model's
    sizes and run options are ``config.model``'s. ``options``: the training options beyond a
    ``TrainConfig`` (``SysIDTrainConfig``: more targets per window, windows at the start,
    window consistency, parameter supervision and teacher forcing; default the paper's). Other
    arguments as ``Trainer``'s. A rerun into the same ``out`` resumes from ``<out>/last``
    (model, optimizer, sampler and run state), as the ``Trainer``'s do; a checkpoint of another
    model is refused. Resuming, ``sysid`` and ``options`` left out are the checkpoint's (its
    config.json records both), so a run continues as started.

    With ``param_loss``, G_ID stays the forward model's latent static graph; the term tells GN_p
    what to identify, at a precision the one-step loss alone rewards too weakly (a 1% error in a
    pendulum's length changes one step's prediction by ~1e-4 of its noise, a 100-step rollout by
    far more); ``gnwarp.models.sysid_params.estimate_params`` reads the parameters back from
    G_ID. The consistency term's aim: G_ID that varies from window to window acts on the forward
    model as noise on its static inputs, which training answers by weakening the parameters'
    effect; no parameter labels are read, and it is scale-free, so shrinking G_ID does not lower
    it."""

    runs_on_ranks = False   # its own sampler and normalizers are not reduced over ranks

    def __init__(self, config: TrainConfig, sysid: SysIDConfig | None = None, datasets=None,
                 model: SysIDModel | None = None, callbacks=(), options: SysIDTrainConfig | None = None):
        saved = _resumable(config)
        if options is None:   # a resumed run's own options, else the paper's
            options = _saved_options(saved) if saved is not None else SysIDTrainConfig()
        if not isinstance(options, SysIDTrainConfig):
            raise TypeError(f"options must be a SysIDTrainConfig, got {type(options).__name__}")
        if sysid is None and model is None and saved is not None:   # a resumed run's model config
            try:
                sysid = SysIDConfig.from_dict(saved["model"])
            except (KeyError, TypeError, ValueError):   # left to the resume check, which names the problem
                sysid = None
        local = (sysid if sysid is not None else model.sysid if model is not None else SysIDConfig()).local_params
        if local and options.param_loss == 0:
            raise ValueError("local_params hands the forward model the parameters param_loss teaches G_ID: it needs "
                             "param_loss > 0")
        self.options = options
        if datasets is None:
            if not config.data:
                raise ValueError("no training data: set `data` to one or more dataset files")
            datasets = [load(p, lazy=True) for p in config.data]
        datasets = list(datasets)
        torch.manual_seed(config.seed)
        model = model if model is not None else build_sysid_model(config.model, datasets, sysid)
        W = model.window
        for d in datasets:
            T = int(d["train"].num_steps)
            if T < W + 1:
                raise ValueError(f"dataset {d.system!r} has sequences of {T} steps; system identification needs "
                                 f"more than the {W}-step window (a window and a different step t0)")
        if self.options.consistency > 0:
            shares = _shares(config.batch_size, len(datasets))
            if any(n % 2 for n in shares):
                raise ValueError(f"consistency pairs each batch's sequences: batch_size {config.batch_size} gives "
                                 f"{len(datasets)} dataset(s) the shares {shares}; each must be even")
        if self.options.param_loss > 0:
            self.param_stats = [param_stats(d) for d in datasets]
            width = model.gid_sizes["globals"]
            for d, st in zip(datasets, self.param_stats):
                if len(st.names) > width:
                    raise ValueError(f"param_loss: dataset {d.system!r} has {len(st.names)} parameters but G_ID "
                                     f"has {width} global columns (widen identifier.out_globals; gnwarp train: "
                                     f"--gid-globals)")
        super().__init__(config, datasets, model, callbacks)
        if self.options.param_loss > 0:   # per sampler part: standardized parameters [I, P] and their mask
            dt = self.model.dtype
            self._param_z = []
            for d, st in zip(self.datasets, self.param_stats):
                z, ok = st.standardize(d.static["params"])
                self._param_z.append((torch.as_tensor(z, device=self.device, dtype=dt),
                                      torch.as_tensor(ok, device=self.device, dtype=dt)))
            self.info["param_stats"] = {d.system: st.to_dict() for d, st in zip(self.datasets, self.param_stats)}
        self.info["kind"] = "sysid"   # in config.json: load_sysid reads it, load_model refuses it
        self.info["sysid_train"] = options.to_dict()   # in config.json: resuming and trained_options read it

    @property
    def log_fields(self) -> tuple[str, ...]:
        o = self.options
        extra = (("window_spread",) if o.consistency > 0 else ()) + (("param_error",) if o.param_loss > 0 else ())
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
        W, K = self.model.window, self.options.targets
        parts = self.sampler.parts
        out = []
        for i, (p, n) in enumerate(zip(parts, _shares(self.config.batch_size, len(parts)))):
            if n == 0:
                continue
            dev, gen = p.body.device, self.generator
            if self.options.consistency > 0:
                seq = torch.randint(p.S, (n // 2,), generator=gen, device=dev).repeat(2)
            else:
                seq = torch.randint(p.S, (n,), generator=gen, device=dev)
            s0 = torch.randint(p.T - W + 1, (n,), generator=gen, device=dev)
            if self.options.start_windows > 0:
                at_start = torch.rand(n, generator=gen, device=dev) < self.options.start_windows
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
            params = None if self.options.param_loss == 0 else tuple(x[inst] for x in self._param_z[i])
            out.append(SysIDSample(window, graph, target, params))
        return (out,)

    def loss(self, parts: list[SysIDSample], accumulate: bool = True) -> dict[str, torch.Tensor]:
        """G_ID of each window, then the forward model's loss at t0 with G_ID as its static graph."""
        m, c = self.model, self.config
        fm = m.forward_model
        graphs, spread, perr = [], [], []
        for p in parts:
            g_id = m.identify_graphs(p.window, len(p.window), fm.stats(p.graph.nodes.dtype))
            if self.options.consistency > 0:
                spread.append(window_spread(g_id))
            if p.params is not None:
                z, ok = p.params
                est = g_id.globals[:, :z.shape[1]].to(z.dtype)
                perr.append(((est - z).square() * ok).sum() / ok.sum().clamp_min(1.0))
                if self.options.param_teacher > 0:   # these windows hand the forward model the true parameters
                    u = torch.rand(z.shape[0], 1, generator=self.generator, device=z.device, dtype=z.dtype)
                    g_id = with_params(g_id, z, ok * (u < self.options.param_teacher))
            if self.options.targets > 1:   # the same G_ID for each of the window's K one-step targets
                K = self.options.targets
                g_id = g_id._replace(**{k: None if getattr(g_id, k) is None else getattr(g_id, k).repeat(K, 1)
                                        for k in ("nodes", "edges", "globals")})
            graphs.append(m.with_gid(p.graph, g_id))
        graph = graphs[0] if len(graphs) == 1 else batch(graphs)
        target = parts[0].target if len(parts) == 1 else torch.cat([p.target for p in parts], 0)
        terms = fm.loss(graph, target, noise_std=c.noise_std, accumulate=accumulate, rotation_scale=c.rotation_loss,
                        generator=self.generator)
        if spread:
            terms["window_spread"] = torch.stack(spread).mean()
            terms["loss"] = terms["loss"] + self.options.consistency * terms["window_spread"]
        if perr:
            terms["param_error"] = torch.stack(perr).mean()
            terms["loss"] = terms["loss"] + self.options.param_loss * terms["param_error"]
        return terms

    def validate(self) -> float:
        c = self.config
        self.model.eval()
        errs = [sysid_rollout_error(self.model, d, "valid", c.valid_horizon, c.valid_sequences) for d in self.valid]
        self.model.train()
        return float(np.mean(errs)) if errs else math.nan


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
