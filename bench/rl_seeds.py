"""Several seeds of one RL run side by side on one machine: a process per seed (``run_rl`` in its
own folder ``<runs>/<agent>-<preset>-<networks>/s<seed>``, ``-utd<k>`` appended where ``--set utd=k``
is not 1, ``-ahead`` where ``--set act_ahead=true``, then each agent setting off its default, e.g.
``-squash_penalty0.001``: ``run_name``), each stopping within the budget and
resumed by the next call; afterwards each seed's records and log are copied to
``<results>/<task>/<that name>/s<seed>/`` for ``bench/rl_summary.py``.

    PYTHONPATH=. python3 bench/rl_seeds.py --agent svg1 --task swimmer6 --seeds 0-5 --budget-seconds 480
    PYTHONPATH=. python3 bench/rl_seeds.py --quick            # CPU-sized, 2 seeds, seconds

``--export DIR`` also writes each seed's trained agent without its replay buffer (``export_agent``)
to ``DIR/<agent>-<preset>-<networks>/s<seed>/`` after every call.

``--set KEY=VALUE`` sets any other ``RLConfig`` key for every seed (values parsed as JSON where
they parse). A call prints one line per seed: env steps reached and whether it is done.

Under ``torchrun`` each rank starts only its share of the seeds (``seeds[rank::world]``), their
processes on the rank's GPU (``CUDA_VISIBLE_DEVICES``; nothing changes on a CPU run); rank 0
gathers every seed's line and files, prints the lines in seed order and copies the files:

    torchrun --nproc_per_node 2 bench/rl_seeds.py --agent svg1 --task swimmer6 --seeds 0-5
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

__all__ = ["seeds_of", "run_name", "seed_config", "main", "rank_env"]

# copied to <results>/<task>/<run>/s<seed>/ for bench/rl_summary.py
COPIED = ("records.jsonl", "progress.csv", "config.json")
# what torchrun sets for its workers; a seed's process runs alone
TORCHRUN_VARS = ("WORLD_SIZE", "RANK", "LOCAL_RANK", "LOCAL_WORLD_SIZE", "GROUP_RANK", "GROUP_WORLD_SIZE",
                 "ROLE_RANK", "ROLE_WORLD_SIZE", "MASTER_ADDR", "MASTER_PORT", "TORCHELASTIC_RUN_ID")

QUICK = dict(task="pendulum-balance", agent="svg0", observation="bodies", num_envs=2, episode_steps=20,
             env_steps=160, hidden=[16], batch_size=16, start_steps=40, update_after=40, buffer_size=1000,
             eval_every=80, eval_episodes=4, device="cpu", backend="mujoco", tensorboard=False, video_episodes=0)


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
    """Run one seed (the child process); with "export" in the JSON, then write its agent there."""
    from gnwarp.rl.config import RLConfig
    from gnwarp.rl.run import export_agent, run_rl
    d = json.loads(cfg_json)
    export = d.pop("export", None)
    r = run_rl(RLConfig.from_dict(d))
    if export:
        try:   # the training is saved either way: a failed export is reported, not a failed seed
            export_agent(d["out"], export)
        except (OSError, ValueError) as e:
            print(f"export to {export} failed: {e}", file=sys.stderr)
    print(json.dumps({k: r[k] for k in ("stop", "env_steps", "updates", "rounds", "seconds")}))
    return 0


def run_name(base: dict) -> str:
    """The run's folder name: ``<agent>-<preset>-<networks>``, ``-utd<k>`` where ``utd`` is not 1,
    ``-ahead`` where ``act_ahead`` is true, then each agent setting off its default, the run's
    own (``batch_size``, ``hidden``, ``start_steps``, ``update_after``) and ``agent_settings``'
    (``gnwarp.rl.settings.settings_tag``, as ``bench/rl_summary.py`` groups the records:
    ``-squash_penalty0.001``), and ``-eval<k>`` where ``eval_seed`` is k (its runs evaluate on
    shared states: a curve of their own) (``ValueError`` naming a bad value)."""
    try:
        utd = float(base.get("utd", 1.0))
    except (TypeError, ValueError):
        raise ValueError(f"--set utd=...: updates per env step must be a number > 0, got {base.get('utd')!r}") from None
    ahead = base.get("act_ahead", False)
    if not isinstance(ahead, bool):
        raise ValueError(f"--set act_ahead=...: true or false, got {ahead!r}")
    extra = base.get("agent_settings") or {}
    if not isinstance(extra, dict):
        raise ValueError(f"--set agent_settings=...: a JSON object of agent settings, got {extra!r}")
    from gnwarp.rl.config import RLConfig
    from gnwarp.rl.settings import settings_tag
    # the agent settings the run's records will hold, its own keys (batch_size, hidden, ...) too; a
    # refused setting raises ConfigError (a ValueError) naming its key
    tag = settings_tag(RLConfig.from_dict({**base, "out": "unused"}).agent_config().to_dict())
    es = base.get("eval_seed")
    return (f"{base['agent']}-{base['preset']}-{base['networks']}" + ("" if utd == 1 else f"-utd{utd:g}")
            + ("-ahead" if ahead else "") + ("-" + tag.replace("=", "").replace(",", "-") if tag else "")
            + ("" if es is None else f"-eval{es}"))


def seed_config(quick: bool, task: str, agent: str, preset: str, networks: str, threads: int,
                env_steps: int | None, sets, **more) -> dict:
    """The ``RLConfig`` keys every seed of a call shares: ``QUICK``'s (whose agent and task stand
    unless ``sets`` change them) or ``task`` and ``agent``; then the preset, networks, MuJoCo C's
    threads (``sim_threads``: processes side by side share the cores), ``env_steps`` where given,
    ``more``, and ``sets`` (``KEY=VALUE``, values parsed as JSON where they parse)."""
    from gnwarp.validation import parse_value
    base: dict = dict(QUICK) if quick else dict(task=task, agent=agent)
    base.update(preset=preset, networks=networks, progress=False, sim_threads=threads, **more)
    if env_steps is not None:
        base["env_steps"] = env_steps
    for item in sets:
        key, _, text = item.partition("=")
        base[key.strip()] = parse_value(text)
    return base


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--agent", default="svg1")
    ap.add_argument("--task", default="swimmer6")
    ap.add_argument("--preset", default="spinningup")
    ap.add_argument("--networks", default="mlp")
    ap.add_argument("--seeds", default="0-5", help="e.g. 0-5 or 0,2,7")
    ap.add_argument("--env-steps", type=int, default=None, help="env steps to train in all (default: RLConfig's)")
    ap.add_argument("--budget-seconds", type=float, default=480.0, help="each seed's budget in this call")
    ap.add_argument("--threads", type=int, default=2, help="CPU threads of each process (OMP_NUM_THREADS, and its MuJoCo C pool: sim_threads)")
    ap.add_argument("--runs", default="runs/rl", help="folder of the run folders")
    ap.add_argument("--results", default=str(Path("bench") / "results" / "rl"),
                    help="where each seed's records.jsonl and progress.csv are copied")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="another RLConfig key")
    ap.add_argument("--export", default=None, metavar="DIR",
                    help="after each seed's call, its trained agent alone (export_agent: no replay buffer, a few MB) "
                         "in DIR/<agent>-<preset>-<networks>/s<seed>: what can leave a machine that keeps nothing")
    ap.add_argument("--quick", action="store_true", help="CPU-sized (pendulum-balance, 2 seeds, tiny networks)")
    ap.add_argument("--one", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.one:
        return _one(a.one)
    base = seed_config(a.quick, a.task, a.agent, a.preset, a.networks, a.threads, a.env_steps, a.set,
                       budget_seconds=a.budget_seconds)
    try:
        seeds = seeds_of("0-1" if a.quick and a.seeds == "0-5" else a.seeds)
        name = run_name(base)
    except ValueError as e:
        ap.error(str(e))
    env = dict(os.environ, OMP_NUM_THREADS=str(a.threads), MKL_NUM_THREADS=str(a.threads))
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    from gnwarp.distributed import close, launched, ranks
    # under torchrun: this process only starts and waits (gloo); its seeds' processes use its GPU
    # the gather waits for every seed of every rank: longer than the budget, whatever the default
    os.environ.setdefault("GNWARP_DIST_TIMEOUT", str(int(2 * a.budget_seconds * max(1, len(seeds)) + 600)))
    r = ranks("cpu")
    if launched():
        env.update(rank_env(r.local_rank, base.get("device", "auto")))
        for k in TORCHRUN_VARS:   # a seed's process is one process, not a rank of this job
            env.pop(k, None)
    started = time.perf_counter()

    def run(mine: list) -> list:
        """This rank's seeds, a process each, side by side: one dict per seed."""
        procs = {}
        for s in mine:
            out = Path(a.runs) / name / f"s{s}"
            out.mkdir(parents=True, exist_ok=True)
            cfg = json.dumps({**base, "seed": s, "out": str(out)}
                             | ({"export": str(Path(a.export) / name / f"s{s}")} if a.export else {}))
            log = open(out / "call.log", "a")
            procs[s] = (subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--one", cfg], env=env,
                                         stdout=log, stderr=subprocess.STDOUT), out, log)
        done = []
        for s, (p, out, log) in procs.items():
            rc = p.wait()
            log.close()
            lines = (out / "call.log").read_text().strip().splitlines()
            files = {f: (out / f).read_bytes() for f in COPIED if rc == 0 and (out / f).is_file()}
            task = json.loads(files["config.json"])["task"] if "config.json" in files else None
            done.append({"seed": s, "rc": rc, "lines": lines, "task": task, "files": files})
        return done

    done = False
    try:
        results = r.map_sharded(seeds, run, batched=True, what="rl seeds")
        done = True
    finally:
        close(sync=done)   # leave the process group before exit (else gloo may abort the process at exit)
    if not r.main:
        return 0
    failed = 0
    for d in results:
        last = d["lines"][-1] if d["lines"] else ""
        print(f"seed {d['seed']}: exit {d['rc']}, {last}")
        if d["rc"] != 0:
            failed += 1
            print("\n".join(d["lines"][-15:]), file=sys.stderr)
            continue
        file_seed(a.results, d["task"], name, d["seed"], d["files"])
    where = f" on {r.world} ranks" if r.distributed else ""
    print(f"{len(seeds)} seeds in {time.perf_counter() - started:.0f} s{where}; records under {a.results}")
    return 1 if failed else 0


