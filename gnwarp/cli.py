"""The gnwarp command line: graph networks as learned physics engines of MuJoCo
systems, and control through them.

Start with "gnwarp demo" (a few minutes on a CPU). Then, step by step:
  gnwarp systems
  gnwarp generate pendulum -n 200
  gnwarp train --data pendulum.h5 --quick
  gnwarp evaluate runs/model/best --data pendulum.h5
  gnwarp mpc --model runs/model/best --task pendulum-balance
"gnwarp COMMAND --help" describes each command and its options."""
from __future__ import annotations

import argparse
import sys
import time

# the GN implementations (``gnwarp.gn.options.IMPLS``, which imports torch and Warp; a test keeps the two
# equal): each command imports what it needs inside its function, so --help loads neither
IMPLS = ("warp", "torch")


def _cmd_systems(args) -> int:
    from gnwarp.sim import systems
    rows = []
    for name in systems.names():
        rows.append(systems.describe(systems.make(name)))
    cols = ["name", "bodies", "nq", "nv", "nu", "actuators", "timestep", "dt", "substeps", "contacts", "parameters"]
    table = [[_fmt(r.get(c, "")) for c in cols] for r in rows]
    widths = [max(len(c), *(len(t[i]) for t in table)) for i, c in enumerate(cols)]
    print("  ".join(c.ljust(w) for c, w in zip(cols, widths)))
    for t in table:
        print("  ".join(x.ljust(w) for x, w in zip(t, widths)))
    return 0


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:g}"
    if isinstance(v, dict):
        return ", ".join(f"{k} {a:g}-{b:g}" if isinstance(a, (int, float)) else f"{k}"
                         for k, (a, b) in v.items()) if v else "-"
    if isinstance(v, (list, tuple)):
        return ",".join(str(x) for x in v)
    return str(v)


def _sizes(args):
    if args.train is None and args.valid is None and args.test is None:
        return args.num_sequences
    if args.num_sequences is not None:
        raise SystemExit("give either --num-sequences or --train/--valid/--test, not both")
    from gnwarp.data.generation import PAPER_SIZES
    paper = PAPER_SIZES[args.parameterized]
    return {k: getattr(args, k) if getattr(args, k) is not None else paper[k] for k in ("train", "valid", "test")}


def _cmd_generate(args) -> int:
    from pathlib import Path

    from gnwarp.data.generation import generate
    from gnwarp.files import remove_stale_temporaries
    from gnwarp.files import check_output_path
    from gnwarp.sim.systems import from_mjcf
    out = check_output_path(args.out or f"{args.system}{'-param' if args.parameterized else ''}.h5")
    if out.exists() and not args.overwrite:  # fail before simulating, not after
        raise FileExistsError(f"output exists: {out} (use --overwrite)")
    remove_stale_temporaries(out)  # what a killed generate to this path left
    system = from_mjcf(args.mjcf, dt=args.dt, substeps=args.substeps) if args.mjcf else args.system
    t0 = time.perf_counter()
    ds = generate(system, _sizes(args), num_steps=args.steps, seed=args.seed,
                  parameterized=args.parameterized, backend=args.backend, progress=not args.quiet)
    ds.save(out, overwrite=args.overwrite)
    n = sum(ds.meta["splits"].values())
    steps = n * ds.meta["num_steps"]
    print(f"wrote {out}: {ds.meta['system']} {ds.meta['splits']} x {ds.meta['num_steps']} steps, "
          f"backend {ds.meta['backend']}, {steps / max(ds.meta['simulation_seconds'], 1e-9):.3g} data steps/s "
          f"simulated, {time.perf_counter() - t0:.1f} s end to end")
    return 0


def _parse_value(text: str):
    """A --set value: JSON when it parses (numbers, true/false/null, lists), else the string; the
    config's validation then checks it like any other value."""
    import json
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def _read_config(path: str | None) -> dict:
    """A JSON or TOML (``.toml``) config file as a dict; a file that does not parse raises
    ``ConfigError`` naming the file and the line."""
    import json
    from pathlib import Path

    from gnwarp.validation import ConfigError
    if path is None:
        return {}
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"no config file at {p}")
    try:
        text = p.read_text()
    except UnicodeDecodeError as e:
        raise ConfigError(str(p), f"not a text file ({e.reason} at byte {e.start})") from None
    if p.suffix == ".toml":
        try:
            import tomllib
        except ImportError:  # Python 3.10
            import tomli as tomllib
        try:
            d = tomllib.loads(text)
        except tomllib.TOMLDecodeError as e:
            raise ConfigError(str(p), f"not valid TOML: {e}") from None
    else:
        try:
            d = json.loads(text)
        except json.JSONDecodeError as e:
            raise ConfigError(str(p), f"not valid JSON: {e.msg} (at line {e.lineno}, column {e.colno}); "
                                      "TOML files need the .toml suffix") from None
    if not isinstance(d, dict):
        raise ConfigError(str(p), f"a config file holds a table of TrainConfig keys, got a {type(d).__name__}")
    return d


