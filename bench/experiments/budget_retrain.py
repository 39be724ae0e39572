"""The seven systems re-trained at the 220 s budget of the committed forward-model table
(``bench/results/forward_models/``, trained with the eager training loop), with the library's
captured training step, one system after another on the one GPU; steps reached and one/20/100-step
errors before and after, side by side.

Same data (2000/50/200 sequences x 100 steps, MuJoCo C, seed 1), GN sizes (latent 128, edge MLP
2x256, node/global 2x128), batch 200, learning rate 1e-3 x0.6 every quarter of the run, validation
on 50 sequences. The "quarter of the run" needs the run's length: a short calibration (1000
captured steps after 300 warm ones) measures each system's steps/s and the schedule is laid over
``rate x seconds`` steps; the wall-clock cap stops the run either way.

Each system's errors are results records (``gnwarp.eval.records``) in ``<out>/results.jsonl``:
variant "captured loop" (this run) and "eager loop" (the forward-model table's GN, from its
records); ``summary.md`` is generated from them (``gnwarp.eval.summarize``).

    python bench/experiments/budget_retrain.py [--systems pendulum,cheetah] [--seconds 220]
    python bench/experiments/budget_retrain.py --quick      # tiny CPU smoke run
"""
from __future__ import annotations

import argparse
import json
import sys
import tarfile
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from bench.harness import SYSTEMS, device_name, ensure_dataset, gn_sizes, mean_errors  # noqa: E402

BEFORE = Path(__file__).resolve().parents[1] / "results" / "forward_models" / "results.jsonl"
HORIZONS = {"one_step": 1, "rollout_20": 20, "rollout_100": 100}
# the summary's ratio: the captured loop's error as a share of the eager loop's
RATIO = ("none (learned, captured loop)", "none (learned, eager loop)")


def before_table(path: Path = BEFORE) -> dict[str, dict]:
    """{system: {"steps", "one_step", "rollout_20", "rollout_100"}} of the forward-model table's GN
    (its results records; {} without them)."""
    from gnwarp.eval.records import read_records
    rows = {}
    if not path.exists():
        return rows
    names = {h: k for k, h in HORIZONS.items()}
    for r in read_records(path):
        if r.variant == "GN" and r.episode_steps in names:
            row = rows.setdefault(r.task, {"steps": r.metrics.get("train_steps")})
            row[names[r.episode_steps]] = r.reported["mean"]
    return rows


def to_records(row: dict, commit: str = "unknown") -> list:
    """One system's row as results records of errors: per horizon (1, 20, 100 steps) the error
    normalized by the constant baseline, averaged over state groups and the 200 test sequences
    (``reported``: per-sequence errors are not kept); planner "none" on learned dynamics, variant
    "captured loop", and, where the row holds the forward-model table's numbers (``before``),
    "eager loop" records with those. Metrics: training steps (and seconds, steps/s, calibration)."""
    from gnwarp.eval.records import ResultRecord
    from gnwarp.sim import systems
    system = systems.make(row["system"])
    common = dict(experiment="budget_retrain", task=row["system"], system=row["system"], planner="none",
                  dynamics="learned", episodes=int(row.get("test_sequences", 200)), control_dt=float(system.dt),
                  action_repeat=int(system.substeps), env_steps=row.get("env_steps"), commit=commit,
                  gpu=row.get("device", "unknown"), date=row.get("date", ""))
    after = {"train_steps": row["steps"], "train_seconds": row["seconds"], "steps_per_s": row["steps_per_s"],
             "calibrated_steps_per_s": row["calibrated_steps_per_s"], "planned_steps": row["planned_steps"]}
    out = []
    for variant, values, metrics in (("captured loop", row, after),
                                     ("eager loop", row.get("before"), {"train_steps": (row.get("before") or {}).get("steps")})):
        if not values:
            continue
        for key, horizon in HORIZONS.items():
            out.append(ResultRecord(variant=variant, episode_steps=horizon,
                                    reported={"mean": float(values[key]), "std": None, "of": "errors"},
                                    metrics={k: v for k, v in metrics.items() if v is not None},
                                    config={"seconds_budget": row["seconds_budget"]}, **common))
    return out


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
                   "data_seconds": round(t_data, 1), "before": before.get(name),
                   "test_sequences": len(ds["test"]), "env_steps": args.sequences[0] * args.steps,
                   "date": time.strftime("%Y-%m-%d %H:%M")}
            rows.append(row)
            print(json.dumps(row), flush=True)
        if args.checkpoints:
            with tarfile.open(args.checkpoints, "w:gz") as tar:
                for r in rows:
                    tar.add(runs / r["system"] / "best", arcname=f"{r['system']}/best")
    from gnwarp.eval.records import git_commit, write_records
    commit = git_commit()
    write_records(out / "results.jsonl", [x for r in rows for x in to_records(r, commit=commit)])
    report(out)


def report(out: Path) -> Path:
    """``summary.md`` from ``out/results.jsonl`` (``gnwarp.eval.summarize``)."""
    from gnwarp.eval.records import read_records
    from gnwarp.eval.summarize import write_summary
    records = read_records(out / "results.jsonl")
    title = (f"The seven systems re-trained at the same budget, before and after captured training "
             f"({records[-1].gpu})")
    path = write_summary(records, out, title, ratio_of=RATIO)
    print(f"wrote {path}")
    return path

if __name__ == "__main__":
    main()
