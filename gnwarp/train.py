"""Training of forward models (supplementary D.7, D.8) and their checkpoints.

``train(config)`` fits a ``ForwardModel`` to one or more datasets: Adam with gradient clipping,
learning rate ``lr * lr_decay ** (step // lr_decay_steps)`` (paper: 1e-4, 0.975, every 50k steps
"fast" or 200k "slow"), batches of ``batch_size`` graphs drawn uniformly over (sequence, step) of
each train split, several datasets mixed in equal proportion, normalizers accumulated from the
training batches, validation by the 20-step rollout error on the valid split, best checkpoint
kept, early stopping.

A run folder holds::

    <out>/last/   the latest checkpoint (training resumes from it)
    <out>/best/   the checkpoint with the lowest validation error
    <out>/log.csv losses, learning rate and validation errors

A checkpoint is a self-describing folder, written to a temporary folder and renamed into place::

    config.json    format, version, ModelConfig, FeatureLayout, the training config and data
    model.pt       state dict: weights and normalizer accumulators (count, sum, squared sum)
    training.pt    optimizer state, step, best validation error, sampler state (optional)
    manifest.json  sha256 of each file above (checked on load)

``gnwarp.load_model(path)`` restores a model from it without any of the training code's state.
"""
from __future__ import annotations

import csv
import dataclasses
import hashlib
import json
import math
import os
import shutil
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from gnwarp.data.layout import FeatureLayout, merge_layouts
from gnwarp.models import ForwardModel, ModelConfig
from gnwarp.optim import FlatAdam
from gnwarp.state import DYN_NODE_SIZE

__all__ = ["TrainConfig", "train", "save_checkpoint", "load_model", "load_checkpoint", "CheckpointError",
           "SCHEDULES", "resolve_device"]

FORMAT, VERSION = "gnwarp-model", 1
SCHEDULES = {"fast": 50_000, "slow": 200_000}   # D.8: learning-rate decay period in steps


class CheckpointError(ValueError):
    """A checkpoint folder that is missing, incomplete, corrupt or of another format."""


