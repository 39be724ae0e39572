"""The checkpoint format of a forward model, and loading a model from it.

A checkpoint is a self-describing folder, written to a temporary folder and renamed into place::

    config.json    format, version, ModelConfig (run options included), FeatureLayout, the
                   training config and data
    model.pt       state dict: weights and normalizer accumulators (count, sum, squared sum)
    training.pt    optimizer state, step, best validation error, sampler state (optional)
    manifest.json  sha256 of each file above (checked on load; it must cover every file)

Loading never runs code: both ``.pt`` files hold only tensors and plain values (dicts, lists,
tuples, numbers, strings) and are read with ``torch.load(weights_only=True)``; a file that needs
more (a pickle payload, or an earlier format's objects) is refused with ``CheckpointError``.
Weights must be finite, and a config asking for an absurd model is refused before allocating.

``load_model(path)`` restores a model from it without any of the training code's state;
``check_checkpoint(path)`` validates a folder and lists its findings. A process killed while
replacing a checkpoint leaves ``.<name>.tmp-<pid>`` / ``.<name>.old-<pid>`` folders beside it;
``recover_checkpoint`` puts the newest intact one back in place and ``clean_debris`` removes
the rest (the ``Trainer`` runs both before resuming).
"""
from __future__ import annotations

import json
import math
import os
import pickle
import re
import shutil
import warnings
from pathlib import Path

import torch

from gnwarp.data.layout import FeatureLayout
from gnwarp.files import atomic_write, pid_alive, plain_values, sha256_file
from gnwarp.gn.options import RunOptions, check_option_names
from gnwarp.interop import resolve_device
from gnwarp.models.config import ModelConfig, check_model_size
from gnwarp.models.forward import ForwardModel, input_sizes
from gnwarp.version import __version__

__all__ = ["FORMAT", "VERSION", "CheckpointError", "CheckpointWriter", "save_checkpoint", "snapshot", "load_model",
           "load_checkpoint", "check_checkpoint", "checkpoint_config", "recover_checkpoint", "clean_debris", "model_config_changes",
           "read_checkpoint", "load_weights", "load_training", "training_env_steps"]

FORMAT, VERSION = "gnwarp-model", 1
MANIFEST = "manifest.json"
_DEBRIS = re.compile(r"^\.(?P<name>.+)\.(?P<kind>tmp|old)-(?P<pid>\d+)$")


class CheckpointError(ValueError):
    """A checkpoint folder that is missing, incomplete, corrupt, unsafe or of another format."""


# -- writing -----------------------------------------------------------------------------------
def save_checkpoint(path, model: ForwardModel, training: dict | None = None, info: dict | None = None) -> Path:
    """Write ``model`` (and optional training state: tensors and plain values only) as a
    checkpoint folder at ``path``, atomically: into a temporary folder beside it, then renamed
    over any previous one (a kill between the two renames is undone by ``recover_checkpoint``)."""
    return _write(Path(path), snapshot(model, training, info))


def snapshot(model: ForwardModel, training: dict | None = None, info: dict | None = None) -> dict:
    """What ``save_checkpoint`` writes, copied now: config text and every tensor on the CPU (copies,
    so that training on may go on while another thread writes them, ``CheckpointWriter``)."""
    if training is not None:
        training = _cpu_copy(plain_values(training, "training"))
    cfg = {"format": FORMAT, "version": VERSION, "gnwarp_version": __version__, "model": model.config.to_dict()}
    if getattr(model, "layout", None) is not None:  # models of observation graphs have input sizes instead
        cfg["layout"] = model.layout.to_dict()
    cfg.update(info or {})
    return {"config": json.dumps(cfg, indent=1), "training": training,
            "model": {k: v.detach().to("cpu", copy=True) for k, v in model.state_dict().items()}}


