"""``gnwarp systems``, ``gnwarp generate`` and ``gnwarp check``: the systems, their datasets and
the validation of datasets and checkpoints."""
from __future__ import annotations

import time

from gnwarp.cli.common import paragraphs

__all__ = ["add_systems", "add_generate", "add_check", "systems_command", "generate_command", "check_command",
           "dm_control_installed"]

COLUMNS = ["name", "bodies", "nq", "nv", "nu", "actuators", "timestep", "dt", "substeps", "contacts", "parameters"]


def dm_control_installed() -> bool:
    """Whether the dm-control package can be imported (found, not imported: it is slow to load)."""
    import importlib.util
    return importlib.util.find_spec("dm_control") is not None


def systems_command(args) -> int:
    """The table of the built-in systems and, where dm-control is installed, of the DeepMind
    Control Suite domains (their parameters column says "DMC domain")."""
    from gnwarp.sim import systems
    rows = [systems.describe(systems.make(name)) for name in systems.names()]
    if dm_control_installed():
        from gnwarp.sim.dmc import dmc_names
        for name in dmc_names():
            rows.append({**systems.describe(systems.make(name)), "parameters": "DMC domain (fixed)"})
    table = [[fmt(r.get(c, "")) for c in COLUMNS] for r in rows]
    widths = [max(len(c), *(len(t[i]) for t in table)) for i, c in enumerate(COLUMNS)]
    print("  ".join(c.ljust(w) for c, w in zip(COLUMNS, widths)))
    for t in table:
        print("  ".join(x.ljust(w) for x, w in zip(t, widths)))
    if not dm_control_installed():
        print("(the DeepMind Control Suite domains, dmc-cheetah and others, need dm-control: "
              'pip install -e ".[dmc]")')
    return 0


def fmt(v) -> str:
    """A table cell: floats short, parameter ranges as "name lo-hi", lists comma-separated."""
    if isinstance(v, float):
        return f"{v:g}"
    if isinstance(v, dict):
        return ", ".join(f"{k} {a:g}-{b:g}" if isinstance(a, (int, float)) else f"{k}"
                         for k, (a, b) in v.items()) if v else "-"
    if isinstance(v, (list, tuple)):
        return ",".join(str(x) for x in v)
    return str(v)


def split_sizes(args):
    """-n, or the --train/--valid/--test sizes (the paper's for those not given)."""
    if args.train is None and args.valid is None and args.test is None:
        return args.num_sequences
    if args.num_sequences is not None:
        raise SystemExit("give either --num-sequences or --train/--valid/--test, not both")
    from gnwarp.data.generation import PAPER_SIZES
    paper = PAPER_SIZES[args.parameterized]
    return {k: getattr(args, k) if getattr(args, k) is not None else paper[k] for k in ("train", "valid", "test")}


def generate_command(args) -> int:
    from gnwarp.data.generation import generate
    from gnwarp.files import check_output_path, remove_stale_temporaries
    from gnwarp.sim.systems import from_mjcf
    out = check_output_path(args.out or f"{args.system}{'-param' if args.parameterized else ''}.h5")
    if out.exists() and not args.overwrite:  # fail before simulating, not after
        raise FileExistsError(f"output exists: {out} (use --overwrite)")
    remove_stale_temporaries(out)  # what a killed generate to this path left
    if not args.mjcf and (args.dt is not None or args.substeps is not None):
        raise ValueError("--dt and --substeps apply to --mjcf only: a built-in system keeps its own timestep "
                         "(`gnwarp systems` lists them)")
    system = (from_mjcf(args.mjcf, dt=args.dt, substeps=1 if args.substeps is None else args.substeps)
              if args.mjcf else args.system)
    t0 = time.perf_counter()
    from gnwarp.distributed import launched
    if launched():   # under torchrun: each rank simulates its share, rank 0 writes the dataset
        from gnwarp.data.shards import generate as generate_sharded
        r = generate_sharded(system, out, overwrite=args.overwrite, num_sequences=split_sizes(args),
                             num_steps=args.steps, seed=args.seed, parameterized=args.parameterized,
                             backend=args.backend, progress=not args.quiet)
        steps = r["sequences"] * args.steps
        print(f"rank {r['rank']} of {r['ranks']}: {r['sequences']} sequences, "
              f"{steps / max(r['simulation_seconds'], 1e-9):.3g} data steps/s simulated"
              + (f"; wrote {out} ({r['merge_seconds']:.1f} s to merge the shards), "
                 f"{time.perf_counter() - t0:.1f} s end to end" if r["rank"] == 0 else ""))
        return 0
    ds = generate(system, split_sizes(args), num_steps=args.steps, seed=args.seed,
                  parameterized=args.parameterized, backend=args.backend, progress=not args.quiet)
    ds.save(out, overwrite=args.overwrite)
    n = sum(ds.meta["splits"].values())
    steps = n * ds.meta["num_steps"]
    print(f"wrote {out}: {ds.meta['system']} {ds.meta['splits']} x {ds.meta['num_steps']} steps, "
          f"backend {ds.meta['backend']}, {steps / max(ds.meta['simulation_seconds'], 1e-9):.3g} data steps/s "
          f"simulated, {time.perf_counter() - t0:.1f} s end to end")
    return 0


