"""The data loop's folder: its state file, its dataset shards and its records.

A loop folder (``gnwarp.control.data_loop``) holds::

    config.json            the ``LoopConfig`` it runs
    state.json             what is finished: iterations, env steps, shards (``LoopState``)
    data/seed.h5           the random-control seed data (a ``gnwarp generate`` dataset)
    data/iter-0001.h5 ...  the transitions each iteration's episodes visited (train split), one
                           dataset file per iteration, its meta["loop"] the iteration's returns
                           and the model's errors on them before training
    models/iter-0001 ...   the checkpoint each iteration planned with (ensemble member k > 0:
                           models/iter-0001-m<k>)
    model/                 the training run (``Trainer``: last, best, log.csv); model-<k>/:
                           ensemble member k's
    value/iter-0002.pt ... the learned terminal value each iteration planned with (where the
                           loop has one; ``gnwarp.control.loop_value``)
    records.jsonl          one results record per iteration (``gnwarp.eval.records``)

Every file is written whole or not at all (a temporary renamed into place), so a kill at any
point leaves the folder at its last finished step. Episodes of E steps are stored as E / L
sequences of the seed data's L steps each, so every shard shares the seed data's layout and the
training data is their concatenation (``concat_train``).
"""
from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import numpy as np

from gnwarp.data.dataset import Dataset, Split
from gnwarp.files import atomic_write

__all__ = ["STATE_FORMAT", "STATE_VERSION", "LoopStateError", "LoopState", "read_state", "write_state",
           "shard_path", "episode_dataset", "concat_train", "subset", "train_env_steps", "write_json",
           "SEED_DATA", "STATE_FILE", "CONFIG_FILE", "RECORDS_FILE"]

STATE_FORMAT, STATE_VERSION = "gnwarp-loop-state", 1
STATE_FILE, CONFIG_FILE, RECORDS_FILE, SEED_DATA = "state.json", "config.json", "records.jsonl", "data/seed.h5"
_SHARD = re.compile(r"^iter-(\d{4,})\.h5$")


class LoopStateError(ValueError):
    """A loop folder whose state file is corrupt, or disagrees with the files beside it."""


@dataclasses.dataclass
class LoopState:
    """What a loop folder has finished. ``iteration``: iterations finished (0: the seed data
    trained on); ``env_steps``: control steps in the training data (seed train split and every
    shard); ``train_steps``: the training run's step count; ``shards``: the iteration shards
    (paths relative to the folder), in order; ``seconds``: wall time spent over all calls;
    ``last_seconds``: the last iteration's wall time (what a time budget expects the next to take)."""
    iteration: int = 0
    env_steps: int = 0
    train_steps: int = 0
    shards: list = dataclasses.field(default_factory=list)
    seconds: float = 0.0
    last_seconds: float | None = None

    def to_dict(self) -> dict:
        return {"format": STATE_FORMAT, "version": STATE_VERSION, **dataclasses.asdict(self)}


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def read_state(folder) -> LoopState | None:
    """The ``LoopState`` of a loop folder (None when it has none yet). ``LoopStateError`` names
    the file and what is wrong: not JSON, another format, a field missing or of the wrong type,
    a shard it lists missing, or shards it does not list."""
    folder = Path(folder)
    path = folder / STATE_FILE
    if not path.exists():
        return None
    fix = (f"; restore it, or move {folder} aside to start afresh (its data files and checkpoints stay "
           "readable by gnwarp train / check)")
    try:
        d = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise LoopStateError(f"{path} is not a valid state file (not JSON: {e}){fix}") from None
    if not isinstance(d, dict) or d.get("format") != STATE_FORMAT:
        what = d.get("format") if isinstance(d, dict) else type(d).__name__
        raise LoopStateError(f"{path} is not a data-loop state file (format {what!r:.60}){fix}")
    if d.get("version") != STATE_VERSION:
        raise LoopStateError(f"{path} has state version {d.get('version')!r}; this gnwarp reads {STATE_VERSION}{fix}")
    names = [f.name for f in dataclasses.fields(LoopState)]
    missing = [k for k in names if k not in d]
    if missing:
        raise LoopStateError(f"{path} lacks {', '.join(missing)}{fix}")
    for k in ("iteration", "env_steps", "train_steps"):
        if not _is_int(d[k]) or d[k] < 0:
            raise LoopStateError(f"{path}: {k} must be an integer >= 0, got {d[k]!r}{fix}")
    if not isinstance(d["shards"], list) or not all(isinstance(s, str) for s in d["shards"]):
        raise LoopStateError(f"{path}: shards must be a list of paths, got {d['shards']!r:.80}{fix}")
    if not isinstance(d["seconds"], (int, float)) or isinstance(d["seconds"], bool):
        raise LoopStateError(f"{path}: seconds must be a number, got {d['seconds']!r}{fix}")
    state = LoopState(**{k: d[k] for k in names})
    if len(state.shards) != state.iteration:
        raise LoopStateError(f"{path}: {state.iteration} iterations finished but {len(state.shards)} shards "
                             f"listed{fix}")
    for i, s in enumerate(state.shards, 1):
        if s != shard_path(i).as_posix():
            raise LoopStateError(f"{path}: shard {i} is {s!r}, expected {shard_path(i).as_posix()!r}{fix}")
        if not (folder / s).is_file():
            raise LoopStateError(f"{path} lists {s}, which is missing from {folder}{fix}")
    extra = [p.name for p in sorted((folder / "data").glob("iter-*.h5"))
             if _SHARD.match(p.name) and int(_SHARD.match(p.name)[1]) > state.iteration + 1]
    if extra:
        raise LoopStateError(f"{folder / 'data'} holds shards of iterations the state has not reached: "
                             f"{', '.join(extra)}{fix}")
    return state