@dataclass
class TrainConfig:
    """Everything a training run needs; saved with every checkpoint.

    ``data``: dataset files (several are mixed in equal proportion within each batch).
    ``lr_decay_steps``: steps per x``lr_decay`` (an int, or "fast" / "slow" for the paper's 50k / 200k).
    ``noise_std``: std of the Gaussian noise on input dynamic nodes (D.7.1), in state units.
    ``rotation_loss``: "normalized" or "paper" (see ``ForwardModel.loss``).
    ``max_seconds``: stop after this much training time (None: ``steps`` only).
    ``patience``: stop after this many validations without improvement (None: never).
    ``device``: "auto" (CUDA when present), "cpu", "cuda", "cuda:1", ...
    ``optimizer``: "adam" (torch.optim.Adam + clip_grad_norm_) or "flat_adam"
    (``gnwarp.optim.FlatAdam``: the same update and clipping over one flat buffer in Warp
    kernels; faster on the GPU, see README). A run resumes with the optimizer it was started with.
    """
    data: list[str] = field(default_factory=list)
    out: str = "runs/model"
    model: ModelConfig = field(default_factory=ModelConfig)
    steps: int = 100_000
    max_seconds: float | None = None
    batch_size: int = 200
    lr: float = 1e-4
    lr_decay: float = 0.975
    lr_decay_steps: int | str = "fast"
    grad_clip: float = 1.0
    noise_std: float = 0.003
    rotation_loss: str = "normalized"
    normalizer_warmup: int = 20
    valid_every: int = 1000
    valid_sequences: int = 100
    valid_horizon: int = 20
    patience: int | None = 20
    checkpoint_every: int = 1000
    log_every: int = 50
    seed: int = 0
    device: str = "auto"
    dtype: str = "float32"
    resume: bool = True
    progress: bool = True
    optimizer: str = "adam"

    def __post_init__(self):
        if isinstance(self.model, dict):
            self.model = ModelConfig.from_dict(self.model)
        if isinstance(self.data, (str, os.PathLike)):
            self.data = [str(self.data)]
        self.data = [str(d) for d in self.data]
        if isinstance(self.lr_decay_steps, str):
            if self.lr_decay_steps not in SCHEDULES:
                raise ValueError(f"lr_decay_steps must be an int or one of {sorted(SCHEDULES)}, "
                                 f"got {self.lr_decay_steps!r}")
        if self.batch_size < 1 or self.steps < 0:
            raise ValueError("batch_size must be >= 1 and steps >= 0")
        if self.optimizer not in ("adam", "flat_adam"):
            raise ValueError(f"optimizer must be 'adam' or 'flat_adam', got {self.optimizer!r}")
        if self.dtype not in ("float32", "float64"):
            raise ValueError(f"dtype must be 'float32' or 'float64', got {self.dtype!r}")

    @property
    def decay_steps(self) -> int:
        return SCHEDULES[self.lr_decay_steps] if isinstance(self.lr_decay_steps, str) else int(self.lr_decay_steps)

    def lr_at(self, step: int) -> float:
        return self.lr * self.lr_decay ** (step // self.decay_steps)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown training config keys: {unknown} (known: {sorted(known)})")
        return cls(**d)


def resolve_device(device: str = "auto") -> torch.device:
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


# -- checkpoints --------------------------------------------------------------------------------

def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def save_checkpoint(path, model: ForwardModel, training: dict | None = None, info: dict | None = None) -> Path:
    """Write ``model`` (and optional training state) as a checkpoint folder at ``path``,
    atomically: into a temporary folder beside it, then renamed over any previous one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f".{path.name}.tmp-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    try:
        cfg = {"format": FORMAT, "version": VERSION, "gnwarp_version": __import__("gnwarp").__version__,
               "model": model.config.to_dict(), "layout": model.layout.to_dict(), **(info or {})}
        (tmp / "config.json").write_text(json.dumps(cfg, indent=1))
        torch.save({k: v.detach().cpu() for k, v in model.state_dict().items()}, tmp / "model.pt")
        if training is not None:
            torch.save(training, tmp / "training.pt")
        files = sorted(p.name for p in tmp.iterdir())
        (tmp / "manifest.json").write_text(json.dumps({n: _sha256(tmp / n) for n in files}, indent=1))
        old = path.parent / f".{path.name}.old-{os.getpid()}"
        if path.exists():
            os.replace(path, old)
        os.replace(tmp, path)
        if old.exists():
            shutil.rmtree(old)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return path


def _read_checkpoint(path) -> tuple[Path, dict]:
    path = Path(path)
    if not path.is_dir():
        raise CheckpointError(f"no checkpoint folder at {path}")
    for name in ("config.json", "model.pt", "manifest.json"):
        if not (path / name).is_file():
            raise CheckpointError(f"{path} is not a complete checkpoint: {name} is missing")
    try:
        manifest = json.loads((path / "manifest.json").read_text())
        cfg = json.loads((path / "config.json").read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CheckpointError(f"{path}: unreadable JSON ({e}); the checkpoint is corrupt") from None
    for name, digest in manifest.items():
        f = path / name
        if not f.is_file():
            raise CheckpointError(f"{path}: {name} listed in the manifest is missing")
        if _sha256(f) != digest:
            raise CheckpointError(f"{path}: {name} is corrupt (its checksum does not match the manifest)")
    if cfg.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not a gnwarp model checkpoint (format {cfg.get('format')!r})")
    if int(cfg.get("version", -1)) > VERSION:
        raise CheckpointError(f"{path} has checkpoint version {cfg.get('version')}, newer than this gnwarp ({VERSION})")
    return path, cfg


def load_model(path, device=None, backend: str | None = None, dtype: torch.dtype | None = None) -> ForwardModel:
    """Restore a ``ForwardModel`` from a checkpoint folder (``<run>/best``, ``<run>/last``, ...).

    ``device``: where to put it (default: CUDA when present, else CPU). ``backend``: override the
    GN backend ("warp" or "torch"). Raises ``CheckpointError`` for a missing or corrupt checkpoint.
    The model is unbound: ``model.bind(dataset_or_system)`` before ``rollout``.
    """
    path, cfg = _read_checkpoint(path)
    try:
        mcfg = ModelConfig.from_dict(cfg["model"])
        layout = FeatureLayout.from_dict(cfg["layout"])
    except (KeyError, TypeError, ValueError) as e:
        raise CheckpointError(f"{path}: config.json does not describe a model ({type(e).__name__}: {e})") from None
    if backend is not None and mcfg.core == "gn":
        mcfg.gn.backend = backend
    model = ForwardModel(mcfg, layout)
    try:
        state = torch.load(path / "model.pt", map_location="cpu", weights_only=True)
        model.load_state_dict(state)
    except Exception as e:  # noqa: BLE001 - any failure to read the weights is a corrupt checkpoint
        raise CheckpointError(f"{path}: cannot load the weights ({type(e).__name__}: {e})") from None
    dev = resolve_device("auto") if device is None else torch.device(device)
    model.to(dev)
    if dtype is not None:
        model.to(dtype)
    model.checkpoint_info = cfg
    return model


def load_checkpoint(path, device=None) -> tuple[ForwardModel, dict | None, dict]:
    """(model, training state or None, config.json) of a checkpoint, for resuming."""
    model = load_model(path, device)
    p = Path(path) / "training.pt"
    training = None
    if p.is_file():
        try:
            training = torch.load(p, map_location="cpu", weights_only=False)
        except Exception as e:  # noqa: BLE001
            raise CheckpointError(f"{path}: cannot read training.pt ({type(e).__name__}: {e})") from None
    return model, training, model.checkpoint_info


# -- data on the device ---------------------------------------------------------------------

class _TrainData:
    """A dataset's train split on the device, its graph builder in the model's layout, and a sampler."""

    def __init__(self, ds, model: ForwardModel, device, dtype):
        sp = ds["train"]
        if len(sp) == 0 or sp.num_steps == 0:
            raise ValueError(f"dataset {ds.system!r} has an empty train split")
        self.name = ds.system
        self.body = torch.as_tensor(np.asarray(sp.body[...]), device=device, dtype=dtype)
        self.ctrl = torch.as_tensor(np.asarray(sp.ctrl[...]), device=device, dtype=dtype)
        self.instance = torch.as_tensor(np.asarray(sp.instance[...]), device=device, dtype=torch.int64)
        self.builder = model.graph_builder(ds)
        self.S, self.T = self.body.shape[0], self.ctrl.shape[1]

    def sample(self, n: int, gen: torch.Generator):
        """(graph, target next states [sum(n_node), 13]) of n uniform (sequence, step) pairs."""
        dev = self.body.device
        seq = torch.randint(self.S, (n,), generator=gen, device=dev)
        t = torch.randint(self.T, (n,), generator=gen, device=dev)
        inst = self.instance[seq]
        g = self.builder(inst, self.body[seq, t], self.ctrl[seq, t])
        nxt = self.body[seq, t + 1]
        b = self.builder
        target = nxt.reshape(-1, DYN_NODE_SIZE) if b.uniform else nxt[b.node_mask[inst]]
        return g, target


def _sample(parts: list[_TrainData], batch_size: int, gen: torch.Generator):
    from gnwarp.graphs import batch
    k = len(parts)
    sizes = [batch_size // k + (1 if i < batch_size % k else 0) for i in range(k)]
    got = [p.sample(n, gen) for p, n in zip(parts, sizes) if n > 0]
    if len(got) == 1:
        return got[0]
    return batch([g for g, _ in got]), torch.cat([t for _, t in got], 0)


def _load_datasets(config: TrainConfig, datasets):
    from gnwarp.data.dataset import load
    if datasets is not None:
        return list(datasets)
    if not config.data:
        raise ValueError("no training data: set `data` to one or more dataset files")
    return [load(p, lazy=True) for p in config.data]


def _build_model(config: TrainConfig, datasets) -> ForwardModel:
    mcfg = dataclasses.replace(config.model)
    layout = merge_layouts([d.layout for d in datasets])
    if mcfg.recenter is None:  # D.4: re-centre single-system models of translation-invariant systems
        mcfg.recenter = len(datasets) == 1 and bool(datasets[0].meta.get("translation_invariant", False))
    if mcfg.core == "mlp":
        B = {int(d.meta["max_bodies"]) for d in datasets}
        E = {int(d.meta["max_edges"]) for d in datasets}
        uniform = all(np.all(np.asarray(d.static["n_node"]) == d.meta["max_bodies"]) for d in datasets)
        if len(B) > 1 or len(E) > 1 or not uniform:
            raise ValueError("the MLP baseline needs one fixed topology; these datasets mix graph sizes")
        mcfg.mlp = dataclasses.replace(mcfg.mlp, n_node=B.pop(), n_edge=E.pop())
    return ForwardModel(mcfg, layout)


def _data_info(datasets) -> list[dict]:
    keys = ("system", "parameterized", "dt", "num_steps", "seed", "splits", "translation_invariant")
    return [{k: d.meta.get(k) for k in keys} for d in datasets]


# -- the loop -----------------------------------------------------------------------------------

_LOG_FIELDS = ("step", "seconds", "lr", "loss", "pos", "quat", "linvel", "angvel", "valid_error")


def train(config: TrainConfig, datasets=None, model: ForwardModel | None = None) -> dict:
    """Train (or resume) a forward model; returns a summary dict (paths, steps, best error, timing).

    ``datasets``: ``Dataset`` objects to use instead of loading ``config.data``.
    ``model``: an initial model (else built from ``config.model``, or resumed from ``<out>/last``).
    """
    from tqdm.auto import tqdm

    from gnwarp.eval.metrics import rollout_error

    out = Path(config.out)
    device = resolve_device(config.device)
    dtype = getattr(torch, config.dtype)
    torch.manual_seed(config.seed)
    datasets = _load_datasets(config, datasets)

    training = None
    if config.resume and (out / "last").is_dir():
        model, training, _ = load_checkpoint(out / "last", device)
        layout = merge_layouts([d.layout for d in datasets])
        if layout.to_dict() != model.layout.to_dict():
            warnings.warn(f"resuming {out / 'last'}: the datasets' merged layout differs from the model's; "
                          "mapping them onto the model's layout")
    elif model is None:
        model = _build_model(config, datasets)
    model.to(device=device, dtype=dtype)
    parts = [_TrainData(d, model, device, dtype) for d in datasets]
    valid = [d for d in datasets if len(d["valid"]) > 0]

    flat = config.optimizer == "flat_adam"
    if flat:  # clipping inside the step, gradients in p.main_grad
        opt = FlatAdam(model.parameters(), lr=config.lr, max_grad_norm=config.grad_clip)
    else:
        opt = torch.optim.Adam(model.parameters(), lr=config.lr)
    gen = torch.Generator(device=device)
    gen.manual_seed(config.seed)
    state = {"step": 0, "best_error": math.inf, "best_step": -1, "bad_validations": 0, "seconds": 0.0}
    if training is not None:
        try:
            opt.load_state_dict(training["optimizer"])
        except (ValueError, KeyError) as exc:
            raise CheckpointError(f"{out / 'last'}: its optimizer state does not fit optimizer="
                                  f"{config.optimizer!r} ({exc}); resume with the optimizer the run started with, "
                                  "or set resume=False") from exc
        state.update(training["state"])
        try:
            gen.set_state(training["generator"])
        except (RuntimeError, TypeError):  # resumed on another kind of device: a fresh sampler stream
            warnings.warn("could not restore the batch sampler's random state; reseeding it")
            gen.manual_seed(config.seed + state["step"])
    info = {"train": config.to_dict(), "data": _data_info(datasets)}

    def checkpoint(name: str):
        readable = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in state.items()}
        save_checkpoint(out / name, model, {"optimizer": opt.state_dict(), "state": dict(state),
                                            "generator": gen.get_state()}, {**info, "state": readable})

    def validate() -> float:
        model.eval()
        errs = [rollout_error(model, d, "valid", config.valid_horizon, config.valid_sequences) for d in valid]
        model.train()
        return float(np.mean(errs)) if errs else math.nan

    # normalizer warm-up: statistics from a few batches before the first gradient step, so the
    # first steps do not train against identity transforms
    if state["step"] == 0 and model.norm_nodes.count.item() == 0:
        with torch.no_grad():
            for _ in range(config.normalizer_warmup):
                g, target = _sample(parts, config.batch_size, gen)
                model.loss(g, target, noise_std=config.noise_std, accumulate=True,
                           rotation_scale=config.rotation_loss, generator=gen)

    out.mkdir(parents=True, exist_ok=True)
    log_path = out / "log.csv"
    new_log = not log_path.exists() or state["step"] == 0
    log_file = open(log_path, "w" if new_log else "a", newline="")
    log = csv.DictWriter(log_file, _LOG_FIELDS)
    if new_log:
        log.writeheader()

    start_step = state["step"]
    t_start = time.perf_counter() - state["seconds"]
    bar = tqdm(total=config.steps, initial=start_step, desc=f"train {model.config.core}", unit="step",
               disable=not config.progress, dynamic_ncols=True, smoothing=0.05)
    running: dict[str, torch.Tensor] = {}
    n_running = 0
    model.train()

    def one_step() -> str | None:
        """One optimization step (with logging, validation, checkpoints); a reason to stop or None."""
        nonlocal running, n_running
        step = state["step"]
        lr = config.lr_at(step)
        for group in opt.param_groups:
            group["lr"] = lr
        g, target = _sample(parts, config.batch_size, gen)
        terms = model.loss(g, target, noise_std=config.noise_std, accumulate=True,
                           rotation_scale=config.rotation_loss, generator=gen)
        opt.zero_grad(set_to_none=True)
        terms["loss"].backward()
        if not flat:
            torch.nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip)
        opt.step()
        for k, v in terms.items():  # summed on the device; read once per log line
            running[k] = running.get(k, 0.0) + v.detach()
        n_running += 1
        state["step"] = step = step + 1
        state["seconds"] = time.perf_counter() - t_start
        bar.update(1)

        row = None
        if step % config.log_every == 0 or step == config.steps:
            vals = {k: float(v) / n_running for k, v in running.items()}
            if not all(math.isfinite(v) for v in vals.values()):
                raise FloatingPointError(f"training diverged at step {step}: losses {vals}")
            running, n_running = {}, 0
            row = {"step": step, "seconds": round(state["seconds"], 3), "lr": lr, **vals, "valid_error": ""}
            bar.set_postfix(loss=f"{vals['loss']:.4g}", best=f"{state['best_error']:.4g}")
        timed_out = config.max_seconds is not None and state["seconds"] >= config.max_seconds
        if valid and (step % config.valid_every == 0 or step == config.steps or timed_out):
            err = validate()
            row = row or {"step": step, "seconds": round(state["seconds"], 3), "lr": lr}
            row["valid_error"] = err
            if err < state["best_error"]:
                state.update(best_error=err, best_step=step, bad_validations=0)
                checkpoint("best")
            else:
                state["bad_validations"] += 1
            bar.set_postfix(loss=row.get("loss", ""), valid=f"{err:.4g}", best=f"{state['best_error']:.4g}")
        if row is not None:
            log.writerow(row)
            log_file.flush()
        if step % config.checkpoint_every == 0:
            checkpoint("last")
        if config.patience is not None and state["bad_validations"] >= config.patience:
            return "early stopping"
        return "time budget" if timed_out else None

    try:
        while state["step"] < config.steps:
            stop_reason = one_step()
            if stop_reason:
                break
        else:
            stop_reason = "steps"
    except KeyboardInterrupt:  # keep what was learned; training resumes from <out>/last
        stop_reason = "interrupted"
    finally:
        bar.close()
        log_file.close()
    checkpoint("last")
    if not (out / "best").is_dir():  # no validation split: the last model is the best we know
        checkpoint("best")
    steps_run = state["step"] - start_step
    return {"out": str(out), "best": str(out / "best"), "last": str(out / "last"), "steps": state["step"],
            "best_step": state["best_step"], "best_error": state["best_error"], "stop": stop_reason,
            "seconds": state["seconds"], "steps_per_second": steps_run / max(state["seconds"], 1e-9)}
