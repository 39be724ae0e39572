"""The ``gnwarp`` command line: ``gnwarp systems``, ``gnwarp generate``, ``gnwarp demo`` ..."""
from __future__ import annotations

import argparse
import sys
import time


def _cmd_systems(args) -> int:
    from gnwarp import systems
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
    from gnwarp.data import PAPER_SIZES
    paper = PAPER_SIZES[args.parameterized]
    return {k: getattr(args, k) if getattr(args, k) is not None else paper[k] for k in ("train", "valid", "test")}


def _cmd_generate(args) -> int:
    from pathlib import Path

    from gnwarp import data, systems
    out = Path(args.out or f"{args.system}{'-param' if args.parameterized else ''}.h5")
    if out.exists() and not args.overwrite:  # fail before simulating, not after
        raise FileExistsError(f"output exists: {out} (use --overwrite)")
    system = systems.from_mjcf(args.mjcf, dt=args.dt, substeps=args.substeps) if args.mjcf else args.system
    t0 = time.perf_counter()
    ds = data.generate(system, _sizes(args), num_steps=args.steps, seed=args.seed,
                       parameterized=args.parameterized, backend=args.backend, progress=not args.quiet)
    ds.save(out, overwrite=args.overwrite)
    n = sum(ds.meta["splits"].values())
    steps = n * ds.meta["num_steps"]
    print(f"wrote {out}: {ds.meta['system']} {ds.meta['splits']} x {ds.meta['num_steps']} steps, "
          f"backend {ds.meta['backend']}, {steps / max(ds.meta['simulation_seconds'], 1e-9):.3g} data steps/s "
          f"simulated, {time.perf_counter() - t0:.1f} s end to end")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="gnwarp", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("systems", help="list the built-in systems")
    s.set_defaults(func=_cmd_systems)

    g = sub.add_parser("generate", help="simulate a dataset under random controls and write it (HDF5)")
    g.add_argument("system", nargs="?", default="pendulum", help="built-in system name (see `gnwarp systems`)")
    g.add_argument("--mjcf", help="simulate this MJCF file instead of a built-in system")
    g.add_argument("--dt", type=float, help="data timestep for --mjcf (default: its timestep x substeps)")
    g.add_argument("--substeps", type=int, default=1, help="physics steps per data step for --mjcf")
    g.add_argument("-n", "--num-sequences", type=int, default=None,
                   help="total sequences, split like the paper (default: the paper's sizes)")
    g.add_argument("--train", type=int)
    g.add_argument("--valid", type=int)
    g.add_argument("--test", type=int)
    g.add_argument("--steps", type=int, default=100, help="data steps per sequence")
    g.add_argument("--seed", type=int, default=0)
    g.add_argument("--parameterized", action="store_true", help="randomize system parameters per sequence")
    g.add_argument("--backend", default="auto", choices=["auto", "mujoco", "mujoco_warp", "mujoco_warp_cpu"])
    g.add_argument("-o", "--out", help="output file (default: <system>.h5)")
    g.add_argument("--overwrite", action="store_true")
    g.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    g.set_defaults(func=_cmd_generate)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, FileNotFoundError, FileExistsError, PermissionError, RuntimeError) as e:
        print(f"gnwarp {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
