"""Benchmark: the training loop users run (``gnwarp.train.Trainer``, what ``gnwarp train`` runs),
captured against eager, beside the captured step alone.

Paper core (edge MLP 3x512, node / global 2x256, latent 128) on cheetah (MuJoCo C data, 2000
train sequences of 100 steps), batch 200, the Trainer's defaults: validation every 1000 steps
(100 sequences x 20 steps), checkpoints every 1000 steps. For each precision and optimizer, in one
process: the eager loop (``capture=False``) and the captured one, steps/s as the Trainer reports
them over a run (kernels compiled beforehand by a short run of each configuration), and the
captured step alone (its replays timed with CUDA events).

    python bench/train_loop.py [--precisions tf32,fp16] [--optimizers flat_adam,adam] [--steps 5000]
    python bench/train_loop.py --quick          # tiny sizes on the CPU: a smoke test of the script
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from bench.harness import (PAPER, QUICK, device_name, median_ms, profile_kernels, results_dir,  # noqa: E402
                           save_results, slug)
from gnwarp import data  # noqa: E402
from gnwarp.gn import RunOptions  # noqa: E402
from gnwarp.models import ModelConfig  # noqa: E402
from gnwarp.train import TrainConfig, Trainer  # noqa: E402


def config(args, tmp, name, precision, optimizer, capture, steps, **kw):
    return TrainConfig(out=str(Path(tmp) / name), steps=steps, batch_size=args.batch, device=args.device,
                       model=ModelConfig(gn=QUICK if args.quick else PAPER, run=RunOptions(precision=precision)),
                       optimizer=optimizer, capture=capture, patience=None, progress=False, resume=False, **kw)


def profile_steps(args, tmp, ds, name):
    """Device time per kernel of the Trainer's step (eager, the same kernels a replay runs)."""
    path = Path(args.out) / f"train_loop_{slug(name)}_profile.txt"
    for prec in args.precisions.split(","):
        opt = args.optimizers.split(",")[0]
        t = Trainer(config(args, tmp, f"prof-{prec}", prec, opt, False, 10 ** 6), [ds])
        t.warmup()
        for _ in range(15):
            t.step()
        calls, total = profile_kernels(t.step, args.profile, path, f"Trainer step, {prec}, {opt}, batch {args.batch}, {name}")
        print(f"== Trainer step, {prec}, {opt}: {calls:.0f} kernels / step, {total:.1f} us device time / step", flush=True)
    print(f"wrote {path}", flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--precisions", default="fp32,tf32,fp16")
    ap.add_argument("--optimizers", default="flat_adam,adam")
    ap.add_argument("--steps", type=int, default=5000, help="steps of each captured run")
    ap.add_argument("--eager-steps", type=int, default=600, help="steps of each eager run")
    ap.add_argument("--batch", type=int, default=200)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--out", default=results_dir("train_loop"))
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--profile", type=int, default=0,
                    help="also profile this many eager steps per precision (torch.profiler: device time per kernel "
                         "and step), written to <out>/train_loop_<device>_profile.txt")
    args = ap.parse_args(argv)
    if args.quick:
        args.device, args.steps, args.eager_steps, args.batch = "cpu", 30, 20, 16
    dev = torch.device(args.device)
    sizes = (60, 5, 20) if args.quick else (2000, 100, 20)
    t0 = time.perf_counter()
    ds = data.generate("cheetah", sizes, num_steps=100, seed=0, backend="mujoco", progress=False)
    print(f"cheetah data {sizes}: {time.perf_counter() - t0:.1f} s", flush=True)
    name = device_name(dev)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for prec in args.precisions.split(","):
            for opt in args.optimizers.split(","):
                for capture in (False, True):
                    tag = f"{prec}-{opt}-{'captured' if capture else 'eager'}"
                    # compile and load every kernel first (a short run of the same configuration)
                    Trainer(config(args, tmp, "warm-" + tag, prec, opt, capture, 30, valid_every=15,
                                   checkpoint_every=30), [ds]).run()
                    steps = args.steps if capture else args.eager_steps
                    t = Trainer(config(args, tmp, tag, prec, opt, capture, steps), [ds])
                    r = t.run()
                    row = dict(device=name, precision=prec, optimizer=opt, captured=capture, steps=r["steps"],
                               seconds=round(r["seconds"], 3), steps_per_s=round(r["steps_per_second"], 1),
                               validations=r["steps"] // t.config.valid_every)
                    if capture and dev.type == "cuda":
                        row["step_ms"] = round(median_ms(t.step, dev, 200, 5), 4)  # the captured step alone
                    rows.append(row)
                    print(json.dumps(row), flush=True)
        if args.profile and dev.type == "cuda":
            try:
                profile_steps(args, tmp, ds, name)
            except Exception as exc:   # a profiler problem must not lose the loop's numbers
                print(f"profile failed: {type(exc).__name__}: {exc}", flush=True)
    lines = [f"# The training loop users run, on {name}", "",
             f"`python bench/train_loop.py` ({time.strftime('%Y-%m-%d')}): `gnwarp.train.Trainer` on cheetah, "
             f"{'quick sizes' if args.quick else 'paper core'}, batch {args.batch}, validation every 1000 steps "
             "(100 sequences x 20 steps) and checkpoints every 1000 steps included; eager and captured loops "
             "in one process after a warm-up run of each configuration.", "",
             "| precision | optimizer | eager loop steps/s | captured loop steps/s | captured / eager | "
             "captured step alone ms | loop ms/step / step alone |", "|---|---|---|---|---|---|---|"]
    for prec in args.precisions.split(","):
        for opt in args.optimizers.split(","):
            e = next(r for r in rows if r["precision"] == prec and r["optimizer"] == opt and not r["captured"])
            c = next(r for r in rows if r["precision"] == prec and r["optimizer"] == opt and r["captured"])
            alone = c.get("step_ms")
            ratio = f"{1000 / c['steps_per_s'] / alone:.2f}" if alone else ""
            lines.append(f"| {prec} | {opt} | {e['steps_per_s']:.0f} | {c['steps_per_s']:.0f} | "
                         f"{c['steps_per_s'] / e['steps_per_s']:.1f}x | {alone if alone else ''} | {ratio} |")
    save_results(args.out, "train_loop", name, args.quick, rows, lines)
    return 0


if __name__ == "__main__":
    sys.exit(main())
