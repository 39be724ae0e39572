"""``bench/results/control/summary.json``: one row per control result, generated from the records.

Reads every results-record file (``gnwarp.eval.records``, JSON lines) under
``bench/results/control/`` and writes a list of rows::

    {"task", "planner", "dynamics", "protocol", "env_steps", "seeds", "episodes", "mean",
     "ci95": [lo, hi], "over", "variant", "source"}

``protocol``: "loop" for records of the data loop (``gnwarp loop``: experiment "loop" or
config "protocol": "loop"), else "paper" (random-control data, Algorithm F.1). Records group by
(task, planner, dynamics, protocol, env_steps, variant, episode length). The interval: with
per-episode returns of two or more seeds, a percentile bootstrap over the seeds' means
("over": "seeds"); with one seed, a bootstrap over its episodes ("episodes"); records holding only
a reported mean and std give a t interval ("reported"); one value alone gives [mean, mean].

Paired comparisons, where a row's records hold per-episode returns from the same initial states
(same file, task, protocol, episode length, seed and number of episodes) as iLQG's and the random
planner's (iLQG on the true MuJoCo C dynamics first where it ran on several):
``"minus_ilqg_ci95"`` (the row's returns minus iLQG's, episode by episode, bootstrapped) and
``"discriminative"`` (whether iLQG minus random excludes 0: where it does not, the task does not
separate a planner from random actions).

    PYTHONPATH=. python3 bench/control_summary.py            # rewrite summary.json
    PYTHONPATH=. python3 bench/control_summary.py --check    # exit 1 where it differs from the records

A ``.jsonl`` file under the folder that holds no results records (a benchmark's own rows) is
skipped and named on stderr.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from gnwarp.eval.records import RecordError, read_records  # noqa: E402
from gnwarp.eval.summarize import t_quantile  # noqa: E402
from gnwarp.files import write_or_check  # noqa: E402

__all__ = ["bootstrap_ci", "protocol_of", "variant_of", "rows", "main"]

CONTROL = Path("bench") / "results" / "control"
BOOTSTRAP = 10_000


def bootstrap_ci(values, n_boot: int = BOOTSTRAP, seed: int = 0) -> tuple[float, float]:
    """Percentile 95% bootstrap interval of the mean of ``values`` (at least two finite numbers)."""
    v = np.asarray(values, dtype=np.float64)
    if v.size < 2 or not np.isfinite(v).all():
        raise ValueError(f"a bootstrap needs at least two finite values, got {v.tolist()}")
    rng = np.random.default_rng(seed)
    means = v[rng.integers(0, v.size, (n_boot, v.size))].mean(1)
    lo, hi = np.percentile(means, [2.5, 97.5])
    return float(lo), float(hi)


def protocol_of(rec) -> str:
    """"loop" for a record of the data loop, else "paper"."""
    p = rec.config.get("protocol") if isinstance(rec.config, dict) else None
    if p in ("loop", "paper"):
        return p
    return "loop" if rec.experiment.split("/")[0] == "loop" else "paper"


def _row(key: tuple, recs: list, source: str) -> dict:
    task, planner, dynamics, protocol, env_steps, variant, _ = key
    with_values = [r for r in recs if r.returns is not None]
    seeds = sorted({r.seed for r in recs}, key=lambda s: (s is None, s))
    row = {"task": task, "planner": planner, "dynamics": dynamics, "protocol": protocol,
           "env_steps": env_steps, "seeds": len(seeds), "episodes": sum(r.episodes for r in recs)}
    if with_values and len(with_values) == len(recs):
        bad = [r.seed for r in recs if not np.isfinite(np.asarray(r.returns, dtype=np.float64)).all()]
        if bad:
            raise ValueError(f"{source}: {task} / {planner} / {dynamics}: the returns of seed(s) {bad} hold NaN or "
                             "Inf (a diverged episode): rerun or drop those records")
        per_seed = [float(np.mean(r.returns)) for r in recs]
        pooled = [float(x) for r in recs for x in r.returns]
        mean = float(np.mean(pooled))
        if len(recs) >= 2:
            ci, over = bootstrap_ci(per_seed), "seeds"
        elif len(pooled) >= 2:
            ci, over = bootstrap_ci(pooled), "episodes"
        else:
            ci, over = (mean, mean), "episodes"
    else:
        r = recs[-1]
        n, mean = r.episodes, float(r.reported["mean"])
        std = r.reported.get("std")
        h = t_quantile(n - 1) * float(std) / math.sqrt(n - 1) if (n > 1 and std is not None) else math.nan
        ci, over = (mean - h, mean + h), "reported"
        row.update(seeds=1, episodes=n)
    row.update(mean=round(mean, 6), ci95=[round(ci[0], 6), round(ci[1], 6)], over=over, variant=variant,
               source=source)
    return row


def variant_of(rec) -> str:
    """The record's variant, with the data loop's terminal value and ensemble named (its records
    all carry variant "loop" or "loop-eval"; the ablation rows must not pool)."""
    loop = rec.config.get("loop") if isinstance(rec.config, dict) else None
    v = rec.variant
    if isinstance(loop, dict):
        if loop.get("value"):
            v += ", terminal value"
        if int(loop.get("ensemble") or 1) > 1:
            v += f", ensemble of {int(loop['ensemble'])}"
    return v


def _paired(row: dict, recs: list, by: dict, key: tuple) -> None:
    """Add the paired comparisons of the module docstring to ``row`` where they exist."""
    if len(recs) != 1 or recs[0].returns is None:
        return
    r = recs[0]

    def peer(planner):
        """The record of ``planner`` from the same initial states: same task, protocol, episode
        length, seed and number of episodes; iLQG on the true MuJoCo C dynamics first."""
        keys = [k for k in by if (k[0], k[1], k[3], k[6]) == (key[0], planner, key[3], key[6])]
        for k in sorted(keys, key=lambda k: k[2] != "true_mujoco_c"):
            p = by[k].get(r.seed)
            if p is not None and p.returns is not None and len(p.returns) == len(r.returns):
                return p
        return None
    i, z = peer("ilqg"), peer("random")
    if i is not None and r.planner != "ilqg":
        d = np.asarray(r.returns, dtype=np.float64) - np.asarray(i.returns, dtype=np.float64)
        lo, hi = bootstrap_ci(d)
        row["minus_ilqg_ci95"] = [round(lo, 6), round(hi, 6)]
    if i is not None and z is not None:
        lo, hi = bootstrap_ci(np.asarray(i.returns, dtype=np.float64) - np.asarray(z.returns, dtype=np.float64))
        row["discriminative"] = bool(lo > 0 or hi < 0)


def rows(root: Path = ROOT) -> list[dict]:
    """The summary's rows from every records file under ``bench/results/control`` of ``root``."""
    out = []
    for path in sorted((root / CONTROL).rglob("*.jsonl")):
        try:
            recs = read_records(path)
        except RecordError as e:   # a benchmark's own rows (timings), not results records
            print(f"control_summary: skipped {path.relative_to(root)}: {e}", file=sys.stderr)
            continue
        by: dict[tuple, dict] = {}
        for r in recs:
            key = (r.task, r.planner, r.dynamics, protocol_of(r), r.env_steps, variant_of(r), r.episode_steps)
            by.setdefault(key, {})[r.seed] = r   # a rerun of a seed: the last one stands
        mixed = {k: v for k, v in by.items()
                 if len({x.returns is None for x in v.values()}) > 1}
        for key, seeds in by.items():
            recs_k = list(seeds.values())
            if key in mixed:   # reported-only records pool with none: keep those with returns
                recs_k = [r for r in recs_k if r.returns is not None]
            row = _row(key, recs_k, str(path.relative_to(root)))
            _paired(row, recs_k, by, key)
            out.append(row)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--check", action="store_true", help="exit 1 where summary.json differs from the records")
    ap.add_argument("--root", default=str(ROOT), help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    root = Path(a.root)
    text = json.dumps(rows(root), indent=1, allow_nan=False) + "\n"
    return write_or_check(root / CONTROL / "summary.json", text, a.check, "python3 bench/control_summary.py")


if __name__ == "__main__":
    raise SystemExit(main())
