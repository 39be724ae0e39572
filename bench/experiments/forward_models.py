"""Experiment 1 and 5 of issue 4: a GN and an MLP baseline per fixed system, at the same training
budget, evaluated like the paper (one-step, 20- and 100-step rollout errors normalized by the
constant-prediction baseline), plus 1000-step stability rollouts of each GN.

Datasets are simulated first (MuJoCo C on all cores), then one training process per system runs
side by side on the one GPU (the GPU has room for many small models; the step loops are
launch-bound, so processes overlap). Each process runs ``gnwarp.demo.run_demo`` on its dataset
with a wall-clock cap, then a 1000-step rollout of the best GN under new random controls.

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
                           experiment_out, forward_args, gn_sizes, run_side_by_side, write_summary)


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
    # experiment 5: a 1000-step rollout stays finite; error growth with horizon from the 100-step test
    ds = data.load(args.dataset, lazy=False)
    dev = summary["device"]
    model = load_model(Path(args.child_out) / "gn" / "best", device=dev).bind(ds)
    system = sim.make(args.system)
    n, T = 16, 1000
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
    t_data = time.perf_counter() - t0
    commands = {}
    for name in names:
        commands[name] = [sys.executable, __file__, "--child", "--system", name,
                          "--dataset", str(out / "data" / f"{name}.h5"), "--child-out", str(out / name),
                          *forward_args(args, "seconds", "max_steps", "lr", "valid_every", "latent", "edge_width",
                                        "node_width", "mlp"), "--valid-eval", str(args.sequences[1])]
    run_side_by_side(commands, out)
    rows = []
    for name in names:
        f = out / name / "results.json"
        if not f.exists():
            rows.append(f"| {name} | failed (see {name}.log) | | | | | | |")
            continue
        s = json.loads(f.read_text())
        r = s["results"]
        mlp_key = [k for k in r if k.startswith("MLP")][0]
        rows.append((name, s, r["GN"], r[mlp_key]))
    lines = [f"# Forward models per system ({device_name()}); GN vs MLP {args.mlp} at the same number of steps", "",
             f"Budget per system: GN training capped at {args.seconds:g} s wall clock (all systems side by side on the one "
             f"device), MLP trained for the GN's step count. Data: {args.sequences[0]}/{args.sequences[1]}/"
             f"{args.sequences[2]} sequences x {args.steps} steps (MuJoCo C, {t_data:.0f} s for all). Errors: squared "
             "error / constant-prediction baseline, averaged over position, orientation, linear and angular "
             "velocity groups (lower is better).", "",
             "| system | GN steps (s) | GN one-step | GN 20-step | GN 100-step | MLP one-step | MLP 20-step | MLP 100-step | "
             "GN 1000-step rollouts finite |", "|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        if isinstance(row, str):
            lines.append(row)
            continue
        name, s, g, m = row
        lines.append(f"| {name} | {s['gn']['steps']} ({s['gn']['seconds']:.0f}) | {_e(g, 'one_step')} | {_e(g, 'rollout_20')} | "
                     f"{_e(g, 'rollout_100')} | {_e(m, 'one_step')} | {_e(m, 'rollout_20')} | {_e(m, 'rollout_100')} | "
                     f"{s['stability']['finite']} |")
    write_summary(out, lines)


def _e(r: dict, key: str) -> str:
    """The normalized error averaged over state groups, for one horizon of an evaluate() result."""
    v = r.get(key, {}).get("mean")
    return "n/a" if v is None else f"{v:.3g}"


if __name__ == "__main__":
    main()
