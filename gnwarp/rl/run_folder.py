"""A training run's folder and true simulator (``gnwarp.rl.run.run_rl``'s first step): the
folder made and its saved config compared with the call's (only ``RESUMABLE`` keys may change
on resume), records that starting over would lose refused, and ``backend`` "auto" resolved and
saved, so that a run keeps the simulator it started on."""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

from gnwarp.eval.records import RecordError, read_records
from gnwarp.files import atomic_write
from gnwarp.interop import cuda_available
from gnwarp.rl.config import CONFIG_FILE, RESUMABLE, RLConfig
from gnwarp.rl.run_log import AGENT_FILE, CHECKPOINT, RECORDS_FILE
from gnwarp.sim.common import BACKENDS, resolve_backend
from gnwarp.validation import ConfigError

__all__ = ["prepare_folder", "run_backend", "SIMULATORS"]


def run_backend(cfg: RLConfig) -> str:
    """The true simulator of ``cfg``: its ``backend``, or for "auto" MuJoCo C where Warp sees no
    CUDA device (``gnwarp.sim.common.resolve_backend``), or where the run acts ahead (its CPU steps the envs while the GPU updates: 1483 env steps a
    second against 795 on MuJoCo-Warp, SVG(1) on swimmer6, one H200, ``bench/rl_loop.py``), and
    MuJoCo-Warp otherwise. ``run_rl`` saves the choice in the run's config, so a run keeps its
    simulator on resume."""
    if cfg.backend != "auto":
        return cfg.backend
    return "mujoco" if cfg.act_ahead else resolve_backend("auto")


SIMULATORS = tuple(b for b in BACKENDS if b != "auto")   # the true simulators a run names


def _legacy_backend(out: Path) -> str:
    """The simulator of a run saved with "auto" before runs saved their choice: the one its
    records in ``out`` name (MuJoCo-Warp on Warp's CPU device where no CUDA is now), else what
    "auto" meant then (MuJoCo-Warp where CUDA is, else MuJoCo C)."""
    try:
        recs = read_records(out / RECORDS_FILE) if (out / RECORDS_FILE).is_file() else []
    except RecordError:
        recs = []
    if recs and recs[-1].dynamics == "true_mujoco_c":
        return "mujoco"
    if recs and recs[-1].dynamics == "true_mjwarp":
        return "mujoco_warp" if cuda_available() else "mujoco_warp_cpu"
    return resolve_backend("auto")


def prepare_folder(cfg: RLConfig) -> tuple[Path, bool, RLConfig]:
    """Make ``cfg.out``; compare a saved config with ``cfg`` (only ``RESUMABLE`` keys may
    differ; a key added since the run was saved counts as its default there; ``backend`` "auto"
    takes the saved run's) and save ``cfg`` with its ``backend`` resolved (``run_backend``; a run
    saved with "auto" before runs recorded their choice: MuJoCo-Warp where CUDA is, as then).
    Returns (folder, whether a checkpoint is there to resume, ``cfg`` so resolved)."""
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    resume = (out / CHECKPOINT).is_file()
    if not resume and (out / AGENT_FILE).is_file():
        raise ConfigError("out", f"{out} holds an exported agent ({AGENT_FILE}), which cannot resume training; "
                                 "train in another folder")
    saved = out / CONFIG_FILE
    if not resume:
        _refuse_orphans(out)
    if resume and not saved.is_file() and cfg.backend == "auto":
        raise ConfigError("backend", f"the run in {out} has no {CONFIG_FILE} to tell which simulator it trained "
                                     "on: name it (mujoco, mujoco_warp or mujoco_warp_cpu; its records' "
                                     "dynamics say which)")
    if resume and saved.is_file():   # (without a checkpoint and records, nothing of an earlier start is lost)
        try:
            old = json.loads(saved.read_text())
            if not isinstance(old, dict):
                raise ValueError("not a JSON object")
        except (ValueError, UnicodeDecodeError) as e:
            raise ConfigError("out", f"{saved} is not a run's config ({e}); train in another folder or remove "
                                     "it") from None
        new = json.loads(json.dumps(cfg.to_dict()))
        defaults = json.loads(json.dumps(RLConfig().to_dict()))
        old = {**{k: defaults[k] for k in set(new) - set(old) if k in defaults}, **old}
        if old.get("backend") == "auto":   # saved before "auto" was resolved: the simulator it ran
            old["backend"] = _legacy_backend(out)
        if cfg.backend == "auto" and old.get("backend") in SIMULATORS:
            cfg = replace(cfg, backend=old["backend"])   # the run's own simulator
            new["backend"] = cfg.backend
        diff = sorted(k for k in set(old) | set(new) if k not in RESUMABLE and k != "out" and old.get(k) != new.get(k))
        if diff:
            raise ConfigError(diff[0], f"differs from the run in {out} ({old.get(diff[0])!r} there, "
                                       f"{new.get(diff[0])!r} here); only {', '.join(RESUMABLE)} may change "
                                       "when resuming (or use another folder)")
    if cfg.backend == "auto":
        cfg = replace(cfg, backend=run_backend(cfg))
    with atomic_write(saved) as tmp:
        Path(tmp).write_text(json.dumps(cfg.to_dict(), indent=1) + "\n")
    return out, resume, cfg


def _refuse_orphans(out: Path) -> None:
    """Refuse a folder with no checkpoint whose ``records.jsonl`` starting over would lose: records
    that are not an RL run's, or evaluations past the first (env steps > 0: the run trained, and
    its checkpoint is gone). The first evaluation (step 0) precedes the first checkpoint; a run
    killed between the two starts over."""
    path = out / RECORDS_FILE
    if not path.is_file():
        return
    try:
        recs = read_records(path)
    except (RecordError, OSError) as e:
        raise ConfigError("out", f"{out} holds a {RECORDS_FILE} that is not a run's records ({e}); train in "
                                 "another folder") from None
    foreign = [r for r in recs if r.experiment != "rl"]
    if foreign:
        raise ConfigError("out", f"{out} holds {RECORDS_FILE} of experiment {foreign[0].experiment!r}, not of a "
                                 "gnwarp rl run; train in another folder")
    trained = max((r.env_steps or 0 for r in recs), default=0)
    if trained > 0:
        raise ConfigError("out", f"{out} holds a run's evaluations up to {trained} env steps but no {CHECKPOINT} "
                                 f"to resume from (it was removed or lost): starting over would drop them. Train "
                                 f"in another folder, or move {RECORDS_FILE} away to start this one over")
