"""``gnwarp mpc``: plan through a learned model, in closed loop on the true simulator; the
results record, timings and video."""
from __future__ import annotations

import dataclasses
import time

from gnwarp.cli.common import IMPLS, paragraphs, parse_value

__all__ = ["add_mpc", "mpc_command", "mpc_settings", "episode_bytes", "timing_line",
           "check_outputs", "PLANNERS",
           "SETTING_FLAGS"]

# the registered planners that plan through a learned model (``gnwarp.control.planner.MODEL_PLANNERS``,
# whose module imports torch; a test keeps the two equal)
PLANNERS = ("gradient", "hybrid", "sampling", "mppi")
# the flags that set a planner's settings field of the same name, where its settings have one
SETTING_FLAGS = ("horizon", "iterations", "warmup", "proposals", "lr")
# planners over a trained gnwarp rl agent (--policy RUN): its policy alone, or planning with its model
AGENT_PLANNERS = ("policy", "policy-mpc")


def episode_bytes(n: int, steps: int, bodies: int, nu: int) -> int:
    """Host memory ``run_episodes`` holds for ``n`` episodes of ``steps`` steps: float32 states
    [n, steps+1, bodies, 13] and actions [n, steps, nu], each per step and stacked, and about
    500 bytes of Python objects a step."""
    return 2 * 4 * (n * (steps + 1) * bodies * 13 + n * steps * nu) + 500 * steps


def mpc_settings(args, task):
    """The settings dataclass of planner ``args.planner``: the flags of ``SETTING_FLAGS`` given
    (each where the settings have that field; elsewhere ValueError), ``--seed``, then ``--set
    KEY=VALUE``; the horizon defaults to the task's, and ``knots`` to at most the horizon. An
    unknown key raises ``ConfigError`` naming the planner's fields, a bad value where it came from."""
    from gnwarp.control.planner import MODEL_PLANNERS, planner_settings
    from gnwarp.validation import ConfigError
    name = args.planner
    if name == "policy":   # a trained agent acts: no planner settings, no model
        given = [f"--{f}" for f in SETTING_FLAGS if getattr(args, f) is not None] + (["--set"] if args.set else [])
        if args.terminal is not None:
            given.append("--terminal")
        if given:
            raise ValueError(f"{', '.join(given)} set a planner's settings; --policy acts with a trained policy "
                             "without planning")
        from gnwarp.rl.planner import PolicySettings   # registers planner "policy"
        try:
            return PolicySettings(run=args.policy or "", device=args.device or "auto")
        except ConfigError as e:
            raise ConfigError("--policy", e.reason) from None
    if name == "policy-mpc":   # a trained SVG(N >= 1) agent, planned over with its model and Q-function
        import gnwarp.rl.planner  # noqa: F401 - registers planner "policy-mpc"
        if args.terminal is not None:
            raise ValueError("--terminal: planner 'policy-mpc' ends its returns with the agent's own Q-function")
        given = {"run": args.policy or "", "device": args.device or "auto", "seed": args.seed}
        source = {"run": "--policy", "device": "--device", "seed": "--seed"}
        # the record names --policy, --device and --seed: --set may not change them
        _flags_and_sets(args, name, given, source, pinned=("run", "device", "seed"))
        try:
            return planner_settings(name, given)
        except ConfigError as e:
            raise ConfigError("--policy" if e.path == "run" else e.path, f"{e.reason} (planner 'policy-mpc')") from None
    if name not in MODEL_PLANNERS:
        why = " (it does not plan through a learned model)" if name in ("ilqg", "random") else ""
        raise ValueError(f"--planner {name!r}{why}: gnwarp mpc plans through a learned model with one of "
                         f"{', '.join(MODEL_PLANNERS)}")
    given, source = {"seed": args.seed}, {"seed": "--seed"}
    fields = _flags_and_sets(args, name, given, source)
    if "horizon" not in given:   # the task's (every planner's default), here also to bound the knots
        given["horizon"] = task.horizon
    if "knots" in fields and "knots" not in given:
        given["knots"] = min(fields["knots"].default, given["horizon"])
    try:
        return planner_settings(name, given)
    except ConfigError as e:   # the key, the value's source and the planner's fields
        raise ConfigError(e.path, f"{e.reason} (planner {name!r}, from {source.get(e.path, 'the defaults')})") from None


