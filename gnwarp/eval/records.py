"""Results records: one JSON line per (experiment, task, planner, dynamics, variant) run.

Every experiment writes its measured outcomes as ``ResultRecord`` lines; summaries and plots are
generated from them (``python -m gnwarp.eval.summarize``), and so are the README tables
(``python bench/results_tables.py``), never typed by hand.

A record holds per-episode values: ``returns`` (control) or ``errors`` (model accuracy), one
float per episode or sequence. Runs whose per-episode values were never written keep their
reported ``mean`` and ``std`` in ``reported`` instead (``returns`` and ``errors`` both null).

    >>> rec = ResultRecord(experiment="control", task="pendulum-balance", planner="gradient",
    ...                    dynamics="learned", seed=0, episodes=2, episode_steps=100,
    ...                    control_dt=0.05, returns=[-190.0, -180.5])
    >>> write_records("results.jsonl", [rec])            # appends, atomically
    >>> read_records("results.jsonl")                     # every line validated
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import subprocess
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

__all__ = ["FORMAT", "VERSION", "PLANNERS", "DYNAMICS", "RecordError", "ResultRecord", "write_records",
           "read_records", "git_commit", "gpu_name"]

FORMAT, VERSION = "gnwarp-result", 1
# planner or agent names a record may carry (the planner registry's names; "policy": a trained
# agent's policy, gnwarp.rl.planner.PolicyPlanner; "policy-mpc": planning over such an agent with
# its model and Q-function, PolicyMPC); "none": a record of a model's accuracy, where nothing plans
PLANNERS = ("gradient", "sampling", "mppi", "ilqg", "random", "hybrid", "policy", "policy-mpc", "none")
# what the planner predicts with: a learned model, the true simulator on MuJoCo-Warp or MuJoCo C,
# or nothing (random actions, model-accuracy records)
DYNAMICS = ("learned", "true_mjwarp", "true_mujoco_c", "none")


class RecordError(ValueError):
    """A results record (or a line of a records file) that is malformed; the message names it."""


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


@dataclass
class ResultRecord:
    """One run's outcome.

    ``experiment``: the producing script or command ("control", "control/fig10", "mpc").
    ``task``: the task (or, for model-accuracy records, the dataset's system). ``planner``: a name
    of ``PLANNERS``. ``dynamics``: one of ``DYNAMICS``. ``variant``: what tells apart runs of the
    same (task, planner, dynamics), e.g. the model ("true_params"); "" when nothing does.
    ``seed``: the seed of initial states and targets (None: not recorded). ``episodes``: the
    number of episodes (or sequences); ``returns`` / ``errors``: one float per episode (NaN is
    written as null), or None for both with ``reported`` = {"mean", "std", "of"} when only those
    exist (std null where unknown; "of": "returns" or "errors").
    ``episode_steps``: control steps per episode; ``control_dt``: seconds per control step
    (None: not recorded); ``action_repeat``: simulator steps per control step; ``env_steps``:
    true-simulator control steps whose data trained any weights used (None: not recorded; 0:
    none). ``metrics``: other measured numbers or lists (timings, distances). ``config``: the
    settings (JSON values). ``commit``, ``gpu``, ``date``: where and when it ran.
    """
    experiment: str
    task: str
    planner: str
    dynamics: str
    episodes: int
    episode_steps: int
    returns: list | None = None
    errors: list | None = None
    reported: dict | None = None
    variant: str = ""
    system: str | None = None
    seed: int | None = None
    control_dt: float | None = None
    action_repeat: int = 1
    env_steps: int | None = None
    metrics: dict = field(default_factory=dict)
    config: dict = field(default_factory=dict)
    commit: str = "unknown"
    gpu: str = "unknown"
    date: str = ""
    format: str = FORMAT
    version: int = VERSION

    def __post_init__(self):
        self.check()

    def check(self) -> None:
        """Raise ``RecordError`` naming the first field that is wrong."""
        def bad(name, msg):
            raise RecordError(f"results record field '{name}': {msg}, got {getattr(self, name)!r}"[:400])
        if self.format != FORMAT:
            bad("format", f"must be {FORMAT!r}")
        if not _is_int(self.version) or self.version != VERSION:
            bad("version", f"must be {VERSION} (this gnwarp reads records of version {VERSION})")
        for name in ("experiment", "task"):
            if not isinstance(getattr(self, name), str) or not getattr(self, name):
                bad(name, "must be a non-empty string")
        for name in ("variant", "commit", "gpu", "date"):
            if not isinstance(getattr(self, name), str):
                bad(name, "must be a string")
        if self.system is not None and not isinstance(self.system, str):
            bad("system", "must be a string or null")
        if self.planner not in PLANNERS:
            bad("planner", f"must be one of {', '.join(PLANNERS)}")
        if self.dynamics not in DYNAMICS:
            bad("dynamics", f"must be one of {', '.join(DYNAMICS)}")
        for name in ("episodes", "episode_steps", "action_repeat"):
            v = getattr(self, name)
            if not _is_int(v) or v < 1:
                bad(name, "must be an integer >= 1")
        for name in ("seed", "env_steps"):
            v = getattr(self, name)
            if v is not None and (not _is_int(v) or v < 0):
                bad(name, "must be an integer >= 0 or null")
        if self.control_dt is not None and (not _is_num(self.control_dt) or not self.control_dt > 0):
            bad("control_dt", "must be a number > 0 or null")
        values = [n for n in ("returns", "errors") if getattr(self, n) is not None]
        if len(values) > 1:
            bad("errors", "a record holds returns or errors, not both")
        for name in values:
            v = getattr(self, name)
            if not isinstance(v, list) or not all(x is None or _is_num(x) for x in v):
                bad(name, "must be a list of numbers (null for NaN)")
            if len(v) != self.episodes:
                bad(name, f"must hold one value per episode ({self.episodes})")
        if self.reported is not None:
            if values:
                bad("reported", "is only for records without per-episode returns or errors")
            if (not isinstance(self.reported, dict) or set(self.reported) - {"mean", "std", "of"}
                    or not {"mean", "std"} <= set(self.reported)
                    or not all(x is None or _is_num(x) for x in (self.reported["mean"], self.reported["std"]))):
                bad("reported", "must be {'mean': number, 'std': number[, 'of': 'returns' or 'errors']}")
            if self.reported.get("of", "returns") not in ("returns", "errors"):
                bad("reported", "its 'of' must be 'returns' or 'errors'")
        elif not values:
            bad("returns", "a record needs per-episode returns or errors (or, for a run that kept only its mean, 'reported')")
        for name in ("metrics", "config"):
            v = getattr(self, name)
            if not isinstance(v, dict) or not all(isinstance(k, str) for k in v):
                bad(name, "must be an object with string keys")
            try:
                json.dumps(v, allow_nan=True)
            except (TypeError, ValueError) as e:
                bad(name, f"must hold JSON values only ({e})")

    # -- values ------------------------------------------------------------------------------
    @property
    def kind(self) -> str:
        """"returns" or "errors": what the record's values are."""
        if self.errors is not None or (self.reported and self.reported.get("of") == "errors"):
            return "errors"
        return "returns"

    @property
    def values(self) -> list[float] | None:
        """Per-episode values with NaN for null, or None when only ``reported`` exists."""
        v = self.returns if self.returns is not None else self.errors
        return None if v is None else [math.nan if x is None else float(x) for x in v]

    @property
    def key(self) -> tuple[str, str, str, str]:
        """(task, planner, dynamics, variant): the group a summary row stands for."""
        return self.task, self.planner, self.dynamics, self.variant

    # -- JSON --------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """The record as JSON values (NaN per-episode values as null, format and version first)."""
        d = dataclasses.asdict(self)
        for name in ("returns", "errors"):
            if d[name] is not None:
                d[name] = [None if x is None or (isinstance(x, float) and math.isnan(x)) else x for x in d[name]]
        head = {"format": d.pop("format"), "version": d.pop("version")}
        return {**head, **d}

    @classmethod
    def from_dict(cls, d: Any, where: str = "results record") -> "ResultRecord":
        """A record from a parsed JSON object; ``RecordError`` naming ``where`` and the problem."""
        if not isinstance(d, dict):
            raise RecordError(f"{where}: a results record is a JSON object, got {type(d).__name__}")
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise RecordError(f"{where}: unknown field(s) {', '.join(unknown)} (a record has {', '.join(sorted(names))})")
        missing = [f.name for f in dataclasses.fields(cls) if f.name not in d
                   and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING]
        if "format" not in d or "version" not in d:
            missing = [m for m in ("format", "version") if m not in d] + missing
        if missing:
            raise RecordError(f"{where}: missing field(s) {', '.join(missing)}")
        try:
            return cls(**d)
        except RecordError as e:
            raise RecordError(f"{where}: {e}") from None


def _dumps(rec: ResultRecord) -> str:
    return json.dumps(rec.to_dict(), allow_nan=True)


def write_records(path: str | os.PathLike, records: Iterable[ResultRecord], append: bool = True) -> Path:
    """Write ``records`` as JSON lines to ``path``, after its existing lines when ``append``.

    Atomic: the whole file is written beside ``path`` and renamed into place, so a reader (or a
    killed writer) never sees half a line. Every record is validated before anything is written;
    the parent folder must exist (``FileNotFoundError`` naming it)."""
    path = Path(path)
    recs = list(records)
    for i, r in enumerate(recs):
        if not isinstance(r, ResultRecord):
            raise RecordError(f"record {i} is a {type(r).__name__}, not a ResultRecord")
        r.check()
    if not path.parent.is_dir():
        raise FileNotFoundError(f"folder of the records file does not exist: {path.parent}")
    from gnwarp.files import locked
    with locked(path):   # another writer's read-add-rename waits: none loses the other's records
        old = path.read_text() if append and path.exists() else ""
        if old and not old.endswith("\n"):
            old += "\n"
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        try:
            with os.fdopen(fd, "w") as f:
                f.write(old + "".join(_dumps(r) + "\n" for r in recs))
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    return path


def read_records(path: str | os.PathLike) -> list[ResultRecord]:
    """Every record of a JSON-lines file (blank lines skipped), each validated; a line that does
    not parse or is no valid record raises ``RecordError`` naming the file and line number."""
    path = Path(path)
    out = []
    with open(path, "rb") as f:   # bytes: a binary file is refused by line, not by a decoder's error
        for n, raw in enumerate(f, 1):
            where = f"{path}, line {n}"
            try:
                line = raw.decode("utf-8")
            except UnicodeDecodeError:
                raise RecordError(f"{where}: not text (a records file holds JSON lines; is this another kind "
                                  "of file?)") from None
            if not line.strip():
                continue
            try:
                d = json.loads(line)
            except json.JSONDecodeError as e:
                raise RecordError(f"{where}: not JSON ({e})") from None
            out.append(ResultRecord.from_dict(d, where))
    return out


def git_commit(cwd: str | os.PathLike | None = None) -> str:
    """The checked-out commit of the repository at ``cwd`` (default: this package's), with
    "+dirty" when files differ from it; "unknown" without git or outside a repository."""
    cwd = Path(cwd) if cwd is not None else Path(__file__).resolve().parent
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=cwd, capture_output=True, text=True, timeout=10)
        if sha.returncode != 0:
            return "unknown"
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=cwd,
                               capture_output=True, text=True, timeout=10)
        return sha.stdout.strip() + ("+dirty" if dirty.returncode == 0 and dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def gpu_name(device=None) -> str:
    """The GPU's name (``device``, default the first CUDA device), or "cpu" without one."""
    try:
        import torch
        if (torch.device(device).type == "cuda") if device is not None else torch.cuda.is_available():
            return torch.cuda.get_device_name(device if device is not None else 0)
    except Exception:  # noqa: BLE001 - no usable CUDA is a CPU run
        pass
    return "cpu"
