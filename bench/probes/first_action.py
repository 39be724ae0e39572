"""Probe: where the first action's time goes (a fresh process, Warp's kernel cache filled earlier).

The gradient planner of ``bench/mpc_latency.py`` (untrained planning core, one system, N
episodes, horizon H, iterations I), timed phase by phase with the device synchronized: planner
construction (binding, engines), the sampled proposal (eager forward rollouts), the first planning
iteration (on CUDA: run eagerly, Warp modules loaded), the second (recorded into a CUDA graph),
the rest of the warm-up and the first control step's iterations (replays). Run it twice: the
first process fills the kernel caches, the second is what a user waits for.

    python bench/probes/first_action.py [--system pendulum] [--episodes 1] [--horizon 50] [--iterations 5] [--fused auto]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

T_START = time.perf_counter()
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from bench.mpc_latency import SIZES, TASKS  # noqa: E402
from gnwarp import systems  # noqa: E402
from gnwarp.control import GradientMPC, GradientMPCConfig  # noqa: E402
from gnwarp.control.tasks import get_task, sample_targets  # noqa: E402
from gnwarp.data.generation import initial_states  # noqa: E402
from gnwarp.gn.options import RunOptions  # noqa: E402
from gnwarp.models import ForwardModel, ModelConfig  # noqa: E402
from gnwarp.sim.body_state import body_states  # noqa: E402
from gnwarp.data.convert import static_arrays  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--system", default="pendulum")
    ap.add_argument("--episodes", type=int, default=1)
    ap.add_argument("--horizon", type=int, default=50)
    ap.add_argument("--iterations", type=int, default=5)
    ap.add_argument("--fused", choices=("auto", "on", "off"), default="auto")
    a = ap.parse_args(argv)
    import mujoco
    dev = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    sync = (lambda: torch.cuda.synchronize(dev)) if dev.type == "cuda" else (lambda: None)  # noqa: E731
    t_import = time.perf_counter() - T_START
    system = systems.make(a.system)
    task = TASKS[a.system]
    model = ForwardModel(ModelConfig(gn=SIZES, run=RunOptions(impl="warp")), static_arrays([system])[1]).to(dev)
    qpos, qvel = initial_states(system, a.episodes, np.random.default_rng(0))
    d, xs = mujoco.MjData(system.model), []
    for q, v in zip(qpos, qvel):
        d.qpos[:], d.qvel[:] = q, v
        mujoco.mj_forward(system.model, d)
        xs.append(body_states(system.model, d))
    x = torch.tensor(np.stack(xs), dtype=torch.float32, device=dev)
    fused = {"auto": None, "on": True, "off": False}[a.fused]
    cfg = GradientMPCConfig(horizon=a.horizon, iterations=a.iterations, seed=0, fused=fused)
    targets = sample_targets(get_task(task), system, a.episodes, seed=0)
    sync()
    phases, t = {}, time.perf_counter()

    def mark(name):
        nonlocal t
        sync()
        now = time.perf_counter()
        phases[name] = round(1e3 * (now - t), 1)
        t = now
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
           "fused": planner.engine.fused, "device": torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu",
           "imports_s": round(t_import, 2), **phases, "total_ms": round(sum(phases.values()), 1)}
    print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