def _apply_overrides(cfg: dict, items: list[str]) -> dict:
    """``key=value`` overrides into a nested dict; dotted keys reach nested configs (model.gn.latent=64)."""
    from gnwarp.validation import ConfigError
    for item in items or []:
        if "=" not in item:
            raise ConfigError("--set", f"expects KEY=VALUE, got {item!r}")
        key, value = item.split("=", 1)
        *parents, leaf = key.strip().split(".")
        if not all(k.strip() for k in parents + [leaf]):
            raise ConfigError("--set", f"malformed key {key!r} in {item!r} (keys are dotted names: model.gn.latent)")
        d = cfg
        for i, k in enumerate(parents):
            d = d.setdefault(k, {})
            if not isinstance(d, dict):
                raise ConfigError(".".join(parents[:i + 1]), f"is not a nested config, so --set {key} cannot "
                                                             "set a key inside it")
        d[leaf] = _parse_value(value)
    return cfg


def _config_source(path: str, items: list[str], flags: dict, config: str | None) -> str:
    """Where the value of config key ``path`` came from, for an error message."""
    parts = path.split(".")
    for item in reversed(items or []):
        key = item.split("=", 1)[0].strip()
        if key.split(".") == parts[:len(key.split("."))] or parts == key.split(".")[:len(parts)]:
            return f"--set {item}"
    if parts[0] in flags:
        return flags[parts[0]]
    return config or "the defaults"


def _cmd_train(args) -> int:
    from gnwarp.demo import quick_train_keys
    from gnwarp.files import check_output_path
    from gnwarp.train import TrainConfig, train
    from gnwarp.validation import ConfigError
    raw = _apply_overrides(_merged(quick_train_keys() if args.quick else {}, _read_config(args.config)), args.set)
    flags = {}
    if args.data:
        raw["data"], flags["data"] = args.data, "--data"
    if args.out:
        raw["out"], flags["out"] = args.out, "--out"
    if args.no_resume:
        raw["resume"] = False
    if args.quiet:
        raw["progress"] = False
    try:
        cfg = TrainConfig.from_dict(raw)
    except ConfigError as e:  # the same error as from Python, plus where the value came from
        source = _config_source(e.path, args.set, flags, args.config)
        source = "--quick" if args.quick and source == "the defaults" else source
        raise ConfigError(e.path, f"{e.reason} (from {source})") from None
    check_output_path(cfg.out, folder=True)
    from gnwarp.train.sysid_config import sysid_flags_given, sysid_settings
    given = sysid_flags_given(args)
    if given and not args.sysid:
        raise SystemExit(f"gnwarp train: {', '.join(given)} apply to system identification (--sysid) only")
    if args.sysid:  # Algorithm D.4: GN_p and the forward model end to end (parameterized data)
        from gnwarp.train.sysid import SysIDTrainer
        if given:
            sysid, options = sysid_settings(args)
            r = SysIDTrainer(cfg, sysid, options=options).run()
        else:   # a resumed run continues as its checkpoint records (a new one: the paper's model and training)
            r = SysIDTrainer(cfg).run()
    else:
        r = train(cfg)
    print(f"trained {r['steps']} steps in {r['seconds']:.1f} s ({r['steps_per_second']:.1f} steps/s, "
          f"stop: {r['stop']}); "
          f"best 20-step validation error {r['best_error']:.4g} at step {r['best_step']}; checkpoints in {r['out']}")
    return 0