def _flags_and_sets(args, name: str, given: dict, source: dict, pinned: tuple = ()) -> dict:
    """Into ``given`` (``source``: where each came from): the flags of ``SETTING_FLAGS`` given (each
    where planner ``name``'s settings have that field; elsewhere ValueError), then ``--set
    KEY=VALUE``; a key set twice is refused, but ``--set seed`` may replace ``--seed`` unless
    ``pinned`` holds it (nor may --set change any other pinned key). Returns the settings' fields."""
    from gnwarp.control.planner import get_planner
    from gnwarp.validation import ConfigError
    entry = get_planner(name)
    fields = {f.name: f for f in dataclasses.fields(entry.settings)}
    for flag in SETTING_FLAGS:
        value = getattr(args, flag)
        if value is None:
            continue
        if flag not in fields:
            raise ValueError(f"--{flag} does not apply to planner {name!r} ({entry.settings.__name__} has no "
                             f"{flag}; its settings: {', '.join(fields)})")
        given[flag], source[flag] = value, f"--{flag}"
    for item in args.set or []:
        key, eq, text = item.partition("=")
        key = key.strip()
        if not eq or not key:
            raise ConfigError("--set", f"expects KEY=VALUE (a field of {entry.settings.__name__}), got {item!r}")
        if key in source and (key in pinned or source[key] != "--seed"):
            raise ValueError(f"--set {item} and {source[key]} both set {key}: "
                             f"give {source[key] if key in pinned else 'one'}")
        given[key], source[key] = parse_value(text), f"--set {item}"
    return fields


def planner_summary(planner, name: str) -> str:
    """What the planner spends a control step on, in words."""
    s = planner.settings
    if name == "policy":
        return f"the trained policy of {s.run}, no planning"
    if name == "policy-mpc":
        return (f"planning over the agent of {s.run}: horizon {s.horizon}, {s.samples} sampled and "
                f"{s.policy_samples} policy sequences, {s.iterations} iterations a step, its Q at the horizon")
    if name == "gradient":
        return (f"horizon {planner.horizon}, {s.iterations} iterations a step: {planner.model_evals_per_step} model "
                "steps an episode")
    if name == "hybrid":
        return (f"hybrid: horizon {planner.horizon}, {s.samples} sampled sequences, the best {s.elites} refined by "
                f"{s.iterations} {planner.refinement} iterations a step")
    return f"{name}: horizon {s.horizon}, {s.samples} sampled sequences a step"


