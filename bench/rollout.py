"""Benchmark: rollouts of a learned model, forward and forward + backward w.r.t. the controls.

Paper core on cheetah graphs (MuJoCo C data for the layout, normalizer statistics and initial
states), 100-step rollouts of 256 and 4096 graphs. Per precision, in one process:

- forward (no grad): ``model.rollout`` as it runs eagerly, and a ``RolloutEngine`` replaying
  its CUDA graph; beside them the captured forward of the model's core alone on one step's
  graphs (what ``bench/gn_block.py`` times), the floor a rollout step can approach;
- forward + backward of a loss on the states w.r.t. the controls: ``model.rollout`` with the
  adjoint loop (eager), the engine (captured; by default its backward replays the GN blocks its
  forward recorded, ``gnwarp/gn/replay.py``), the engine recomputing them (``store=False``), and
  plain autograd (``adjoint=False``) where it fits; time per step and peak memory above what the
  model and data hold (the engine's store, kept between calls, is listed on its own).

    python bench/rollout.py [--precisions tf32,fp16] [--batches 256,4096] [--steps 100]
    python bench/rollout.py --quick          # tiny sizes on the CPU: a smoke test of the script
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

from bench.harness import PAPER, QUICK, captured_us, device_name, median_ms, results_dir, save_results  # noqa: E402
from gnwarp import data  # noqa: E402
from gnwarp.models import ForwardModel, ModelConfig  # noqa: E402
from gnwarp.models.normalizer import normalize_graph  # noqa: E402
from gnwarp.train.sampler import BatchSampler  # noqa: E402


def peak_mb(fn, dev) -> float:
    """Peak device memory of ``fn()`` above what was allocated before it (MB)."""
    if dev.type != "cuda":
        fn()
        return float("nan")
    torch.cuda.synchronize()
    torch.cuda.reset_peak_memory_stats()
    base = torch.cuda.memory_allocated()
    fn()
    torch.cuda.synchronize()
    return (torch.cuda.max_memory_allocated() - base) / 2 ** 20


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--precisions", default="fp32,tf32,fp16")
    ap.add_argument("--batches", default="256,4096")
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--plain-max", type=int, default=256, help="largest batch timed with plain autograd")
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--out", default=results_dir("rollout"))
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    if args.quick:
        args.device, args.batches, args.steps, args.reps = "cpu", "8", 5, 1
    dev = torch.device(args.device)
    T = args.steps
    ds = data.generate("cheetah", (64, 4, 4) if args.quick else (400, 20, 20), num_steps=max(T, 20), seed=0,
                       backend="mujoco", progress=False)
    model = ForwardModel(ModelConfig(gn=QUICK if args.quick else PAPER), ds.layout).to(dev).bind(ds)
    for p in model.parameters():  # a planner's gradients are w.r.t. the controls only
        p.requires_grad_(False)
    gen = torch.Generator(device=dev).manual_seed(0)
    sampler = BatchSampler([ds], model, dev)
    with torch.no_grad():  # normalizer statistics from the data, as after training
        for _ in range(10):
            model.loss(*sampler.sample(200, gen), accumulate=True)
    sp = ds["train"]
    name = device_name(dev)
    rows = []
    for prec in args.precisions.split(","):
        model.set_options(precision=prec)
        for N in (int(b) for b in args.batches.split(",")):
            idx = np.arange(N) % len(sp)
            x0 = torch.as_tensor(sp.body[idx, 0], device=dev)
            u = torch.as_tensor(sp.ctrl[idx, :T], device=dev)
            inst = np.asarray(sp.instance[idx])
            tmpl = model.template(torch.as_tensor(inst))
            engine = model.rollout_engine(inst, T)
            recompute = model.rollout_engine(inst, T, store=False)
            row = dict(device=name, precision=prec, graphs=N, steps=T)

            def fwd_eager():
                with torch.no_grad():
                    model.rollout(x0, u, template=tmpl)

            def fwd_engine():
                with torch.no_grad():
                    engine.rollout(x0, u)

            def loss_grad(run):
                def go():
                    uu = u.clone().requires_grad_()
                    run(uu).square().mean().backward()
                return go
            adjoint = loss_grad(lambda uu: model.rollout(x0, uu, template=tmpl))
            engine_bwd = loss_grad(lambda uu: engine.rollout(x0, uu))
            recompute_bwd = loss_grad(lambda uu: recompute.rollout(x0, uu))
            plain = loss_grad(lambda uu: model.rollout(x0, uu, template=tmpl, adjoint=False))
            for key, fn in (("fwd_eager", fwd_eager), ("fwd_engine", fwd_engine), ("fwdbwd_eager", adjoint),
                            ("fwdbwd_engine", engine_bwd), ("fwdbwd_recompute", recompute_bwd)):
                fn()  # compile, record
                row[f"{key}_ms_per_step"] = round(median_ms(fn, dev, args.reps, 2) / T, 4)
                row[f"{key}_peak_mb"] = round(peak_mb(fn, dev), 1)
            st = engine.store
            row["store_mb"] = round(st.step_bytes(0) * T / 2 ** 20, 1) if st is not None else 0.0
            recompute = None   # its engine's memory freed before the plain autograd run
            if N <= args.plain_max:
                row["fwdbwd_plain_ms_per_step"] = round(median_ms(plain, dev, args.reps, 1) / T, 4)
                row["fwdbwd_plain_peak_mb"] = round(peak_mb(plain, dev), 1)
            if dev.type == "cuda":  # the floor: the core alone on one step's input graphs, captured
                with torch.no_grad():
                    g = tmpl.graph(x0, u[:, 0])
                    ctx = model.context(g)
                    gn = normalize_graph(g, ctx.stats)
                    row["core_fwd_ms"] = round(captured_us(lambda: model.core(gn, ctx.index)) / 1e3, 4)
            rows.append(row)
            print(json.dumps(row), flush=True)
    lines = [f"# Rollouts of the learned model, on {name}", "",
             f"`python bench/rollout.py` ({time.strftime('%Y-%m-%d')}): {'quick sizes' if args.quick else 'paper core'} "
             f"on cheetah graphs, {T}-step rollouts; ms per rollout step (median of {args.reps}), peak memory above "
             "the model and data; fwd+bwd: a loss on all states, gradients w.r.t. the controls.", "",
             "| precision | graphs | fwd eager | fwd engine (captured) | core fwd alone (captured) | engine / core | "
             "fwd+bwd eager (adjoint) | fwd+bwd engine | engine fwd+bwd / fwd | fwd+bwd engine, recompute | "
             "recompute / fwd | fwd+bwd plain autograd | peak MB: engine fwd+bwd (+ store) / recompute / adjoint / "
             "plain |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        core = r.get("core_fwd_ms")
        plain = r.get("fwdbwd_plain_ms_per_step")
        over_core = f"{r['fwd_engine_ms_per_step'] / core:.2f}" if core else ""
        lines.append(
            f"| {r['precision']} | {r['graphs']} | {r['fwd_eager_ms_per_step']} | {r['fwd_engine_ms_per_step']} | "
            f"{core if core else ''} | {over_core} | "
            f"{r['fwdbwd_eager_ms_per_step']} | {r['fwdbwd_engine_ms_per_step']} | "
            f"{r['fwdbwd_engine_ms_per_step'] / r['fwd_engine_ms_per_step']:.2f} | {r['fwdbwd_recompute_ms_per_step']} | "
            f"{r['fwdbwd_recompute_ms_per_step'] / r['fwd_engine_ms_per_step']:.2f} | {plain if plain else 'not run'} | "
            f"{r['fwdbwd_engine_peak_mb']} (+ {r['store_mb']}) / {r['fwdbwd_recompute_peak_mb']} / "
            f"{r['fwdbwd_eager_peak_mb']} / {r.get('fwdbwd_plain_peak_mb', '-')} |")
    save_results(args.out, "rollout", name, args.quick, rows, lines)
    return 0


if __name__ == "__main__":
    sys.exit(main())
