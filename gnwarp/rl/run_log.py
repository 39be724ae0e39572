"""A reinforcement-learning run's files: the checkpoint (written whole or not at all, read
without running code, its corruption detected), the progress log (CSV, and TensorBoard where
``torch.utils.tensorboard`` imports), the evaluation records (``records.jsonl``), each cut back to
the checkpoint when a run resumes.

The checkpoint file holds {"format": "gnwarp-rl-checkpoint", "version", "sha256", "payload"}:
the state (tensors and plain values only; NumPy arrays stored as tensors) serialized by
``torch.save`` into the bytes ``payload``, and their sha256. Both levels are read with
``torch.load(weights_only=True)``."""
from __future__ import annotations

import csv
import hashlib
import io
import pickle
from pathlib import Path

import torch

from gnwarp.eval.records import read_records, write_records
from gnwarp.files import atomic_write, plain_values

__all__ = ["CHECKPOINT", "AGENT_FILE", "LOG_FILE", "RECORDS_FILE", "TIMING_FILE", "LOG_COLUMNS", "save_checkpoint", "load_checkpoint",
           "RunLog", "cut_records", "RLCheckpointError"]

FORMAT, VERSION = "gnwarp-rl-checkpoint", 1


class RLCheckpointError(ValueError):
    """An RL checkpoint that cannot be read: not one, another version, or corrupt."""

CHECKPOINT, LOG_FILE, RECORDS_FILE = "checkpoint.pt", "progress.csv", "records.jsonl"
AGENT_FILE = "agent.pt"   # an exported agent: its networks alone, no replay buffer
TIMING_FILE = "timing.json"   # the run's last checkpoint and video times: the budget's estimate of a call's end
LOG_COLUMNS = ("env_steps", "round", "updates", "episodes", "seconds", "round_seconds", "train_return", "eval_median", "eval_mean",
               "q_loss", "policy_loss", "model_loss", "saturated")


def save_checkpoint(path: str | Path, state: dict) -> None:
    """``state`` (tensors and plain values; NumPy arrays become tensors) to ``path``, atomically
    (a kill leaves the previous checkpoint) and with its checksum (the module docstring)."""
    buf = io.BytesIO()
    torch.save(plain_values(state, "the RL checkpoint"), buf)
    view = buf.getbuffer()            # the serialized state, not copied again below
    digest = hashlib.sha256(view).hexdigest()
    with atomic_write(path) as tmp:
        torch.save({"format": FORMAT, "version": VERSION, "sha256": digest,
                    "payload": torch.frombuffer(view, dtype=torch.uint8)}, tmp)


def load_checkpoint(path: str | Path) -> dict:
    """The state ``save_checkpoint`` wrote at ``path``, its tensors on the CPU (``load_state_dict``
    moves them); no code runs. ``RLCheckpointError`` names what is wrong with a file that is not
    such a checkpoint, of another version, or corrupt."""
    path = Path(path)
    try:   # mapped, not read: the payload is hashed and parsed in place
        outer = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except pickle.UnpicklingError:
        raise RLCheckpointError(f"{path} is not a gnwarp rl checkpoint: it holds objects other than tensors and "
                                "plain values (a checkpoint of an older gnwarp, or another program's file); start "
                                "the run in a new folder") from None
    except Exception as e:  # noqa: BLE001 - any unreadable file: one clear error
        raise RLCheckpointError(f"{path} is not a readable gnwarp rl checkpoint ({type(e).__name__}: "
                                f"{str(e).strip().splitlines()[0] if str(e).strip() else 'no detail'})") from None
    if not isinstance(outer, dict) or outer.get("format") != FORMAT:
        raise RLCheckpointError(f"{path} is not a gnwarp rl checkpoint (written by an older gnwarp or another "
                                "program; start the run in a new folder)")
    if outer.get("version") != VERSION:
        raise RLCheckpointError(f"{path} is a version {outer.get('version')!r} rl checkpoint; this gnwarp reads "
                                f"version {VERSION}")
    payload = outer.get("payload")
    if not isinstance(payload, torch.Tensor) or payload.dtype != torch.uint8 or payload.ndim != 1:
        raise RLCheckpointError(f"{path}: its payload is missing or malformed")
    data = memoryview(payload.numpy())
    if hashlib.sha256(data).hexdigest() != outer.get("sha256"):
        raise RLCheckpointError(f"{path} is corrupt (its checksum does not match its contents)")
    return torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)


def _read_log(path: Path) -> list[dict]:
    if not path.is_file():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


class RunLog:
    """Rows of ``LOG_COLUMNS`` in ``<out>/progress.csv`` (and scalars in ``<out>/tb`` when
    ``tensorboard`` and ``torch.utils.tensorboard`` imports). ``keep_until``: env steps of the
    checkpoint resumed from (rows past it are dropped; None: a fresh run, the log emptied)."""

    def __init__(self, out: str | Path, keep_until: int | None, tensorboard: bool = True):
        self.path = Path(out) / LOG_FILE
        rows = [r for r in _read_log(self.path) if keep_until is not None and int(r["env_steps"]) <= keep_until]
        self._write(rows)
        self.writer = None
        if tensorboard:
            try:
                from torch.utils.tensorboard import SummaryWriter
            except ImportError:   # tensorboard not installed: the CSV only
                SummaryWriter = None
            if SummaryWriter is not None:
                self.writer = SummaryWriter(str(Path(out) / "tb"), purge_step=keep_until)

    def _write(self, rows: list[dict]) -> None:
        buf = io.StringIO()
        w = csv.DictWriter(buf, LOG_COLUMNS, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
        with atomic_write(self.path) as tmp:
            Path(tmp).write_text(buf.getvalue())

    def add(self, row: dict) -> None:
        """Append one row (missing columns blank); floats rounded to 6 significant digits."""
        row = {k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items() if v is not None}
        fresh = not self.path.is_file()
        with open(self.path, "a", newline="") as f:
            w = csv.DictWriter(f, LOG_COLUMNS, extrasaction="ignore")
            if fresh:
                w.writeheader()
            w.writerow(row)
        if self.writer is not None:
            for k, v in row.items():
                if k not in ("env_steps", "round") and v != "":
                    self.writer.add_scalar(k, float(v), int(row["env_steps"]))
            self.writer.flush()

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()


def cut_records(path: str | Path, keep_until: int | None) -> None:
    """Keep the records of ``path`` with env_steps <= ``keep_until`` (None: none)."""
    path = Path(path)
    if not path.is_file():
        return
    keep = [r for r in read_records(path) if keep_until is not None and (r.env_steps or 0) <= keep_until]
    write_records(path, keep, append=False)