def mpc_command(args) -> int:
    """``gnwarp mpc``: a registered planner (``--planner``) through a learned model, in closed
    loop on the true simulator."""
    from pathlib import Path

    import numpy as np
    import torch

    from gnwarp.control import control_timestep, episode_starts, get_task, plan_timing, run_episodes
    from gnwarp.control.gradient import model_systems
    from gnwarp.control.planner import check_plan_memory, make_planner, planner_name
    from gnwarp.distributed import ranks
    from gnwarp.eval.records import ResultRecord, git_commit, gpu_name, write_records
    from gnwarp.sim import make_env, systems
    from gnwarp.sim.families import family_name
    from gnwarp.train import load_model
    from gnwarp.train.checkpoint import training_env_steps
    from gnwarp.validation import check_memory

    task = get_task(args.task)
    # refused before anything is loaded
    if args.policy is not None:
        given = [f for f, v in (("--planner", args.planner not in (None, *AGENT_PLANNERS)), ("--model", args.model),
                                ("--impl", args.impl)) if v]
        if given:
            raise ValueError(f"--policy acts with a trained gnwarp rl policy: it takes no {' or '.join(given)}")
    if args.planner == "policy-mpc" and args.policy is None:
        raise ValueError("planner 'policy-mpc' plans over a trained gnwarp rl agent: give --policy RUN")
    args.planner = ((args.planner if args.planner in AGENT_PLANNERS else "policy") if args.policy is not None
                    else (args.planner or "gradient"))
    if args.model is None and args.planner not in AGENT_PLANNERS:
        raise ValueError(f"--model is required: planner {args.planner!r} plans through a learned model "
                         "(or act with a trained gnwarp rl policy: --policy RUN)")
    policy = args.planner in AGENT_PLANNERS   # an agent's run, no gnwarp model
    settings = mpc_settings(args, task)
    args.steps = args.steps if args.steps is not None else (getattr(task, "episode_steps", None) or 100)
    if args.episodes < 1 or args.steps < 1:
        raise ValueError(f"--episodes and --steps must be >= 1, got {args.episodes} and {args.steps}")
    if args.terminal is not None and not Path(args.terminal).is_file():
        raise FileNotFoundError(f"--terminal: no terminal-value file at {args.terminal}")
    records = Path(args.records or f"mpc-{task.name}.jsonl")
    video = None if args.video == "none" else Path(args.video or f"mpc-{task.name}.gif")
    check_outputs(records, video)   # before planning, not after
    rk = ranks(args.device or "auto")   # rank 0 of 1 unless started by torchrun
    model = None if policy else load_model(args.model, device=rk.device if rk.distributed else args.device,
                                           **({"impl": args.impl} if args.impl else {}))
    # the system: --system, else the one the model was trained on that fits the task
    name = args.system or next((s for s in (model_systems(model) if model is not None else ())
                                if family_name(s) == task.system),
                               "swimmer6" if task.system == "swimmer" else task.system)
    system = systems.make(name)
    n = args.episodes
    check_memory(episode_bytes(n, args.steps, system.nbody, system.nu),
                 f"{n} episodes x {args.steps} steps x {system.nbody} bodies (every state kept)",
                 "Use fewer --steps or --episodes")
    check_plan_memory(args.planner, settings, n, task, system, model.device if model is not None else "cpu",
                      hint="Use a shorter --horizon (or fewer samples or episodes)")
    terminal = None
    if args.terminal is not None:
        from gnwarp.control.value import TerminalValue
        terminal = TerminalValue.load(args.terminal, device=model.device)
        if terminal.nbody != system.nbody:
            raise ValueError(f"--terminal {args.terminal}: a value of states of {terminal.nbody} bodies; "
                             f"{system.name} has {system.nbody}")
    qpos, qvel, target = episode_starts(task, system, n, args.seed)
    k_video = 0 if video is None else min(3, n)
    mine = {}

    def plan(idx: list) -> list:
        """This rank's episodes ``idx`` (of the n), planned together: (return, states or None) each."""
        pick = (lambda a: a) if len(idx) == n else (lambda a: None if a is None else a[np.asarray(idx)])
        m, tgt = len(idx), pick(target)
        own = settings
        if rk.distributed and "seed" in {f.name for f in dataclasses.fields(settings)}:   # each rank its own draws
            own = dataclasses.replace(settings, seed=settings.seed + rk.rank * 1_000_003)
        planner = make_planner(args.planner, model, task, system, m, own, tgt, terminal)
        gradient = planner_name(planner) == "gradient"
        from tqdm.auto import tqdm  # gradient MPC: one bar over every planning iteration, the warm-up included
        bar = tqdm(total=planner.warmup + settings.iterations * args.steps if gradient else args.steps,
                   desc=f"mpc {task.name}", unit="it" if gradient else "step", disable=args.quiet or not rk.main,
                   dynamic_ncols=True)
        episode_kw = {}
        if gradient:
            planner.progress = bar.update
        else:
            episode_kw["progress"] = lambda done: bar.update(done - bar.n)
        env = make_env(system, m, backend=args.backend)
        t0 = time.perf_counter()
        out = run_episodes(planner, env, task, args.steps, env.reset(pick(qpos), pick(qvel)), target=tgt,
                           **episode_kw)
        mine.update(planner=planner, secs=time.perf_counter() - t0, plan_seconds=out["plan_seconds"])
        bar.close()
        # clones: a view would pickle the whole batch's states to rank 0
        return [(float(out["returns"][j]), out["states"][j].clone() if i < k_video else None)
                for j, i in enumerate(idx)]

    # one process plans the n episodes together; under torchrun each rank its share, gathered on rank 0
    results = rk.map_sharded(range(n), plan, batched=True, what="mpc episodes")
    timings = rk.gather_objects(None if not mine else (mine["secs"], mine["plan_seconds"]))
    if not rk.main:
        return 0
    planner = mine["planner"]
    kind = planner_name(planner)
    gradient = kind == "gradient"
    done = [t for t in timings if t is not None]
    secs = max(t[0] for t in done)
    # the slowest rank's time at each control step: the job's step time
    plan_seconds = np.max(np.stack([t[1] for t in done]), axis=0)
    out = {"returns": torch.tensor([x[0] for x in results], dtype=torch.float32), "plan_seconds": plan_seconds}
    if k_video:
        out["states"] = torch.stack([x[1] for x in results[:k_video]])
    r = out["returns"]
    timing = plan_timing(out["plan_seconds"], control_timestep(system))
    print(f"{task.name} on {system.name}: true return {float(r.mean()):.4g} +- {float(r.std(unbiased=False)):.3g} "
          f"over {n} episodes of {args.steps} steps{f' on {rk.world} ranks' if rk.distributed else ''} "
          f"({planner_summary(planner, kind)})")
    print(timing_line(timing, planner, n))
    metrics = {k: timing[k] for k in ("first_step_ms", "steady_ms", "real_time_factor", "steady_after", "mean_ms")}
    if gradient:
        metrics.update(model_evals_per_step=planner.model_evals_per_step, warmup_iterations=planner.warmup,
                       proposal_evals=planner.proposal_evals)
    metrics.update(episode_steps_per_s=n * args.steps / secs, plan_ms=[1e3 * float(t) for t in out["plan_seconds"]])
    if timing["steady_ms"]:
        metrics["steady_episode_steps_per_s"] = 1e3 * n / timing["steady_ms"]
    if rk.distributed:
        metrics["ranks"] = rk.world
    fields = {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(settings).items()}
    horizon = getattr(planner, "horizon", None) or getattr(settings, "horizon", None)
    record = ResultRecord(
        experiment="mpc", task=task.name, system=system.name, planner=kind,
        dynamics="none" if kind == "policy" else "learned",
        seed=args.seed, episodes=n, episode_steps=args.steps, returns=[float(x) for x in r.double().cpu()],
        control_dt=float(system.dt), action_repeat=int(system.substeps),
        env_steps=planner.agent.env_steps if policy else training_env_steps(args.model),
        metrics=metrics, variant="terminal" if terminal is not None else "",
        config={"model": None if policy else str(args.model), "policy": args.policy, "horizon": horizon,
                "iterations": fields.get("iterations"),
                "warmup": planner.warmup if gradient else fields.get("warmup"), "proposals": fields.get("proposals"),
                "lr": fields.get("lr"), "backend": args.backend, "settings": fields,
                "terminal": None if args.terminal is None else str(args.terminal),
                "initial_qpos": np.asarray(qpos).tolist(), "initial_qvel": np.asarray(qvel).tolist(),
                "targets": None if target is None else target.cpu().double().numpy().tolist()},
        commit=git_commit(), gpu=gpu_name(planner.device if policy else model.device),
        date=time.strftime("%Y-%m-%d %H:%M:%S"))
    write_records(records, [record])
    print(f"wrote {records}")
    if video is not None:
        from gnwarp.eval.animation import animate_system
        what = "gradient MPC" if gradient else f"{kind} planner"
        animate_system(out["states"][:min(3, n)].numpy(), system, video,
                       title=f"{task.name}: {what}, true simulator", renderer=args.renderer)
        print(f"wrote {video}")
    return 0


