"""Closed-loop returns of gradient MPC with the fused model step against the unfused one.

For each system (pendulum-balance, cartpole-balance, swimmer-reach on swimmer6, cheetah-forward)
a small forward model is trained here on the CPU (MuJoCo C data, a small GN core; checkpoints
under ``<out>/checkpoints/<system>/best``, reused when present), then ``GradientMPC`` plans
through it in closed loop on the true simulator (``make_env``, MuJoCo C) from the same seeded
initial states (and targets) twice: ``GradientMPCConfig(fused=True)`` and ``fused=False``, both
float32. One results record per (system, path) holds the per-episode true returns (planner
"gradient", dynamics "learned", variant "fused" / "unfused") in ``<out>/results.jsonl``.

The summary (``--summarize``: only that, from the records) gives per path the mean return and
its 95% interval (Student t over the episodes), whether the fused mean lies within the unfused
interval, and the largest per-episode difference |fused - unfused| (same initial states), into
the generated block of ``<out>/README.md`` (text outside the block is kept).

    python bench/experiments/fused_returns.py [--episodes 20] [--systems pendulum,cartpole]
    python bench/experiments/fused_returns.py --summarize
    python bench/experiments/fused_returns.py --quick        # tiny smoke run (temp folder)
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from bench.harness import device_name, ensure_dataset, experiment_out, gn_sizes, train_model  # noqa: E402

# system -> the task its episodes run
TASKS = {"pendulum": "pendulum-balance", "cartpole": "cartpole-balance", "swimmer6": "swimmer-reach",
         "cheetah": "cheetah-forward"}
PATHS = {"fused": True, "unfused": False}
BEGIN, END = "<!-- BEGIN GENERATED: fused_returns.py --summarize -->", "<!-- END GENERATED -->"


def train(args, system: str, out: Path) -> Path:
    """``<out>/checkpoints/<system>/best``: reused when present, else trained here on the CPU."""
    best = out / "checkpoints" / system / "best"
    if best.exists():
        print(f"{system}: checkpoint {best}", flush=True)
        return best
    from gnwarp.models import ModelConfig
    (out / "data").mkdir(parents=True, exist_ok=True)
    data = ensure_dataset(out / "data" / f"{system}.h5", system, args.sequences, args.seq_steps, seed=1)
    t0 = time.perf_counter()
    res = train_model([str(data)], out / "checkpoints" / system, ModelConfig(gn=gn_sizes(*args.gn)),
                      args.train_steps, lr=1e-3, decay_every=args.train_steps // 4, valid_every=args.valid_every,
                      valid=args.sequences[1], seconds=args.train_seconds, batch_size=args.batch, device="cpu")
    print(f"{system}: trained {res['steps']} steps in {time.perf_counter() - t0:.0f} s -> {res['best']}", flush=True)
    return Path(res["best"])


def run_system(args, system_name: str, out: Path, commit: str) -> list:
    """Both paths' episodes of one system; their two ``ResultRecord``s."""
    from gnwarp.control import GradientMPC, GradientMPCConfig, get_task, run_episodes, sample_targets
    from gnwarp.data.generation import initial_states
    from gnwarp.eval.records import ResultRecord
    from gnwarp.sim import make_env, systems
    from gnwarp.train import load_model
    from gnwarp.train.checkpoint import training_env_steps
    task = get_task(TASKS[system_name])
    system = systems.make(system_name)
    path = train(args, system_name, out)
    model = load_model(path, device="cpu").bind(system)
    n = args.episodes
    qpos, qvel = initial_states(system, n, np.random.default_rng(args.seed))
    target = sample_targets(task, system, n, args.seed)
    config = {"horizon": args.horizon, "iterations": args.iterations, "warmup": args.warmup, "proposals": 0,
              "lr": args.lr, "dtype": "float32", "backend": "mujoco", "gn": list(args.gn),
              "train_steps": args.train_steps, "quick": args.quick}
    records = []
    for variant, fused in PATHS.items():
        cfg = GradientMPCConfig(horizon=args.horizon, iterations=args.iterations, warmup=args.warmup, proposals=0,
                                lr=args.lr, seed=args.seed, fused=fused)
        planner = GradientMPC(model, task, system, n, cfg, target)
        if planner.engine.fused != fused:
            raise RuntimeError(f"{system_name}: asked for fused={fused}, the rollout engine runs fused={planner.engine.fused}")
        env = make_env(system, n, backend="mujoco")
        t0 = time.perf_counter()
        res = run_episodes(planner, env, task, args.steps, qpos0=qpos, qvel0=qvel, target=target)
        wall = time.perf_counter() - t0
        env.close()
        r = [float(x) for x in torch.as_tensor(res["returns"]).double()]
        secs = np.asarray(res["plan_seconds"], dtype=np.float64)
        print(f"{system_name} {variant}: return {np.mean(r):.4g} +- {np.std(r):.3g} ({wall:.0f} s)", flush=True)
        records.append(ResultRecord(
            experiment="fused_returns", task=task.name, system=system.name, planner="gradient", dynamics="learned",
            variant=variant, seed=args.seed, episodes=n, episode_steps=args.steps, returns=r,
            control_dt=float(system.dt), action_repeat=int(system.substeps), env_steps=training_env_steps(path),
            metrics={"wall_s": wall, "engine_fused": bool(planner.engine.fused), "plan_ms": 1e3 * float(secs[1:].mean() if len(secs) > 1 else secs.mean())},
            config={**config, "fused": fused}, commit=commit, gpu=device_name(torch.device("cpu")),
            date=time.strftime("%Y-%m-%d")))
    return records


