"""Issue 14, "then use it": the seven systems re-trained at the 220 s budget of the committed
forward-model table (``bench/results/forward_models/summary.md``, trained before the training step
was captured), now with the library's captured training step, one system after another on the
one GPU; steps reached and one/20/100-step errors before and after, side by side.

Same data (2000/50/200 sequences x 100 steps, MuJoCo C, seed 1), GN sizes (latent 128, edge MLP
2x256, node/global 2x128), batch 200, learning rate 1e-3 x0.6 every quarter of the run, validation
on 50 sequences. The "quarter of the run" needs the run's length: a short calibration (1000
captured steps after 300 warm ones) measures each system's steps/s and the schedule is laid over
``rate x seconds`` steps; the wall-clock cap stops the run either way.

    python bench/experiments/budget_retrain.py [--systems pendulum,cheetah] [--seconds 220]
    python bench/experiments/budget_retrain.py --quick      # tiny CPU smoke run
"""
from __future__ import annotations

import argparse
import json
import re
import sys
import tarfile
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from bench.harness import SYSTEMS, device_name, ensure_dataset, gn_sizes, mean_errors  # noqa: E402

BEFORE = Path(__file__).resolve().parents[1] / "results" / "forward_models" / "summary.md"


def before_table(path: Path = BEFORE) -> dict[str, dict]:
    """{system: {"steps", "one_step", "rollout_20", "rollout_100"}} of the committed GN table."""
    rows = {}
    if not path.exists():
        return rows
    for line in path.read_text().splitlines():
        m = re.match(r"\|\s*(\w+)\s*\|\s*(\d+)\s*\(\d+\)\s*\|\s*([\d.e+-]+)\s*\|\s*([\d.e+-]+)\s*\|\s*([\d.e+-]+)\s*\|", line)
        if m:
            rows[m.group(1)] = {"steps": int(m.group(2)), "one_step": float(m.group(3)),
                                "rollout_20": float(m.group(4)), "rollout_100": float(m.group(5))}
    return rows


def config(args, data, out, steps, seconds, **kw):
    from gnwarp.models import ModelConfig
    from gnwarp.train import TrainConfig
    return TrainConfig(data=[str(data)], out=str(out), model=ModelConfig(gn=gn_sizes(args.latent, args.edge_width,
                                                                                       args.node_width)),
                       steps=steps, max_seconds=seconds, batch_size=200, lr=1e-3, lr_decay=0.6,
                       lr_decay_steps=max(1, steps // 4), valid_every=args.valid_every, valid_sequences=args.valid,
                       patience=None, checkpoint_every=max(1, steps), resume=False, progress=False,
                       device=args.device, optimizer="flat_adam", **kw)


def steps_per_second(args, data, tmp) -> float:
    """Captured steps/s of this system's training step (after warm-up), validation excluded."""
    import torch

    from gnwarp.train import Trainer
    t = Trainer(config(args, data, Path(tmp) / "calibrate", 10**6, None))
    for _ in range(args.calib[0]):
        t.step()
    sync = torch.cuda.synchronize if t.device.type == "cuda" else (lambda: None)
    sync()
    t0 = time.perf_counter()
    for _ in range(args.calib[1]):
        t.step()
    sync()
    return args.calib[1] / (time.perf_counter() - t0)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--systems", default=",".join(SYSTEMS))
    ap.add_argument("--seconds", type=float, default=220.0)
    ap.add_argument("--sequences", type=int, nargs=3, default=(2000, 50, 200))
    ap.add_argument("--steps", type=int, default=100, help="steps per simulated sequence")
    ap.add_argument("--latent", type=int, default=128)
    ap.add_argument("--edge-width", type=int, default=256)
    ap.add_argument("--node-width", type=int, default=128)
    ap.add_argument("--valid-every", type=int, default=2000)
    ap.add_argument("--device", default="auto")
    ap.add_argument("--data", default=None, help="dataset folder (default: a temporary one)")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "results" / "budget_retrain"))
    ap.add_argument("--checkpoints", default=None, help="also pack the best checkpoints into this .tar.gz")
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    args.valid = args.sequences[1]
    args.calib = (300, 1000)
    if args.quick:
        args.sequences, args.steps, args.seconds, args.valid = (40, 5, 10), 20, 8.0, 5
        args.latent, args.edge_width, args.node_width, args.valid_every, args.calib = 16, 32, 16, 100, (5, 20)
        args.device, args.out = "cpu", tempfile.mkdtemp(prefix="budget_retrain_")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    from gnwarp.data import load
    from gnwarp.eval.metrics import evaluate
    from gnwarp.train import Trainer, load_model

    before = before_table()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        data_dir = Path(args.data or tmp)
        data_dir.mkdir(parents=True, exist_ok=True)
        runs = Path(tmp) / "runs"
        for name in args.systems.split(","):
            t0 = time.perf_counter()
            data = ensure_dataset(data_dir / f"{name}.h5", name, args.sequences, args.steps, seed=1)
            t_data = time.perf_counter() - t0
            rate = steps_per_second(args, data, tmp)
            planned = max(4, int(rate * args.seconds))
            result = Trainer(config(args, data, runs / name, planned, args.seconds)).run()
            ds = load(data, lazy=False)
            model = load_model(result["best"], device=args.device)
            errs = mean_errors(evaluate(model, ds, "test", horizons=(20, 100)))
            row = {"system": name, "device": device_name(model.device), "seconds_budget": args.seconds,
                   "calibrated_steps_per_s": round(rate, 1), "planned_steps": planned, "steps": result["steps"],
                   "seconds": round(result["seconds"], 1), "steps_per_s": round(result["steps_per_second"], 1),
                   "one_step": errs["one_step"], "rollout_20": errs["rollout_20"], "rollout_100": errs["rollout_100"],
                   "data_seconds": round(t_data, 1), "before": before.get(name)}
            rows.append(row)
            print(json.dumps(row), flush=True)
        if args.checkpoints:
            with tarfile.open(args.checkpoints, "w:gz") as tar:
                for r in rows:
                    tar.add(runs / r["system"] / "best", arcname=f"{r['system']}/best")
    with open(out / "results.jsonl", "a") as f:
        for r in rows:
            f.write(json.dumps(r) + "\n")
    write_table(out, rows, args)
    plot(out, rows)


