"""``bench/results/rl/summary.json`` and learning-curve plots, generated from the RL records.

Reads every results-record file (``gnwarp.eval.records``, JSON lines; ``gnwarp rl`` writes
``records.jsonl`` in its run folder: copy or concatenate those under ``bench/results/rl/``) and
writes a list of rows, one per (task, agent, preset, networks, utd, act_ahead, settings, eval_seed,
env_steps)::

    {"task", "agent", "preset", "networks", "utd", "act_ahead", "settings", "eval_seed", "env_steps",
     "seeds", "eval_episodes", "median", "q25", "q75", "mean", "se", "dynamics"}

(``utd``: gradient updates per env step, ``RLConfig.utd``; 1 for records without it.
``act_ahead``: the training loop picked each action before the previous step's updates,
``RLConfig.act_ahead``; false for records without it. ``settings``: the agent settings off
their defaults, ``gnwarp.rl.settings.settings_tag``: "" for none. ``eval_seed``: the shared
evaluation states' seed, ``RLConfig.eval_seed``; null where each run evaluated on its own seed's.
``dynamics``: the true
simulators its seeds trained and evaluated on, sorted, the records' own field: "true_mujoco_c"
(MuJoCo C), "true_mjwarp" (MuJoCo-Warp). One curve holds both: the same MJCF, and a trained
policy scores the same on either, episode by episode: ``results/rl/simulators``.)

Each seed counts once per point: its evaluation's mean return (over its deterministic episodes;
a rerun of a seed at the same env steps: the last record stands). ``median``, ``q25``, ``q75``:
of those seed means (linear interpolation); ``mean`` and its standard error ``se`` (sample
standard deviation / sqrt(seeds); null for one seed). ``eval_episodes``: the fewest episodes
of any seed at that point.

Plots (``learning_curves_<task>.png``): per task, each run variant (agent, preset, networks, utd,
act_ahead, settings) against env
steps: the median with its 25-75% band (left) and the mean with +- one standard error (right).

    PYTHONPATH=. python3 bench/rl_summary.py              # rewrite summary.json and the plots
    PYTHONPATH=. python3 bench/rl_summary.py --check      # exit 1 where summary.json differs
    PYTHONPATH=. python3 bench/rl_summary.py --folder bench/results/rl_cpu   # another folder's
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
from gnwarp.files import atomic_write, write_or_check  # noqa: E402
from gnwarp.rl.settings import settings_tag  # noqa: E402

__all__ = ["RL", "seed_means", "rows", "point", "difference", "eval_order", "main_curve", "plot_curves", "main"]

RL = Path("bench") / "results" / "rl"


def point(seed_means: list[float]) -> dict:
    """{"median", "q25", "q75", "mean", "se"} of per-seed mean returns (se None for one seed)."""
    v = np.asarray(seed_means, dtype=np.float64)
    if v.size == 0 or not np.isfinite(v).all():
        raise ValueError(f"a learning-curve point needs finite per-seed returns, got {v.tolist()}")
    q25, med, q75 = np.percentile(v, [25, 50, 75])
    se = float(v.std(ddof=1) / math.sqrt(v.size)) if v.size > 1 else None
    return dict(median=float(med), q25=float(q25), q75=float(q75), mean=float(v.mean()), se=se)


def _group(rec) -> tuple:
    c = rec.config
    agent, preset, networks = (rec.variant.split("/") + ["", "", ""])[:3]
    agent, preset = c.get("agent", agent), c.get("preset", preset)
    given = c.get("agent_settings") or {}
    return (rec.task, agent, preset, c.get("networks", networks or "mlp"),
            float(c.get("utd", 1.0)), bool(given.get("act_ahead", False)),
            settings_tag({**given, "agent": agent, "preset": preset}, strict=False), c.get("eval_seed"))


def rl_records(root: Path = ROOT, folder: Path = RL):
    """Every evaluation record (experiment "rl", with returns and env steps) of the records files
    under ``folder`` of ``root``, file by file in sorted order (a benchmark's own rows skipped)."""
    for path in sorted((root / folder).rglob("*.jsonl")):
        try:
            recs = read_records(path)
        except RecordError:
            continue   # a benchmark's own rows (timings), not results records
        yield from (r for r in recs if r.experiment == "rl" and r.returns is not None and r.env_steps is not None)


def seed_means(root: Path = ROOT, folder: Path = RL, stratify=None) -> dict[tuple, dict[int, tuple[float, int, str, float]]]:
    """{(task, agent, preset, networks, utd, act_ahead, settings, eval_seed, env_steps): {seed: (its evaluation's mean return, its
    episodes, its true simulator, the variance of that mean from its episodes' spread: their variance / episodes,
    nan for one)}} from every records file under ``folder`` of ``root`` (experiment "rl" only; a
    rerun of a seed at the same env steps: the last record stands).

    ``stratify``: a function of a record giving (a boolean mask of its episodes, the share of
    such episodes in the task's own draw), or None to leave it: that record's mean is then the
    post-stratified one, share x mean(masked) + (1 - share) x mean(the rest), with its variance
    share^2 var(masked) / their number + (1 - share)^2 var(rest) / theirs (the raw mean where a
    stratum holds fewer than two episodes). On swimmer6 the mask is "the target is near"
    (``bench/results_tables.py``): a seed's mean then no longer depends on how many near targets
    its evaluation happened to draw."""
    by: dict[tuple, dict] = {}
    for r in rl_records(root, folder):
        v = np.asarray(r.values, dtype=np.float64)
        ok = np.isfinite(v)
        mean, var = _mean_var(v[ok])
        strata = stratify(r) if stratify is not None else None
        if strata is not None:
            mask, share = np.asarray(strata[0], dtype=bool), float(strata[1])
            (m1, v1), (m0, v0) = _mean_var(v[ok & mask]), _mean_var(v[ok & ~mask])
            if min((ok & mask).sum(), (ok & ~mask).sum()) >= 2:
                mean, var = share * m1 + (1 - share) * m0, share ** 2 * v1 + (1 - share) ** 2 * v0
        by.setdefault((*_group(r), r.env_steps), {})[r.seed] = (mean, r.episodes, r.dynamics, var)
    return by


def _mean_var(v: np.ndarray) -> tuple[float, float]:
    """(mean, variance of the mean: var / n) of finite values (nan where too few)."""
    return (float(v.mean()) if v.size else math.nan, float(v.var(ddof=1) / v.size) if v.size > 1 else math.nan)


def rows(root: Path = ROOT, folder: Path = RL) -> list[dict]:
    """The summary's rows from every records file under ``folder`` (``bench/results/rl``) of
    ``root`` (records of experiment "rl" only), sorted by task, agent, preset, networks, utd,
    act_ahead, settings, eval_seed (unset first), env steps."""
    by = seed_means(root, folder)
    out = []
    for key in sorted(by, key=lambda k: (*k[:7], eval_order(k[7]), k[8])):
        seeds = by[key]
        task, agent, preset, networks, utd, ahead, tag, eval_seed, steps = key
        out.append(dict(task=task, agent=agent, preset=preset, networks=networks, utd=utd, act_ahead=ahead,
                        settings=tag, eval_seed=eval_seed,
                        env_steps=steps,
                        seeds=len(seeds), eval_episodes=min(x[1] for x in seeds.values()),
                        **point([x[0] for x in seeds.values()]), dynamics=sorted({x[2] for x in seeds.values()})))
    return out


def difference(a, b) -> tuple[float, float, float]:
    """(mean(a) - mean(b), and its 95% Welch interval): the seeds of the two runs independent, their
    spreads unequal, Student's t at the Welch-Satterthwaite degrees of freedom rounded down (at
    least two finite values a side; a percentile bootstrap is too narrow at a handful of seeds)."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if min(a.size, b.size) < 2 or not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise ValueError(f"a difference needs at least two finite values a side, got {a.tolist()} and {b.tolist()}")
    d = float(a.mean() - b.mean())
    va, vb = a.var(ddof=1) / a.size, b.var(ddof=1) / b.size
    if va + vb == 0:
        return d, d, d
    df = (va + vb) ** 2 / (va ** 2 / (a.size - 1) + vb ** 2 / (b.size - 1))
    half = t_quantile(max(1, math.floor(df))) * math.sqrt(va + vb)
    return d, d - half, d + half


def paired_difference(a: dict, b: dict) -> tuple[float, float, float, list]:
    """(the mean over the seeds both hold of a[seed] - b[seed], its 95% interval (Student's t at
    seeds - 1 degrees of freedom), those seeds): two runs blocked on what each seed shares across
    them (its evaluation states). At least two shared seeds with finite values."""
    seeds = sorted(set(a) & set(b))
    d = np.asarray([a[s] - b[s] for s in seeds], dtype=np.float64)
    if d.size < 2 or not np.isfinite(d).all():
        raise ValueError(f"a paired difference needs at least two shared seeds with finite values, got seeds {seeds}")
    m = float(d.mean())
    half = t_quantile(d.size - 1) * float(d.std(ddof=1)) / math.sqrt(d.size)
    return m, m - half, m + half, seeds


def _run(row: dict) -> tuple:
    """(agent, preset, networks, utd, act_ahead, settings, eval_seed) of a summary row (utd 1,
    act_ahead false, settings "", eval_seed None where the row predates them)."""
    return (row["agent"], row["preset"], row["networks"], row.get("utd", 1.0), row.get("act_ahead", False),
            row.get("settings", ""), row.get("eval_seed"))


def eval_order(eval_seed) -> tuple:
    """Sort key of an ``eval_seed``: unset (each run on its own seed's states) first, then by seed."""
    return (eval_seed is not None, eval_seed or 0)


def main_curve(run: tuple) -> bool:
    """Whether a curve (``_run``'s tuple) belongs on a task's main figure: DDPG, SVG(0) or SVG(1)
    with MLPs, one update an env step, default settings, each seed on its own evaluation states
    (in turn or acting ahead); every other curve goes on the variants figure."""
    agent, _preset, networks, utd, _ahead, settings, eval_seed = run
    return agent in ("ddpg", "svg0", "svg1") and networks == "mlp" and utd == 1 and not settings and eval_seed is None


def plot_curves(summary: list[dict], folder: Path) -> list[Path]:
    """Per task in ``folder``: ``learning_curves_<task>.png``, the main curves (``main_curve``),
    and, where there are others, ``learning_curves_<task>_variants.png`` with every curve (each
    its own colour, the legend below); the paths written."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    written = []
    for task in sorted({r["task"] for r in summary}):
        runs = sorted({_run(r) for r in summary if r["task"] == task}, key=lambda run: (*run[:6], eval_order(run[6])))
        main = [run for run in runs if main_curve(run)]
        for name, shown in (("", main), ("_variants", runs if len(main) < len(runs) else [])):
            if not shown:
                continue
            colours = plt.get_cmap("tab10" if len(shown) <= 10 else "tab20")
            legend_in = 0.17 * ((len(shown) + 1) // 2) + 0.3 if name else 0.0   # the legend's rows below, inches
            fig, (ax_med, ax_mean) = plt.subplots(1, 2, figsize=(11, 4 + legend_in), sharey=True)
            for k, run in enumerate(shown):
                pts = sorted((r for r in summary if r["task"] == task and _run(r) == run), key=lambda r: r["env_steps"])
                x = np.array([p["env_steps"] for p in pts], dtype=float)
                utd = (("" if run[3] == 1 else f", {run[3]:g} updates a step") + (", acting ahead" if run[4] else "")
                       + (f", {run[5]}" if run[5] else "") + (f", eval_seed {run[6]}" if run[6] is not None else ""))
                label = f"{run[0]} ({run[1]}, {run[2]}{utd}; {max(p['seeds'] for p in pts)} seeds)"
                c = colours(k % colours.N)
                ax_med.plot(x, [p["median"] for p in pts], color=c, label=label)
                ax_med.fill_between(x, [p["q25"] for p in pts], [p["q75"] for p in pts], color=c, alpha=0.2)
                mean = np.array([p["mean"] for p in pts])
                se = np.array([p["se"] if p["se"] is not None else 0.0 for p in pts])
                ax_mean.plot(x, mean, color=c, label=label)
                ax_mean.fill_between(x, mean - se, mean + se, color=c, alpha=0.2)
            what = ", every curve" if name else ""
            ax_med.set_title(f"{task}{what}: median, 25-75% over seeds", fontsize=10)
            ax_mean.set_title("mean +- standard error over seeds", fontsize=10)
            for ax in (ax_med, ax_mean):
                ax.set_xlabel("environment steps")
                ax.grid(alpha=0.3)
            ax_med.set_ylabel("evaluation return")
            if name:   # many curves: the legend below the plots, not over them
                handles, labels = ax_med.get_legend_handles_labels()
                fig.legend(handles, labels, loc="lower center", ncol=2, fontsize=8, frameon=False)
                fig.tight_layout(rect=(0, legend_in / (4 + legend_in), 1, 1))
            else:
                ax_med.legend(fontsize=8)
                fig.tight_layout()
            path = folder / f"learning_curves_{task}{name}.png"
            with atomic_write(path) as tmp:
                fig.savefig(tmp, dpi=120, format="png")
            plt.close(fig)
            written.append(path)
    return written

def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--check", action="store_true", help="exit 1 where summary.json differs from the records")
    ap.add_argument("--no-plot", action="store_true", help="summary.json only")
    ap.add_argument("--folder", default=str(RL),
                    help="the records' folder in the repository, where summary.json and the plots go")
    ap.add_argument("--root", default=str(ROOT), help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    root = Path(a.root)
    summary = rows(root, Path(a.folder))
    text = json.dumps(summary, indent=1, allow_nan=False) + "\n"
    path = root / a.folder / "summary.json"
    status = write_or_check(path, text, a.check, "python3 bench/rl_summary.py")
    if a.check:
        return status
    if not a.no_plot and summary:
        for p in plot_curves(summary, path.parent):
            print(f"wrote {p}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
