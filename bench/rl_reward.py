"""Benchmark: the DMC reward SVG(N) differentiates inside every update (``ObservationReward`` of a
predicted observation, forward and backward), with the planar forward kinematics
(``gnwarp/rl/planar_fk.py``) against the body-by-body composition, in the same process.

Per task and batch: the reward's forward and backward on random observations (``obs.grad``), as
milliseconds (median after a warm-up) and as the number of torch operations dispatched (views
included: a proxy for kernel launches, which is what the time is on a GPU even replayed from a
CUDA graph), eager and, on CUDA, recorded once in a CUDA graph and replayed.

    python bench/rl_reward.py [--tasks cheetah-run,walker-walk] [--batches 100,256] [--device cuda]
    python bench/rl_reward.py --quick      # CPU, few repetitions: a smoke test of the script
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402
from torch.utils._python_dispatch import TorchDispatchMode  # noqa: E402

from bench.harness import add_run_args, device_name, experiment_out, median_ms, save_results  # noqa: E402
from gnwarp.rl.obs_reward import ObservationReward  # noqa: E402
from gnwarp.rl.planar_fk import planar_chain  # noqa: E402

__all__ = ["time_reward", "main"]


class _Count(TorchDispatchMode):
    """Counts the operations dispatched inside it."""

    def __init__(self):
        super().__init__()
        self.n = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.n += 1
        return func(*args, **(kwargs or {}))


def time_reward(task: str, batch: int, planar: bool, dev: torch.device, reps: int) -> dict:
    """One row: the reward of ``task`` forward and backward on ``batch`` observations."""
    reward = ObservationReward(task, planar=planar)
    if planar and planar_chain(reward.observation.coords) is None:
        raise ValueError(f"{task}: its model is not a planar chain")
    gen = torch.Generator(dev).manual_seed(0)
    obs = torch.randn(batch, reward.observation.size, generator=gen, device=dev).requires_grad_(True)

    def step():
        obs.grad = None
        reward(None, None, obs).sum().backward()
    step()   # constants made, modules loaded
    with _Count() as c:
        step()
    eager = median_ms(step, dev, reps, warmup=3)
    graph_ms = None
    if dev.type == "cuda":
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            for _ in range(3):
                step()
        torch.cuda.current_stream().wait_stream(side)
        g = torch.cuda.CUDAGraph()
        with torch.cuda.graph(g):
            reward(None, None, obs).sum().backward()
        graph_ms = median_ms(g.replay, dev, reps, warmup=3)
    assert obs.grad is not None and bool(torch.isfinite(obs.grad).all())
    return dict(task=task, batch=batch, fk="planar" if planar else "general", ops=c.n, eager_ms=round(eager, 4),
                graph_ms=None if graph_ms is None else round(graph_ms, 4))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tasks", default="cheetah-run,walker-walk")
    ap.add_argument("--batches", default="100,256")
    ap.add_argument("--reps", type=int, default=50)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    add_run_args(ap, "rl")   # --out, --quick
    a = ap.parse_args(argv)
    if a.quick:
        a.device, a.batches, a.reps = "cpu", "16", 3
    dev = torch.device(a.device)
    name, rows = device_name(dev), []
    for task in a.tasks.split(","):
        for batch in (int(b) for b in a.batches.split(",")):
            for planar in (False, True):
                row = dict(device=name, date=time.strftime("%Y-%m-%d"),
                           **time_reward(task.strip(), batch, planar, dev, a.reps))
                rows.append(row)
                print(json.dumps(row), flush=True)
    lines = [f"# SVG(N)'s reward in an update: planar kinematics against body by body, on {name}", "",
             f"`python bench/rl_reward.py` ({time.strftime('%Y-%m-%d')}): `ObservationReward` forward and "
             "backward on random observations; ops = torch operations dispatched (views included); ms = "
             f"median of {a.reps} after 3 warm-up calls (eager; replayed from a CUDA graph on CUDA).", "",
             "| task | batch | kinematics | ops | eager ms | CUDA graph ms | eager: general / planar |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        peer = next(p for p in rows if p["task"] == r["task"] and p["batch"] == r["batch"] and p["fk"] == "general")
        lines.append(f"| {r['task']} | {r['batch']} | {r['fk']} | {r['ops']} | {r['eager_ms']} | "
                     f"{r['graph_ms'] if r['graph_ms'] is not None else '-'} | "
                     f"{peer['eager_ms'] / r['eager_ms']:.2f} |")
    save_results(experiment_out("rl", a.out, a.quick), "rl_reward", name, a.quick, rows, lines)


if __name__ == "__main__":
    main()
