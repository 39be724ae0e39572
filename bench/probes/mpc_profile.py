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
    a = p.parse_args(argv)
    ds = data.generate(a.system, (4, 1, 1), num_steps=10, seed=0, backend="mujoco", progress=False)
    cfg = ModelConfig(gn=GNCoreConfig(latent=128, edge_hidden=(256, 256), node_hidden=(256, 256),
                                      global_hidden=(256, 256)))
    cfg.run = cfg.run.replace(path=a.path)
    model = ForwardModel(cfg, ds.layout).to("cuda").bind(ds)
    x = torch.as_tensor(ds["test"].body[:1, 0]).expand(a.n, -1, -1).contiguous().cuda()
    for capture in (False, True):
        pl = GradientMPC(model, TASK[a.system], a.system, n=a.n,
                         config=GradientMPCConfig(horizon=a.horizon, iterations=1, warmup=0, capture=capture))
        xs = pl.check_state(x)
        for _ in range(3):
            pl.iterate(xs, 1)
        torch.cuda.synchronize()
        if not capture:
            from torch.profiler import ProfilerActivity, profile
            with profile(activities=[ProfilerActivity.CUDA, ProfilerActivity.CPU]) as prof:
                pl.iterate(xs, 1)
                torch.cuda.synchronize()
            per = {}
            for ev in prof.events():
                if ev.device_type == torch.autograd.DeviceType.CUDA:
                    k = per.setdefault(ev.name[:90], [0, 0.0])
                    k[0] += 1
                    k[1] += ev.device_time_total
            H = a.horizon
            tot = sum(v[1] for v in per.values())
            cnt = sum(v[0] for v in per.values())
            print(f"eager iteration: {cnt} kernels, {tot:.0f} us device; per model step {cnt / H:.1f} kernels, "
                  f"{tot / H:.1f} us")
            for n_, (c, us) in sorted(per.items(), key=lambda kv: -kv[1][1])[:45]:
                print(f"{us / H:8.1f} us {c / H:6.1f}x  {n_}")
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
