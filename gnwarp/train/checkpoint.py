"""The checkpoint format of a forward model, and loading a model from it.

A checkpoint is a self-describing folder, written to a temporary folder and renamed into place::

    config.json    format, version, ModelConfig (run options included), FeatureLayout, the
                   training config and data
    model.pt       state dict: weights and normalizer accumulators (count, sum, squared sum)
    training.pt    optimizer state, step, best validation error, sampler state (optional)
    manifest.json  sha256 of each file above (checked on load)

``load_model(path)`` restores a model from it without any of the training code's state.
"""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import torch

from gnwarp.data.layout import FeatureLayout
from gnwarp.files import sha256_file
from gnwarp.gn.options import RunOptions, check_option_names
from gnwarp.interop import resolve_device
from gnwarp.models.config import ModelConfig
from gnwarp.models.forward import ForwardModel

__all__ = ["FORMAT", "VERSION", "CheckpointError", "save_checkpoint", "load_model", "load_checkpoint"]

FORMAT, VERSION = "gnwarp-model", 1


class CheckpointError(ValueError):
    """A checkpoint folder that is missing, incomplete, corrupt or of another format."""


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
        (tmp / "manifest.json").write_text(json.dumps({n: sha256_file(tmp / n) for n in files}, indent=1))
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
        if sha256_file(f) != digest:
            raise CheckpointError(f"{path}: {name} is corrupt (its checksum does not match the manifest)")
    if cfg.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not a gnwarp model checkpoint (format {cfg.get('format')!r})")
    if int(cfg.get("version", -1)) > VERSION:
        raise CheckpointError(f"{path} has checkpoint version {cfg.get('version')}, newer than this gnwarp ({VERSION})")
    return path, cfg


def load_model(path, device=None, *, options: RunOptions | None = None, **option_changes) -> ForwardModel:
    """Restore a ``ForwardModel`` from a checkpoint folder (``<run>/best``, ``<run>/last``, ...).

    ``device``: where to put it (default: CUDA when present, else CPU). How it runs is the run
    options it was saved with, replaced by ``options`` and then by ``option_changes`` (fields of
    ``RunOptions``: ``precision="tf32"``, ``impl="torch"``, ...); the weights are the same
    whatever the options ("fp64" casts them to float64). Raises ``CheckpointError`` for a
    missing or corrupt checkpoint, ``ValueError`` / ``TypeError`` for unknown options. The model
    is unbound: ``model.bind(dataset_or_system)`` before ``rollout``.
    """
    path, cfg = _read_checkpoint(path)
    try:
        mcfg = ModelConfig.from_dict(cfg["model"])
        layout = FeatureLayout.from_dict(cfg["layout"])
    except (KeyError, TypeError, ValueError) as e:
        raise CheckpointError(f"{path}: config.json does not describe a model ({type(e).__name__}: {e})") from None
    check_option_names(option_changes, "load_model")
    mcfg.run = (options if options is not None else mcfg.run).replace(**option_changes)
    model = ForwardModel(mcfg, layout)
    try:
        state = torch.load(path / "model.pt", map_location="cpu", weights_only=True)
        model.load_state_dict(state)
    except Exception as e:  # noqa: BLE001 - any failure to read the weights is a corrupt checkpoint
        raise CheckpointError(f"{path}: cannot load the weights ({type(e).__name__}: {e})") from None
    model.to(resolve_device(device))
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