def file_seed(results, task: str, name: str, seed, files: dict) -> Path:
    """Write a seed's copied files (``{file name: bytes}``, of ``COPIED``) to
    ``<results>/<task>/<name>/s<seed>``, each to a temporary name, then renamed; the folder."""
    from gnwarp.files import atomic_write
    dest = Path(results) / task / name / f"s{seed}"
    dest.mkdir(parents=True, exist_ok=True)
    for f, data in files.items():
        with atomic_write(dest / f) as tmp:
            tmp.write_bytes(data)
    return dest


def rank_env(local_rank: int, device) -> dict:
    """The environment of a rank's seed processes: the GPU of its local rank alone
    (``CUDA_VISIBLE_DEVICES``, an entry of the one given), or nothing on a CPU run."""
    import torch
    if str(device) == "cpu" or not torch.cuda.is_available():
        return {}
    given = os.environ.get("CUDA_VISIBLE_DEVICES")
    gpus = [g.strip() for g in given.split(",") if g.strip()] if given else \
        [str(i) for i in range(torch.cuda.device_count())]
    if local_rank >= len(gpus):
        raise ValueError(f"local rank {local_rank} has no GPU of its own ({len(gpus)} visible): start at most "
                         f"{len(gpus)} processes per host (torchrun --nproc_per_node {len(gpus)})")
    return {"CUDA_VISIBLE_DEVICES": gpus[local_rank]}


if __name__ == "__main__":
    raise SystemExit(main())
