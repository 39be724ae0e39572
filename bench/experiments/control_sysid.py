"""Figure 10 (issue 17): planning on systems whose parameters the planner is not told.

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
to ``<out>/results.jsonl``, ``summary.md`` and ``fig10.png``.

    python bench/experiments/control_sysid.py [--systems pendulum,cartpole] [--episodes 20]
    python bench/experiments/control_sysid.py --quick        # tiny CPU smoke run (temp folder)
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import types
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from bench.harness import device_name, experiment_out, results_dir, write_summary  # noqa: E402

TASKS = {"pendulum": "pendulum-balance", "cartpole": "cartpole-balance", "cheetah": "cheetah-forward",
         "jaco": "jaco-palm-pose"}
PLANNERS = ("no_params", "true_params", "sysid", "random")
LABELS = {"no_params": "GN-MPC, no params", "true_params": "GN-MPC, true params", "sysid": "GN-MPC, system ID",
          "random": "random"}


def model_args(args) -> types.SimpleNamespace:
    """The training settings ``sysid_figures.train_all`` reads."""
    return types.SimpleNamespace(
        steps=args.train_steps, seconds=args.train_seconds, batch=args.batch, lr=1e-3, valid_every=args.valid_every,
        valid=args.sequences[1], latent=args.gn[0], edge_width=args.gn[1], node_width=args.gn[2], impl=args.impl,
        device=args.device, seed=args.seed, normalizer_warmup=args.normalizer_warmup, no_capture=False,
        gid=args.gid, identifier_latent=args.gn[0], identifier_mlp=(args.gn[2], args.gn[2]), window=args.window)


def run_system(args, system: str, runs: Path, out: Path) -> list[dict]:
    from bench.experiments import sysid_figures as sf
    from gnwarp import data
    from gnwarp.control import GradientMPC, GradientMPCConfig, identify_on_env
    from gnwarp.sim import make_env
    from gnwarp.control.episodes import run_episodes
    from gnwarp.control.sampling import RandomPlanner
    from gnwarp.control.tasks import get_task, sample_targets
    from gnwarp.data.generation import initial_states
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
    cfg = GradientMPCConfig(iterations=args.iterations, warmup=args.warmup, lr=args.lr, seed=args.seed)
    rows = []
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
        with open(out / "results.jsonl", "a") as f:
            f.write(json.dumps(row) + "\n")
        rows.append(row)
    env.close()
    return rows


def report(out: Path, rows: list[dict], args) -> None:
    by = {(r["system"], r["planner"]): r for r in rows}
    systems_ = list(dict.fromkeys(r["system"] for r in rows))
    cell = lambda r: "-" if r is None else f"{r['return_mean']:.4g} +- {r['return_std']:.2g}"  # noqa: E731
    lines = [f"# Figure 10: planning without the parameters ({rows[0]['device'] if rows else '?'}"
             f"{', QUICK smoke run' if args.quick else ''})", "",
             f"`python bench/experiments/control_sysid.py` ({time.strftime('%Y-%m-%d')}): each episode on its own "
             f"random instance of the system; {args.window} steps of random actions first (the identification "
             f"window, the same for every planner), then {args.steps} steps of GN-MPC ({args.iterations} Adam "
             "iterations per step) through each model, in closed loop on the true simulator. True returns over the "
             "planned steps, mean +- std over episodes.", "",
             "| system (task) | episodes | " + " | ".join(LABELS[p] for p in PLANNERS) + " | sysid / true params |",
             "|---" * (len(PLANNERS) + 3) + "|"]
    for s in systems_:
        sy, tp = by.get((s, "sysid")), by.get((s, "true_params"))
        ratio = "-" if not (sy and tp) else (f"{100 * tp['return_mean'] / sy['return_mean']:.0f}%"
                                             if tp["return_mean"] < 0 else
                                             f"{100 * sy['return_mean'] / tp['return_mean']:.0f}%")
        eps = next(r["episodes"] for r in rows if r["system"] == s)
        lines.append(f"| {s} ({TASKS[s]}) | {eps} | " + " | ".join(cell(by.get((s, p))) for p in PLANNERS)
                     + f" | {ratio} |")
    steps = {s: next(r["train_steps"] for r in rows if r["system"] == s) for s in systems_}
    lines += ["", "Training steps per model: " + "; ".join(f"{s}: {v}" for s, v in steps.items()),
              "", "Ratio: system ID's share of the true-parameter planner's performance (returns are negative on "
              "the balance tasks, so it is true / sysid there)."]
    write_summary(out, lines)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, len(systems_), figsize=(4.2 * len(systems_), 3.6), squeeze=False)
    for ax, s in zip(axes[0], systems_):
        names = [p for p in PLANNERS if (s, p) in by]
        ax.bar(range(len(names)), [by[(s, p)]["return_mean"] for p in names],
               yerr=[by[(s, p)]["return_std"] for p in names], capsize=3, color=[f"C{PLANNERS.index(p)}" for p in names])
        ax.set_xticks(range(len(names)), [LABELS[p] for p in names], rotation=35, ha="right", fontsize=8)
        ax.set_title(TASKS[s])
        ax.set_ylabel("true return")
    fig.tight_layout()
    fig.savefig(out / "fig10.png", dpi=110)
    plt.close(fig)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--systems", default="pendulum,cartpole", help=f"comma-separated, of {', '.join(TASKS)}")
    ap.add_argument("--planners", default=",".join(PLANNERS))
    ap.add_argument("--episodes", type=int, default=20)
    ap.add_argument("--steps", type=int, default=100, help="planned control steps per episode (after the window)")
    ap.add_argument("--window", type=int, default=20)
    ap.add_argument("--iterations", type=int, default=5)
    ap.add_argument("--warmup", type=int, default=None)
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
    ap.add_argument("--rebuild", action="store_true", help="only rebuild summary.md and fig10.png")
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
    every = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines() if line.strip()]
    report(out, list({(r["system"], r["planner"]): r for r in every}.values()), args)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
