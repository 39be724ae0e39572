"""Plots of a data loop from its records (``records.jsonl``): the returns of each iteration's
episodes against the env steps trained on, and the model's errors on the states each iteration
visited before training on them beside its errors on the data it had trained on (the paper's
Figure H.1, per iteration)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from gnwarp.control.loop_store import RECORDS_FILE

__all__ = ["loop_curves", "plot_loop"]


def loop_curves(records) -> dict:
    """{"iteration" [K], "env_steps" [K], "model_env_steps" [K], "mean" [K], "returns" (K lists),
    "errors": {"new" | "trained": {"one_step" [K], "rollout" [K]}}, and of the evaluation
    episodes where the loop ran them: "eval_env_steps" [K'], "eval_mean" [K']} from a loop's
    records (a list of ``ResultRecord`` or a records file / loop folder), ordered by iteration."""
    from gnwarp.eval.records import read_records
    if isinstance(records, (str, Path)):
        p = Path(records)
        records = read_records(p / RECORDS_FILE if p.is_dir() else p)
    records = [r for r in records if r.experiment == "loop"]
    recs = sorted((r for r in records if r.variant == "loop"), key=lambda r: r.metrics["iteration"])
    evals = sorted((r for r in records if r.variant == "loop-eval"), key=lambda r: r.metrics["iteration"])
    if not recs:
        raise ValueError("no data-loop records to plot")

    def err(r, which, kind):
        v = r.metrics.get("errors", {}).get(which, {}).get(kind)
        return math.nan if v is None else float(v)
    return {"iteration": np.array([r.metrics["iteration"] for r in recs]),
            "env_steps": np.array([r.env_steps for r in recs]),
            "model_env_steps": np.array([r.metrics.get("model_env_steps", math.nan) for r in recs], dtype=float),
            "mean": np.array([np.nanmean(r.values) for r in recs]),
            "returns": [r.values for r in recs],
            "errors": {w: {k: np.array([err(r, w, k) for r in recs]) for k in ("one_step", "rollout")}
                       for w in ("new", "trained")},
            "eval_env_steps": np.array([r.env_steps for r in evals]),
            "eval_mean": np.array([np.nanmean(r.values) for r in evals]),
            "task": recs[0].task, "planner": recs[0].planner}


def plot_loop(records, path, dpi: int = 120) -> Path:
    """Two panels written to ``path`` (PNG): returns per episode (dots) and their mean (line)
    against the env steps trained on after each iteration; normalized one-step and rollout
    errors per iteration on the newly visited states (before training) and on the trained data."""
    import matplotlib
    matplotlib.use("Agg")   # figures go to files, never to a display
    import matplotlib.pyplot as plt
    c = loop_curves(records)
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    for x, rets in zip(c["env_steps"], c["returns"]):
        a.scatter(np.full(len(rets), x), rets, s=6, color="tab:blue", alpha=0.35)
    a.plot(c["env_steps"], c["mean"], "-o", color="tab:blue", ms=3, label="mean return (data episodes)")
    if len(c["eval_mean"]):
        a.plot(c["eval_env_steps"], c["eval_mean"], "-s", color="tab:green", ms=3, label="mean return (evaluation)")
    a.set_xlabel("env steps trained on")
    a.set_ylabel("return")
    a.set_title(f"{c['task']}: {c['planner']} through the learned model")
    a.legend(loc="best")
    styles = {("new", "one_step"): ("tab:red", "-"), ("new", "rollout"): ("tab:red", "--"),
              ("trained", "one_step"): ("tab:gray", "-"), ("trained", "rollout"): ("tab:gray", "--")}
    labels = {"new": "visited states (before training)", "trained": "training data"}
    for (w, k), (color, ls) in styles.items():
        y = c["errors"][w][k]
        if np.isfinite(y).any():
            b.plot(c["iteration"], y, ls, color=color, marker="o", ms=3,
                   label=f"{'one-step' if k == 'one_step' else 'rollout'}: {labels[w]}")
    b.set_yscale("log")
    b.set_xlabel("iteration")
    b.set_ylabel("normalized error (model / constant)")
    b.set_title("model error where control goes (Figure H.1)")
    b.legend(loc="best", fontsize=8)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path
