"""Summaries and plots generated from results records (``gnwarp.eval.records``); the README
tables built on the same groups are ``bench/results_tables.py``'s.

    python -m gnwarp.eval.summarize RECORDS.jsonl [...] --out DIR [--title T] [--ratio A/B]

writes ``DIR/summary.md`` (markdown tables: per group the episodes, mean, std and 95% interval of
the mean; a task-by-column table of mean +- std; the scalar metrics) and ``DIR/returns.png`` (or
``errors.png``): bars of each group's mean with its 95% interval.

A group is one (task, system, episode steps, planner, dynamics, variant). Records of a group with
the same seed are reruns: the last one read stands. Records of a group with different seeds pool
their episodes; where they hold only reported means (no per-episode values), the group's values
are those means, one per seed.
"""
from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gnwarp.eval.records import ResultRecord, read_records

__all__ = ["Group", "groups", "t_quantile", "summary_lines", "write_summary", "plot_groups", "main"]

# two-sided 95% Student t quantiles (0.975) for 1..30 degrees of freedom
_T975 = (12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179, 2.160, 2.145, 2.131,
         2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064, 2.060, 2.056, 2.052, 2.048, 2.045, 2.042)
DYNAMICS_LABELS = {"learned": "learned", "true_mjwarp": "true, MuJoCo-Warp", "true_mujoco_c": "true, MuJoCo C",
                   "none": "no model"}


def t_quantile(df: int) -> float:
    """The 0.975 quantile of Student's t with ``df`` >= 1 degrees of freedom (a table to 30, then
    the Cornish-Fisher expansion, within 1e-4 there)."""
    if df < 1:
        raise ValueError(f"degrees of freedom must be >= 1, got {df}")
    if df <= len(_T975):
        return _T975[df - 1]
    z = 1.959964
    return (z + (z ** 3 + z) / (4 * df) + (5 * z ** 5 + 16 * z ** 3 + 3 * z) / (96 * df ** 2)
            + (3 * z ** 7 + 19 * z ** 5 + 17 * z ** 3 - 15 * z) / (384 * df ** 3))


@dataclass
class Group:
    """The records of one group and their statistics: ``n`` episodes, ``mean``, ``std`` (over
    episodes, population: divided by n) and ``ci`` (half width of the 95% t interval of the mean,
    from the sample std; NaN for one episode). ``reported``: the numbers are a record's reported
    mean and std (no per-episode values); ``over``: what ``n`` counts, "episodes" or, for reported
    means of several seeds pooled, "seeds"."""
    task: str
    system: str
    episode_steps: int
    planner: str
    dynamics: str
    variant: str
    records: list
    n: int
    mean: float
    std: float
    ci: float
    reported: bool
    over: str = "episodes"

    @property
    def case(self) -> str:
        """The task, with its system and episode length ("swimmer-reach on swimmer7, 700 steps")
        where they differ from the first group of the task (set by ``groups``)."""
        return self._case

    @property
    def column(self) -> str:
        """The planner, its dynamics and variant: "gradient (learned)", "gradient (learned, sysid)"."""
        extra = f", {self.variant}" if self.variant else ""
        return f"{self.planner} ({DYNAMICS_LABELS[self.dynamics]}{extra})"

    @property
    def kind(self) -> str:
        return self.records[-1].kind


def _stats(values: list[float]) -> tuple[int, float, float, float]:
    v = np.asarray(values, dtype=np.float64)
    n = len(v)
    mean, std = float(np.mean(v)), float(np.std(v))
    ci = float(t_quantile(n - 1) * np.std(v, ddof=1) / math.sqrt(n)) if n > 1 else math.nan
    return n, mean, std, ci


