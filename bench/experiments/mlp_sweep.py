"""The MLP baseline sweep of section E: the five MLP sizes per system, each trained for the same
number of steps as the GN of ``bench/experiments/forward_models.py`` on the same data (regenerated
from the same seed), evaluated the same way; the best MLP per system is the paper's baseline.

Each (system, model, horizon) is a results record (``gnwarp.eval.records``) in
``<out>/results.jsonl``: the MLPs (variant "MLP <size>") and, beside them, the GN of the
forward-model experiment (variant "GN", from its ``<system>/results.json``); ``summary.md`` and
``errors.png`` are generated from them (``gnwarp.eval.summarize``).

    python bench/experiments/mlp_sweep.py --gn-results bench/results/forward_models --out bench/results/mlp_sweep
    python bench/experiments/mlp_sweep.py --quick
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from bench.harness import (SYSTEMS, add_run_args, ensure_dataset, experiment_out, mean_errors,  # noqa: E402
                           results_dir, run_side_by_side, train_model)
from gnwarp.models import MLP_SIZES  # noqa: E402


def child(args):
    from gnwarp import data
    from gnwarp import eval as ev
    from gnwarp.models import MLPCoreConfig, ModelConfig
    from gnwarp.train import load_model
    ds_path = str(Path(args.out) / "data" / f"{args.system}.h5")
    ds = data.load(ds_path, lazy=False)
    for size in [args.size] if args.size else MLP_SIZES:
        out = Path(args.out) / args.system / size
        model = ModelConfig(core="mlp", mlp=MLPCoreConfig.preset(size))
        run = train_model([ds_path], out, model, args.train_steps, lr=args.lr, decay_every=args.decay_every,
                          valid_every=args.valid_every, valid=args.valid)
        res = mean_errors(ev.evaluate(load_model(run["best"]).bind(ds), ds, "test"))
        res["steps"] = run["steps"]
        (out / "results.json").write_text(json.dumps(res, indent=1, default=float))


def collect(out: Path, system: str) -> dict:
    """The finished sizes of one system: per-size files, or the older one-file-per-system form."""
    f = out / system / "results.json"
    res = json.loads(f.read_text()) if f.exists() else {}
    for size in MLP_SIZES:
        g = out / system / size / "results.json"
        if g.exists():
            res[size] = json.loads(g.read_text())
    return res


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--systems", default=",".join(SYSTEMS))
    ap.add_argument("--gn-results", default=results_dir("forward_models"),
                    help="bench/experiments/forward_models.py's results (their steps, data sizes and schedule)")
    add_run_args(ap, "mlp_sweep", "--system", "--size")
    ap.add_argument("--deadline", type=float, default=None,
                    help="seconds after which unfinished trainings are stopped and the table written")
    ap.add_argument("--train-steps", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--lr", type=float, default=1e-3, help=argparse.SUPPRESS)
    ap.add_argument("--decay-every", type=int, default=10000, help=argparse.SUPPRESS)
    ap.add_argument("--valid-every", type=int, default=2000, help=argparse.SUPPRESS)
    ap.add_argument("--valid", type=int, default=50, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        return child(args)
    names = args.systems.split(",")
    out = experiment_out("mlp_sweep", args.out, args.quick)
    (out / "data").mkdir(parents=True, exist_ok=True)
    gn = {}
    commands = {}
    for s in names:
        g = json.loads((Path(args.gn_results) / s / "results.json").read_text())
        gn[s] = g
        cfg = g["config"]
        sizes = (cfg["train_sequences"], cfg["valid_sequences"], cfg["test_sequences"]) if not cfg.get("dataset") \
            else tuple(g["dataset"][k] for k in ("train", "valid", "test"))
        steps, valid_every, decay = g["gn"]["steps"], cfg["valid_every"], cfg["lr_decay_every"]
        if args.quick:
            sizes, steps, valid_every, decay = (30, 4, 8), 40, 20, 20
        # the same data as bench/experiments/forward_models.py (seed 1, MuJoCo C)
        ensure_dataset(out / "data" / f"{s}.h5", s, sizes, g["num_steps"] if not args.quick else 20, seed=1)
        for size in MLP_SIZES:  # one process per (system, size)
            commands[f"{s}_{size}"] = [sys.executable, __file__, "--child", "--system", s, "--size", size,
                                       "--out", str(out), "--train-steps", str(steps), "--lr", str(cfg["lr"]),
                                       "--decay-every", str(decay), "--valid-every", str(valid_every),
                                       "--valid", str(sizes[1])]
    run_side_by_side(commands, out, threads=1, deadline=args.deadline)
    for s in SYSTEMS:  # systems measured in earlier runs stay in the table
        if s not in gn and (Path(args.gn_results) / s / "results.json").exists() and collect(out, s):
            gn[s] = json.loads((Path(args.gn_results) / s / "results.json").read_text())
            names.append(s)
    from gnwarp.eval.records import git_commit, write_records
    from gnwarp.eval.summarize import write_summary
    records, commit = [], git_commit()
    for s in names:
        r = collect(out, s)
        if not r:
            print(f"{s}: failed (see {s}_*.log)", flush=True)
        records += to_records(s, gn[s], r, commit=commit)
    write_records(out / "results.jsonl", records, append=False)
    title = "MLP baseline sweep (section E) beside the GN of bench/experiments/forward_models.py"
    print(f"wrote {write_summary(records, out, title)}")


HORIZONS = {"one_step": 1, "rollout_20": 20, "rollout_100": 100}


def to_records(system: str, gn: dict, mlps: dict, gpu: str = "unknown", commit: str = "unknown",
               date: str = "") -> list:
    """One system's errors as results records: the GN (``gn``: the forward-model experiment's
    ``results.json`` of the system) and each MLP size of ``mlps`` ({size: its results.json}), per
    horizon (1, 20, 100 steps) the error normalized by the constant baseline, averaged over state
    groups and test sequences (``reported``: per-sequence errors are not kept); planner "none" on
    learned dynamics, variants "GN" and "MLP <size>". Metrics: training steps."""
    from gnwarp.eval.records import ResultRecord
    from gnwarp.sim import systems
    sim = systems.make(system)
    env_steps = int(gn["dataset"]["train"]) * int(gn["num_steps"]) if gn.get("dataset") else None
    g = gn["results"]["GN"]
    runs = [("GN", {k: g[k]["mean"] for k in HORIZONS if k in g} | {"sequences": g["sequences"]}, gn["gn"]["steps"])]
    runs += [(f"MLP {size}", r, r["steps"]) for size, r in mlps.items()]
    out = []
    for variant, r, steps in runs:
        for key, horizon in HORIZONS.items():
            if r.get(key) is None:
                continue
            out.append(ResultRecord(
                experiment="mlp_sweep", task=system, system=system, planner="none", dynamics="learned",
                variant=variant, episodes=int(r["sequences"]), episode_steps=horizon,
                reported={"mean": float(r[key]), "std": None, "of": "errors"}, control_dt=float(sim.dt),
                action_repeat=int(sim.substeps), env_steps=env_steps, metrics={"train_steps": int(steps)},
                commit=commit, gpu=gpu, date=date))
    return out

if __name__ == "__main__":
    main()