def write_state(folder, state: LoopState) -> None:
    """Write ``state.json`` atomically."""
    write_json(Path(folder) / STATE_FILE, state.to_dict())


def write_json(path: Path, d: dict) -> None:
    with atomic_write(path) as tmp:
        tmp.write_text(json.dumps(d, indent=1) + "\n")


def shard_path(iteration: int) -> Path:
    """The shard of ``iteration`` (1-based), relative to the loop folder."""
    return Path("data") / f"iter-{iteration:04d}.h5"


def episode_dataset(template: Dataset, body, ctrl, qpos, qvel, seq_len: int, loop_meta: dict) -> Dataset:
    """The transitions of N episodes as a dataset in ``template``'s layout (its static graph and
    metadata): body [N, E+1, B, 13], ctrl [N, E, U], qpos [N, E+1, nq], qvel [N, E+1, nv] cut into
    N * E / ``seq_len`` train sequences of ``seq_len`` steps (sequence j of an episode: steps
    j*L .. (j+1)*L, its last state the next one's first); valid and test empty. ``loop_meta`` goes
    to meta["loop"]."""
    body, ctrl, qpos, qvel = (np.asarray(a, dtype=np.float32) for a in (body, ctrl, qpos, qvel))
    N, E = ctrl.shape[:2]
    L = int(seq_len)
    if E % L:
        raise ValueError(f"episodes of {E} steps do not cut into sequences of {L} steps")
    k = E // L

    def cut(a, extra):   # [N, E(+1), ...] -> [N * k, L(+1), ...]
        idx = np.arange(k)[:, None] * L + np.arange(L + extra)[None]
        return a[:, idx].reshape(N * k, L + extra, *a.shape[2:])
    meta = json.loads(json.dumps(template.meta))
    nq, nv = int(meta["nq"]), int(meta["nv"])
    if qpos.shape[-1] != nq or qvel.shape[-1] != nv or body.shape[2] != template.static["nodes"].shape[1]:
        raise ValueError(f"episodes of qpos [.., {qpos.shape[-1]}], qvel [.., {qvel.shape[-1]}], {body.shape[2]} "
                         f"bodies do not fit the seed data's nq {nq}, nv {nv}, "
                         f"{template.static['nodes'].shape[1]} bodies")
    sizes = {"train": N * k, "valid": 0, "test": 0}
    meta.update(splits=sizes, num_steps=L, loop=loop_meta)
    for k_ in ("generation_seconds", "simulation_seconds"):
        meta.pop(k_, None)
    train = Split(cut(body, 1), cut(ctrl, 0), cut(qpos, 1), cut(qvel, 1), np.zeros(N * k, dtype=np.int64))
    empty = Split(*(np.zeros((0,) + a.shape[1:], a.dtype) for a in (train.body, train.ctrl, train.qpos, train.qvel,
                                                                   train.instance)))
    return Dataset(meta, dict(template.static), {"train": train, "valid": empty, "test": empty})


def concat_train(seed: Dataset, shards: list[Dataset]) -> Dataset:
    """One dataset: the seed data with every shard's train sequences appended to its train split
    (valid and test: the seed data's), in memory; meta["splits"] counts them."""
    parts = [seed["train"]] + [s["train"] for s in shards]
    arrays = [np.concatenate([np.asarray(getattr(p, k)[...]) for p in parts])
              for k in ("body", "ctrl", "qpos", "qvel", "instance")]
    for s in shards:
        if s["train"].num_steps != seed["train"].num_steps:
            raise ValueError(f"a shard holds sequences of {s['train'].num_steps} steps, the seed data "
                             f"{seed['train'].num_steps}")
    splits = {"train": Split(*arrays), "valid": seed["valid"].load(), "test": seed["test"].load()}
    meta = json.loads(json.dumps({k: v for k, v in seed.meta.items()}))
    meta["splits"] = {k: len(sp) for k, sp in splits.items()}
    return Dataset(meta, dict(seed.static), splits)


def subset(ds: Dataset, split: str, idx) -> Dataset:
    """A dataset of sequences ``idx`` of ``ds``'s ``split`` (as its test split), for evaluation."""
    sp = ds[split]
    idx = np.sort(np.asarray(idx, dtype=np.int64))
    test = Split(*(np.asarray(getattr(sp, k)[...])[idx] for k in ("body", "ctrl", "qpos", "qvel", "instance")))
    empty = Split(*(a[:0] for a in (test.body, test.ctrl, test.qpos, test.qvel, test.instance)))
    meta = dict(ds.meta, splits={"train": 0, "valid": 0, "test": len(idx)})
    return Dataset(meta, ds.static, {"train": empty, "valid": empty, "test": test})


def train_env_steps(ds: Dataset) -> int:
    """Control steps in ``ds``'s train split (sequences x steps)."""
    return len(ds["train"]) * ds["train"].num_steps
