"""Figure 10: planning on systems whose parameters the planner is not told.

For each system (default: pendulum and cartpole with their balance tasks), a parameterized dataset
(``gnwarp generate --parameterized``) and the three models of ``sysid_figures.py`` trained on it:
a fixed-system model that never sees the parameters ("no params"), the parameterized model given
the true ones ("true params"), and the system-identification model ("sysid"). N episodes, each on
its own random instance (the true env holds one model per world), from random initial states:

1. W steps of uniform random actions on the true env, the same for every planner. This is the
   identification window of the system-ID planner (``control.identify_on_env``).
2. ``--steps`` steps in closed loop from there, under GN-MPC through each model:
   - "no params": the fixed-system model;
   - "true params": each episode's true static graph (``GradientMPC`` given one System per episode);
   - "sysid": G_ID from the window, fixed (``SysIDModel.with_fixed_gid``).
   Random actions are the floor.

Reported: each planner's true return over the planned steps (mean, std over episodes). Written
as results records (``gnwarp.eval.records``) to ``<out>/results.jsonl``; ``summary.md`` and
``returns.png`` are generated from them (``gnwarp.eval.summarize``).

    python bench/experiments/control_sysid.py [--systems pendulum,cartpole] [--episodes 20]
    python bench/experiments/control_sysid.py --quick        # tiny CPU smoke run (temp folder)
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
import types
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from bench.harness import device_name, experiment_out, results_dir  # noqa: E402

TASKS = {"pendulum": "pendulum-balance", "cartpole": "cartpole-balance", "cheetah": "cheetah-forward",
         "jaco": "jaco-palm-pose"}
PLANNERS = ("no_params", "true_params", "sysid", "random")
# the summary's ratio: system ID's share of the true-parameter planner's performance
RATIO = ("gradient (learned, sysid)", "gradient (learned, true_params)")


def model_args(args) -> types.SimpleNamespace:
    """The training settings ``sysid_figures.train_all`` reads: ``sysid_figures``' defaults (its
    precision, noise, EMA, system-identification flags) with this script's sizes and budgets."""
    from bench.experiments import sysid_figures as sf
    base = vars(sf.build_parser().parse_args([]))
    return types.SimpleNamespace(**{
        **base, "steps": args.train_steps, "seconds": args.train_seconds, "batch": args.batch, "lr": 1e-3,
        "valid_every": args.valid_every, "valid": args.sequences[1], "latent": args.gn[0], "edge_width": args.gn[1],
        "node_width": args.gn[2], "impl": args.impl, "device": args.device, "seed": args.seed,
        "normalizer_warmup": args.normalizer_warmup, "no_capture": False, "gid": args.gid,
        "identifier_latent": args.gn[0], "identifier_mlp": (args.gn[2], args.gn[2]), "window": args.window})


def run_system(args, system: str, runs: Path, out: Path) -> list[dict]:
    from bench.experiments import sysid_figures as sf
    from gnwarp import data
    from gnwarp.control import GradientMPC, GradientMPCConfig, identify_on_env
    from gnwarp.sim import make_env
    from gnwarp.control.episodes import run_episodes
    from gnwarp.control.sampling import RandomPlanner
    from gnwarp.control.tasks import get_task, sample_targets
    from gnwarp.data.generation import initial_states
    from gnwarp.eval.records import git_commit, write_records
    from gnwarp.sim import systems

    task = TASKS[system]
    t0 = time.perf_counter()
    ds = data.generate(system, tuple(args.sequences), num_steps=args.num_steps, seed=args.seed,
                       backend=args.data_backend, parameterized=True, progress=False)
    t_data = time.perf_counter() - t0
    models, info = sf.train_all(model_args(args), ds, system, runs)
    print(f"{system}: data {t_data:.0f} s; trained " + ", ".join(
        f"{k} {v['steps']} steps in {v['seconds']:.0f} s" for k, v in info.items()), flush=True)
    n = args.episodes
    rng = np.random.default_rng(args.seed + 7)
    insts = [systems.make(system, systems.sample_params(system, rng)) for _ in range(n)]
    base = systems.make(system)
    qpos, qvel = initial_states(base, n, rng)
    env = make_env(insts, n, backend=args.backend)
    sysid = models["sysid"].bind(base)
    fixed, _, _ = identify_on_env(sysid, env, seed=args.seed, qpos0=qpos, qvel0=qvel)
    qpos_w, qvel_w = env.qpos.cpu().numpy(), env.qvel.cpu().numpy()          # where the window left each world
    target = sample_targets(get_task(task), base, n, seed=args.seed)        # None for tasks without targets
    # the paper's first state: iterations x horizon from a random sequence (unless --warmup)
    warm = args.iterations * get_task(task).horizon if args.warmup is None else args.warmup
    cfg = GradientMPCConfig(iterations=args.iterations, warmup=warm, proposals=0, lr=args.lr, seed=args.seed)
    rows, commit = [], git_commit()
    for kind in args.planners:
        print(f"{system}: {kind} ...", flush=True)
        if kind == "random":
            planner = RandomPlanner(env.ctrlrange, n, seed=args.seed, device=env.device)
        elif kind == "no_params":
            planner = GradientMPC(models["no params"], task, base, n, cfg, target)
        elif kind == "true_params":
            planner = GradientMPC(models["true params"], task, insts, n, cfg, target)
        else:
            planner = GradientMPC(fixed, task, base, n, cfg, target)
        t1 = time.perf_counter()
        res = run_episodes(planner, env, task, args.steps, qpos0=qpos_w, qvel0=qvel_w, target=target)
        r = torch.as_tensor(res["returns"]).double()
        row = {"system": system, "task": task, "planner": kind, "episodes": n, "steps": args.steps,
               "window": args.window, "return_mean": float(r.mean()), "return_std": float(r.std(unbiased=False)),
               "returns": r.tolist(), "wall_s": round(time.perf_counter() - t1, 1),
               "train_steps": {k: v["steps"] for k, v in info.items()}, "device": device_name(),
               "quick": args.quick, "date": time.strftime("%Y-%m-%d %H:%M")}
        print(f"  true return {row['return_mean']:.4g} +- {row['return_std']:.3g} ({row['wall_s']} s)", flush=True)
        write_records(out / "results.jsonl", [to_record(row, seed=args.seed, commit=commit)])
        rows.append(row)
    env.close()
    return rows


