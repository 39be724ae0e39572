"""Probe: where an engine rollout's backward spends its time (device time per kernel).

Paper core on cheetah graphs (``bench/rollout.py``'s set-up), an eager ``RolloutEngine``
(``graphs=False``: the same kernels a replay runs, visible to torch.profiler), T steps of N
graphs: one forward, then one backward w.r.t. the controls; kernel tables per precision, device
time per rollout step. Written to ``<out>/rollout_profile_<device>.txt``.

    python bench/probes/rollout_profile.py [--precisions tf32,fp16] [--graphs 4096] [--steps 5]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from bench.harness import PAPER, device_name, results_dir  # noqa: E402
from gnwarp import data  # noqa: E402
from gnwarp.models import ForwardModel, ModelConfig  # noqa: E402
from gnwarp.train.sampler import BatchSampler  # noqa: E402


def table(prof, steps: int) -> tuple[float, int, list[str]]:
    per = {}
    for ev in prof.events():
        if ev.device_type == torch.autograd.DeviceType.CUDA:
            k = per.setdefault(ev.name[:100], [0, 0.0])
            k[0] += 1
            k[1] += ev.device_time_total
    total = sum(v[1] for v in per.values()) / steps
    lines = [f"{us / steps:9.1f} us {c / steps:6.1f}x  {n}" for n, (c, us) in sorted(per.items(), key=lambda kv: -kv[1][1])]
    return total, int(sum(v[0] for v in per.values()) / steps), lines


def main(argv=None):
    from torch.profiler import ProfilerActivity, profile
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--precisions", default="tf32,fp16")
    ap.add_argument("--graphs", type=int, default=4096)
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--out", default=results_dir("rollout"))
    args = ap.parse_args(argv)
    dev = torch.device("cuda")
    T, N = args.steps, args.graphs
    ds = data.generate("cheetah", (400, 20, 20), num_steps=20, seed=0, backend="mujoco", progress=False)
    model = ForwardModel(ModelConfig(gn=PAPER), ds.layout).to(dev).bind(ds)
    sampler = BatchSampler([ds], model, dev)
    gen = torch.Generator(device=dev).manual_seed(0)
    with torch.no_grad():
        for _ in range(10):
            model.loss(*sampler.sample(200, gen), accumulate=True)
    sp = ds["train"]
    idx = np.arange(N) % len(sp)
    x0 = torch.as_tensor(sp.body[idx, 0], device=dev)
    u = torch.as_tensor(sp.ctrl[idx, :T], device=dev)
    name = device_name(dev)
    path = Path(args.out) / f"rollout_profile_{name.replace(' ', '_').lower()}.txt"
    with open(path, "a") as f:
        for prec in args.precisions.split(","):
            model.set_options(precision=prec)
            engine = model.rollout_engine(np.asarray(sp.instance[idx]), T, graphs=False)
            for _ in range(2):   # compile, warm
                uu = u.clone().requires_grad_()
                engine.rollout(x0, uu).square().mean().backward()
            torch.cuda.synchronize()
            uu = u.clone().requires_grad_()
            with profile(activities=[ProfilerActivity.CUDA]) as pf:
                traj = engine.rollout(x0, uu)
                torch.cuda.synchronize()
            loss = traj.square().mean()
            with profile(activities=[ProfilerActivity.CUDA]) as pb:
                loss.backward()
                torch.cuda.synchronize()
            for what, prof in (("forward", pf), ("backward (recompute + vjp)", pb)):
                total, calls, lines = table(prof, T)
                head = f"== {prec} {what}, {N} cheetah graphs, {name}: {calls} kernels / step, {total:.1f} us / step"
                print(head, flush=True)
                f.write(head + "\n" + "\n".join(lines[:45]) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    sys.exit(main())
