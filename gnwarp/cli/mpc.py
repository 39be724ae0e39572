"""``gnwarp mpc``: plan through a learned model, in closed loop on the true simulator; the
results record, timings and video."""
from __future__ import annotations

import time

from gnwarp.cli.common import IMPLS, paragraphs

__all__ = ["add_mpc", "mpc_command", "episode_bytes", "timing_line", "check_outputs"]


def episode_bytes(n: int, steps: int, bodies: int, nu: int) -> int:
    """Host memory ``run_episodes`` holds for ``n`` episodes of ``steps`` steps: float32 states
    [n, steps+1, bodies, 13] and actions [n, steps, nu], each per step and stacked, and about
    500 bytes of Python objects a step."""
    return 2 * 4 * (n * (steps + 1) * bodies * 13 + n * steps * nu) + 500 * steps


def mpc_command(args) -> int:
    """``gnwarp mpc``: gradient MPC through a learned model, in closed loop on the true simulator."""
    import types
    from pathlib import Path

    import numpy as np

    from gnwarp.control import (GradientMPC, GradientMPCConfig, control_timestep, get_task, plan_timing, run_episodes,
                                sample_targets)
    from gnwarp.sim import make_env
    from gnwarp.control.gradient import model_systems
    from gnwarp.sim.families import family_name
    from gnwarp.data.generation import initial_states
    from gnwarp.eval.records import ResultRecord, git_commit, gpu_name, write_records
    from gnwarp.sim import systems
    from gnwarp.train import load_model
    from gnwarp.train.checkpoint import training_env_steps
    from gnwarp.validation import check_memory

    task = get_task(args.task)
    # refused before anything is loaded
    config = GradientMPCConfig(horizon=args.horizon, iterations=args.iterations, warmup=args.warmup,
                               proposals=args.proposals, lr=args.lr, seed=args.seed)
    args.steps = args.steps if args.steps is not None else (getattr(task, "episode_steps", None) or 100)
    if args.episodes < 1 or args.steps < 1:
        raise ValueError(f"--episodes and --steps must be >= 1, got {args.episodes} and {args.steps}")
    records = Path(args.records or f"mpc-{task.name}.jsonl")
    video = None if args.video == "none" else Path(args.video or f"mpc-{task.name}.gif")
    check_outputs(records, video)   # before planning, not after
    model = load_model(args.model, device=args.device, **({"impl": args.impl} if args.impl else {}))
    # the system: --system, else the one the model was trained on that fits the task
    name = args.system or next((s for s in model_systems(model) if family_name(s) == task.system),
                               "swimmer6" if task.system == "swimmer" else task.system)
    system = systems.make(name)
    n = args.episodes
    check_memory(episode_bytes(n, args.steps, system.nbody, system.nu),
                 f"{n} episodes x {args.steps} steps x {system.nbody} bodies (every state kept)",
                 "Use fewer --steps or --episodes")
    target = sample_targets(task, system, n, args.seed)
    planner = GradientMPC(model, task, system, n, config, target)
    from tqdm.auto import tqdm  # one bar over every planning iteration, the first state's warm-up included
    bar = tqdm(total=planner.warmup + config.iterations * args.steps, desc=f"mpc {task.name}", unit="it",
               disable=args.quiet, dynamic_ncols=True)
    planner.progress = bar.update
    env = make_env(system, n, backend=args.backend)
    qpos, qvel = (getattr(task, "initial", None) or initial_states)(system, n, np.random.default_rng(args.seed))
    t0 = time.perf_counter()
    out = run_episodes(planner, env, task, args.steps, env.reset(qpos, qvel), target=target)
    secs = time.perf_counter() - t0
    bar.close()
    r = out["returns"]
    timing = plan_timing(out["plan_seconds"], control_timestep(system))
    print(f"{task.name} on {system.name}: true return {float(r.mean()):.4g} +- {float(r.std(unbiased=False)):.3g} "
          f"over {n} episodes of {args.steps} steps (horizon {planner.horizon}, {config.iterations} iterations "
          f"a step: {planner.model_evals_per_step} model steps an episode)")
    print(timing_line(timing, planner, n))
    metrics = {k: timing[k] for k in ("first_step_ms", "steady_ms", "real_time_factor", "steady_after", "mean_ms")}
    metrics.update(model_evals_per_step=planner.model_evals_per_step, warmup_iterations=planner.warmup,
                   proposal_evals=planner.proposal_evals, episode_steps_per_s=n * args.steps / secs,
                   plan_ms=[1e3 * float(t) for t in out["plan_seconds"]])
    if timing["steady_ms"]:
        metrics["steady_episode_steps_per_s"] = 1e3 * n / timing["steady_ms"]
    record = ResultRecord(
        experiment="mpc", task=task.name, system=system.name, planner="gradient", dynamics="learned", seed=args.seed,
        episodes=n, episode_steps=args.steps, returns=[float(x) for x in r.double().cpu()], control_dt=float(system.dt),
        action_repeat=int(system.substeps), env_steps=training_env_steps(args.model),
        metrics=metrics,
        config={"model": str(args.model), "horizon": planner.horizon, "iterations": config.iterations,
                "warmup": planner.warmup, "proposals": config.proposals, "lr": args.lr, "backend": args.backend,
                "initial_qpos": np.asarray(qpos).tolist(), "initial_qvel": np.asarray(qvel).tolist(),
                "targets": None if target is None else target.cpu().double().numpy().tolist()},
        commit=git_commit(), gpu=gpu_name(model.device), date=time.strftime("%Y-%m-%d %H:%M:%S"))
    write_records(records, [record])
    print(f"wrote {records}")
    if video is not None:
        from gnwarp.eval.animation import animate
        k = min(3, n)
        shim = types.SimpleNamespace(meta={"system": system.name, "parameterized": False, "dt": system.dt},
                                     static={"n_node": np.full(k, system.nbody)})
        animate(out["states"][:k].numpy(), {}, shim, np.zeros(k, dtype=np.int64), video, dt=system.dt,
                title=f"{task.name}: gradient MPC, true simulator", renderer=args.renderer)
        print(f"wrote {video}")
    return 0