def _cpu_copy(x):
    if isinstance(x, torch.Tensor):
        return x.to("cpu", copy=True)
    if isinstance(x, dict):
        return {k: _cpu_copy(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return type(x)(_cpu_copy(v) for v in x)
    return x


def _write(path: Path, snap: dict) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path, folder=True) as tmp:
        (tmp / "config.json").write_text(snap["config"])
        torch.save(snap["model"], tmp / "model.pt")
        if snap["training"] is not None:
            torch.save(snap["training"], tmp / "training.pt")
        files = sorted(p.name for p in tmp.iterdir())
        (tmp / MANIFEST).write_text(json.dumps({n: sha256_file(tmp / n) for n in files}, indent=1))
    return path


class CheckpointWriter:
    """Checkpoints written by one background thread, in the order submitted, so that training
    does not wait on the disk: ``submit`` copies the state to the CPU at once (a consistent
    snapshot of that step) and returns; ``done()`` gives the (name, path) of the writes finished
    since the last call and re-raises a write's error; ``wait()`` waits for all of them first.
    Each write is atomic, as ``save_checkpoint``'s."""

    def __init__(self):
        from concurrent.futures import ThreadPoolExecutor
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="gnwarp-checkpoint")
        self._jobs: list = []

    def submit(self, name: str, path, model: ForwardModel, training: dict | None = None,
               info: dict | None = None) -> None:
        snap = snapshot(model, training, info)
        self._jobs.append((name, self._pool.submit(_write, Path(path), snap)))

    def done(self, wait: bool = False) -> list[tuple[str, Path]]:
        out = []
        while self._jobs and (wait or self._jobs[0][1].done()):
            name, fut = self._jobs.pop(0)
            out.append((name, fut.result()))   # a failed write raises here, in the caller's thread
        return out

    def wait(self) -> list[tuple[str, Path]]:
        return self.done(wait=True)

    def close(self) -> None:
        try:
            self.wait()
        finally:
            self._pool.shutdown(wait=True)