def groups(records: list[ResultRecord]) -> list[Group]:
    """The records' groups in the order their first record appears (see the module docstring)."""
    by: dict[tuple, dict] = {}
    for r in records:
        key = (r.task, r.system or "", r.episode_steps, r.planner, r.dynamics, r.variant)
        by.setdefault(key, {})[r.seed] = r  # same seed: a rerun, the last one stands
    out = []
    first_of_task: dict[str, tuple] = {}
    for key, seeds in by.items():
        recs = list(seeds.values())
        only_reported = [r for r in recs if r.values is None]
        if only_reported and len(recs) > 1 and len(only_reported) < len(recs):
            raise ValueError(f"group {key}: a record without per-episode values cannot be pooled with records "
                             "that have them")
        if only_reported and len(recs) > 1:   # one reported mean per seed: statistics over the seeds
            g = Group(*key, recs, *_stats([float(r.reported["mean"]) for r in recs]), True, "seeds")
        elif only_reported:
            r = recs[0]
            n, mean = r.episodes, float(r.reported["mean"])
            std = math.nan if r.reported["std"] is None else float(r.reported["std"])
            ci = t_quantile(n - 1) * std * math.sqrt(n / (n - 1)) / math.sqrt(n) if n > 1 else math.nan
            g = Group(*key, recs, n, mean, std, ci, True)
        else:
            g = Group(*key, recs, *_stats([x for r in recs for x in r.values]), False)
        base = first_of_task.setdefault(g.task, (g.system, g.episode_steps))
        case = g.task
        if g.system and g.system != base[0]:
            case += f" on {g.system}"
        if g.episode_steps != base[1]:
            case += f", {g.episode_steps} steps"
        g._case = case
        out.append(g)
    return out


def ratio(a: float, b: float) -> float | None:
    """``a`` as a share of ``b``'s performance: a / b for positive values, b / a for negative ones
    (costs), None when the signs differ or either is zero."""
    if a > 0 and b > 0:
        return a / b
    if a < 0 and b < 0:
        return b / a
    return None


def _pm(g: Group) -> str:
    """"mean +- std", or the mean alone where the std is unknown."""
    return f"{g.mean:.4g}" if math.isnan(g.std) else f"{g.mean:.4g} +- {g.std:.2g}"


def _count_note(g: Group) -> str:
    """What a group's count stands for, beside it: "", " (reported)" or " seeds (reported means)"."""
    if g.over == "seeds":
        return " seeds (reported means)"
    return " (reported)" if g.reported else ""


def _g(x: float, spec: str) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, spec)