def _g(x) -> str:
    return "-" if x is None else f"{x:.2g}"


def write_table(out: Path, rows: list[dict], args) -> None:
    dev = rows[0]["device"] if rows else "?"
    lines = [f"# The seven systems re-trained at the same budget, before and after captured training ({dev})", "",
             f"`python bench/experiments/budget_retrain.py` ({time.strftime('%Y-%m-%d')}): GN training capped at "
             f"{args.seconds:g} s per system. Before: the committed table `bench/results/forward_models/summary.md` "
             "(all seven side by side, eager training loop). After: one system at a time, the library's captured "
             "step (tf32, FlatAdam), learning-rate schedule laid over the steps the calibrated rate allows. Errors: "
             "squared error / constant-prediction baseline, mean over the state groups, 200 test sequences.", "",
             "| system | steps before | steps after | x | one-step before | after | 20-step before | after | "
             "100-step before | after |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        b = r["before"] or {}
        x = f"{r['steps'] / b['steps']:.1f}x" if b.get("steps") else "-"
        lines.append(f"| {r['system']} | {b.get('steps', '-')} | {r['steps']} | {x} | {_g(b.get('one_step'))} | "
                     f"{_g(r['one_step'])} | {_g(b.get('rollout_20'))} | {_g(r['rollout_20'])} | "
                     f"{_g(b.get('rollout_100'))} | {_g(r['rollout_100'])} |")
    (out / "summary.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def plot(out: Path, rows: list[dict]) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    names = [r["system"] for r in rows]
    x = np.arange(len(rows))
    fig, axes = plt.subplots(1, 4, figsize=(16, 3.6))
    for ax, key, title in zip(axes, ("steps", "one_step", "rollout_20", "rollout_100"),
                              ("training steps in the budget", "one-step error", "20-step error", "100-step error")):
        b = [np.nan if not r["before"] else r["before"][key] for r in rows]
        a = [r[key] for r in rows]
        ax.bar(x - 0.2, b, 0.4, label="before (eager loop)")
        ax.bar(x + 0.2, a, 0.4, label="after (captured step)")
        ax.set_yscale("log")
        ax.set_xticks(x, names, rotation=45)
        ax.set_title(title)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "before_after.png", dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