def _evaluate_sysid(paths, ds, args, sequences, horizons) -> int:
    """Rollout errors of system-identification checkpoints: G_ID identified from the first
    window of each sequence of the split (the same instance) and from another instance's window
    (of the same graph topology: ``other_instance_windows``), then rollouts from the window's end. A checkpoint trained
    with ``--param-loss`` adds a row with G_ID's supervised columns set to the true parameters
    (what its forward model does when those are identified perfectly)."""
    import math
    from pathlib import Path

    from gnwarp.eval.sysid import sysid_error_rows
    from gnwarp.train.sysid import load_sysid, trained_param_stats
    print("| model | identified from | " + " | ".join(f"{h}-step rollout" for h in horizons) + " |")
    print("|---|---|" + "---|" * len(horizons))
    bad = False
    for path in paths:
        m = load_sysid(path, device=args.device)
        for label, errs in sysid_error_rows(m, ds, args.split, horizons, sequences, trained_param_stats(m, ds.system)):
            bad |= not all(math.isfinite(e) for e in errs)
            print(f"| {Path(path).resolve().parent.name} | {label} | " + " | ".join(f"{e:.4g}" for e in errs) + " |")
    if bad:
        raise FloatingPointError("a system-identification rollout left the finite range")
    return 0


def _positive_ints(option: str, values) -> list[int]:
    """``values`` (strings; commas also separate) as integers >= 1, or ValueError naming ``option``."""
    out = []
    for v in values:
        for part in str(v).split(","):
            try:
                n = int(part.strip())
            except ValueError:
                n = None
            if n is None or n < 1:
                raise ValueError(f"{option} must be an integer >= 1, got {part.strip()!r}")
            out.append(n)
    if not out:
        raise ValueError(f"{option} needs at least one integer >= 1")
    return out


def _cmd_evaluate(args) -> int:
    import json
    import math
    from pathlib import Path

    # the arguments first: nothing is loaded for a run that cannot report anything
    sequences = None
    if args.sequences is not None:
        try:
            sequences = int(args.sequences)
        except ValueError:
            sequences = 0
        if sequences < 1:
            raise ValueError(f"-n/--sequences must be an integer >= 1, got {args.sequences!r}")
    horizons = tuple(dict.fromkeys(_positive_ints("--horizons", args.horizons)))
    if args.out:  # a folder that cannot be made is refused before anything loads
        from gnwarp.files import check_output_path
        check_output_path(args.out, folder=True)

    from gnwarp.data.dataset import load
    from gnwarp.eval.metrics import evaluate
    from gnwarp.eval.report import markdown_table, write_report
    from gnwarp.files import jsonable
    from gnwarp.train import load_model
    ds = load(args.data)
    results = {}
    from gnwarp.train.checkpoint import CheckpointError, checkpoint_config

    def kind(path):  # (a folder that is no checkpoint gets load_model's error below)
        try:
            return checkpoint_config(path).get("kind")
        except CheckpointError:
            return None
    sysid = [p for p in args.checkpoints if kind(p) == "sysid"]
    if sysid:  # system identification: G_ID from each sequence's first window, then rollouts
        return _evaluate_sysid(sysid, ds, args, sequences, horizons)
    for k, path in enumerate(args.checkpoints):
        name = args.names[k] if args.names and k < len(args.names) else Path(path).resolve().parent.name
        m = load_model(path, device=args.device, **({"impl": args.impl} if args.impl else {}))
        results[name] = evaluate(m, ds, args.split, sequences, horizons, keep_predictions=bool(args.out))
    if args.out:
        out = Path(args.out)
        table = write_report(results, ds, out)
        print(table)
        (out / "results.json").write_text(json.dumps(jsonable(results), indent=1))
        print(f"wrote {out}/errors.md, errors.png, states.png, rollouts.gif, results.json")
    else:
        print(markdown_table(results, ds.system))
    # predictions that left the finite range: reported above, and the exit status says so
    bad = []
    for name, r in results.items():
        step = r.get("first_nonfinite_step")
        if step is not None:
            bad.append(f"{name}: rollouts not finite from step {step} ({r['nonfinite_sequences']} of "
                       f"{r['sequences']} sequences)")
        elif r["one_step"].get("nonfinite_steps") or not math.isfinite(r["one_step"]["mean"]):
            bad.append(f"{name}: {r['one_step'].get('nonfinite_steps', 0)} one-step predictions not finite")
    if bad:
        print(f"gnwarp evaluate: error: predictions left the finite range: {'; '.join(bad)}", file=sys.stderr)
        return 1
    return 0


def _cmd_check(args) -> int:
    """``gnwarp check PATH``: the full validation of a dataset file or a checkpoint folder; prints
    what it found, one line per problem; exit 0 when clean, 1 when there are problems."""
    from pathlib import Path
    path = Path(args.path)
    if not path.exists():
        raise FileNotFoundError(f"nothing at {path}")
    if path.is_dir():
        from gnwarp.train.checkpoint import check_checkpoint  # lines starting with "error:" are problems
        lines = [str(x) for x in check_checkpoint(path)]
    else:
        from gnwarp.data.dataset import check
        lines = check(path)
    for line in lines:
        print(line)
    return 1 if any(line.startswith("error:") for line in lines) else 0


