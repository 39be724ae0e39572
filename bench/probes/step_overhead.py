"""Probe: what a gradient-MPC control step spends beyond its planning iterations.

Builds the planner of ``bench/mpc_latency.py`` (``planning_setup``, ``GradientMPCConfig(horizon=H,
iterations=I, seed=0, fused=...)``), takes a few control steps, then times with CUDA events:
``iterate(x, I)`` alone (the captured iterations), ``step(x)`` (the control step the benchmark
times: check, iterations, plan copy, shift) and ``check_state(x)``; and lists the kernels of one
``step`` and of ``iterate(x, I)`` (torch.profiler) into ``--out``.

    python bench/probes/step_overhead.py [--system pendulum] [--n 4096] [--horizon 100] [--iterations 5] [--fused true]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import torch  # noqa: E402

from bench.harness import profile_kernels  # noqa: E402
from bench.mpc_latency import planning_setup  # noqa: E402
from gnwarp.control import GradientMPC, GradientMPCConfig  # noqa: E402


def timed(fn, reps: int) -> float:
    """Milliseconds per call of ``fn`` (CUDA events, ``reps`` calls after one)."""
    fn()
    a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    torch.cuda.synchronize()
    a.record()
    for _ in range(reps):
        fn()
    b.record()
    b.synchronize()
    return a.elapsed_time(b) / reps


def main(argv=None):
    p = argparse.ArgumentParser()
    p.add_argument("--system", default="pendulum")
    p.add_argument("--n", type=int, default=4096)
    p.add_argument("--horizon", type=int, default=100)
    p.add_argument("--iterations", type=int, default=5)
    p.add_argument("--fused", choices=["auto", "true", "false"], default="true")
    p.add_argument("--out", default=".")
    a = p.parse_args(argv)
    dev = torch.device("cuda")
    system, task, model, x, targets = planning_setup(a.system, a.n, dev)
    cfg = GradientMPCConfig(horizon=a.horizon, iterations=a.iterations, seed=0,
                            fused={"auto": None, "true": True, "false": False}[a.fused])
    pl = GradientMPC(model, task, system, a.n, cfg, targets)
    for _ in range(4):
        pl.step(x)
    xs = pl.check_state(x)
    t_iter = timed(lambda: pl.iterate(xs, a.iterations), 5)
    t_step = timed(lambda: pl.step(x), 5)
    t_check = timed(lambda: pl.check_state(x), 5)
    t_shift = timed(pl.shift, 5)
    print(f"{a.system} N={a.n} H={a.horizon} I={a.iterations} fused={a.fused}: iterate(x, I) {t_iter:.2f} ms, "
          f"step {t_step:.2f} ms, check_state {t_check:.3f} ms, shift {t_shift:.3f} ms, "
          f"x {tuple(x.shape)} {x.dtype} {x.device} contiguous={x.is_contiguous()}")
    table = Path(a.out) / f"step_overhead_{a.system}_{a.n}_fused_{a.fused}.txt"
    for name, fn in (("step", lambda: pl.step(x)), ("iterate", lambda: pl.iterate(xs, a.iterations))):
        k, us = profile_kernels(fn, 2, table, f"{name}: {a.system} N={a.n} H={a.horizon} I={a.iterations}",
                                top=25, unit=name)
        print(f"{name}: {k:.0f} kernels, {us / 1e3:.2f} ms device (table: {table})")


if __name__ == "__main__":
    main()
