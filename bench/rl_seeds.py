"""Several seeds of one RL run side by side on one machine: a process per seed (``run_rl`` in its
own folder ``<runs>/<agent>-<preset>-<networks>/s<seed>``), each stopping within the budget and
resumed by the next call; afterwards each seed's records and log are copied to
``<results>/<task>/<agent>-<preset>-<networks>/s<seed>/`` for ``bench/rl_summary.py``.

    PYTHONPATH=. python3 bench/rl_seeds.py --agent svg1 --task swimmer6 --seeds 0-5 --budget-seconds 480
    PYTHONPATH=. python3 bench/rl_seeds.py --quick            # CPU-sized, 2 seeds, seconds

``--set KEY=VALUE`` sets any other ``RLConfig`` key for every seed (values parsed as JSON where
they parse). A call prints one line per seed: env steps reached and whether it is done.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

__all__ = ["seeds_of", "main"]

QUICK = dict(task="pendulum-balance", agent="svg0", observation="bodies", num_envs=2, episode_steps=20,
             env_steps=160, hidden=[16], batch_size=16, start_steps=40, update_after=40, buffer_size=1000,
             eval_every=80, eval_episodes=4, device="cpu", backend="mujoco", tensorboard=False)


def seeds_of(text: str) -> list[int]:
    """"0-5" or "0,2,7" as a list of seeds."""
    out = []
    try:
        for part in text.split(","):
            lo, _, hi = part.strip().partition("-")
            out += list(range(int(lo), int(hi) + 1)) if hi else [int(lo)]
    except ValueError:
        out = []
    if not out or min(out) < 0 or len(set(out)) != len(out):
        raise ValueError(f"seeds must be distinct integers >= 0 such as 0-5 or 0,2,7, got {text!r}")
    return out


def _one(cfg_json: str) -> int:
    """Run one seed (the child process)."""
    from gnwarp.rl.config import RLConfig
    from gnwarp.rl.run import run_rl
    r = run_rl(RLConfig.from_dict(json.loads(cfg_json)))
    print(json.dumps({k: r[k] for k in ("stop", "env_steps", "updates", "rounds", "seconds")}))
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--agent", default="svg1")
    ap.add_argument("--task", default="swimmer6")
    ap.add_argument("--preset", default="spinningup")
    ap.add_argument("--networks", default="mlp")
    ap.add_argument("--seeds", default="0-5", help="e.g. 0-5 or 0,2,7")
    ap.add_argument("--env-steps", type=int, default=None, help="env steps to train in all (default: RLConfig's)")
    ap.add_argument("--budget-seconds", type=float, default=480.0, help="each seed's budget in this call")
    ap.add_argument("--threads", type=int, default=2, help="CPU threads of each process (OMP_NUM_THREADS)")
    ap.add_argument("--runs", default="runs/rl", help="folder of the run folders")
    ap.add_argument("--results", default=str(Path("bench") / "results" / "rl"),
                    help="where each seed's records.jsonl and progress.csv are copied")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="another RLConfig key")
    ap.add_argument("--quick", action="store_true", help="CPU-sized (pendulum-balance, 2 seeds, tiny networks)")
    ap.add_argument("--one", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.one:
        return _one(a.one)
    base: dict = dict(QUICK) if a.quick else dict(task=a.task, agent=a.agent)
    base.update(preset=a.preset, networks=a.networks, budget_seconds=a.budget_seconds, progress=False)
    if a.env_steps is not None:
        base["env_steps"] = a.env_steps
    for item in a.set:
        key, _, text = item.partition("=")
        try:
            base[key.strip()] = json.loads(text)
        except json.JSONDecodeError:
            base[key.strip()] = text
    seeds = seeds_of("0-1" if a.quick and a.seeds == "0-5" else a.seeds)
    name = f"{base['agent']}-{base['preset']}-{base['networks']}"
    env = dict(os.environ, OMP_NUM_THREADS=str(a.threads), MKL_NUM_THREADS=str(a.threads))
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    procs = {}
    started = time.perf_counter()
    for s in seeds:
        out = Path(a.runs) / name / f"s{s}"
        out.mkdir(parents=True, exist_ok=True)
        cfg = json.dumps({**base, "seed": s, "out": str(out)})
        log = open(out / "call.log", "a")
        procs[s] = (subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--one", cfg], env=env,
                                     stdout=log, stderr=subprocess.STDOUT), out, log)
    failed = 0
    for s, (p, out, log) in procs.items():
        rc = p.wait()
        log.close()
        lines = (out / "call.log").read_text().strip().splitlines()
        last = lines[-1] if lines else ""
        print(f"seed {s}: exit {rc}, {last}")
        if rc != 0:
            failed += 1
            print("\n".join(lines[-15:]), file=sys.stderr)
            continue
        task = json.loads((out / "config.json").read_text())["task"]
        dest = Path(a.results) / task / name / f"s{s}"
        dest.mkdir(parents=True, exist_ok=True)
        for f in ("records.jsonl", "progress.csv", "config.json"):
            if (out / f).is_file():
                shutil.copyfile(out / f, dest / f)
    print(f"{len(seeds)} seeds in {time.perf_counter() - started:.0f} s; records under {a.results}")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
