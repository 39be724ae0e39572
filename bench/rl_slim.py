"""Benchmark: a run's slim copy (``gnwarp.rl.slim``): its size against the full checkpoint's, and
how fast the replay buffer is rebuilt by re-simulating its actions, on one machine.

Per task: a run of ``--rounds`` rounds (``num_envs`` episodes each) of random actions and no
updates (``start_steps`` and ``update_after`` past its end: the buffer is what any run stores), its
checkpoint's size, the slim copy's (and each one xz-compressed, as an archive brings it back),
then the rebuild alone (``rebuild_buffer``, timed after the copy is loaded) as env steps a second,
in this process and in ``--workers`` worker processes (their start counted), and the sizes scaled
to a 1M-step buffer.

    python bench/rl_slim.py [--tasks swimmer6,cheetah-run,walker-walk] [--rounds 3] [--envs 10]
    python bench/rl_slim.py --quick      # pendulum, tiny: a smoke test of the script
"""
from __future__ import annotations

import argparse
import lzma
import os
import sys
import tempfile
import time
from functools import partial
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from bench.harness import add_run_args, device_name, experiment_out, save_results  # noqa: E402
from gnwarp.rl.config import RLConfig  # noqa: E402
from gnwarp.rl.run import build_run, round_seed, run_rl, training_env  # noqa: E402
from gnwarp.rl.run_log import CHECKPOINT, load_checkpoint  # noqa: E402
from gnwarp.rl.slim import rebuild_buffer, slim_run  # noqa: E402

__all__ = ["measure", "main"]


def _xz_mb(path: Path) -> float:
    return len(lzma.compress(path.read_bytes(), preset=6)) / 2**20


def measure(base: dict, work: Path, workers: int) -> dict:
    """One row: the run of ``base`` (RLConfig keys) trained in ``work/run``, its slim copy, sizes
    and the rebuild's rate, in this process and in ``workers`` worker processes."""
    cfg = RLConfig(**base, out=str(work / "run"))
    run_rl(cfg)
    slim_run(work / "run", work / "slim")
    full, slim = work / "run" / CHECKPOINT, work / "slim" / CHECKPOINT
    parts = build_run(RLConfig(**{**base, "out": str(work / "slim")}))
    buf, task, T = parts["buffer"], parts["task"], parts["env"].episode_steps
    parts["env"].close()
    parts["eval_env"].close()
    saved = load_checkpoint(slim)["buffer"]
    steps = saved["filled"] * buf.num_envs
    rate = {}
    for w in dict.fromkeys((1, workers)):   # here, then in worker processes (their start counted)
        buf.load_state_dict(saved)
        t = time.perf_counter()
        rebuild_buffer(buf, partial(training_env, cfg), partial(round_seed, cfg.seed), T, workers=w)
        rate[w] = steps / (time.perf_counter() - t)
    scale = 1e6 / steps
    row = dict(task=task.name, envs=cfg.num_envs, transitions=steps,
               full_mb=round(full.stat().st_size / 2**20, 3), slim_mb=round(slim.stat().st_size / 2**20, 3),
               full_xz_mb=round(_xz_mb(full), 3), slim_xz_mb=round(_xz_mb(slim), 3), workers=workers,
               rebuild_steps_per_s_here=round(rate[1], 1), rebuild_steps_per_s=round(rate[workers], 1))
    # a 1M-step buffer: the buffer's share scales, the networks' does not (counted once, from the
    # copy without buffer: the slim checkpoint less its actions)
    actions = buf.action[:buf.filled].numel() * buf.action.element_size() / 2**20
    row["slim_mb_at_1m"] = round(row["slim_mb"] - actions + actions * scale, 1)
    row["full_mb_at_1m"] = round(row["slim_mb"] - actions + (row["full_mb"] - row["slim_mb"] + actions) * scale, 1)
    return row


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tasks", default="swimmer6,cheetah-run,walker-walk")
    ap.add_argument("--rounds", type=int, default=3, help="rounds of num_envs episodes stored")
    ap.add_argument("--envs", type=int, default=10, help="envs stepped together (num_envs)")
    ap.add_argument("--workers", type=int, default=os.cpu_count(), help="worker processes of the second rebuild")
    add_run_args(ap, "rl")
    a = ap.parse_args(argv)
    tasks = ["pendulum-balance"] if a.quick else [t for t in a.tasks.split(",") if t]
    if a.quick:
        a.workers = 1   # a smoke test: no worker processes to start (tests/test_rl_slim.py runs them)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)   # as each rebuild worker runs; the caller's setting back afterwards
    try:
        rows = [_task_row(task, a) for task in tasks]
    finally:
        torch.set_num_threads(threads)
    name = rows[0]["device"]
    lines = [f"# A run's slim copy: sizes and the replay buffer's rebuild, on {name}", "",
             f"`python bench/rl_slim.py` ({time.strftime('%Y-%m-%d')}): {a.rounds} rounds of {a.envs} episodes of "
             f"random actions, MuJoCo C; the rebuild re-simulates every stored step (`gnwarp.rl.slim`) in this "
             f"process, or in {a.workers} worker processes (their start included).", "",
             "| task | transitions | checkpoint MiB (xz) | slim MiB (xz) | at 1M steps: full / slim MiB | "
             f"rebuild env steps / s: here / {a.workers} workers |", "|---|---|---|---|---|---|"]
    lines += [f"| {r['task']} | {r['transitions']} | {r['full_mb']} ({r['full_xz_mb']}) | {r['slim_mb']} "
              f"({r['slim_xz_mb']}) | {r['full_mb_at_1m']} / {r['slim_mb_at_1m']} | "
              f"{r['rebuild_steps_per_s_here']} / {r['rebuild_steps_per_s']} |" for r in rows]
    save_results(experiment_out("rl", a.out, a.quick), "rl_slim", name, a.quick, rows, lines)


def _task_row(task: str, a) -> dict:
    """One task's row: a run of ``a.rounds`` rounds of random actions, measured (``measure``)."""
    base = dict(task=task, agent="ddpg", num_envs=a.envs, device="cpu", backend="mujoco", sim_threads=1,
                progress=False, tensorboard=False, video_episodes=0, eval_episodes=1)
    if a.quick:
        base.update(observation="bodies", episode_steps=10, num_envs=2, hidden=(8,))
    steps = a.rounds * base["num_envs"] * (base.get("episode_steps") or 1000)
    base.update(env_steps=steps, start_steps=steps + 1, update_after=steps + 1, eval_every=10 * steps)
    with tempfile.TemporaryDirectory() as d:
        row = measure(base, Path(d), a.workers)
    row.update(device=device_name(torch.device("cpu")), date=time.strftime("%Y-%m-%d"))
    print(row, flush=True)
    return row


if __name__ == "__main__":
    main()