def timing_line(timing: dict, planner, n: int) -> str:
    """The first control step and the steady state apart, and the real-time factor, in words."""
    proposed = planner.proposal_evals // planner.horizon
    start = f"the best of {proposed} proposed sequences" if proposed else "a random sequence"
    first = f"first control step {timing['first_step_ms']:.1f} ms ({planner.warmup} warm-up iterations from {start})"
    if timing["steady_ms"] is None:
        return f"{first}; no steady state (one step)"
    after = timing["steady_after"]
    return (f"{first}; steady {timing['steady_ms']:.2f} ms a control step (median of steps {after + 1}-"
            f"{timing['steps']}), real-time factor {timing['real_time_factor']:.3g} (control step "
            f"{timing['control_dt_ms']:.3g} ms), {1e3 * n / timing['steady_ms']:.0f} episode-steps/s")


def check_outputs(records, video) -> None:
    """Refuse output paths that cannot be written (``files.check_output_path``) and a records file
    that is not one, before any work, with ``OSError`` / ``RecordError`` naming them."""
    from gnwarp.eval.records import read_records
    from gnwarp.files import check_output_path
    for what, path in (("--records", records), ("--video", video)):
        if path is not None:
            try:
                check_output_path(path)
            except OSError as e:
                raise type(e)(f"{what} {path}: {e}") from None
    if records.exists():
        read_records(records)   # appended to: it must hold valid records



def add_mpc(sub) -> None:
    m = sub.add_parser("mpc", help="gradient MPC through a learned model, run in closed loop on the true simulator",
                       description=paragraphs(
                           "Plan actions by gradient steps on the task reward of rollouts of a learned model "
                           "(paper F.1.1), apply them on the true simulator, print the true returns, append them "
                           "as a results record to --records and write a video of the first episodes. Output "
                           "paths are checked before planning. A progress bar counts the planning iterations: "
                           "the first state's warm-up (4 x iterations by default, after a proposal of sampled "
                           "sequences), then --iterations a step. Prints the first control step and the steady "
                           "state apart, with the real-time factor (control timestep / steady time).",
                           "On a CPU, start small: --episodes 2 --steps 20 --warmup 20."))
    m.add_argument("--model", required=True, help="checkpoint folder (e.g. runs/pendulum/best)")
    m.add_argument("--task", required=True, help="task name (gnwarp.control.TASKS, e.g. pendulum-balance, cheetah-run)")
    m.add_argument("--system", help="system to control (default: the model's system that fits the task)")
    m.add_argument("--episodes", type=int, default=8, help="episodes planned together")
    m.add_argument("--steps", type=int, default=None,
                   help="control steps per episode (default: the task's episode length, DMC's 1000, else 100; every "
                        "state is kept in memory: a run that cannot fit in the available memory is refused first)")
    m.add_argument("--horizon", type=int, help="planning horizon (default: the task's)")
    m.add_argument("--iterations", type=int, default=5, help="gradient iterations per control step")
    m.add_argument("--warmup", type=int, help="extra iterations at the first state (default: 4 x iterations; the "
                                              "paper: iterations x horizon, with --proposals 0)")
    m.add_argument("--proposals", type=int, default=30,
                   help="random action sequences rolled out at the first state (beside the mid one); Adam starts "
                        "from the best (0: from a random sequence)")
    m.add_argument("--lr", type=float, default=0.1, help="Adam's step size")
    m.add_argument("--seed", type=int, default=0, help="initial states, targets and initial plans")
    m.add_argument("--backend", default="auto", choices=["auto", "mujoco", "mujoco_warp", "mujoco_warp_cpu"],
                   help="true simulator (default: MuJoCo-Warp on a GPU, else MuJoCo C)")
    m.add_argument("--device", default=None, help="the model's device: cpu, cuda, ... (default: CUDA when present)")
    m.add_argument("--impl", choices=IMPLS, default=None, help="GN implementation (default: the checkpoint's)")
    m.add_argument("-o", "--out", "--records", dest="records", metavar="PATH",
                   help="results records file (JSON lines, appended; default: mpc-<task>.jsonl): per-episode "
                        "returns, initial states, targets and settings (gnwarp.eval.records)")
    m.add_argument("--video", help="video path (default: mpc-<task>.gif; 'none': no video)")
    m.add_argument("--renderer", default="auto", choices=["auto", "mujoco", "matplotlib"],
                   help="how the video is drawn: MuJoCo's renderer (EGL/OSMesa), matplotlib, or auto "
                        "(MuJoCo where it renders, else matplotlib)")
    m.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    m.set_defaults(func=mpc_command)
