"""``gnwarp evaluate`` (one-step and rollout errors of checkpoints, system identification's
included) and ``gnwarp demo`` (the whole pipeline in minutes)."""
from __future__ import annotations

import sys

from gnwarp.cli.common import IMPLS, paragraphs, positive_ints

__all__ = ["add_evaluate", "add_demo", "evaluate_command", "evaluate_sysid", "demo_command"]


def evaluate_sysid(paths, ds, args, sequences, horizons) -> int:
    """Rollout errors of system-identification checkpoints: G_ID identified from the first
    window of each sequence of the split (the same instance) and from another instance's window
    (of the same graph topology: ``other_instance_windows``), then rollouts from the window's end. A checkpoint trained
    with ``--param-loss`` adds a row with G_ID's supervised columns set to the true parameters
    (what its forward model does when those are identified perfectly)."""
    import math
    from pathlib import Path

    from gnwarp.eval.sysid import sysid_error_rows
    from gnwarp.train.sysid import load_sysid, trained_param_stats
    from gnwarp.eval.report import rollout_label
    models = {path: load_sysid(path, device=args.device) for path in paths}
    steps = ds[args.split].ctrl.shape[1]
    # the rollout steps each model's window leaves (a rollout starts where its window ends)
    used = {path: [min(h, steps - m.window) for h in horizons] for path, m in models.items()}
    same = [len({u[i] for u in used.values()}) == 1 for i in range(len(horizons))]
    print("| model | identified from | " + " | ".join(
        rollout_label(h, next(iter(used.values()))[i]) if same[i]
        else f"{h}-step rollout (fewer where a model's window leaves fewer steps: in its cells)"
        for i, h in enumerate(horizons)) + " |")
    print("|---|---|" + "---|" * len(horizons))
    bad = False
    for k, (path, m) in enumerate(models.items()):
        name = args.names[k] if args.names else Path(path).resolve().parent.name
        for label, errs in sysid_error_rows(m, ds, args.split, horizons, sequences, trained_param_stats(m, ds.system)):
            bad |= not all(math.isfinite(e) for e in errs)
            print(f"| {name} | {label} | " + " | ".join(
                f"{e:.4g}" + ("" if same[i] or used[path][i] == h else f" ({used[path][i]} steps)")
                for i, (h, e) in enumerate(zip(horizons, errs))) + " |")
    if bad:
        raise FloatingPointError("a system-identification rollout left the finite range")
    return 0


def evaluate_command(args) -> int:
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
    horizons = tuple(dict.fromkeys(positive_ints("--horizons", args.horizons)))
    if args.names and len(args.names) != len(args.checkpoints):
        raise ValueError(f"--names gives {len(args.names)} names for {len(args.checkpoints)} checkpoints: one each")
    if args.out:  # a folder that cannot be made is refused before anything loads
        from gnwarp.files import check_output_path
        check_output_path(args.out, folder=True)
    if args.device is not None:   # a device that is not here, likewise
        from gnwarp.interop import resolve_device
        resolve_device(args.device)

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
        others = [p for p in args.checkpoints if p not in sysid]
        if others:
            raise ValueError(f"system-identification checkpoints ({', '.join(sysid)}) and forward models "
                             f"({', '.join(others)}) are evaluated apart: give one kind at a time")
        unused = [f for f, v in (("-o/--out", args.out), ("--impl", args.impl)) if v]
        if unused:
            raise ValueError(f"{' and '.join(unused)}: not taken for system-identification checkpoints (their "
                             "table is printed)")
        return evaluate_sysid(sysid, ds, args, sequences, horizons)
    for k, path in enumerate(args.checkpoints):
        name = args.names[k] if args.names else Path(path).resolve().parent.name
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


def demo_command(args) -> int:
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


def add_evaluate(sub) -> None:
    e = sub.add_parser("evaluate", help="one-step and rollout errors of checkpoints on a dataset",
                       description=paragraphs(
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
    e.set_defaults(func=evaluate_command)


def add_demo(sub) -> None:
    d = sub.add_parser("demo", help="simulate Pendulum, train a GN and an MLP, evaluate, write a report",
                       description=paragraphs(
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
    d.set_defaults(func=demo_command)
