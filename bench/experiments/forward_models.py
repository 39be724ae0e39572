"""Forward models per fixed system: a GN and an MLP baseline at the same training
budget, evaluated like the paper (one-step, 20- and 100-step rollout errors normalized by the
constant-prediction baseline), plus 1000-step stability rollouts of each GN.

Datasets are simulated first (MuJoCo C on all cores), then one training process per system runs
side by side on the one GPU (the GPU has room for many small models; the step loops are
launch-bound, so processes overlap). Each process runs ``gnwarp.demo.run_demo`` on its dataset
with a wall-clock cap, then a 1000-step rollout of the best GN under new random controls.

Each system's errors are results records (``gnwarp.eval.records``) in ``<out>/results.jsonl``;
``summary.md`` and ``errors.png`` are generated from them (``gnwarp.eval.summarize``).

    python bench/experiments/forward_models.py --seconds 240 --out bench/results/forward_models
    python bench/experiments/forward_models.py --quick      # tiny CPU smoke run
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from bench.harness import (SYSTEMS, add_run_args, add_training_args, device_name, ensure_dataset,  # noqa: E402
                           experiment_out, forward_args, gn_sizes, run_side_by_side)


def child(args) -> None:
    """One system: train GN and MLP (run_demo), then a 1000-step GN stability rollout."""
    import numpy as np
    import torch

    from gnwarp import data, sim
    from gnwarp.demo import DemoConfig, run_demo
    from gnwarp.train import load_model

    cfg = DemoConfig(out=args.child_out, system=args.system, dataset=args.dataset,
                     valid_sequences=args.valid_eval, train_steps=args.max_steps, train_seconds=args.seconds,
                     lr=args.lr, lr_decay=0.6, lr_decay_every=max(1, args.max_steps // 4), valid_every=args.valid_every,
                     mlp_size=args.mlp, progress=False, gn=gn_sizes(args.latent, args.edge_width, args.node_width))
    summary = run_demo(cfg)
    # stability: a 1000-step rollout stays finite; error growth with horizon from the 100-step test
    ds = data.load(args.dataset, lazy=False)
    dev = summary["device"]
    model = load_model(Path(args.child_out) / "gn" / "best", device=dev).bind(ds)
    system = sim.make(args.system)
    n, T = min(16, len(ds["test"])), 1000   # the quick run's test split holds fewer
    u = sim.random_spline_controls(n, T, sim.control_range(system.model), np.random.default_rng(7))
    te = ds["test"]
    x0 = torch.as_tensor(te.body[:n, 0], device=dev)
    inst = torch.as_tensor(te.instance[:n], device=dev)
    t0 = time.perf_counter()
    with torch.no_grad():
        traj = model.rollout(x0, torch.as_tensor(u, device=dev, dtype=x0.dtype), inst)
    torch.cuda.synchronize() if torch.cuda.is_available() else None
    tr = traj.float().cpu().numpy()
    summary["stability"] = {"steps": T, "rollouts": n, "finite": bool(np.isfinite(tr).all()),
                            "max_abs_state": float(np.nanmax(np.abs(tr))), "seconds": time.perf_counter() - t0}
    (Path(args.child_out) / "results.json").write_text(json.dumps(summary, indent=1, default=float))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--systems", default=",".join(SYSTEMS))
    ap.add_argument("--steps", type=int, default=100, help="steps per simulated sequence")
    add_training_args(ap, seconds=240.0, max_steps=40000)
    ap.add_argument("--mlp", default="3x512")
    add_run_args(ap, "forward_models", "--system", "--dataset", "--child-out")
    ap.add_argument("--valid-eval", type=int, default=50, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        return child(args)
    if args.quick:
        args.sequences, args.steps, args.seconds, args.max_steps = (40, 5, 10), 20, 20.0, 60
        args.valid_every, args.latent, args.edge_width, args.node_width, args.mlp = 30, 16, 32, 16, "3x32"
    out = experiment_out("forward_models", args.out, args.quick)
    (out / "data").mkdir(parents=True, exist_ok=True)
    names = args.systems.split(",")
    t0 = time.perf_counter()
    for name in names:  # MuJoCo C on every core: seconds per system
        ensure_dataset(out / "data" / f"{name}.h5", name, args.sequences, args.steps, seed=1)
    print(f"datasets: {time.perf_counter() - t0:.0f} s", flush=True)
    commands = {}
    for name in names:
        commands[name] = [sys.executable, __file__, "--child", "--system", name,
                          "--dataset", str(out / "data" / f"{name}.h5"), "--child-out", str(out / name),
                          *forward_args(args, "seconds", "max_steps", "lr", "valid_every", "latent", "edge_width",
                                        "node_width", "mlp"), "--valid-eval", str(args.sequences[1])]
    run_side_by_side(commands, out)
    from gnwarp.eval.records import git_commit, write_records
    from gnwarp.eval.summarize import write_summary as summarize
    records, commit, gpu = [], git_commit(), device_name()
    for name in names:
        f = out / name / "results.json"
        if not f.exists():
            print(f"{name}: failed (see {name}.log)", flush=True)
            continue
        records += to_records(json.loads(f.read_text()), gpu=gpu, commit=commit)
    write_records(out / "results.jsonl", records, append=False)
    title = f"Forward models per system ({gpu}); GN vs MLP {args.mlp} at the same number of steps"
    print(f"wrote {summarize(records, out, title)}")


HORIZONS = {"one_step": 1, "rollout_20": 20, "rollout_100": 100}


def to_records(s: dict, gpu: str = "unknown", commit: str = "unknown", date: str = "") -> list:
    """One system's ``results.json`` (``run_demo``'s summary plus the stability rollout) as
    results records of errors: per model (GN, MLP) and horizon (1, 20, 100 steps) the normalized
    error averaged over state groups and sequences (``reported``: per-sequence errors are not
    kept), planner "none" on learned dynamics, the model as the variant."""
    from gnwarp.eval.records import ResultRecord
    from gnwarp.sim import systems
    system = systems.make(s["system"])
    env_steps = int(s["dataset"]["train"]) * int(s["num_steps"])
    stable = s.get("stability")   # absent when the child's stability rollout failed
    out = []
    for model, r in s["results"].items():
        train = s["gn"] if model == "GN" else s["mlp"]
        for key, horizon in HORIZONS.items():
            if r.get(key, {}).get("mean") is None:
                continue
            out.append(ResultRecord(
                experiment="forward_models", task=s["system"], system=s["system"], planner="none", dynamics="learned",
                variant=model, episodes=int(r["sequences"]), episode_steps=horizon,
                reported={"mean": float(r[key]["mean"]), "std": None, "of": "errors"},
                control_dt=float(system.dt), action_repeat=int(system.substeps), env_steps=env_steps,
                metrics={"train_steps": train["steps"], "train_seconds": train["seconds"],
                         **({"stability_finite": int(stable["finite"])} if model == "GN" and stable else {})},
                config={"groups": {k: v for k, v in r[key].items() if k in ("pos", "quat", "linvel", "angvel")},
                        "simulator": s.get("simulator"), "gn_impl": s.get("gn_impl", s.get("gn_backend"))},
                commit=commit, gpu=gpu, date=date))
    return out


if __name__ == "__main__":
    main()
