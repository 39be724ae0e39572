"""Reports of evaluation results: markdown tables, bar charts of the normalized errors (like the
paper's Figs. 4-5), state traces along a rollout (Fig. H.1), training curves, and all of them
written to one folder (``write_report``, what ``gnwarp evaluate -o`` and ``gnwarp demo`` write)."""
from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from gnwarp.state import DYN_NODE_NAMES, GROUPS

__all__ = ["markdown_table", "plot_errors", "plot_state_traces", "plot_training", "write_report"]


def _pyplot():
    """matplotlib.pyplot on the Agg backend (figures go to files, never to a display)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _save(fig, path, dpi: int) -> Path:
    """Write ``fig`` to ``path`` at ``dpi`` and close it; returns the path."""
    path = Path(path)
    fig.savefig(path, dpi=dpi)
    _pyplot().close(fig)
    return path


def _fmt(x: float) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "n/a"          # a group the constant baseline predicts exactly: no ratio
    if isinstance(x, float) and math.isinf(x):
        return "non-finite"   # the model's predictions left the finite range
    return f"{x:.3g}"


def _nonfinite(r: dict) -> str:
    """The "first non-finite step" cell of one model's ``evaluate`` results."""
    step = r.get("first_nonfinite_step")
    if step is not None:
        return f"{step} ({r.get('nonfinite_sequences', '?')} of {r.get('sequences', '?')} sequences)"
    n = r.get("one_step", {}).get("nonfinite_steps", 0)
    return f"one-step: {n} predictions" if n else "none"


def rollout_label(asked: int, used: int | None = None, short: bool = False) -> str:
    """A rollout column's name: "H-step rollout", or, where the data's sequences held fewer steps
    than asked, the steps used with the ones asked ("19-step rollout (100 asked: the data's
    length)"), so that two columns of the same steps never read as different horizons."""
    word = "step" if short else "step rollout"
    if used is None or int(used) == int(asked):
        return f"{asked}-{word}"
    return f"{used}-{word} ({asked} asked: the data's length)"


def _column(key: str, r: dict, short: bool = False) -> str:
    if key == "one_step":
        return "one-step"
    return rollout_label(int(key.split("_")[1]), r[key].get("steps"), short)


def markdown_table(results: dict[str, dict], system: str = "") -> str:
    """Markdown tables of normalized errors: ``results`` is {model name: ``evaluate`` output}; a
    "constant" row (1 by definition) is added. First the mean over groups per horizon, with the
    first rollout step at which a model's predictions left the finite range ("non-finite"
    errors), then the per-group ratios of each horizon."""
    first = next(iter(results.values()))
    keys = [k for k in first if k == "one_step" or k.startswith("rollout_")]
    head = {k: _column(k, first) for k in keys}
    lines = [f"Normalized error{f' on {system}' if system else ''} (model / constant-prediction baseline; "
             f"lower is better):", "", "| model | " + " | ".join(head[k] for k in keys) + " | first non-finite step |",
             "|---|" + "---|" * (len(keys) + 1)]
    for name, r in results.items():
        lines.append(f"| {name} | " + " | ".join(_fmt(r[k]["mean"]) for k in keys) + f" | {_nonfinite(r)} |")
    lines.append("| constant | " + " | ".join("1" for _ in keys) + " | none |")
    lines += ["", "Per state group (position, orientation, linear and angular velocity; n/a: the constant "
              "baseline predicts the group exactly, so it has no ratio):", "",
              "| model | horizon | pos | quat | linvel | angvel |", "|---|---|---|---|---|---|"]
    for name, r in results.items():
        for k in keys:
            lines.append(f"| {name} | {head[k]} | " + " | ".join(_fmt(r[k][g]) for g in GROUPS) + " |")
    return "\n".join(lines) + "\n"


def plot_errors(results: dict[str, dict], path, title: str = "") -> Path:
    """Bar chart of normalized errors per horizon, one bar per model plus the constant baseline
    (log scale, like the paper's Figs. 4-5)."""
    plt = _pyplot()
    keys = [k for k in next(iter(results.values())) if k == "one_step" or k.startswith("rollout_")]
    names = list(results) + ["constant"]
    vals = np.array([[results[n][k]["mean"] if n != "constant" else 1.0 for k in keys] for n in names])
    vals[~np.isfinite(vals)] = np.nan   # no bar for a non-finite error (the table names its step)
    fig, ax = plt.subplots(figsize=(1.6 + 1.6 * len(keys), 3.2))
    width = 0.8 / len(names)
    colors = ["tab:red", "tab:blue", "tab:green", "tab:purple", "tab:orange", "0.6"]
    for i, n in enumerate(names):
        c = "0.6" if n == "constant" else colors[i % (len(colors) - 1)]
        ax.bar(np.arange(len(keys)) + (i - (len(names) - 1) / 2) * width, vals[i], width, label=n, color=c)
    ax.set_xticks(np.arange(len(keys)))
    ax.set_xticklabels([_column(k, results[names[0]], short=True) for k in keys])
    ax.set_yscale("log")
    ax.set_ylabel("error / constant baseline")
    ax.set_title(title)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, path, 120)


