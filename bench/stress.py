"""Numerical stress of trained forward models, per system:

- long rollouts: 10000 steps from the test split's initial states under new random spline
  controls; finite or the first non-finite step, and the largest |state| against the training data's;
- states far outside the data: initial velocities x10 and x100, 1000 steps;
- precision: tf32 / fp16 / bf16 / fp16x3 rollouts against a float64 rollout of the same weights
  (the same model cast), errors at steps 10, 100 and 1000 in units of the data's state std;
- gradients through 100-step rollouts: the norm of d(sum of final body positions)/d(controls) per
  control step, finite, and how it grows from the last step to the first.

    python bench/stress.py --checkpoints DIR [--systems pendulum,cheetah]   # DIR/<system>/best
    python bench/stress.py --quick        # tiny CPU smoke run (trains nothing: a fresh model)
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from bench.harness import SYSTEMS, device_name  # noqa: E402


def first_nonfinite(traj: torch.Tensor) -> int | None:
    """First step index (1..T) at which any state is NaN/Inf, None when finite throughout."""
    bad = ~torch.isfinite(traj).flatten(2).all(-1).all(0)   # [T+1]
    idx = torch.nonzero(bad)
    return None if idx.numel() == 0 else int(idx[0])


def long_rollout(model, x0, ctrl, inst, chunk: int) -> torch.Tensor:
    """A rollout of ctrl.shape[1] steps in chunks of ``chunk`` (a RolloutEngine each), no grad."""
    engine = model.rollout_engine(inst, chunk)
    out, x = [x0], x0
    with torch.no_grad():
        for k in range(0, ctrl.shape[1], chunk):
            traj = engine.rollout(x, ctrl[:, k:k + chunk])
            out.append(traj[:, 1:].float().cpu())
            x = traj[:, -1]
            if not torch.isfinite(x).all():
                break
    return torch.cat([out[0].float().cpu()[:, None]] + out[1:], 1)


def system_stress(name, ckpt, args, dev) -> dict:
    from gnwarp import data, sim
    from gnwarp.train import load_model
    ds = data.generate(name, (args.data, 0, args.n), num_steps=args.data_steps, seed=3, backend="mujoco",
                       progress=False)
    system = sim.make(name)
    model = load_model(ckpt, device=dev).bind(ds)
    te, tr = ds["test"], ds["train"]
    body = torch.as_tensor(np.asarray(tr.body[...]))
    from gnwarp.state import GROUPS
    scale = torch.ones(13)                                       # [13] the data's std per state group
    for sl in GROUPS.values():                                   # (pooled over the group and the moving bodies)
        scale[sl] = body[:, :, 1:, sl].std().clamp_min(1e-6)
    data_max = float(body.abs().max())
    x0 = torch.as_tensor(np.asarray(te.body[:, 0]), device=dev)
    inst = torch.as_tensor(np.asarray(te.instance), device=dev)
    rng = np.random.default_rng(11)
    cr = sim.control_range(system.model)
    u_long = torch.as_tensor(sim.random_spline_controls(args.n, args.long, cr, rng), device=dev, dtype=torch.float32)
    row = {"system": name, "device": device_name(torch.device(dev))}
    t0 = time.perf_counter()
    traj = long_rollout(model, x0, u_long, inst, args.chunk)
    row["long_steps"] = args.long
    row["long_first_nonfinite"] = first_nonfinite(traj)
    row["long_max_abs"] = float(traj[torch.isfinite(traj)].abs().max())
    row["data_max_abs"] = data_max
    row["long_seconds"] = round(time.perf_counter() - t0, 1)
    # far outside the data: velocities x10, x100
    for f in (10, 100):
        x = x0.clone()
        x[:, 1:, 7:] *= f
        tr_f = long_rollout(model, x, u_long[:, :args.far], inst, args.chunk)
        row[f"vel_x{f}_first_nonfinite"] = first_nonfinite(tr_f)
        row[f"vel_x{f}_max_abs"] = float(tr_f[torch.isfinite(tr_f)].abs().max())
    # precisions against float64 (same weights, cast)
    u = u_long[:, :args.prec_steps]
    ref = long_rollout(model.set_options(precision="fp64"), x0.double(), u.double(), inst, args.chunk)
    for prec in ("tf32", "fp16", "bf16", "fp16x3"):
        model.set_options(precision=prec)
        p = long_rollout(model, x0, u, inst, args.chunk)
        err = ((p - ref)[:, :, 1:].abs() / scale).flatten(2)    # [N, T+1, moving bodies x 13] in data stds
        for t in (10, 100, args.prec_steps):
            if t <= args.prec_steps:
                row[f"{prec}_err_{t}"] = float(err[:, t].max())
        row[f"{prec}_first_nonfinite"] = first_nonfinite(p)
    model.set_options(precision="tf32")
    # gradients through 100 steps w.r.t. the controls
    uu = u_long[:, :args.grad_steps].clone().requires_grad_()
    traj = model.rollout_engine(inst, args.grad_steps).rollout(x0, uu)
    traj[:, -1, :, :3].sum().backward()
    g = uu.grad.norm(dim=(0, 2)).cpu()                           # [T] per control step
    row["grad_finite"] = bool(torch.isfinite(uu.grad).all())
    row["grad_norm_last_step"] = float(g[-1])
    row["grad_norm_first_step"] = float(g[0])
    row["grad_norm_max"] = float(g.max())
    return row


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoints", help="folder holding <system>/best checkpoints")
    ap.add_argument("--systems", default=",".join(SYSTEMS))
    ap.add_argument("--n", type=int, default=16, help="rollouts per test")
    ap.add_argument("--long", type=int, default=10000)
    ap.add_argument("--far", type=int, default=1000)
    ap.add_argument("--prec-steps", type=int, default=1000)
    ap.add_argument("--grad-steps", type=int, default=100)
    ap.add_argument("--chunk", type=int, default=1000)
    ap.add_argument("--data", type=int, default=100, help="train sequences simulated for the data's range")
    ap.add_argument("--data-steps", type=int, default=100)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results" / "stress"))
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    if args.quick:
        args.systems, args.n, args.long, args.far, args.prec_steps, args.grad_steps, args.chunk = \
            "pendulum", 2, 40, 20, 20, 10, 20
        args.data, args.data_steps, args.device = 4, 10, "cpu"
        args.out = tempfile.mkdtemp(prefix="stress_")
        args.checkpoints = _quick_checkpoints(args.out)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in args.systems.split(","):
        row = system_stress(name, Path(args.checkpoints) / name / "best", args, args.device)
        rows.append(row)
        print(json.dumps(row), flush=True)
    with open(out / "results.jsonl", "a") as f:
        for r in rows:
            f.write(json.dumps(r) + "\n")
    write_table(out, rows, args)


def _quick_checkpoints(tmp) -> str:
    from gnwarp import data
    from gnwarp.models import ForwardModel, GNCoreConfig, ModelConfig
    from gnwarp.train.checkpoint import save_checkpoint
    ds = data.generate("pendulum", (2, 0, 1), num_steps=5, seed=0, backend="mujoco", progress=False)
    m = ForwardModel(ModelConfig(gn=GNCoreConfig(latent=8, edge_hidden=(8,), node_hidden=(8,), global_hidden=(8,))),
                     ds.layout)
    save_checkpoint(Path(tmp) / "ckpt" / "pendulum" / "best", m)
    return str(Path(tmp) / "ckpt")


def _f(x) -> str:
    return "finite" if x is None else f"step {x}"


def write_table(out: Path, rows: list[dict], args) -> None:
    dev = rows[0]["device"] if rows else "?"
    lines = [f"# Numerical stress of the trained models ({dev})", "",
             f"`python bench/stress.py` ({time.strftime('%Y-%m-%d')}): the budget-retrained GNs "
             f"(`bench/results/budget_retrain/`), {args.n} rollouts each from test initial states under new random "
             f"spline controls. Precision errors: largest |state - float64 state| over rollouts, bodies and features, "
             "in units of the data's std of that state group (position, orientation, linear, angular velocity), same weights.", "",
             f"| system | {args.long} steps | max abs state / data's | velocities x10, {args.far} steps | x100 | "
             f"tf32 err @100 / @{args.prec_steps} | fp16 | bf16 | fp16x3 | grad finite | grad norm first / last step |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    p = args.prec_steps
    for r in rows:
        prec = [f"{r.get(f'{k}_err_100', float('nan')):.2g} / {r.get(f'{k}_err_{p}', float('nan')):.2g}"
                + ("" if r[f"{k}_first_nonfinite"] is None else f" (NaN at {r[f'{k}_first_nonfinite']})")
                for k in ("tf32", "fp16", "bf16", "fp16x3")]
        lines.append(f"| {r['system']} | {_f(r['long_first_nonfinite'])} | {r['long_max_abs']:.3g} / "
                     f"{r['data_max_abs']:.3g} | {_f(r['vel_x10_first_nonfinite'])} | "
                     f"{_f(r['vel_x100_first_nonfinite'])} | " + " | ".join(prec) +
                     f" | {r['grad_finite']} | {r['grad_norm_first_step']:.3g} / {r['grad_norm_last_step']:.3g} |")
    (out / "summary.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
