"""Experiments 2 and 3 of issue 4: one model for several systems, and SwimmerN zero-shot.

- ``multi4``: one GN on Pendulum, Cartpole, Acrobot and Swimmer6 (batches mixed in equal
  proportion); ``multi5``: the same plus Cheetah. Each evaluated on every system's test split.
- ``swimmerN``: one GN on SwimmerN for N in {3, 4, 5, 6, 8, 9}, tested on N = 3..15 (7 and
  10-15 never seen in training).

Datasets are simulated with MuJoCo C on all cores; the three trainings run side by side on the one
device, each capped at ``--seconds`` of wall clock.

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
                           forward_args, gn_sizes, mean_errors, run_side_by_side, train_model, write_summary)

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
    lines = [f"# One model for several systems, and SwimmerN zero-shot ({device_name()})", "",
             f"Data: {args.sequences[0]}/{args.sequences[1]}/{args.sequences[2]} sequences x {args.steps} steps per "
             f"trained system (MuJoCo C, {t_data:.0f} s); GN latent {args.latent}, edge MLP 2x{args.edge_width}, node/"
             f"global 2x{args.node_width}; each run capped at {args.seconds:g} s of training, the runs side by side on "
             "one device. Errors: model / constant baseline, averaged over state groups.", "",
             "| run | steps | test system | seen in training | one-step | 20-step | 100-step |", "|---|---|---|---|---|---|---|"]
    for r in runs:
        f = out / r / "results.json"
        if not f.exists():
            lines.append(f"| {r} | failed (see {r}.log) | | | | | |")
            continue
        s = json.loads(f.read_text())
        for name, v in s["results"].items():
            lines.append(f"| {r} | {s['steps']} | {name} | {'yes' if v['seen_in_training'] else 'no'} | "
                         f"{_f(v.get('one_step'))} | {_f(v.get('rollout_20'))} | {_f(v.get('rollout_100'))} |")
    write_summary(out, lines)


def _f(x) -> str:
    return "n/a" if x is None else f"{x:.3g}"


if __name__ == "__main__":
    main()