# -- summary ----------------------------------------------------------------------------------------

def interval(values) -> tuple[float, float]:
    """(mean, half width of its 95% Student-t interval) of per-episode values."""
    v = np.asarray(values, dtype=np.float64)
    if len(v) < 2:
        return float(v.mean()), math.nan
    from gnwarp.eval.summarize import t_quantile
    return float(v.mean()), float(t_quantile(len(v) - 1) * v.std(ddof=1) / math.sqrt(len(v)))


def table(records) -> str:
    """The markdown table of the newest fused and unfused record of each (task, system)."""
    newest = {}
    for r in records:
        newest[(r.task, r.system, r.variant)] = r
    lines = ["| system | task | episodes x steps | fused mean +- 95% | unfused mean +- 95% | fused mean within "
             "unfused 95% | max per-episode abs difference | max relative to unfused spread (std) |",
             "|---|---|---|---|---|---|---|---|"]
    for (task, system, variant), f in newest.items():
        u = newest.get((task, system, "unfused"))
        if variant != "fused" or u is None:
            continue
        (fm, fh), (um, uh) = interval(f.values), interval(u.values)
        fv, uv = np.asarray(f.values), np.asarray(u.values)
        same = f.seed == u.seed and f.episodes == u.episodes
        diff = float(np.abs(fv - uv).max()) if same else math.nan
        within = "yes" if abs(fm - um) <= uh else "no"
        spread = float(uv.std(ddof=1)) if len(uv) > 1 else math.nan
        lines.append(f"| {system} | {task} | {f.episodes} x {f.episode_steps} | {fm:.4g} +- {fh:.3g} | "
                     f"{um:.4g} +- {uh:.3g} | {within} | {diff:.3g} | {diff / spread:.3g} |")
    if records:
        c = records[-1].config
        lines.append("")
        lines.append(f"Gradient MPC through the learned model (horizon {c.get('horizon')}, {c.get('iterations')} Adam "
                     f"iterations per step, {c.get('warmup')} at the first state, lr {c.get('lr')}, {c.get('dtype')}), "
                     f"true simulator MuJoCo C; {records[-1].gpu}; commit {records[-1].commit}, {records[-1].date}"
                     + (" (QUICK smoke run)" if c.get("quick") else "") + ".")
    return "\n".join(lines)


def summarize(out: Path) -> Path:
    """Write the table generated from ``<out>/results.jsonl`` between the markers of
    ``<out>/README.md`` (the text around them is kept); returns the README's path."""
    from gnwarp.eval.records import read_records
    block = f"{BEGIN}\n{table(read_records(out / 'results.jsonl'))}\n{END}"
    readme = out / "README.md"
    text = readme.read_text() if readme.exists() else "# Fused model step: closed-loop returns\n\n"
    if BEGIN in text and END in text:
        head, rest = text.split(BEGIN, 1)
        text = head + block + rest.split(END, 1)[1]
    else:
        text = text.rstrip("\n") + "\n\n" + block + "\n"
    readme.write_text(text)
    print(block)
    return readme


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--systems", default=",".join(TASKS), help=f"comma-separated of {', '.join(TASKS)}")
    ap.add_argument("--episodes", type=int, default=20)
    ap.add_argument("--steps", type=int, default=50, help="control steps per episode")
    ap.add_argument("--horizon", type=int, default=20)
    ap.add_argument("--iterations", type=int, default=5, help="Adam iterations per control step")
    ap.add_argument("--warmup", type=int, default=20, help="Adam iterations at the first state")
    ap.add_argument("--lr", type=float, default=0.1)
    ap.add_argument("--seed", type=int, default=0, help="seed of the initial states, targets and first plans")
    ap.add_argument("--train-steps", type=int, default=2000, help="training steps of a model trained here")
    ap.add_argument("--train-seconds", type=float, default=120.0, help="training budget per system (s)")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    ap.add_argument("--out", default=None, help="default: bench/results/fused_returns (--quick: a temporary folder)")
    ap.add_argument("--summarize", action="store_true", help="only regenerate the README table from the records")
    ap.add_argument("--quick", action="store_true", help="tiny sizes: a smoke test of the script")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    args.gn = (32, 64, 64)
    args.sequences, args.seq_steps, args.batch, args.valid_every = (100, 10, 10), 50, 32, 200
    if args.quick:
        args.episodes, args.steps, args.horizon, args.iterations, args.warmup = 2, 4, 4, 1, 2
        args.sequences, args.seq_steps, args.batch, args.valid_every = (6, 2, 2), 10, 4, 20
        args.gn, args.train_steps, args.train_seconds = (8, 16, 8), 20, 20.0
    systems = args.systems.split(",")
    bad = [s for s in systems if s not in TASKS]
    if bad:
        ap.error(f"unknown systems {bad}; choose from {', '.join(TASKS)}")
    out = experiment_out("fused_returns", args.out, args.quick)
    out.mkdir(parents=True, exist_ok=True)
    if args.summarize:
        summarize(out)
        return
    from gnwarp.eval.records import git_commit, write_records
    print(f"writing to {out}", flush=True)
    commit, t0 = git_commit(), time.perf_counter()
    for s in systems:
        write_records(out / "results.jsonl", run_system(args, s, out, commit))
    print(f"all systems in {time.perf_counter() - t0:.0f} s", flush=True)
    summarize(out)


if __name__ == "__main__":
    main()