def timing_line(timing: dict, planner, n: int) -> str:
    """The first control step and the steady state apart, and the real-time factor, in words."""
    first = f"first control step {timing['first_step_ms']:.1f} ms"
    if hasattr(planner, "proposal_evals"):   # gradient MPC: its warm-up and where it started
        proposed = planner.proposal_evals // planner.horizon
        start = f"the best of {proposed} proposed sequences" if proposed else "a random sequence"
        first += f" ({planner.warmup} warm-up iterations from {start})"
    if timing["steady_ms"] is None:
        return f"{first}; no steady state (one step)"
    after = timing["steady_after"]
    return (f"{first}; steady {timing['steady_ms']:.2f} ms a control step (median of steps {after + 1}-"
            f"{timing['steps']}), real-time factor {timing['real_time_factor']:.3g} (control step "
            f"{timing['control_dt_ms']:.3g} ms), {1e3 * n / timing['steady_ms']:.0f} episode-steps/s")


def check_outputs(records, video) -> None:
    """Refuse output paths that cannot be written (``files.check_output_path``), a video format
    that cannot be (``eval.video.check_video_path``) and a records file that is not one, before
    any work, with ``OSError`` / ``ValueError`` / ``RecordError`` naming them."""
    from gnwarp.eval.records import read_records
    from gnwarp.eval.video import check_video_path
    from gnwarp.files import check_output_path
    for what, path, check in (("--records", records, check_output_path), ("--video", video, check_video_path)):
        if path is not None:
            try:
                check(path)
            except OSError as e:
                raise type(e)(f"{what} {path}: {e}") from None
            except ValueError as e:   # the message names the path
                raise ValueError(f"{what}: {e}") from None
    if records.exists():
        read_records(records)   # appended to: it must hold valid records


