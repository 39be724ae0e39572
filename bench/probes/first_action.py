"""Probe: where the first action's time goes (a fresh process, Warp's kernel cache filled earlier).

The gradient planner of ``bench/mpc_latency.py`` (untrained planning core, one system, N
episodes, horizon H, iterations I), timed phase by phase with the device synchronized: planner
construction (binding, engines), the sampled proposal (eager forward rollouts), the first planning
iteration (on CUDA with the default ``--capture-warmup 0``: the one-step prime, the recording and
its replay; with 1 or more: eager, Warp modules loaded), the second (a replay with 0, the
recording with 1, eager with 2), the rest of the warm-up and the first control step's iterations
(the recording, where it was not yet made, then replays). Run it twice: the
first process fills the kernel caches, the second is what a user waits for.

    python bench/probes/first_action.py [--system pendulum] [--episodes 1] [--horizon 50] [--iterations 5]
        [--fused auto] [--sample 20] [--warp-log] [--cuda-output auto] [--gemm-first] [--no-prime-dense]

``--sample MS``: also sample every thread's Python stack every MS milliseconds (the autograd
engine runs a CUDA backward on its own thread, which cProfile does not see) and print, per phase,
the functions (file:line name) that were on a stack in the most samples (inclusive time).
``--gemm-first``: before construction, one dense layer of the model's width forward and backward,
timed alone (``gemm_first_ms``: the process's first GEMMs, cuBLAS's handle, workspace and
heuristics), so that the phases after it show what is left without that first use.
``--warp-log``: Warp's info log on (each module load's time, "(cached)" or "(compiled)").
``--cuda-output ptx|cubin``: ``wp.config.cuda_output`` (auto: Warp writes PTX where the driver
is at least as new as its toolkit, and the driver compiles that PTX at every process's module
load unless its own cache, ``CUDA_CACHE_PATH`` / ``CUDA_CACHE_MAXSIZE``, holds it; a cubin loads
as is). A format the cache lacks is compiled by the first process.
"""
from __future__ import annotations

import argparse
import collections
import json
import sys
import threading
import time
from pathlib import Path

T_START = time.perf_counter()
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import torch  # noqa: E402

from bench.mpc_latency import SIZES, planning_setup  # noqa: E402
from gnwarp.control import GradientMPC, GradientMPCConfig  # noqa: E402
from gnwarp.interop import warp  # noqa: E402


class StackSampler:
    """Every ``period`` seconds, counts each function (once a sample, inclusive) on any thread's
    Python stack but the sampler's own, under the phase set in ``phase``."""

    def __init__(self, period: float):
        self.period, self.phase, self.counts = period, "setup", collections.defaultdict(collections.Counter)
        self.samples = collections.Counter()
        sys.setswitchinterval(1e-4)   # the sampler gets the GIL soon, and gives it back soon
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        me = threading.get_ident()
        while not self._stop.wait(self.period):
            phase, seen = self.phase, set()
            for tid, frame in sys._current_frames().items():
                while tid != me and frame is not None:
                    c = frame.f_code
                    seen.add(f"{c.co_filename.split('site-packages/')[-1]}:{c.co_firstlineno} {c.co_name}")
                    frame = frame.f_back
            self.counts[phase].update(seen)
            self.samples[phase] += 1

    def report(self, top: int = 40):
        self._stop.set()
        self._thread.join()
        for phase, counter in self.counts.items():
            n = self.samples[phase]
            print(f"-- {phase}: {n} samples of {1e3 * self.period:.0f} ms", flush=True)
            for name, k in counter.most_common(top):
                print(f"{100 * k / n:5.1f}%  {name}", flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--system", default="pendulum")
    ap.add_argument("--episodes", type=int, default=1)
    ap.add_argument("--horizon", type=int, default=50)
    ap.add_argument("--iterations", type=int, default=5)
    ap.add_argument("--fused", choices=("auto", "on", "off"), default="auto")
    ap.add_argument("--sample", type=float, default=0.0, help="sample every thread's stack every this many ms")
    ap.add_argument("--warp-log", action="store_true", help="Warp's info log: each module load's time")
    ap.add_argument("--cuda-output", choices=("auto", "ptx", "cubin"), default="auto")
    ap.add_argument("--capture-warmup", type=int, default=0,
                    help="eager iterations before the recording (0: the one-step prime instead)")
    ap.add_argument("--gemm-first", action="store_true",
                    help="before construction, time one dense layer forward and backward of the model's "
                         "widths (cuBLAS's first use in the process), as gemm_first_ms")
    ap.add_argument("--no-prime-dense", action="store_true",
                    help="GradientMPCConfig(prime_dense=False): no cuBLAS first use on a thread beside construction")
    a = ap.parse_args(argv)
    wp = warp()   # initialized with gnwarp's log level, then the options
    if a.warp_log:
        wp.config.log_level = wp.LOG_INFO
    if a.cuda_output != "auto":
        wp.config.cuda_output = a.cuda_output
    sampler = StackSampler(a.sample / 1e3) if a.sample > 0 else None
    dev = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    sync = (lambda: torch.cuda.synchronize(dev)) if dev.type == "cuda" else (lambda: None)  # noqa: E731
    t_import = time.perf_counter() - T_START
    system, task, model, x, targets = planning_setup(a.system, a.episodes, dev)
    fused = {"auto": None, "on": True, "off": False}[a.fused]
    cfg = GradientMPCConfig(horizon=a.horizon, iterations=a.iterations, seed=0, fused=fused,
                            capture_warmup=a.capture_warmup, prime_dense=not a.no_prime_dense)
    sync()
    first_use = {}
    if a.gemm_first:   # what the process's first GEMMs cost alone (handle, workspace, heuristics)
        t0 = time.perf_counter()
        width = SIZES.edge_hidden[0]   # the planning core's MLP width
        w = torch.randn(width, width, device=dev, requires_grad=True)
        h = torch.randn(32, width, device=dev, requires_grad=True)
        torch.nn.functional.linear(torch.relu(h @ w), w).sum().backward()
        sync()
        first_use["gemm_first_ms"] = round(1e3 * (time.perf_counter() - t0), 1)
    phases, t = {}, time.perf_counter()
    order = iter(["construct", "proposal", "iteration_1", "iteration_2", "iterations_rest", "end"])
    if sampler is not None:
        sampler.phase = next(order)

    def mark(name):
        nonlocal t
        sync()
        now = time.perf_counter()
        phases[name] = round(1e3 * (now - t), 1)
        t = now
        if sampler is not None:
            sampler.phase = next(order)
    planner = GradientMPC(model, task, system, a.episodes, cfg, targets)
    mark("construct_ms")
    xc = planner.check_state(x)
    planner.propose(xc)
    mark("proposal_ms")
    planner.iterate(xc, 1)
    mark("iteration_1_ms")
    planner.iterate(xc, 1)
    mark("iteration_2_ms")
    rest = planner.warmup + cfg.iterations - 2
    planner.iterate(xc, rest)
    mark(f"iterations_3_to_{rest + 2}_ms")
    row = {"system": a.system, "episodes": a.episodes, "horizon": a.horizon, "iterations": a.iterations,
           "fused": planner.engine.fused, "capture_warmup": a.capture_warmup,
           "prime_dense": cfg.prime_dense, "device": torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu",
           "imports_s": round(t_import, 2), **first_use, **phases, "total_ms": round(sum(phases.values()), 1)}
    print(json.dumps(row), flush=True)
    if sampler is not None:
        sampler.report()


if __name__ == "__main__":
    main()
