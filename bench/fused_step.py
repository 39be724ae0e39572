"""Benchmark: a rollout engine's model step, fused (``FusedStep``) beside unfused (``next_nodes``).

Per system and batch size (graphs N), ``RolloutEngine``s of ``--horizon`` steps (captured CUDA
graphs on CUDA) with ``fused=False`` and ``fused=True`` on the same model, states and controls:

- microseconds per model step of the forward (no grad) and of forward + backward (a loss on all
  states, gradients w.r.t. the initial states and the controls, as a gradient planner takes);
- on CUDA, CUDA kernels and device time per model step forward + backward (torch.profiler over
  replays of both captured graphs);
- the largest difference of the fused rollout and its gradients from the unfused ones (a
  correctness column: it must stay at rounding).

The crossover of fused vs unfused over N set ``gnwarp.gn.rules.choose_fused``'s bound
(``TUNABLES.fused_step_max_graphs``) until 2026-11-27 (now set from planning iterations,
bench/results/mpc_latency/NOTES.md); the core is the model's own GN core.

    python bench/fused_step.py [--systems pendulum,cheetah] [--batches 1,16,256,4096] [--horizon 50]
    python bench/fused_step.py --quick          # tiny sizes on the CPU: a smoke test of the script
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from bench.harness import PAPER, QUICK, device_name, experiment_out, median_ms, profile_kernels, save_results  # noqa: E402
from gnwarp import data  # noqa: E402
from gnwarp.models import ForwardModel, ModelConfig  # noqa: E402
from gnwarp.train.sampler import BatchSampler  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--systems", default="pendulum,cartpole,swimmer6,cheetah,walker")
    ap.add_argument("--batches", default="1,16,64,256,1024,4096")
    ap.add_argument("--horizon", type=int, default=50)
    ap.add_argument("--core", choices=("paper", "quick"), default="paper")
    ap.add_argument("--precision", default="fp32")
    ap.add_argument("--reps", type=int, default=10)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--out", default=None, help="default: bench/results/fused_step (--quick: a temporary folder)")
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    args.out = str(experiment_out("fused_step", args.out, args.quick))
    if args.quick:
        args.device, args.systems, args.batches, args.horizon, args.reps, args.core = \
            "cpu", "pendulum,cheetah", "1,4", 4, 2, "quick"
    dev = torch.device(args.device)
    T = args.horizon
    name = device_name(dev)
    rows = []
    for system in args.systems.split(","):
        ds = data.generate(system, (16, 2, 2) if args.quick else (64, 4, 4), num_steps=max(T, 8), seed=0,
                           backend="mujoco", progress=False)
        model = ForwardModel(ModelConfig(gn=QUICK if args.core == "quick" else PAPER,
                                         recenter=system not in ("pendulum",)), ds.layout).to(dev).bind(ds)
        model.set_options(precision=args.precision)
        for p in model.parameters():   # a planner's gradients are w.r.t. the states and controls only
            p.requires_grad_(False)
        gen = torch.Generator(device=dev).manual_seed(0)
        sampler = BatchSampler([ds], model, dev)
        with torch.no_grad():   # normalizer statistics from the data, as after training
            for _ in range(5):
                model.loss(*sampler.sample(64, gen), accumulate=True)
        sp = ds["train"]
        for N in (int(b) for b in args.batches.split(",")):
            idx = np.arange(N) % len(sp)
            inst = np.asarray(sp.instance[idx])
            x0 = torch.as_tensor(sp.body[idx, 0], device=dev)
            u = torch.as_tensor(sp.ctrl[idx, :T], device=dev)
            engines = {"unfused": model.rollout_engine(inst, T, fused=False, check=False),
                       "fused": model.rollout_engine(inst, T, fused=True, check=False)}
            row = dict(device=name, system=system, graphs=N, horizon=T, core=args.core, precision=args.precision,
                       auto_fused=bool(model.rollout_engine(inst, T, check=False).fused))
            outs = {}
            for key, e in engines.items():
                def fwd(e=e):
                    with torch.no_grad():
                        e.rollout(x0, u)

                def fwdbwd(e=e):
                    xa, ua = x0.clone().requires_grad_(), u.clone().requires_grad_()
                    traj = e.rollout(xa, ua)
                    traj.square().mean().backward()
                    return traj, xa.grad, ua.grad
                outs[key] = fwdbwd()
                row[f"{key}_fwd_us_per_step"] = round(1e3 * median_ms(fwd, dev, args.reps, 2) / T, 2)
                row[f"{key}_fwdbwd_us_per_step"] = round(1e3 * median_ms(fwdbwd, dev, args.reps, 2) / T, 2)
                if dev.type == "cuda":
                    path = Path(args.out) / f"fused_step_kernels_{system}_{N}.txt"
                    k, us = profile_kernels(fwdbwd, 3, path, f"{system} N={N} {key} fwd+bwd, {T} steps",
                                            unit="rollout")   # a call is the whole rollout: per step is k / T
                    row[f"{key}_kernels_per_step"] = round(k / T, 1)
                    row[f"{key}_device_us_per_step"] = round(us / T, 2)
            row["max_abs_diff"] = float(max((a - b).abs().max() for a, b in zip(outs["fused"], outs["unfused"])))
            row["speedup_fwdbwd"] = round(row["unfused_fwdbwd_us_per_step"] / row["fused_fwdbwd_us_per_step"], 2)
            rows.append(row)
            print(json.dumps(row), flush=True)
    lines = [f"# Fused vs unfused model step in a rollout engine, on {name}", "",
             f"`python bench/fused_step.py` ({time.strftime('%Y-%m-%d')}): {args.core} core, {args.precision}, "
             f"{T}-step rollouts; us per model step (median of {args.reps} rollouts / horizon); fwd+bwd: a loss on "
             "all states, gradients w.r.t. x0 and the controls; kernels and device us per model step fwd+bwd from "
             "torch.profiler (CUDA).", "",
             "| system | graphs | auto picks fused | fwd unfused | fwd fused | fwd+bwd unfused | "
             "fwd+bwd fused | speed-up fwd+bwd | kernels / step unfused / fused | device us / step unfused / fused | "
             "max abs diff |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        kern = (f"{r['unfused_kernels_per_step']} / {r['fused_kernels_per_step']}" if "fused_kernels_per_step" in r
                else "-")
        dus = (f"{r['unfused_device_us_per_step']} / {r['fused_device_us_per_step']}" if "fused_device_us_per_step" in r
               else "-")
        lines.append(f"| {r['system']} | {r['graphs']} | {r['auto_fused']} | "
                     f"{r['unfused_fwd_us_per_step']} | {r['fused_fwd_us_per_step']} | {r['unfused_fwdbwd_us_per_step']} | "
                     f"{r['fused_fwdbwd_us_per_step']} | {r['speedup_fwdbwd']} | {kern} | {dus} | {r['max_abs_diff']:.2e} |")
    save_results(args.out, "fused_step", name, args.quick, rows, lines)
    return 0


if __name__ == "__main__":
    sys.exit(main())