def plot_state_traces(true: np.ndarray, preds: dict[str, np.ndarray], dt: float, path, title: str = "") -> Path:
    """The 13 state variables of one body along a rollout, true vs predicted (like Fig. H.1).
    ``true`` [H+1, 13], ``preds`` {name: [H+1, 13]}."""
    plt = _pyplot()
    t = np.arange(true.shape[0]) * dt
    fig, axes = plt.subplots(4, 4, figsize=(12, 8), sharex=True)
    styles = [("tab:red", "--"), ("tab:blue", ":"), ("tab:green", "-.")]
    for k, ax in enumerate(axes.flat):
        if k >= true.shape[1]:
            ax.axis("off")
            continue
        ax.plot(t, true[:, k], color="k", lw=1.5, label="true")
        for j, (name, p) in enumerate(preds.items()):
            c, ls = styles[j % len(styles)]
            ax.plot(t, p[:, k], color=c, ls=ls, lw=1.2, label=name)
        ax.set_title(DYN_NODE_NAMES[k], fontsize=9)
        ax.tick_params(labelsize=7)
    axes.flat[0].legend(fontsize=7)
    for ax in axes[-1]:
        ax.set_xlabel("time (s)", fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    return _save(fig, path, 110)


def plot_training(logs: dict[str, Path], path) -> Path:
    """Training loss and validation error against training steps, one line per run: ``logs``
    {run name: its ``log.csv`` (``gnwarp.train``)}; at most two runs (red, blue)."""
    plt = _pyplot()
    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.2))
    for (name, p), c in zip(logs.items(), ("tab:red", "tab:blue")):
        rows = list(csv.DictReader(open(p)))
        tr = [(int(r["step"]), float(r["loss"])) for r in rows if r.get("loss")]
        va = [(int(r["step"]), float(r["valid_error"])) for r in rows if r.get("valid_error")]
        if tr:
            a.plot(*zip(*tr), color=c, label=name)
        if va:
            b.plot(*zip(*va), "o-", color=c, label=name)
    a.set(yscale="log", xlabel="training step", ylabel="training loss (with input noise)")
    b.set(yscale="log", xlabel="training step", ylabel="20-step rollout error (valid)")
    a.legend(fontsize=8)
    b.legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, path, 110)


def write_report(results: dict[str, dict], dataset, out, rollouts: int = 3, renderer: str = "matplotlib") -> str:
    """Write the report of ``evaluate`` results (``results``: {model name: its output}) on
    ``dataset`` into the folder ``out`` (made if missing): ``errors.md`` (``markdown_table``),
    ``errors.png`` (``plot_errors``) and, where the results kept their predictions
    (``keep_predictions=True``; they are popped from ``results``), ``states.png`` (the 13 state
    variables of one body along the first test rollout) and ``rollouts.gif`` (the first
    ``rollouts`` rollouts, true vs predicted, drawn by ``renderer``, as ``animate``'s). Returns
    the markdown table."""
    from gnwarp.eval.animation import animate
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    system = dataset.system
    preds = {n: r.pop("predictions", None) for n, r in results.items()}
    table = markdown_table(results, system)
    (out / "errors.md").write_text(table)
    plot_errors(results, out / "errors.png", f"{system}: normalized errors")
    first = next(iter(preds.values()))
    if first is not None:
        true, inst = first["true"], first["instance"]
        body = 1 if true.shape[2] > 1 else 0   # the first body that moves in a chain fixed to the world
        plot_state_traces(true[0, :, body], {n: p["pred"][0, :, body] for n, p in preds.items()}, dataset.dt,
                          out / "states.png", f"{system}, body {body}: {true.shape[1] - 1}-step rollout")
        k = min(rollouts, true.shape[0])
        animate(true[:k], {n: p["pred"][:k] for n, p in preds.items()}, dataset, inst[:k], out / "rollouts.gif",
                title=f"{system}: true (grey) vs predicted rollouts", renderer=renderer)
    return table