def _cmd_demo(args) -> int:
    from gnwarp.demo import DemoConfig, run_demo
    over = {k: v for k, v in (("out", args.out), ("train_steps", args.steps), ("train_seconds", args.seconds),
                              ("impl", args.impl), ("device", args.device), ("system", args.system))
            if v is not None}
    if args.quiet:
        over["progress"] = False
    from pathlib import Path

    from gnwarp.files import check_output_path
    cfg = DemoConfig(**over)
    check_output_path(cfg.out, folder=True)
    summary = run_demo(cfg)
    if args.quiet:  # the progress lines and the table were left out: one line says where everything is
        print(f"wrote {Path(cfg.out) / 'report.md'} in {summary['timings_s']['total']:.0f} s")
    return 0


def _episode_bytes(n: int, steps: int, bodies: int, nu: int) -> int:
    """Host memory ``run_episodes`` holds for ``n`` episodes of ``steps`` steps: float32 states
    [n, steps+1, bodies, 13] and actions [n, steps, nu], each per step and stacked, and about
    500 bytes of Python objects a step."""
    return 2 * 4 * (n * (steps + 1) * bodies * 13 + n * steps * nu) + 500 * steps


def _cmd_mpc(args) -> int:
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
    _check_outputs(records, video)   # before planning, not after
    model = load_model(args.model, device=args.device, **({"impl": args.impl} if args.impl else {}))
    # the system: --system, else the one the model was trained on that fits the task
    name = args.system or next((s for s in model_systems(model) if family_name(s) == task.system),
                               "swimmer6" if task.system == "swimmer" else task.system)
    system = systems.make(name)
    n = args.episodes
    check_memory(_episode_bytes(n, args.steps, system.nbody, system.nu),
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
    print(_timing_line(timing, planner, n))
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


def _timing_line(timing: dict, planner, n: int) -> str:
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


def _check_outputs(records, video) -> None:
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


class _Help(argparse.RawDescriptionHelpFormatter):
    """Help with each option's default appended, unless its text names one already or there is
    none to show (None, an empty list, an off switch); descriptions keep their own lines."""

    def _get_help_string(self, action):
        text = action.help or ""
        d = action.default
        if ("default" in text or d is None or d is False or d == [] or d is argparse.SUPPRESS
                or action.required or not (action.option_strings or action.nargs == "?")):
            return text
        shown = " ".join(d) if isinstance(d, list) else d
        return f"{text} (default: {shown})"


def _paragraphs(*texts: str) -> str:
    """Paragraphs wrapped to 78 columns, a blank line between them (a parser's description)."""
    import textwrap
    return "\n\n".join(textwrap.fill(" ".join(t.split()), 78) for t in texts)


def _merged(base: dict, over: dict) -> dict:
    """``base`` with ``over``'s keys on top, nested tables merged key by key."""
    out = dict(base)
    for k, v in over.items():
        out[k] = _merged(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _flat(d: dict, prefix: str = "") -> list[str]:
    """A nested dict as ``key=value`` strings, nested keys dotted (what --set would take)."""
    import json
    out = []
    for k, v in d.items():
        out += _flat(v, f"{prefix}{k}.") if isinstance(v, dict) else [f"{prefix}{k}={json.dumps(v)}"]
    return out


def _train_epilog() -> str:
    """``train --help``'s list of the keys ``--set`` takes, from TrainConfig's fields (each
    with its default, allowed values and the first sentence of its description)."""
    import json
    import textwrap

    from gnwarp.demo import quick_train_keys
    from gnwarp.files import jsonable
    from gnwarp.train import TrainConfig
    from gnwarp.validation import config_keys
    lines = ["On a CPU: --quick sets " + " ".join(_flat(quick_train_keys(), "")) + ", or --set steps=2000 "
             "alone keeps the paper's model and shortens the run.",
             "", "config keys (a config file's keys, or --set KEY=VALUE; nested keys dotted):"]
    lines = textwrap.wrap(lines[0], 78) + lines[1:]
    keys = config_keys(TrainConfig)
    for key, default, allowed, doc in sorted(keys, key=lambda r: "." in r[0]):  # top-level keys first
        shown = default if isinstance(default, str) else json.dumps(jsonable(default))
        text = f"{key}={shown}: {allowed}" + (f"; {doc}" if doc else "")
        lines += textwrap.wrap(text, 78, initial_indent="  ", subsequent_indent="      ")
    return "\n".join(lines)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The command line's parser. ``command``: the command about to run; the train command's
    config-key list and system-ID options (which import the training stack) are added only for
    "train" or for None (every command in full)."""
    full_train = command in (None, "train")
    p = argparse.ArgumentParser(prog="gnwarp", description=__doc__, formatter_class=_Help)
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    s = sub.add_parser("systems", help="list the built-in systems",
                       description="List the built-in systems: bodies, generalized coordinates (nq, nv), "
                                   "actuators, timesteps and the parameters that --parameterized data varies.")
    s.set_defaults(func=_cmd_systems)

    g = sub.add_parser("generate", help="simulate a dataset under random controls and write it (HDF5)",
                       description=_paragraphs(
                           "Simulate sequences of a system under random spline controls and write them as "
                           "one HDF5 dataset with train, valid and test splits (what train and evaluate read). "
                           "The output path is checked, and a dataset too large for this machine's memory "
                           "refused, before anything is simulated.",
                           "On a CPU, -n 200 (a few seconds for the pendulum) is a good start; the paper's "
                           "sizes are tens of thousands of sequences."))
    g.add_argument("system", nargs="?", default="pendulum", help="built-in system name (see: gnwarp systems)")
    g.add_argument("--mjcf", help="simulate this MJCF file instead of a built-in system (default: none)")
    g.add_argument("--dt", type=float, help="data timestep for --mjcf (default: its timestep x substeps)")
    g.add_argument("--substeps", type=int, default=1, help="physics steps per data step for --mjcf")
    g.add_argument("-n", "--num-sequences", type=int, default=None,
                   help="total sequences, split like the paper (default: the paper's sizes)")
    g.add_argument("--train", type=int, help="train sequences, instead of -n (default: the paper's)")
    g.add_argument("--valid", type=int, help="validation sequences, instead of -n (default: the paper's)")
    g.add_argument("--test", type=int, help="test sequences, instead of -n (default: the paper's)")
    g.add_argument("--steps", type=int, default=100, help="data steps per sequence")
    g.add_argument("--seed", type=int, default=0, help="random seed of initial states, controls and parameters")
    g.add_argument("--parameterized", action="store_true", help="randomize system parameters per sequence")
    g.add_argument("--backend", default="auto", choices=["auto", "mujoco", "mujoco_warp", "mujoco_warp_cpu"],
                   help="simulator (default: MuJoCo-Warp on a GPU, else MuJoCo C)")
    g.add_argument("-o", "--out", help="output file (default: <system>.h5)")
    g.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    g.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    g.set_defaults(func=_cmd_generate)

    t = sub.add_parser("train", help="train a forward model (config file plus --set overrides)",
                       description=_paragraphs(
                           "Train a forward model on dataset files. Settings come from the defaults (the "
                           "paper's model and schedule, sized for a GPU), then --quick, then a config file, "
                           "then --set KEY=VALUE; nested keys are dotted, e.g. --set model.core=mlp --set "
                           "model.gn.latent=64. Every value is validated, and the run folder checked, before "
                           "anything runs. Resumes from <out>/last when it exists.",
                           "Example: gnwarp train --data pendulum.h5 --quick -o runs/pendulum"),
                       epilog=_train_epilog() if full_train else None)
    t.add_argument("config", nargs="?", help="JSON or TOML training config, keys as listed below (default: none)")
    t.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config key (repeatable; values parsed as JSON when they parse; "
                        "default: none)")
    t.add_argument("--quick", action="store_true",
                   help="a run sized for a CPU (minutes): the demo's smaller GN and schedule (listed below)")
    t.add_argument("--data", nargs="+", help="dataset file(s); overrides the config's data (default: the config's)")
    t.add_argument("-o", "--out", help="run folder (checkpoints and log); overrides the config's out "
                                       "(default: the config's, runs/model)")
    t.add_argument("--no-resume", action="store_true", help="start afresh even if <out>/last exists")
    t.add_argument("--sysid", action="store_true",
                   help="train system identification end to end (Algorithm D.4) on parameterized data: a recurrent "
                        "GN infers a latent static graph from a 20-step window; gnwarp evaluate reads its checkpoints")
    if full_train:
        from gnwarp.train.sysid_config import add_sysid_arguments
        add_sysid_arguments(t.add_argument_group("system identification (with --sysid; SysIDConfig and "
                                                 "SysIDTrainConfig fields)"))
    t.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    t.set_defaults(func=_cmd_train)

    e = sub.add_parser("evaluate", help="one-step and rollout errors of checkpoints on a dataset",
                       description=_paragraphs(
                           "One-step and rollout errors of checkpoints on a dataset, normalized by those of "
                           "predicting the initial state unchanged, printed as a table. Predictions that "
                           "leave the finite range are reported with the first step where they did, and "
                           "the exit status is then 1."))
    e.add_argument("checkpoints", nargs="+", help="checkpoint folders (e.g. runs/gn/best runs/mlp/best)")
    e.add_argument("--data", required=True, help="dataset file")
    e.add_argument("--names", nargs="+", help="model names for the table (default: the run folder names)")
    e.add_argument("--split", default="test", choices=["train", "valid", "test"], help="dataset split to evaluate on")
    e.add_argument("-n", "--sequences", default=None, metavar="N",
                   help="first N sequences of the split, N >= 1 (default all)")
    e.add_argument("--horizons", nargs="+", default=["20", "100"], metavar="H",
                   help="rollout horizons in steps, each >= 1 (default: 20 100; commas also separate)")
    e.add_argument("--device", default=None, help="cpu, cuda, ... (default: CUDA when present)")
    e.add_argument("--impl", choices=IMPLS, default=None,
                   help="run the GN on Warp kernels or the torch reference (default: as the checkpoint was saved)")
    e.add_argument("-o", "--out", help="also write the table, bar chart, state plot and GIF into this folder "
                                       "(default: none, the table is printed)")
    e.set_defaults(func=_cmd_evaluate)

    d = sub.add_parser("demo", help="simulate Pendulum, train a GN and an MLP, evaluate, write a report",
                       description=_paragraphs(
                           "The whole pipeline in a few minutes on a CPU: simulate a small dataset, train a "
                           "graph network and an MLP baseline for the same number of steps, evaluate both "
                           "against the constant baseline, and write report.md with error plots, a rollout "
                           "GIF and results.json into the output folder."))
    d.add_argument("-o", "--out", help="output folder (default: ./gnwarp-demo)")
    d.add_argument("--steps", type=int, help="training steps per model (default: 8000)")
    d.add_argument("--seconds", type=float, help="training time cap for the GN; the MLP gets its step count "
                                                 "(default: 300)")
    d.add_argument("--system", help="system to model (default: pendulum)")
    d.add_argument("--impl", choices=IMPLS, help="GN implementation (default: warp)")
    d.add_argument("--device", help="cpu, cuda, ... (default: CUDA when present)")
    d.add_argument("-q", "--quiet", action="store_true",
                   help="no progress lines or table; one line says where the report went")
    d.set_defaults(func=_cmd_demo)

    c = sub.add_parser("check", help="validate a dataset file or a checkpoint folder (every array read, checksums "
                                     "verified); exit 1 when it finds problems",
                       description=_paragraphs(
                           "Validate a dataset file or a checkpoint folder in full: every array is read and "
                           "checked, checksums verified. Prints one line per finding (problems start with "
                           "'error:'); the exit status is 0 when clean, 1 when there are problems."))
    c.add_argument("path", help="dataset file (.h5) or checkpoint folder (e.g. runs/gn/best)")
    c.set_defaults(func=_cmd_check)

    m = sub.add_parser("mpc", help="gradient MPC through a learned model, run in closed loop on the true simulator",
                       description=_paragraphs(
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
    m.set_defaults(func=_cmd_mpc)
    lp = sub.add_parser("loop", help="the data loop: plan on the true simulator, add the data, train on, repeat")
    if command in (None, "loop"):   # its flags are LoopConfig's, whose module loads torch
        from gnwarp.control.loop_command import add_loop_arguments
        add_loop_arguments(lp)
    for name, action in sub.choices.items():  # every command: its defaults shown, a description
        action.formatter_class = _Help
        action.description = action.description or next(a.help for a in sub._choices_actions if a.dest == name)
    return p


def _command_of(argv: list[str]) -> str:
    """The command named in ``argv`` (its first word not starting with "-"), or "" for none."""
    return next((a for a in argv if not a.startswith("-")), "")


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser(_command_of(argv)).parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, OSError, FloatingPointError, RuntimeError, TypeError) as e:
        print(f"gnwarp {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