def summary_lines(gs: list[Group], title: str = "Results", ratio_of: tuple[str, str] | None = None) -> list[str]:
    """The markdown of ``summary.md`` for groups ``gs``. ``ratio_of``: two column names (see
    ``Group.column``); a last column gives the first's mean as a share of the second's."""
    kinds = {g.kind for g in gs}
    what = "/".join(sorted(kinds)) or "returns"
    lines = [f"# {title}", "", f"Generated by `python -m gnwarp.eval.summarize` from results records: {what} per "
             "group (task, system, episode steps, planner, dynamics, variant); mean and std over episodes, 95% "
             "t interval of the mean.", "",
             "| task | system | steps | planner | dynamics | variant | episodes | mean | std | 95% interval |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for g in gs:
        lo, hi = g.mean - g.ci, g.mean + g.ci
        interval = "-" if math.isnan(g.ci) else f"[{lo:.4g}, {hi:.4g}]"
        lines.append(f"| {g.task} | {g.system or '-'} | {g.episode_steps} | {g.planner} | {g.dynamics} | "
                     f"{g.variant or '-'} | {g.n}{_count_note(g)} | {g.mean:.4g} | "
                     f"{_g(g.std, '.2g')} | {interval} |")
    cases = list(dict.fromkeys(g.case for g in gs))
    cols = list(dict.fromkeys(g.column for g in gs))
    cell = {(g.case, g.column): g for g in gs}
    head = "| task | " + " | ".join(cols)
    if ratio_of:
        head += f" | {ratio_of[0]} / {ratio_of[1]}"
    lines += ["", "Mean +- std over episodes (the mean alone where a record has no std):", "", head + " |", "|---" * (len(cols) + 1 + bool(ratio_of)) + "|"]
    for c in cases:
        row = f"| {c} | " + " | ".join(_pm(cell[c, k]) if (c, k) in cell else "-" for k in cols)
        if ratio_of:
            a, b = cell.get((c, ratio_of[0])), cell.get((c, ratio_of[1]))
            r = ratio(a.mean, b.mean) if a and b else None
            row += f" | {'-' if r is None else f'{100 * r:.0f}%'}"
        lines.append(row + " |")
    metrics = list(dict.fromkeys(k for g in gs for r in g.records for k, v in r.metrics.items()
                                 if isinstance(v, (int, float)) and not isinstance(v, bool)))
    if metrics:
        lines += ["", "Metrics (each group's last record):", "", "| task | column | " + " | ".join(metrics) + " |",
                  "|---" * (len(metrics) + 2) + "|"]
        for g in gs:
            m = g.records[-1].metrics
            lines.append(f"| {g.case} | {g.column} | " + " | ".join(
                _g(m[k], ".3g") if isinstance(m.get(k), (int, float)) else "-" for k in metrics) + " |")
    notes = [(g, g.records[-1].config.get("note")) for g in gs]
    notes = [f"- {g.case}, {g.column}: {n}" for g, n in notes if isinstance(n, str) and n]
    if notes:
        lines += ["", "Notes (each group's last record):", ""] + notes
    return lines


def plot_groups(path: Path, gs: list[Group]) -> Path:
    """Bars of each group's mean with its 95% interval, one panel per task case."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    cases = list(dict.fromkeys(g.case for g in gs))
    cols = list(dict.fromkeys(g.column for g in gs))
    fig, axes = plt.subplots(1, len(cases), figsize=(4.2 * len(cases), 4.2), squeeze=False)
    for ax, c in zip(axes[0], cases):
        mine = [g for g in gs if g.case == c]
        x = np.arange(len(mine))
        ax.bar(x, [g.mean for g in mine], yerr=[0 if math.isnan(g.ci) else g.ci for g in mine], capsize=3,
               color=[f"C{cols.index(g.column) % 10}" for g in mine])
        ax.set_xticks(x, [g.column for g in mine], rotation=40, ha="right", fontsize=7)
        ax.set_title(c, fontsize=9)
        ax.set_ylabel(mine[0].kind[:-1] if mine else "")
        ax.axhline(0, color="k", lw=0.5)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return Path(path)


def write_summary(records: list[ResultRecord], out, title: str = "Results", ratio_of=None,
                  plot: bool = True) -> Path:
    """``out/summary.md`` (and, with ``plot``, ``out/returns.png`` or ``errors.png``) from
    ``records``; returns the summary's path."""
    out = Path(out)
    if not records:
        raise ValueError("no results records to summarize")
    gs = groups(records)
    out.mkdir(parents=True, exist_ok=True)
    (out / "summary.md").write_text("\n".join(summary_lines(gs, title, ratio_of)) + "\n")
    if plot:
        plot_groups(out / f"{gs[0].kind}.png", gs)
    return out / "summary.md"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m gnwarp.eval.summarize", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("records", nargs="+", help="results records files (JSON lines)")
    ap.add_argument("--out", required=True, help="folder for summary.md and the plot (made if missing)")
    ap.add_argument("--title", default="Results", help="the summary's heading (default: Results)")
    ap.add_argument("--ratio", metavar="A/B", help="add a column: column A's mean as a share of column B's "
                    "(column names as in the table, e.g. 'gradient (learned)/ilqg (true, MuJoCo C)')")
    ap.add_argument("--no-plot", action="store_true", help="write summary.md only")
    args = ap.parse_args(argv)
    from gnwarp.eval.records import RecordError
    from gnwarp.files import check_output_path
    try:
        check_output_path(args.out, folder=True)   # before reading: a file where the folder goes, say
        records = [r for p in args.records for r in read_records(p)]
    except (RecordError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    ratio_of = tuple(args.ratio.split("/", 1)) if args.ratio else None
    if ratio_of and len(ratio_of) != 2:
        ap.error("--ratio takes two column names separated by '/'")
    path = write_summary(records, args.out, args.title, ratio_of, plot=not args.no_plot)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
