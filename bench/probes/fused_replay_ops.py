"""Probe: host-side work of a fused rollout engine's backward per model step, with and without
the activation store (``RolloutEngine(fused=True, store=...)``).

``bench/fused_step.py``'s set-up (paper core, fp32, normalizers from the data), N graphs, eager
engines (``graphs=False``). Per system and store setting, one forward then the backward alone,
counted on the host: Warp launches (``wp.launch`` + ``wp.launch_tiled``), torch ops
(torch.profiler CPU events named ``aten::`` with no ``aten::`` op above them) and among those the
GEMMs (``mm`` / ``addmm`` / ``_addmm_activation`` / ``matmul`` / ``bmm`` / ``addmv`` / ``mv``).
Per model step: the difference of two horizons divided by their difference (the per-rollout work
cancels). The unfused engine with its store is printed beside them. Runs on the CPU (the calls a
CUDA replay records are the same) or CUDA.

    python bench/probes/fused_replay_ops.py [--systems pendulum,cheetah] [--graphs 1] [--device cpu]
    python bench/probes/fused_replay_ops.py --quick   # the small core: a smoke test
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np  # noqa: E402
import torch  # noqa: E402
import warp as wp  # noqa: E402

from bench.harness import PAPER, QUICK  # noqa: E402
from gnwarp import data  # noqa: E402
from gnwarp.models import ForwardModel, ModelConfig  # noqa: E402
from gnwarp.train.sampler import BatchSampler  # noqa: E402

GEMMS = {"aten::mm", "aten::addmm", "aten::_addmm_activation", "aten::matmul", "aten::bmm", "aten::addmv", "aten::mv",
         "aten::baddbmm"}


class LaunchCount:
    """Counts ``wp.launch`` / ``wp.launch_tiled`` calls inside the block (restored after)."""

    def __enter__(self):
        self.n = 0
        self.saved = wp.launch, wp.launch_tiled

        def counted(fn):
            def call(*a, **kw):
                self.n += 1
                return fn(*a, **kw)
            return call
        wp.launch, wp.launch_tiled = counted(self.saved[0]), counted(self.saved[1])
        return self

    def __exit__(self, *exc):
        wp.launch, wp.launch_tiled = self.saved


def top_ops(prof) -> tuple[int, int]:
    """(torch ops with no torch op above them, GEMMs among them) of a CPU profile."""
    n = gemm = 0
    for ev in prof.events():
        if not ev.name.startswith("aten::"):
            continue
        p = ev.cpu_parent
        while p is not None and not p.name.startswith("aten::"):
            p = p.cpu_parent
        if p is None:
            n += 1
            gemm += ev.name in GEMMS
    return n, gemm


def backward_counts(engine, x0, u) -> tuple[int, int, int]:
    """(Warp launches, torch ops, GEMMs) of one backward of ``engine`` after a forward."""
    from torch.profiler import ProfilerActivity, profile  # noqa: PLC0415
    uu = u.clone().requires_grad_()
    loss = engine.rollout(x0.clone().requires_grad_(), uu).square().mean()
    with LaunchCount() as lc, profile(activities=[ProfilerActivity.CPU]) as prof:
        loss.backward()
    return (lc.n, *top_ops(prof))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--systems", default="pendulum,cheetah")
    ap.add_argument("--graphs", type=int, default=1)
    ap.add_argument("--horizons", default="2,6")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    dev = torch.device(args.device)
    T1, T2 = (int(t) for t in args.horizons.split(","))
    N = args.graphs
    for system in args.systems.split(","):
        ds = data.generate(system, (8, 2, 2), num_steps=max(T2, 8), seed=0, backend="mujoco", progress=False)
        model = ForwardModel(ModelConfig(gn=QUICK if args.quick else PAPER, recenter=system != "pendulum"),
                             ds.layout).to(dev).bind(ds)
        for p in model.parameters():
            p.requires_grad_(False)
        sampler = BatchSampler([ds], model, dev)
        gen = torch.Generator(device=dev).manual_seed(0)
        with torch.no_grad():
            for _ in range(2):
                model.loss(*sampler.sample(32, gen), accumulate=True)
        sp = ds["train"]
        idx = np.arange(N) % len(sp)
        inst = np.asarray(sp.instance[idx])
        x0 = torch.as_tensor(sp.body[idx, 0], device=dev)
        for fused, store in ((True, False), (True, True), (False, True)):
            counts = []
            for T in (T1, T2):
                u = torch.as_tensor(sp.ctrl[idx, :T], device=dev)
                e = model.rollout_engine(inst, T, fused=fused, store=store, check=False, graphs=False)
                backward_counts(e, x0, u)   # compile, allocate
                counts.append(backward_counts(e, x0, u))
            per = [(b - a) / (T2 - T1) for a, b in zip(*counts)]
            what = "fused" if fused else "unfused"
            print(f"{system} N={N} {what} backward, store={store}: per model step {per[0]:.1f} Warp launches, "
                  f"{per[1]:.1f} torch ops ({per[2]:.1f} GEMMs); per rollout of {T2} steps "
                  f"{counts[1][0]} launches, {counts[1][1]} torch ops", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
