"""``gnwarp train``: a forward model (or system identification) from a config file plus
``--set`` overrides."""
from __future__ import annotations

from gnwarp.cli.common import apply_overrides, config_source, flat, merged, paragraphs, read_config

__all__ = ["add_train", "train_command", "train_epilog"]


def train_command(args) -> int:
    from gnwarp.demo import quick_train_keys
    from gnwarp.files import check_output_path
    from gnwarp.train import TrainConfig, train
    from gnwarp.validation import ConfigError
    raw = apply_overrides(merged(quick_train_keys() if args.quick else {}, read_config(args.config)), args.set)
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
        source = config_source(e.path, args.set, flags, args.config)
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
    if r.get("rank", 0) != 0:   # under torchrun, rank 0 reports for all
        return 0
    ranks = f" on {r['ranks']} ranks" if r.get("ranks", 1) > 1 else ""
    again = ", none left to train this call" if r["stop"] == "steps" and r.get("steps_this_call") == 0 else ""
    print(f"trained {r['steps']} steps{ranks} in {r['seconds']:.1f} s ({r['steps_per_second']:.1f} steps/s, "
          f"stop: {r['stop']}{again}); "
          + (f"best {r['valid_horizon']}-step validation error {r['best_error']:.4g} at step {r['best_step']}"
             if r.get("valid_horizon") else "not validated (no valid split)") + f"; checkpoints in {r['out']}")
    return 0


def train_epilog() -> str:
    """``train --help``'s list of the keys ``--set`` takes, from TrainConfig's fields (each
    with its default, allowed values and the first sentence of its description)."""
    import json
    import textwrap

    from gnwarp.demo import quick_train_keys
    from gnwarp.files import jsonable
    from gnwarp.train import TrainConfig
    from gnwarp.validation import config_keys
    lines = ["On a CPU: --quick sets " + " ".join(flat(quick_train_keys(), "")) + ", or --set steps=2000 "
             "alone keeps the paper's model and shortens the run.",
             "", "config keys (a config file's keys, or --set KEY=VALUE; nested keys dotted):"]
    lines = textwrap.wrap(lines[0], 78) + lines[1:]
    keys = config_keys(TrainConfig)
    for key, default, allowed, doc in sorted(keys, key=lambda r: "." in r[0]):  # top-level keys first
        shown = default if isinstance(default, str) else json.dumps(jsonable(default))
        text = f"{key}={shown}: {allowed}" + (f"; {doc}" if doc else "")
        lines += textwrap.wrap(text, 78, initial_indent="  ", subsequent_indent="      ")
    return "\n".join(lines)


def add_train(sub, full: bool) -> None:
    """The train command on ``sub``; ``full``: with its config-key list and system-ID options
    (which import the training stack: only when train is the command, or for the whole parser)."""
    t = sub.add_parser("train", help="train a forward model (config file plus --set overrides)",
                       description=paragraphs(
                           "Train a forward model on dataset files. Settings come from the defaults (the "
                           "paper's model and schedule, sized for a GPU), then --quick, then a config file, "
                           "then --set KEY=VALUE; nested keys are dotted, e.g. --set model.core=mlp --set "
                           "model.gn.latent=64. Every value is validated, and the run folder checked, before "
                           "anything runs. Resumes from <out>/last when it exists.",
                           "Example: gnwarp train --data pendulum.h5 --quick -o runs/pendulum"),
                       epilog=train_epilog() if full else None)
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
    if full:
        from gnwarp.train.sysid_config import add_sysid_arguments
        add_sysid_arguments(t.add_argument_group("system identification (with --sysid; SysIDConfig and "
                                                 "SysIDTrainConfig fields)"))
    t.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    t.set_defaults(func=train_command)