def check_command(args) -> int:
    """``gnwarp check PATH``: the full validation of a dataset file or a checkpoint folder; prints
    what it found, one line per problem; exit 0 when clean, 1 when there are problems."""
    from pathlib import Path
    path = Path(args.path)
    if not path.exists():
        raise FileNotFoundError(f"nothing at {path}")
    if path.is_dir():
        lines = _check_folder(path)   # lines starting with "error:" are problems
    else:
        from gnwarp.data.dataset import check
        lines = check(path)
    for line in lines:
        print(line)
    return 1 if any(line.startswith("error:") for line in lines) else 0


def _check_folder(path) -> list[str]:
    """``gnwarp check``'s findings for a folder: a forward model's checkpoint (its full check), a
    system-identification checkpoint (loaded as ``load_sysid`` loads it: manifest, checksums,
    config, finite weights that fit) or a ``gnwarp rl`` run (its ``checkpoint.pt`` read as a
    resume reads it)."""
    from gnwarp.train.checkpoint import CheckpointError, check_checkpoint, checkpoint_config
    from gnwarp.rl.run_log import CHECKPOINT
    if (path / CHECKPOINT).is_file() and not (path / "model.pt").is_file():
        from gnwarp.rl.run_log import RLCheckpointError, load_checkpoint
        try:
            ck = load_checkpoint(path / CHECKPOINT)
        except RLCheckpointError as e:
            return [f"error: {e}"]
        env = ck.get("env", {}) if isinstance(ck, dict) else {}
        buf = ck.get("buffer") if isinstance(ck, dict) else None
        slim = ("; a slim copy: its replay buffer's transitions are rebuilt on resuming (gnwarp.rl.slim)"
                if isinstance(buf, dict) and buf.get("actions_only") else "")
        return [f"ok: {path}: a gnwarp rl run; {CHECKPOINT} read and verified (no code run), "
                f"{env.get('control_steps', '?')} env steps{slim}"]
    try:
        kind = checkpoint_config(path).get("kind")
    except CheckpointError:
        kind = None   # check_checkpoint names what is wrong
    if kind == "sysid":
        from gnwarp.train.sysid import load_sysid
        try:
            m = load_sysid(path, device="cpu")
        except (CheckpointError, ValueError, OSError) as e:
            return [f"error: {e}"]
        n = sum(p.numel() for p in m.parameters())
        return [f"ok: {path}: a system-identification checkpoint (window {m.window}); manifest and checksums "
                f"match, {n} weight elements finite and fitting its config"]
    return [str(x) for x in check_checkpoint(path)]


def add_systems(sub) -> None:
    s = sub.add_parser("systems", help="list the built-in systems and the DeepMind Control Suite domains",
                       description=paragraphs(
                           "List the built-in systems: bodies, generalized coordinates (nq, nv), actuators, "
                           "timesteps and the parameters that --parameterized data varies. Where dm-control is "
                           "installed, the DeepMind Control Suite domains (dmc-cheetah, ...) follow, marked "
                           "'DMC domain' (their own MJCF at DMC's control timestep; fixed, never parameterized)."))
    s.set_defaults(func=systems_command)


def add_generate(sub) -> None:
    g = sub.add_parser("generate", help="simulate a dataset under random controls and write it (HDF5)",
                       description=paragraphs(
                           "Simulate sequences of a system under random spline controls and write them as "
                           "one HDF5 dataset with train, valid and test splits (what train and evaluate read). "
                           "The output path is checked, and a dataset too large for this machine's memory "
                           "refused, before anything is simulated.",
                           "On a CPU, -n 200 (a few seconds for the pendulum) is a good start; the paper's "
                           "sizes are tens of thousands of sequences."))
    g.add_argument("system", nargs="?", default="pendulum", help="built-in system name (see: gnwarp systems)")
    g.add_argument("--mjcf", help="simulate this MJCF file instead of a built-in system (default: none)")
    g.add_argument("--dt", type=float, help="data timestep for --mjcf (default: its timestep x substeps)")
    g.add_argument("--substeps", type=int, default=None, help="physics steps per data step for --mjcf (default: 1)")
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
    g.set_defaults(func=generate_command)


def add_check(sub) -> None:
    c = sub.add_parser("check", help="validate a dataset file or a checkpoint folder (every array read, checksums "
                                     "verified); exit 1 when it finds problems",
                       description=paragraphs(
                           "Validate a dataset file or a checkpoint folder in full: every array is read and "
                           "checked, checksums verified. Prints one line per finding (problems start with "
                           "'error:'); the exit status is 0 when clean, 1 when there are problems."))
    c.add_argument("path", help="dataset file (.h5) or checkpoint folder (e.g. runs/gn/best)")
    c.set_defaults(func=check_command)