# -- reading -----------------------------------------------------------------------------------
def read_checkpoint(path) -> tuple[Path, dict]:
    """(path, config.json) of a checkpoint folder whose manifest covers every file and matches it."""
    path = Path(path)
    if not path.is_dir():
        raise CheckpointError(f"no checkpoint folder at {path}")
    for name in ("config.json", "model.pt", MANIFEST):
        if not (path / name).is_file():
            raise CheckpointError(f"{path} is not a complete checkpoint: {name} is missing")
    try:
        manifest = json.loads((path / MANIFEST).read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CheckpointError(f"{path}: unreadable JSON in {MANIFEST} ({e}); the checkpoint is corrupt") from None
    if not isinstance(manifest, dict) or not all(isinstance(k, str) and isinstance(v, str)
                                                 for k, v in manifest.items()):
        raise CheckpointError(f"{path}: {MANIFEST} is not a map of file names to sha256 digests")
    for name in manifest:
        if name in ("", ".", "..", MANIFEST) or "/" in name or "\\" in name:
            raise CheckpointError(f"{path}: {MANIFEST} lists {name!r}, which is not a file of the checkpoint")
    for name in ("config.json", "model.pt"):
        if name not in manifest:
            raise CheckpointError(f"{path}: {MANIFEST} does not cover {name}; the checkpoint is incomplete or "
                                  "was altered")
    extra = sorted(p.name for p in path.iterdir() if p.name != MANIFEST and p.name not in manifest)
    if extra:
        raise CheckpointError(f"{path}: {', '.join(extra)} not covered by {MANIFEST}; the checkpoint was altered "
                              "(a checkpoint folder holds only the files its manifest lists)")
    for name, digest in manifest.items():
        f = path / name
        if not f.is_file():
            raise CheckpointError(f"{path}: {name} listed in the manifest is missing")
        if sha256_file(f) != digest:
            raise CheckpointError(f"{path}: {name} is corrupt (its checksum does not match the manifest)")
    try:
        cfg = json.loads((path / "config.json").read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CheckpointError(f"{path}: unreadable JSON in config.json ({e}); the checkpoint is corrupt") from None
    if not isinstance(cfg, dict) or cfg.get("format") != FORMAT:
        fmt = cfg.get("format") if isinstance(cfg, dict) else None
        raise CheckpointError(f"{path} is not a gnwarp model checkpoint (format {fmt!r})")
    try:
        version = int(cfg.get("version", -1))
    except (TypeError, ValueError):
        raise CheckpointError(f"{path}: config.json has version {cfg.get('version')!r}, not a number") from None
    if version > VERSION:
        raise CheckpointError(f"{path} has checkpoint version {cfg.get('version')}, newer than this gnwarp ({VERSION})")
    return path, cfg


def _model_of(path: Path, cfg: dict) -> tuple[ModelConfig, FeatureLayout]:
    """The model config and layout of config.json, its size checked before anything is allocated."""
    try:
        mcfg = ModelConfig.from_dict(cfg["model"])
        layout = FeatureLayout.from_dict(cfg["layout"])
        sizes = input_sizes(layout)
    except (KeyError, TypeError, ValueError) as e:
        raise CheckpointError(f"{path}: config.json does not describe a model ({type(e).__name__}: {e})") from None
    try:
        check_model_size(mcfg, sizes)
    except ValueError as e:
        raise CheckpointError(f"{path}: config.json asks for an impossible model: {e}") from None
    return mcfg, layout


def _safe_load(path: Path, name: str):
    """``torch.load(weights_only=True)`` of a checkpoint file: tensors and plain values, no code."""
    try:
        return torch.load(path / name, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        if "weights only" in str(e).lower():
            raise CheckpointError(
                f"{path}: {name} holds objects other than tensors and plain values (a pickle payload, or the format "
                "of an earlier gnwarp); it is refused unread, since unpickling it could run code. Only checkpoints "
                "written by this gnwarp load; start a new run (resume=False), or re-save the model from a trusted "
                "source") from None
        raise CheckpointError(f"{path}: cannot read {name} (UnpicklingError: {e})") from None
    except Exception as e:  # noqa: BLE001 - any failure to read the file is a corrupt checkpoint
        raise CheckpointError(f"{path}: cannot read {name} ({type(e).__name__}: {e})") from None


def _nonfinite(tensors: dict, prefix: str = "") -> list[str]:
    """Names of the floating tensors in a (nested) dict / list holding NaN or Inf."""
    bad = []
    items = tensors.items() if isinstance(tensors, dict) else enumerate(tensors)
    for k, v in items:
        name = f"{prefix}{k}"
        if isinstance(v, torch.Tensor):
            if (v.is_floating_point() or v.is_complex()) and not bool(torch.isfinite(v).all()):
                bad.append(name)
        elif isinstance(v, (dict, list, tuple)):
            bad += _nonfinite(v, name + ".")
        elif isinstance(v, float) and math.isnan(v):
            bad.append(name)
    return bad


def load_weights(path: Path) -> dict[str, torch.Tensor]:
    """The state dict in a checkpoint folder's model.pt, read without running code (tensors only)."""
    state = _safe_load(path, "model.pt")
    if not isinstance(state, dict) or not all(isinstance(k, str) and isinstance(v, torch.Tensor)
                                              for k, v in state.items()):
        raise CheckpointError(f"{path}: model.pt is not a state dict (names to tensors)")
    bad = _nonfinite(state)
    if bad:
        raise CheckpointError(f"{path}: model.pt has NaN or Inf in {', '.join(bad[:5])}"
                              f"{f' and {len(bad) - 5} more tensors' if len(bad) > 5 else ''}")
    return state


def _load_training(path: Path) -> dict:
    t = _safe_load(path, "training.pt")
    if not isinstance(t, dict):
        raise CheckpointError(f"{path}: training.pt is not a training state (a dict)")
    for key, kind in (("optimizer", dict), ("state", dict), ("generator", torch.Tensor), ("average", dict)):
        if key in t and not isinstance(t[key], kind):
            raise CheckpointError(f"{path}: training.pt's {key!r} is a {type(t[key]).__name__}, not a {kind.__name__}")
    state = t.get("state", {})
    if not all(isinstance(v, (int, float, type(None))) for v in state.values()):
        raise CheckpointError(f"{path}: training.pt's run state holds values other than numbers: {state}")
    bad = _nonfinite(t.get("optimizer", {}), "optimizer.")
    if bad:
        raise CheckpointError(f"{path}: training.pt has NaN or Inf in {', '.join(bad[:5])}")
    return t


def load_model(path, device=None, *, options: RunOptions | None = None, **option_changes) -> ForwardModel:
    """Restore a ``ForwardModel`` from a checkpoint folder (``<run>/best``, ``<run>/last``, ...).

    ``device``: where to put it (default: CUDA when present, else CPU). How it runs is the run
    options it was saved with, replaced by ``options`` and then by ``option_changes`` (fields of
    ``RunOptions``: ``precision="tf32"``, ``impl="torch"``, ...); the weights are the same
    whatever the options ("fp64" casts them to float64). Raises ``CheckpointError`` for a
    missing, corrupt or unsafe checkpoint (weights read with ``weights_only=True``, checked
    finite), ``ValueError`` / ``TypeError`` for unknown options. A folder a killed save left
    missing is first restored from what it left beside it (``recover_checkpoint``). The model
    is unbound: ``model.bind(dataset_or_system)`` before ``rollout``.
    """
    path = Path(path)
    if not path.exists():
        recover_checkpoint(path)
    path, cfg = read_checkpoint(path)
    mcfg, layout = _model_of(path, cfg)
    check_option_names(option_changes, "load_model")
    state = load_weights(path)
    mcfg.run = (options if options is not None else mcfg.run).replace(**option_changes)
    model = ForwardModel(mcfg, layout)
    try:
        model.load_state_dict(state)
    except Exception as e:  # noqa: BLE001 - weights of another architecture
        raise CheckpointError(f"{path}: cannot load the weights ({type(e).__name__}: {e})") from None
    model.to(resolve_device(device))
    model.checkpoint_info = cfg
    return model


def load_checkpoint(path, device=None) -> tuple[ForwardModel, dict | None, dict]:
    """(model, training state or None, config.json) of a checkpoint, for resuming. The training
    state is read with ``weights_only=True``: tensors and plain values, never code."""
    model = load_model(path, device)
    return model, load_training(path), model.checkpoint_info


def load_training(path) -> dict | None:
    """The training state of a checkpoint folder (optimizer, run state, sampler), or None when it
    has none; read with ``weights_only=True`` and checked (``CheckpointError``)."""
    path = Path(path)
    return _load_training(path) if (path / "training.pt").is_file() else None


# -- checking ----------------------------------------------------------------------------------
def check_checkpoint(path) -> list[str]:
    """Validate a checkpoint folder fully: manifest (covering every file) and checksums, config
    format and model sizes, weights (loaded safely, finite, fitting the model) and training
    state (loaded safely). Returns findings, one line each, starting "ok: " or "error: "; raises
    nothing (the ``gnwarp check`` command prints them)."""
    out: list[str] = []
    p = Path(path)
    try:
        p, cfg = read_checkpoint(p)
        names = sorted(json.loads((p / MANIFEST).read_text()))
        out.append(f"ok: {MANIFEST} covers every file ({', '.join(names)}); checksums match")
        out.append(f"ok: format {cfg['format']} version {cfg.get('version')} (written by gnwarp "
                   f"{cfg.get('gnwarp_version', '?')})")
        mcfg, layout = _model_of(p, cfg)
        n = check_model_size(mcfg, input_sizes(layout))
        core = (f"gn latent {mcfg.gn.latent}" if mcfg.core == "gn" else f"mlp {mcfg.mlp.layers}x{mcfg.mlp.width}")
        out.append(f"ok: model config: core {core}, {n} weight elements; run options {mcfg.run.to_dict()}")
    except Exception as e:  # noqa: BLE001 - later checks need these
        return out + [f"error: {e}"]
    try:
        state = load_weights(p)
        model = ForwardModel(mcfg, layout)
        model.load_state_dict(state)
        out.append(f"ok: model.pt: {len(state)} tensors, all finite, loaded with weights_only=True, fit the model")
    except CheckpointError as e:
        out.append(f"error: {e}")
    except Exception as e:  # noqa: BLE001
        out.append(f"error: {p}: model.pt does not fit the model its config describes ({type(e).__name__}: {e})")
    if (p / "training.pt").is_file():
        try:
            t = _load_training(p)
            st = t.get("state", {})
            out.append(f"ok: training.pt: loaded with weights_only=True; step {st.get('step')}, best error "
                       f"{st.get('best_error')} at step {st.get('best_step')}")
        except Exception as e:  # noqa: BLE001
            out.append(f"error: {e}")
    else:
        out.append("ok: no training.pt (a model-only checkpoint: loads, cannot resume training)")
    return out


# -- resuming ----------------------------------------------------------------------------------
def _flat(d, prefix: str = "") -> dict:
    if not isinstance(d, dict):
        return {prefix[:-1]: d}
    out = {}
    for k, v in d.items():
        out.update(_flat(v, f"{prefix}{k}."))
    return out


def model_config_changes(saved: ModelConfig | dict, wanted: ModelConfig | dict) -> list[str]:
    """What differs between a checkpoint's model config and the one a run asks for, apart from
    the run options (which may change on resume) and what ``wanted`` leaves to be decided from
    the data (``recenter`` None, the MLP's ``n_node`` / ``n_edge`` 0): lines
    "model.gn.latent: 16 -> 32"."""
    a = saved.to_dict() if isinstance(saved, ModelConfig) else ModelConfig.from_dict(saved).to_dict()
    b = wanted.to_dict() if isinstance(wanted, ModelConfig) else ModelConfig.from_dict(wanted).to_dict()
    a, b = (_flat({k: v for k, v in d.items() if k != "run"}, "model.") for d in (a, b))
    if a.get("model.core") != b.get("model.core"):  # another core: its sizes do not compare
        return [f"model.core: {a.get('model.core')!r} -> {b.get('model.core')!r}"]
    core = "model.gn." if a.get("model.core") == "gn" else "model.mlp."
    keys = [k for k in sorted(set(a) | set(b)) if not k.startswith(("model.gn.", "model.mlp.")) or k.startswith(core)]
    undecided = {"model.recenter": None, "model.mlp.n_node": 0, "model.mlp.n_edge": 0}
    norm = lambda v: list(v) if isinstance(v, tuple) else v  # noqa: E731
    return [f"{k}: {a.get(k)!r} -> {b.get(k)!r}" for k in keys
            if norm(a.get(k)) != norm(b.get(k)) and not (k in undecided and b.get(k) == undecided[k])]


def checkpoint_config(path) -> dict:
    """The config.json of a checkpoint folder, after checking its manifest (``CheckpointError``)."""
    return read_checkpoint(path)[1]


def training_env_steps(path) -> int | None:
    """Simulator control steps in the training splits of the datasets a checkpoint names (the
    ``env_steps`` of a results record): the sum over its datasets of train sequences x steps;
    None when its config does not say."""
    try:
        data = checkpoint_config(path).get("data") or []
        return int(sum(d["splits"]["train"] * d["num_steps"] for d in data)) or None
    except (KeyError, TypeError, ValueError, OSError):
        return None


def _debris(folder: Path, name: str | None = None) -> list[tuple[Path, str, str, int]]:
    """(path, name, kind, pid) of the temporary folders of checkpoint saves in ``folder``."""
    if not folder.is_dir():
        return []
    got = []
    for p in folder.iterdir():
        m = _DEBRIS.match(p.name)
        if m and (name is None or m["name"] == name):
            got.append((p, m["name"], m["kind"], int(m["pid"])))
    return got


def _step_of(path: Path) -> int | None:
    """The training step of an intact checkpoint (-1 without one), None if it is not intact."""
    try:
        _, cfg = read_checkpoint(path)
    except CheckpointError:
        return None
    st = cfg.get("state")
    step = st.get("step") if isinstance(st, dict) else None
    return int(step) if isinstance(step, int) else -1


def recover_checkpoint(path, fallbacks=()) -> Path | None:
    """If the checkpoint folder ``path`` is missing, put back the newest intact one that a killed
    save left beside it (``.<name>.old-<pid>``: the previous one, moved aside; ``.<name>.tmp-<pid>``:
    a complete new one not yet renamed; only of processes no longer running), or else a copy of
    the newest intact folder of ``fallbacks`` (e.g. ``<run>/best`` for ``<run>/last``). Returns
    where it came from, or None (nothing to do, or nothing intact). Intact: a manifest that
    covers every file and matches it."""
    path = Path(path)
    if path.exists():
        return None
    found = [(s, 1, p) for p, _, _, pid in _debris(path.parent, path.name)
             if not pid_alive(pid) and (s := _step_of(p)) is not None]
    found += [(s, 0, Path(f)) for f in fallbacks if Path(f).is_dir() and (s := _step_of(Path(f))) is not None]
    if not found:
        return None
    _, moved, src = max(found, key=lambda x: (x[0], x[1], x[2].stat().st_mtime))
    if moved:
        os.replace(src, path)
    else:
        with atomic_write(path, folder=True) as tmp:
            tmp.rmdir()
            shutil.copytree(src, tmp)
    warnings.warn(f"restored {path} from {src.name}, left by a run killed while saving it", stacklevel=2)
    return src


def clean_debris(folder, names=None) -> list[Path]:
    """Remove the temporary folders (``.<name>.tmp-<pid>``, ``.<name>.old-<pid>``; or files of
    that name) that killed saves left in ``folder``: those of processes no longer running that
    are incomplete or whose ``<name>`` exists (run ``recover_checkpoint`` first), of the names
    ``names`` (None: any). Returns what was removed."""
    removed = []
    for p, name, _, pid in _debris(Path(folder)):
        if (names is None or name in names) and not pid_alive(pid) and (
                (Path(folder) / name).exists() or _step_of(p) is None):
            if p.is_dir():
                shutil.rmtree(p, ignore_errors=True)
            else:
                p.unlink(missing_ok=True)
            removed.append(p)
    return removed
