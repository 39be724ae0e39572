"""A reinforcement-learning run's files: the checkpoint (written whole or not at all), the
progress log (CSV, and TensorBoard where ``torch.utils.tensorboard`` imports), the evaluation
records (``records.jsonl``), each cut back to the checkpoint when a run resumes."""
from __future__ import annotations

import csv
import io
from pathlib import Path

import torch

from gnwarp.eval.records import read_records, write_records
from gnwarp.files import atomic_write

__all__ = ["CHECKPOINT", "LOG_FILE", "RECORDS_FILE", "LOG_COLUMNS", "save_checkpoint", "load_checkpoint",
           "RunLog", "cut_records"]

CHECKPOINT, LOG_FILE, RECORDS_FILE = "checkpoint.pt", "progress.csv", "records.jsonl"
LOG_COLUMNS = ("env_steps", "round", "updates", "episodes", "seconds", "round_seconds", "train_return", "eval_median", "eval_mean",
               "q_loss", "policy_loss", "model_loss", "saturated")


def save_checkpoint(path: str | Path, state: dict) -> None:
    """``torch.save(state)`` to ``path`` atomically (a kill leaves the previous checkpoint)."""
    with atomic_write(path) as tmp:
        torch.save(state, tmp)


def load_checkpoint(path: str | Path) -> dict:
    """The checkpoint at ``path``, its tensors on the CPU (``load_state_dict`` moves them)."""
    return torch.load(path, map_location="cpu", weights_only=False)


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

