"""``gnwarp loop``: the data loop from the command line (``gnwarp.control.data_loop``).

Its flags are made from ``LoopConfig``'s fields; nested settings (the planner's, the training's)
come from a JSON / TOML config file or ``--set planner_settings.iterations=10`` /
``--set train.model.gn.latent=64``. A folder that holds a loop is resumed with its own
config.json underneath: ``gnwarp loop -o runs/loop --iterations 20`` goes on to 20 iterations.
"""
from __future__ import annotations

from pathlib import Path

from gnwarp.control.data_loop import RESUMABLE, LoopConfig, run_loop
from gnwarp.control.loop_store import CONFIG_FILE
from gnwarp.validation import add_config_flags, apply_overrides, config_flags_given, read_config_file

__all__ = ["add_loop_arguments", "loop_command", "LOOP_DESCRIPTION", "PER_CALL"]

PER_CALL = ("chunk", "budget_seconds")   # limits of one call: not taken from a resumed folder's config.json

# the fields with a flag of their own (the nested tables go through a config file or --set)
_FLAGGED = [n for n in LoopConfig.__dataclass_fields__ if n not in ("out", "progress", "planner_settings", "train", "value")]

LOOP_DESCRIPTION = (
    "The data loop: plan with the learned model in closed loop on the true simulator (many episodes batched), "
    "add the visited transitions to the dataset, train on, plan again. Works in the folder -o, which it "
    "resumes: each iteration writes its data shard, checkpoint, a results record (records.jsonl: returns, "
    "env steps, the model's errors on the newly visited states before training on them and on its training "
    "data) and state.json, so a killed run goes on at its last finished step. Settings: LoopConfig's fields "
    "(below), a JSON / TOML config file, --set KEY=VALUE for nested keys (planner_settings.*, train.*). "
    "Example: gnwarp loop --task cheetah-run -o runs/loop --iterations 10 --budget-seconds 480 (run it again to "
    "go on); docs/data_loop.md has a CPU-sized one.")


def add_loop_arguments(parser) -> None:
    """The loop command's arguments on ``parser`` (its subparser), its description and its function."""
    import textwrap
    parser.description = textwrap.fill(LOOP_DESCRIPTION, 78)
    parser.add_argument("config", nargs="?", help="JSON or TOML file of LoopConfig keys (default: none)")
    parser.add_argument("-o", "--out", help="the loop folder (default: runs/loop); resumed where it holds a loop")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="set a config key, nested keys dotted (planner_settings.iterations=10, "
                             "train.model.gn.latent=64); values parsed as JSON when they parse (repeatable; "
                             "default: none)")
    add_config_flags(parser, LoopConfig, _FLAGGED)
    parser.add_argument("--no-plot", action="store_true", help="do not write <out>/loop.png")
    parser.add_argument("-q", "--quiet", action="store_true",
                        help="no progress bars (a line per iteration stays)")
    parser.set_defaults(func=loop_command)


def _read(path: str) -> dict:
    return read_config_file(path, "LoopConfig keys")


def loop_config(args) -> LoopConfig:
    """The config of a ``gnwarp loop`` call: the folder's config.json (a resumed loop, less its
    per-call limits ``PER_CALL``), then the config file, ``--set`` and the flags on top."""
    out = args.out or (_read(args.config).get("out") if args.config else None) or "runs/loop"
    saved = Path(out) / CONFIG_FILE
    raw = {k: v for k, v in _read(str(saved)).items() if k not in PER_CALL} if saved.is_file() else {}
    if args.config:
        raw.update(_read(args.config))
    apply_overrides(raw, args.set)
    raw.update(config_flags_given(args, LoopConfig, _FLAGGED))
    raw["out"] = str(out)
    raw["progress"] = not args.quiet
    return LoopConfig.from_dict(raw)


def loop_command(args) -> int:
    """Run ``gnwarp loop``; prints where it stopped and writes the plot."""
    cfg = loop_config(args)
    import logging
    logging.basicConfig(level=logging.INFO, format="%(message)s")   # a line per iteration, also with -q
    r = run_loop(cfg)
    from gnwarp.distributed import ranks
    if not ranks(cfg.device).main:   # under torchrun rank 0 prints and plots
        return 0
    line = (f"{r['iterations']} of {cfg.iterations} iterations finished ({r['stop']}), {r['env_steps']} env steps, "
            f"{r['train_steps']} training steps, {r['seconds']:.1f} s this call; records in {r['records']}")
    print(line)
    if not args.no_plot and r["iterations"] > 0:
        from gnwarp.control.loop_plots import plot_loop
        print(f"wrote {plot_loop(r['records'], Path(cfg.out) / 'loop.png')}")
    if r["stop"] in ("budget", "chunk"):
        print(f"stopped by --{'budget-seconds' if r['stop'] == 'budget' else 'chunk'}: run again to go on "
              f"({', '.join(RESUMABLE)} may change)")
    return 0
