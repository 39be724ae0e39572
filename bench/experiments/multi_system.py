"""One model for several systems, and SwimmerN zero-shot.

- ``multi4``: one GN on Pendulum, Cartpole, Acrobot and Swimmer6 (batches mixed in equal
  proportion); ``multi5``: the same plus Cheetah. Each evaluated on every system's test split.
- ``swimmerN``: one GN on SwimmerN for N in {3, 4, 5, 6, 8, 9}, tested on N = 3..15 (7 and
  10-15 never seen in training).

Datasets are simulated with MuJoCo C on all cores; the three trainings run side by side on the one
device, each capped at ``--seconds`` of wall clock. Each run's errors on each test system are
results records (``gnwarp.eval.records``) in ``<out>/results.jsonl``; ``summary.md`` and
``errors.png`` are generated from them (``gnwarp.eval.summarize``).

    python bench/experiments/multi_system.py --seconds 300 --out bench/results/multi_system
    python bench/experiments/multi_system.py --quick
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from bench.harness import (add_run_args, add_training_args, device_name, ensure_dataset, experiment_out,  # noqa: E402
                           forward_args, gn_sizes, mean_errors, run_side_by_side, train_model)

RUNS = {
    "multi4": (["pendulum", "cartpole", "acrobot", "swimmer6"], ["pendulum", "cartpole", "acrobot", "swimmer6"]),
    "multi5": (["pendulum", "cartpole", "acrobot", "swimmer6", "cheetah"],
               ["pendulum", "cartpole", "acrobot", "swimmer6", "cheetah"]),
    "swimmerN": ([f"swimmer{n}" for n in (3, 4, 5, 6, 8, 9)], [f"swimmer{n}" for n in range(3, 16)]),
}


def child(args):
    from gnwarp import data
    from gnwarp import eval as ev
    from gnwarp.models import ModelConfig
    from gnwarp.train import load_model

    train_sys, test_sys = RUNS[args.run]
    out = Path(args.out) / args.run
    files = [str(Path(args.out) / "data" / f"{s}.h5") for s in train_sys]
    gn = gn_sizes(args.latent, args.edge_width, args.node_width)
    run = train_model(files, out, ModelConfig(core="gn", gn=gn), args.max_steps, seconds=args.seconds, lr=args.lr,
                      decay_every=args.max_steps // 4, valid_every=args.valid_every, valid=args.valid)
    model = load_model(Path(run["best"]))
    results = {}
    for s in test_sys:
        ds = data.load(Path(args.out) / "data" / f"{s}.h5", lazy=False)
        results[s] = mean_errors(ev.evaluate(model.bind(ds), ds, "test"))
        results[s]["seen_in_training"] = s in train_sys
    summary = {"run": args.run, "train_systems": train_sys, "steps": run["steps"], "seconds": run["seconds"],
               "results": results}
    (out / "results.json").write_text(json.dumps(summary, indent=1, default=float))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", default=",".join(RUNS))
    ap.add_argument("--steps", type=int, default=100, help="steps per simulated sequence")
    add_training_args(ap, seconds=300.0, max_steps=60000)
    add_run_args(ap, "multi_system", "--run")
    ap.add_argument("--valid", type=int, default=50, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        return child(args)
    if args.quick:
        args.sequences, args.steps, args.seconds, args.max_steps = (30, 4, 6), 12, 15.0, 40
        args.valid_every, args.latent, args.edge_width, args.node_width = 20, 16, 32, 16
    runs = args.runs.split(",")
    out = experiment_out("multi_system", args.out, args.quick)
    (out / "data").mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    needed = sorted({s for r in runs for s in RUNS[r][0] + RUNS[r][1]})
    for s in needed:
        trained = any(s in RUNS[r][0] for r in runs)
        sizes = tuple(args.sequences) if trained else (1, 1, args.sequences[2])  # test-only systems
        ensure_dataset(out / "data" / f"{s}.h5", s, sizes, args.steps, seed=2)
    t_data = time.perf_counter() - t0
    commands = {}
    for r in runs:
        commands[r] = [sys.executable, __file__, "--child", "--run", r, "--out", str(out),
                       *forward_args(args, "seconds", "max_steps", "lr", "valid_every", "latent", "edge_width",
                                     "node_width"), "--valid", str(args.sequences[1])]
    run_side_by_side(commands, out)
    print(f"datasets: {t_data:.0f} s", flush=True)
    from gnwarp.eval.records import git_commit, write_records
    from gnwarp.eval.summarize import write_summary
    records, commit, gpu = [], git_commit(), device_name()
    for r in runs:
        f = out / r / "results.json"
        if not f.exists():
            print(f"{r}: failed (see {r}.log)", flush=True)
            continue
        s = json.loads(f.read_text())
        config = {"sequences": list(args.sequences), "sequence_steps": args.steps, "seconds": args.seconds,
                  "gn": [args.latent, args.edge_width, args.node_width]}
        records += to_records(s, env_steps=args.sequences[0] * args.steps * len(s["train_systems"]), gpu=gpu,
                              commit=commit, date=time.strftime("%Y-%m-%d %H:%M"), config=config)
    write_records(out / "results.jsonl", records, append=False)
    print(f"wrote {write_summary(records, out, f'One model for several systems, and SwimmerN zero-shot ({gpu})')}")


HORIZONS = {"one_step": 1, "rollout_20": 20, "rollout_100": 100}


def to_records(s: dict, env_steps: int | None = None, gpu: str = "unknown", commit: str = "unknown",
               date: str = "", config: dict | None = None) -> list:
    """One run's ``results.json`` as results records of errors: per test system and horizon (1,
    20, 100 steps) the error normalized by the constant baseline, averaged over state groups and
    test sequences (``reported``: per-sequence errors are not kept); planner "none" on learned
    dynamics, the run ("multi4", "multi5", "swimmerN") as the variant. Metrics: the run's training
    steps and seconds, whether the test system is one it trained on (1 or 0). ``env_steps``:
    simulated steps of the training data (None: not recorded)."""
    from gnwarp.eval.records import ResultRecord
    from gnwarp.sim import systems
    out = []
    for name, r in s["results"].items():
        system = systems.make(name)
        for key, horizon in HORIZONS.items():
            if r.get(key) is None:
                continue
            out.append(ResultRecord(
                experiment="multi_system", task=name, system=name, planner="none", dynamics="learned",
                variant=s["run"], episodes=int(r["sequences"]), episode_steps=horizon,
                reported={"mean": float(r[key]), "std": None, "of": "errors"},
                control_dt=float(system.dt), action_repeat=int(system.substeps), env_steps=env_steps,
                metrics={"train_steps": s["steps"], "train_seconds": round(float(s["seconds"]), 1),
                         "seen_in_training": int(bool(r["seen_in_training"]))},
                config={"train_systems": s["train_systems"], "finite": r.get("finite"), **(config or {})},
                commit=commit, gpu=gpu, date=date))
    return out

if __name__ == "__main__":
    main()