def add_mpc(sub) -> None:
    m = sub.add_parser("mpc", help="MPC through a learned model (gradient, hybrid, sampling, mppi), run in closed "
                                   "loop on the true simulator",
                       description=paragraphs(
                           "Plan actions through a learned model, apply them on the true simulator, print the "
                           "true returns, append them as a results record to --records and write a video of "
                           "the first episodes. Output paths and planner settings are checked before planning.",
                           "--planner: gradient (the default: gradient steps on the task reward of the model's "
                           "rollouts, paper F.1.1; its first state warms up, 4 x iterations by default, after "
                           "a proposal of sampled sequences), hybrid (sampled sequences, the best refined by "
                           "gradient steps), sampling (predictive sampling) or mppi, all through the model. "
                           "--horizon, --iterations, --warmup, --proposals and --lr set the planner's settings "
                           "field of that name where it has one; --set KEY=VALUE sets any field "
                           "(GradientMPCConfig, HybridConfig, SamplingConfig). --terminal adds a learned "
                           "terminal value to every planned return.",
                           "A progress bar counts gradient MPC's planning iterations (other planners': control "
                           "steps). Prints the first control step and the steady state apart, with the real-time "
                           "factor (control timestep / steady time).",
                           "--policy RUN acts with the trained policy of a gnwarp rl run on the same task instead "
                           "(no model, no planning: a baseline beside the planners); with --planner policy-mpc it "
                           "plans over that agent (SVG(N >= 1)) with its own model, reward and Q-function.",
                           "On a CPU, start small: --episodes 2 --steps 20 --warmup 20."))
    m.add_argument("--model", help="checkpoint folder (e.g. runs/pendulum/best; default: none, required unless --policy)")
    m.add_argument("--policy", metavar="RUN",
                   help="act with the trained policy of the gnwarp rl run in folder RUN instead of planning "
                        "(planner 'policy'; no --model; default: none), or plan over that agent with "
                        "--planner policy-mpc (its model, reward and Q-function; settings through --set)")
    m.add_argument("--task", required=True, help="task name (gnwarp.control.TASKS, e.g. pendulum-balance, cheetah-run)")
    m.add_argument("--system", help="system to control (default: the model's system that fits the task; with "
                                    "--policy, the task's)")
    m.add_argument("--planner", default=None, metavar="NAME",
                   help=f"planner through the model: {', '.join(p for p in PLANNERS if p not in AGENT_PLANNERS)} "
                        "(gnwarp.control.PLANNERS; default: gradient); with --policy RUN: policy (default) or "
                        "policy-mpc (planning over the agent)")
    m.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="a field of the planner's settings (repeatable; values parsed as JSON when they parse, "
                        "e.g. --set samples=128 --set noise=0.3; policy-mpc: PolicyMPCSettings' fields; default: none)")
    m.add_argument("--terminal", metavar="VALUE_FILE",
                   help="a terminal value (gnwarp.control.value.TerminalValue.save) added to planned returns "
                        "(default: none)")
    m.add_argument("--episodes", type=int, default=8, help="episodes planned together")
    m.add_argument("--steps", type=int, default=None,
                   help="control steps per episode (default: the task's episode length, DMC's 1000, else 100; every "
                        "state is kept in memory: a run that cannot fit in the available memory is refused first)")
    m.add_argument("--horizon", type=int, help="planning horizon (default: the task's; policy-mpc: 5)")
    m.add_argument("--iterations", type=int, help="iterations per control step (gradient, hybrid: gradient steps, "
                                                   "default 5; policy-mpc: sampling rounds, default 4)")
    m.add_argument("--warmup", type=int, help="extra iterations at the first state (gradient, hybrid; default: 4 x "
                                              "iterations; the paper: iterations x horizon, with --proposals 0)")
    m.add_argument("--proposals", type=int,
                   help="random action sequences rolled out at the first state (beside the mid one); Adam starts "
                        "from the best (0: from a random sequence; gradient only; default: 30)")
    m.add_argument("--lr", type=float, help="Adam's step size (gradient, hybrid; default: the planner's, 0.1 and "
                                            "0.05)")
    m.add_argument("--seed", type=int, default=0, help="initial states, targets and the planner's seed")
    m.add_argument("--backend", default="auto", choices=["auto", "mujoco", "mujoco_warp", "mujoco_warp_cpu"],
                   help="true simulator (default: MuJoCo-Warp on a GPU, else MuJoCo C)")
    m.add_argument("--device", default=None, help="the model's device: cpu, cuda, ... (default: CUDA when present)")
    m.add_argument("--impl", choices=IMPLS, default=None, help="GN implementation (default: the checkpoint's)")
    m.add_argument("-o", "--out", "--records", dest="records", metavar="PATH",
                   help="results records file (JSON lines, appended; default: mpc-<task>.jsonl): per-episode "
                        "returns, initial states, targets and settings (gnwarp.eval.records)")
    m.add_argument("--video", help="video path, .gif, .png (APNG) or .webp (default: mpc-<task>.gif; "
                        "'none': no video)")
    m.add_argument("--renderer", default="auto", choices=["auto", "mujoco", "matplotlib"],
                   help="how the video is drawn: MuJoCo's renderer (EGL/OSMesa), matplotlib, or auto "
                        "(MuJoCo where it renders, else matplotlib)")
    m.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    m.set_defaults(func=mpc_command)