def to_record(row: dict, seed=None, commit: str = "unknown"):
    """A row of this script as a ``ResultRecord``: GN-MPC through each model is planner
    "gradient" on learned dynamics, the model named by the variant ("no_params", "true_params",
    "sysid"); random actions plan with no model. Numbers unchanged."""
    from gnwarp.eval.records import ResultRecord
    from gnwarp.sim import systems
    system = systems.make(row["system"])
    gradient = row["planner"] != "random"
    return ResultRecord(
        experiment="control/fig10", task=row["task"], system=row["system"],
        planner="gradient" if gradient else "random", dynamics="learned" if gradient else "none",
        variant=row["planner"] if gradient else "", seed=seed, episodes=int(row["episodes"]),
        episode_steps=int(row["steps"]), returns=[float(x) for x in row["returns"]], control_dt=float(system.dt),
        action_repeat=int(system.substeps), env_steps=None if gradient else 0,
        metrics={k: row[k] for k in ("wall_s",) if k in row},
        config={k: row[k] for k in ("window", "train_steps", "quick") if k in row},
        commit=commit, gpu=row.get("device", "unknown"), date=row.get("date", ""))


def report(out: Path, records, quick: bool = False) -> None:
    """``summary.md`` and ``returns.png`` from the records (``gnwarp.eval.summarize``)."""
    from gnwarp.eval.summarize import write_summary
    title = (f"Figure 10: planning without the parameters ({records[0].gpu if records else '?'}"
             f"{', QUICK smoke run' if quick else ''})")
    write_summary(records, out, title, ratio_of=RATIO)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--systems", default="pendulum,cartpole", help=f"comma-separated, of {', '.join(TASKS)}")
    ap.add_argument("--planners", default=",".join(PLANNERS))
    ap.add_argument("--episodes", type=int, default=20)
    ap.add_argument("--steps", type=int, default=100, help="planned control steps per episode (after the window)")
    ap.add_argument("--window", type=int, default=20)
    ap.add_argument("--iterations", type=int, default=5)
    ap.add_argument("--warmup", type=int, default=None,
                    help="iterations at the first state (default: iterations x horizon, as the paper)")
    ap.add_argument("--lr", type=float, default=0.1)
    ap.add_argument("--sequences", type=int, nargs=3, default=(5000, 100, 100))
    ap.add_argument("--num-steps", type=int, default=100)
    ap.add_argument("--train-steps", type=int, default=6000, help="steps of each model")
    ap.add_argument("--train-seconds", type=float, default=150.0, help="wall-clock cap of each model")
    ap.add_argument("--backend", default="auto", help="the true env's backend")
    ap.add_argument("--data-backend", default="mujoco")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", default=None, help="default: bench/results/control/fig10 (--quick: a temporary folder)")
    ap.add_argument("--rebuild", action="store_true", help="only rebuild summary.md and returns.png")
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    args.batch, args.valid_every, args.normalizer_warmup, args.gid, args.impl = 200, 1000, 20, 10, "warp"
    args.gn = (128, 256, 128)
    if args.quick:
        args.sequences, args.num_steps, args.window, args.train_seconds, args.train_steps = (32, 4, 4), 24, 6, 20.0, 30
        args.batch, args.normalizer_warmup, args.gn, args.gid, args.impl = 16, 2, (16, 32, 16), 4, "torch"
        args.episodes, args.steps, args.iterations, args.warmup = 2, 4, 2, 2
        args.device, args.backend = "cpu", "mujoco"
    if args.device == "auto":
        args.device = "cuda" if torch.cuda.is_available() else "cpu"
    args.planners = args.planners.split(",")
    bad = [p for p in args.planners if p not in PLANNERS]
    if bad:
        ap.error(f"unknown planners {bad}; choose from {PLANNERS}")
    out = Path(args.out) if args.out else (experiment_out("control_fig10", None, True) if args.quick
                                           else Path(results_dir("control")) / "fig10")
    out.mkdir(parents=True, exist_ok=True)
    if not args.rebuild:
        with tempfile.TemporaryDirectory() as tmp:
            for system in filter(None, args.systems.split(",")):
                if system not in TASKS:
                    ap.error(f"unknown system {system!r}; choose from {', '.join(TASKS)}")
                run_system(args, system, Path(tmp), out)
    from gnwarp.eval.records import read_records
    report(out, read_records(out / "results.jsonl"), args.quick)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
