"""Probe: where one gradient-MPC planning iteration spends its device time at small batch.

A pendulum / cheetah ForwardModel (latent 128, edge MLP 2x256, untrained weights: timing only),
``GradientMPC`` with N episodes, horizon H: kernels of one eager iteration (count, device time)
under torch.profiler, and the captured iteration's time with CUDA events.

    python bench/probes/mpc_profile.py [--system pendulum] [--n 1] [--horizon 50]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import torch  # noqa: E402

from bench.harness import profile_kernels  # noqa: E402
from gnwarp import data  # noqa: E402
from gnwarp.control import GradientMPC, GradientMPCConfig  # noqa: E402
from gnwarp.models import ForwardModel, GNCoreConfig, ModelConfig  # noqa: E402

TASK = {"pendulum": "pendulum-balance", "cheetah": "cheetah-forward", "swimmer6": "swimmer-reach",
        "cartpole": "cartpole-balance", "walker": "walker-forward"}


def main(argv=None):
    p = argparse.ArgumentParser()
    p.add_argument("--system", default="pendulum")
    p.add_argument("--n", type=int, default=1)
    p.add_argument("--horizon", type=int, default=50)
    p.add_argument("--path", default="auto")
    p.add_argument("--fused", choices=["auto", "true", "false"], default="auto",
                   help="GradientMPCConfig.fused: the rule's choice, or forced")
    p.add_argument("--out", default=".", help="folder of the kernel table")
    a = p.parse_args(argv)
    ds = data.generate(a.system, (4, 1, 1), num_steps=10, seed=0, backend="mujoco", progress=False)
    cfg = ModelConfig(gn=GNCoreConfig(latent=128, edge_hidden=(256, 256), node_hidden=(256, 256),
                                      global_hidden=(256, 256)))
    cfg.run = cfg.run.replace(path=a.path)
    model = ForwardModel(cfg, ds.layout).to("cuda").bind(ds)
    x = torch.as_tensor(ds["test"].body[:1, 0]).expand(a.n, -1, -1).contiguous().cuda()
    for capture in (False, True):
        pl = GradientMPC(model, TASK[a.system], a.system, n=a.n,
                         config=GradientMPCConfig(horizon=a.horizon, iterations=1, warmup=0, capture=capture,
                                                  fused={"auto": None, "true": True, "false": False}[a.fused]))
        xs = pl.check_state(x)
        for _ in range(3):
            pl.iterate(xs, 1)
        torch.cuda.synchronize()
        if not capture:   # the eager iteration's kernels (a captured replay hides them from the profiler)
            table = Path(a.out) / f"mpc_profile_{a.system}_{a.n}{'' if a.fused == 'auto' else '_fused_' + a.fused}.txt"
            k, us = profile_kernels(lambda: pl.iterate(xs, 1), 1, table, f"{a.system} N={a.n} H={a.horizon} "
                                    "eager planning iteration", top=45, unit="iteration")
            print(f"eager iteration: {k:.0f} kernels, {us:.0f} us device; per model step {k / a.horizon:.1f} "
                  f"kernels, {us / a.horizon:.1f} us (table: {table})")
        t0 = time.perf_counter()
        ev0, ev1 = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        ev0.record()
        for _ in range(20):
            pl.iterate(xs, 1)
        ev1.record()
        torch.cuda.synchronize()
        ms = ev0.elapsed_time(ev1) / 20
        print(f"capture={capture}: {ms:.3f} ms per iteration, {ms * 1e3 / a.horizon:.1f} us per model step fwd+bwd "
              f"(wall {1e3 * (time.perf_counter() - t0) / 20:.3f} ms)")


if __name__ == "__main__":
    main()
