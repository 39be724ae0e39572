"""Planners that reach far, compared in closed loop: gradient MPC, predictive sampling and the
hybrid planner (sampled proposals refined by gradient steps; CEM on the true dynamics), each
without and with a learned terminal value, on one task.

For each seed, N episodes from the task's random initial states (``Task.initial`` where the task
has one, e.g. the DMC tasks; else ``gnwarp.data.generation.initial_states``) and targets run on
the true environment (``make_env``: MuJoCo-Warp on a GPU, ``--backend``) for the task's episode
length (``Task.episode_steps``; ``--steps``) under each planner of ``--planners``, planning
through ``--dynamics``:

- ``learned``: the model of ``--model`` (a checkpoint; ``--quick`` without one: an untrained
  tiny model, for a smoke run only);
- ``true``: the true simulator itself (sampling and hybrid on an env of N x K worlds read from
  the closed-loop env: the oracle); gradient MPC needs gradients and is skipped there.

``--terminal none,value``: "value" fits a ``TerminalValue`` (TD(lambda)) on the closed-loop
episodes of the same planner without one (same seed), then runs the planner again with it
(variant "terminal"); "none" is the ablation (variant ""). Each (planner, variant, seed) is one
``gnwarp.eval.records.ResultRecord`` (per-episode true returns, scored with the task's exact
reward by ``run_episodes``) appended to ``--out`` (JSON lines), with the settings and the
planning time per control step.

    python bench/experiments/planners.py --task dmc-cheetah-run --dynamics learned --model ckpt/best \\
        --episodes 10 --seeds 0,1,2,3,4 --out bench/results/control/planners.jsonl
    python bench/experiments/planners.py --task dmc-cheetah-run --dynamics true --episodes 10 --seeds 0
    python bench/experiments/planners.py --quick        # tiny CPU smoke run (temp folder)
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from bench.harness import experiment_out  # noqa: E402

PLANNER_NAMES = ("gradient", "sampling", "hybrid")
TERMINALS = ("none", "value")


def task_and_system(name: str):
    """The task (``get_task``) and the system it runs on here (SwimmerN tasks: swimmer6)."""
    from gnwarp.control import get_task
    from gnwarp.sim import systems
    task = get_task(name)
    system = "swimmer6" if task.system == "swimmer" else task.system
    return task, systems.make(system)


def initial(task, system, n: int, seed: int):
    """(qpos [n, nq], qvel [n, nv]) of the task's random initial states, and its targets
    (``gnwarp.control.episode_starts``: targets independent of the initial states)."""
    from gnwarp.control import episode_starts
    return episode_starts(task, system, n, seed)


def quick_model(system):
    """An untrained tiny GN model bound to ``system`` (a smoke run's stand-in for a checkpoint)."""
    from gnwarp import data
    from gnwarp.gn import RunOptions
    from gnwarp.models import ForwardModel, GNCoreConfig, ModelConfig
    ds = data.generate(system.name, (2, 1, 1), num_steps=4, seed=0, backend="mujoco", progress=False)
    torch.manual_seed(0)
    tiny = GNCoreConfig(latent=8, edge_hidden=(16,), node_hidden=(16,), global_hidden=(16,))
    return ForwardModel(ModelConfig(gn=tiny, run=RunOptions(impl="torch")), ds.layout).bind(system)


def make_planner(name: str, args, model, task, system, env, n: int, targets, terminal):
    """The planner ``name`` through the learned ``model`` (None: the true simulator), or None
    where it cannot run (gradient MPC on the true simulator): ``gnwarp.control.planner.make_planner``
    with this script's settings."""
    from gnwarp.control.planner import make_planner as build
    from gnwarp.control.sampling import true_dynamics
    if name == "gradient" and model is None:
        return None
    H = args.horizon or task.horizon
    settings = {"horizon": H, "discount": args.discount}
    if name == "gradient":
        settings.update(iterations=args.iterations, grad_norm=args.grad_norm, grad_decay=args.grad_decay)
    elif name == "sampling":
        settings.update(samples=args.samples, knots=min(args.knots, H))
    else:
        settings.update(samples=args.samples, elites=min(args.elites, args.samples), iterations=args.iterations,
                        knots=min(args.knots, H), grad_norm=args.grad_norm, grad_decay=args.grad_decay)
    dyn = model if model is not None else true_dynamics(system, n, args.samples, backend=args.backend, source=env)
    return build(name, dyn, task, system, n, settings, targets, terminal, ctrlrange=env.ctrlrange)


def dynamics_name(args, env) -> str:
    if args.dynamics == "learned":
        return "learned"
    return "true_mujoco_c" if type(env).__name__ == "MujocoEnv" else "true_mjwarp"


def run(args, out_path: Path) -> list:
    from gnwarp.control import run_episodes
    from gnwarp.control.value import TerminalValue, fit_terminal_value
    from gnwarp.eval.records import ResultRecord, git_commit, gpu_name, write_records
    from gnwarp.sim.env import make_env
    task, system = task_and_system(args.task)
    steps = args.steps or getattr(task, "episode_steps", None) or 100
    model = None
    if args.dynamics == "learned":
        if args.model:
            from gnwarp.train import load_model
            model = load_model(args.model, device=args.device)
        elif args.quick:
            model = quick_model(system)
        else:
            raise SystemExit("--dynamics learned needs --model CHECKPOINT (or --quick for a smoke run)")
    n = args.episodes
    env = make_env(system, n, backend=args.backend)
    commit, gpu = git_commit(), gpu_name()
    records = []
    for seed in args.seeds:
        qpos, qvel, targets = initial(task, system, n, seed)
        for name in args.planners:
            value, base = None, None
            for variant in args.terminal:
                if variant == "value":
                    if base is None:   # the value is fitted on this planner's own episodes without one
                        continue
                    value = TerminalValue.for_system(system, gamma=args.value_gamma)
                    hist = fit_terminal_value(base, task, value, targets=targets, rounds=args.value_rounds,
                                              steps=args.value_steps)
                planner = make_planner(name, args, model, task, system, env, n, targets,
                                       value if variant == "value" else None)
                if planner is None:
                    print(f"{name}: skipped on the true dynamics (it plans by gradients through a learned model)")
                    break
                t0 = time.perf_counter()
                out = run_episodes(planner, env, task, steps, qpos0=qpos, qvel0=qvel, target=targets)
                wall = time.perf_counter() - t0
                if variant == "none":
                    base = out
                rets = [float(x) for x in out["returns"]]
                settings = {k: (list(v) if isinstance(v, tuple) else v)
                            for k, v in dataclasses.asdict(planner.settings).items()}
                metrics = {"plan_ms_mean": 1e3 * float(np.mean(out["plan_seconds"])),
                           "plan_ms_steady": 1e3 * float(np.median(out["plan_seconds"][1:] if steps > 1
                                                                   else out["plan_seconds"])),
                           "wall_seconds": wall}
                if variant == "value":
                    metrics["value_td_error"] = [hist["td_error"][0], hist["td_error"][-1]]
                rec = ResultRecord(
                    experiment="control/planners", task=task.name, system=system.name, planner=name,
                    dynamics=dynamics_name(args, env), variant="terminal" if variant == "value" else "",
                    seed=int(seed), episodes=n, episode_steps=int(steps), returns=rets,
                    control_dt=float(system.dt), action_repeat=int(system.substeps),
                    env_steps=None if model is None or args.quick else args.env_steps, metrics=metrics,
                    config={"settings": settings, "model": args.model or ("quick" if model is not None else None),
                            "quick": bool(args.quick)},
                    commit=commit, gpu=gpu, date=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()))
                write_records(out_path, [rec])
                records.append(rec)
                print(f"seed {seed} {name:8s} {rec.variant or 'no value':9s} return {np.mean(rets):10.3f} "
                      f"+- {np.std(rets):8.3f}  plan {metrics['plan_ms_steady']:.1f} ms/step", flush=True)
    return records


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--task", default="pendulum-balance", help="a task name (e.g. dmc-cheetah-run)")
    ap.add_argument("--dynamics", choices=("learned", "true"), default="learned")
    ap.add_argument("--model", help="checkpoint of the learned model (--dynamics learned)")
    ap.add_argument("--env-steps", type=int, default=None, help="env steps whose data trained the model (records)")
    ap.add_argument("--planners", default=",".join(PLANNER_NAMES))
    ap.add_argument("--terminal", default="none,value", help="none (ablation), value (fitted terminal value)")
    ap.add_argument("--episodes", type=int, default=10)
    ap.add_argument("--steps", type=int, default=None, help="control steps per episode (default: the task's)")
    ap.add_argument("--seeds", default="0")
    ap.add_argument("--horizon", type=int, default=None, help="planning horizon (default: the task's)")
    ap.add_argument("--samples", type=int, default=64)
    ap.add_argument("--elites", type=int, default=4)
    ap.add_argument("--iterations", type=int, default=5, help="Adam steps (gradient) / refinements (hybrid)")
    ap.add_argument("--knots", type=int, default=4)
    ap.add_argument("--discount", type=float, default=1.0)
    ap.add_argument("--grad-norm", choices=("none", "step"), default="step")
    ap.add_argument("--grad-decay", type=float, default=1.0, help="soft truncated backprop window (1: full)")
    ap.add_argument("--value-gamma", type=float, default=0.99)
    ap.add_argument("--value-rounds", type=int, default=20)
    ap.add_argument("--value-steps", type=int, default=100)
    ap.add_argument("--backend", default="auto", help="the true env's backend (auto, mujoco, mujoco_warp)")
    ap.add_argument("--device", default=None, help="the learned model's device (default: its checkpoint's)")
    ap.add_argument("--out", default=None,
                    help="records file (JSON lines; default bench/results/control/planners.jsonl)")
    ap.add_argument("--quick", action="store_true", help="tiny CPU smoke run")
    args = ap.parse_args(argv)
    args.planners = [p for p in args.planners.split(",") if p]
    args.terminal = [t for t in args.terminal.split(",") if t]
    args.seeds = [int(s) for s in str(args.seeds).split(",") if s != ""]
    bad = [p for p in args.planners if p not in PLANNER_NAMES] + [t for t in args.terminal if t not in TERMINALS]
    if bad:
        ap.error(f"unknown planners or terminals {bad}; planners: {PLANNER_NAMES}, terminals: {TERMINALS}")
    if "value" in args.terminal and "none" not in args.terminal:
        ap.error("--terminal value fits on the planner's episodes without one: give none,value")
    if args.quick:
        args.episodes, args.steps = min(args.episodes, 2), min(args.steps or 4, 4)
        args.horizon, args.samples, args.elites = min(args.horizon or 5, 5), min(args.samples, 6), min(args.elites, 2)
        args.iterations, args.knots = min(args.iterations, 2), min(args.knots, 2)
        args.value_rounds, args.value_steps = 2, 5
        if args.backend == "auto":
            args.backend = "mujoco"
    out = Path(args.out) if args.out else experiment_out("control", None, args.quick) / "planners.jsonl"
    out.parent.mkdir(parents=True, exist_ok=True)
    records = run(args, out)
    print(f"wrote {len(records)} records to {out}")
    return records


if __name__ == "__main__":
    main()
