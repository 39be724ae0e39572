"""Benchmark: environment steps per second of the Gymnasium vector environments
(``gnwarp.control.vector_env``), the true simulator and a learned model behind the same API.

Cheetah (``cheetah-forward``), uniform random actions, ``output="torch"`` (no copy to the host),
per batch of envs: the true simulator's vector env and, beside it, its ``Env.step`` alone (the
vector env's overhead: actions checked and clamped, reward, observation); the learned model's
vector env (the paper core, untrained: the speed does not depend on the weights). Env steps per
second = envs x steps / seconds; the reset (initial states drawn per env on the host) is timed
on its own.

    python bench/vector_env.py [--batches 256,4096] [--steps 200] [--backend auto]
    python bench/vector_env.py --quick       # tiny sizes on the CPU: a smoke test of the script

``--task`` another task (its system's model for the learned row); ``--observation dmc``: the
suite's observation (``gnwarp.rl.observations.DMCObservation``, what ``gnwarp rl`` trains on)
instead of the body states; ``--dynamics true``: the true simulator's rows only. The RL loop's
environment side, e.g. on the CPU:

    python bench/vector_env.py --task dmc-swimmer-swimmer6 --observation dmc --dynamics true \
        --batches 10 --backend mujoco --device cpu
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from bench.harness import PAPER, QUICK, device_name, experiment_out, save_results  # noqa: E402
from gnwarp import data  # noqa: E402
from gnwarp.control.tasks import get_task  # noqa: E402
from gnwarp.control.vector_env import make_vector_env  # noqa: E402
from gnwarp.models import ForwardModel, ModelConfig  # noqa: E402

TASK = "cheetah-forward"


def _sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def steps_per_second(env, steps: int, gen: torch.Generator) -> tuple[float, float]:
    """(env steps per second over ``steps`` steps after a warm-up, reset seconds) of a vector env."""
    t0 = time.perf_counter()
    env.reset(seed=0)
    reset_s = time.perf_counter() - t0
    lo = torch.as_tensor(env.single_action_space.low, device=env.device)
    hi = torch.as_tensor(env.single_action_space.high, device=env.device)
    u = [lo + (hi - lo) * torch.rand(env.num_envs, lo.shape[0], generator=gen, device="cpu").to(env.device)
         for _ in range(8)]
    for k in range(3):   # compile, capture
        env.step(u[k % 8])
    _sync(env.device)
    t0 = time.perf_counter()
    for k in range(steps):
        env.step(u[k % 8])
    _sync(env.device)
    return env.num_envs * steps / (time.perf_counter() - t0), reset_s


def raw_steps_per_second(env, steps: int) -> float:
    """Env steps per second of the true simulator's own ``Env.step`` under fixed actions."""
    inner = env.sim.env
    u = torch.zeros(env.num_envs, env.nu, device=env.device)
    for _ in range(3):
        inner.step(u)
    _sync(env.device)
    t0 = time.perf_counter()
    for _ in range(steps):
        inner.step(u)
    _sync(env.device)
    return env.num_envs * steps / (time.perf_counter() - t0)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batches", default="256,4096")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--backend", default="auto")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--precision", default="tf32")
    ap.add_argument("--task", default=TASK)
    ap.add_argument("--observation", choices=("bodies", "dmc"), default="bodies")
    ap.add_argument("--dynamics", default="true,learned", help="true, learned, or true,learned")
    ap.add_argument("--out", default=None, help="default: bench/results/vector_env (--quick: a temporary folder)")
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    if args.quick:
        args.device, args.batches, args.steps, args.backend = "cpu", "8", 5, "mujoco"
    dev = torch.device(args.device)
    kinds = [k.strip() for k in args.dynamics.split(",")]
    if not kinds or set(kinds) - {"true", "learned"}:
        ap.error(f"--dynamics: true, learned, or true,learned, got {args.dynamics!r}")
    task = get_task(args.task)
    obs = "bodies"
    if args.observation == "dmc":
        from gnwarp.rl.observations import DMCObservation
        try:
            obs = DMCObservation(task)
        except ValueError as e:
            ap.error(f"--observation dmc: {e}")
    model = None
    if "learned" in kinds:
        ds = data.generate(task.system, (16, 2, 2), num_steps=10, seed=0, backend="mujoco", progress=False)
        model = ForwardModel(ModelConfig(gn=QUICK if args.quick else PAPER), ds.layout).to(dev)
        model.set_options(precision=args.precision)
        for p in model.parameters():
            p.requires_grad_(False)
    gen = torch.Generator().manual_seed(0)
    name, rows = device_name(dev), []
    common = dict(task=task.name, observation=args.observation, device=name)
    for n in (int(b) for b in args.batches.split(",")):
        if "true" in kinds:
            true = make_vector_env(task, n, dynamics="true", backend=args.backend, episode_steps=10 ** 6,
                                   output="torch", observation=obs)
            sps, reset_s = steps_per_second(true, args.steps, gen)
            rows.append(dict(common, dynamics="true", backend=true.backend, envs=n, steps=args.steps,
                             env_steps_per_s=round(sps),
                             raw_env_steps_per_s=round(raw_steps_per_second(true, args.steps)), reset_s=round(reset_s, 4)))
            true.close()
            print(json.dumps(rows[-1]), flush=True)
        if model is not None:
            learned = make_vector_env(task, n, dynamics=model, episode_steps=10 ** 6, output="torch", observation=obs)
            sps, reset_s = steps_per_second(learned, args.steps, gen)
            rows.append(dict(common, dynamics="learned", backend=f"model ({args.precision})", envs=n,
                             steps=args.steps, env_steps_per_s=round(sps), raw_env_steps_per_s=None,
                             reset_s=round(reset_s, 4)))
            learned.close()
            print(json.dumps(rows[-1]), flush=True)
    lines = [f"# Vector environments: env steps per second, on {name}", "",
             f"`python bench/vector_env.py` ({time.strftime('%Y-%m-%d')}): {task.name}, {args.observation} observation, "
             "random actions, output torch, "
             f"{args.steps} steps after a warm-up; the learned model is the {'quick' if args.quick else 'paper'} core "
             "(untrained); 'Env.step alone' is the true simulator without the vector env around it.", "",
             "| dynamics | backend | envs | env steps / s | Env.step alone, env steps / s | reset (s) |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        raw = r["raw_env_steps_per_s"]
        lines.append(f"| {r['dynamics']} | {r['backend']} | {r['envs']} | {r['env_steps_per_s']} | "
                     f"{raw if raw is not None else ''} | {r['reset_s']} |")
    save_results(experiment_out("vector_env", args.out, args.quick), "vector_env", name, args.quick, rows, lines)


if __name__ == "__main__":
    main()
