"""``gnwarp rl``: a reinforcement-learning run (``gnwarp.rl.run.run_rl``) from the command line.

Its flags are made from ``RLConfig``'s fields; further agent settings come from a JSON file or
``--set agent_settings.gamma=0.98``. A folder that holds a run is resumed with its own
config.json underneath (``--chunk`` and ``--budget-seconds`` bind only the call that gives them).
"""
from __future__ import annotations

import json
import textwrap
from pathlib import Path

__all__ = ["add_rl", "rl_command", "RL_DESCRIPTION"]

RL_DESCRIPTION = (
    "Train an agent (ddpg, svg0, svg1 .. svg5) off-policy on a task of the true simulator, in the folder -o, "
    "which it resumes: a progress bar with returns, rate and ETA; progress.csv (a row per round of num_envs "
    "episodes; TensorBoard in tb/ where it imports); records.jsonl (an evaluation record of eval_episodes "
    "deterministic-policy episodes before training, every eval_every env steps and at the end); checkpoint.pt. "
    "A call stops at whole episodes (--chunk env steps, --budget-seconds), so a resumed run equals an "
    "uninterrupted one. Example: gnwarp rl --agent svg1 --task swimmer6 -o runs/rl/svg1-s0 --seed 0 "
    "--budget-seconds 540 (run it again to go on); docs/rl.md.")
# per-call limits: never read back from a resumed folder's config
_PER_CALL = ("chunk", "budget_seconds")
_WIDTHS = ("hidden", "model_hidden")


def add_rl(sub, full: bool = True) -> None:
    """The rl command on the subparsers ``sub``; its RLConfig flags only with ``full`` (their
    module is read only when the command runs or its help is asked for)."""
    p = sub.add_parser("rl", help="reinforcement learning: DDPG, SVG(0), SVG(N) through a model trained alongside")
    if not full:
        return
    from gnwarp.rl.config import RLConfig
    from gnwarp.validation import add_config_flags, flag_name
    p.description = textwrap.fill(RL_DESCRIPTION, 78)
    p.add_argument("config", nargs="?", help="JSON file of RLConfig keys (default: none)")
    p.add_argument("-o", "--out", help="the run folder (default: runs/rl); resumed where it holds a run")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="set a config key, agent settings dotted (agent_settings.gamma=0.98); values parsed as "
                        "JSON when they parse (repeatable; default: none)")
    add_config_flags(p, RLConfig, _flagged(RLConfig))
    for name in _WIDTHS:
        p.add_argument(flag_name(name), dest=name, type=_widths, metavar="W,W",
                       help=f"{RLConfig.__dataclass_fields__[name].metadata['help']}, comma-separated (default: unset)")
    p.add_argument("--no-tensorboard", dest="tensorboard", action="store_false", default=None,
                   help="no TensorBoard logs (default: written where torch.utils.tensorboard imports)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.add_argument("--slim", metavar="DEST", help="train nothing: write a resumable copy of the run in -o without "
                   "its replay buffer's transitions (its actions and their digest; rebuilt by re-simulating them "
                   "when DEST resumes) into the new folder DEST: the run moved in MBs (gnwarp.rl.slim; training flags "
                   "are refused beside it: give them when DEST resumes; default: train)")
    p.set_defaults(func=rl_command)


def _flagged(cls) -> list[str]:
    return [n for n in cls.__dataclass_fields__ if n not in ("out", "progress", "agent_settings", "tensorboard")
            + _WIDTHS]


def _widths(text: str) -> list[int]:
    """Layer widths from "256,256" (argparse's type)."""
    import argparse
    try:
        w = [int(x) for x in text.replace(" ", "").split(",") if x]
    except ValueError:
        w = []
    if not w or min(w) < 1:
        raise argparse.ArgumentTypeError(f"must be comma-separated widths >= 1 such as 256,256, got {text!r}")
    return w


def _read(path: Path) -> dict:
    from gnwarp.validation import ConfigError
    if not path.is_file():
        raise FileNotFoundError(f"no config file at {path}")
    try:
        d = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ConfigError(str(path), f"not valid JSON: {e.msg} (line {e.lineno})") from None
    if not isinstance(d, dict):
        raise ConfigError(str(path), f"a config file holds a table of RLConfig keys, got a {type(d).__name__}")
    return d


def _set(d: dict, item: str) -> None:
    from gnwarp.validation import ConfigError
    if "=" not in item:
        raise ConfigError("--set", f"expects KEY=VALUE, got {item!r}")
    key, text = item.split("=", 1)
    *parents, leaf = key.strip().split(".")
    if not all(k.strip() for k in parents + [leaf]):
        raise ConfigError("--set", f"malformed key {key!r} (keys are dotted names: agent_settings.gamma)")
    try:
        value = json.loads(text)
    except json.JSONDecodeError:
        value = text
    for k in parents:
        d = d.setdefault(k, {})
        if not isinstance(d, dict):
            raise ConfigError("--set", f"{key}: {k} is not a nested table")
    d[leaf] = value


def _out(args) -> str:
    """The run folder of a ``gnwarp rl`` call: -o, else the config file's ``out``, else runs/rl."""
    return args.out or (_read(Path(args.config)).get("out") if args.config else None) or "runs/rl"


def rl_config(args):
    """The ``RLConfig`` of a ``gnwarp rl`` call: the folder's config.json (a resumed run, less its
    per-call limits), then the config file, ``--set`` and the flags on top."""
    from gnwarp.rl.config import CONFIG_FILE, RLConfig
    from gnwarp.validation import config_flags_given
    out = _out(args)
    saved = Path(out) / CONFIG_FILE
    raw = {k: v for k, v in _read(saved).items() if k not in _PER_CALL} if saved.is_file() else {}
    if args.config:
        raw.update(_read(Path(args.config)))
    for item in args.set:
        _set(raw, item)
    raw.update(config_flags_given(args, RLConfig, _flagged(RLConfig)))
    raw.update({k: getattr(args, k) for k in _WIDTHS + ("tensorboard",) if getattr(args, k) is not None})
    raw["out"] = str(out)
    raw["progress"] = not args.quiet
    return RLConfig.from_dict(raw)


def rl_command(args) -> int:
    """Run ``gnwarp rl``; prints where it stopped and the last evaluation (``--slim``: writes the
    run's slim copy instead)."""
    if args.slim:
        from gnwarp.rl.config import RLConfig
        from gnwarp.rl.slim import slim_run
        from gnwarp.validation import ConfigError, config_flags_given, flag_name
        ignored = [flag_name(k) for k in config_flags_given(args, RLConfig, _flagged(RLConfig))]
        ignored += [flag_name(k) for k in _WIDTHS if getattr(args, k) is not None]
        ignored += ["--no-tensorboard"] * (args.tensorboard is not None) + ["--set"] * bool(args.set)
        if ignored:
            raise ConfigError("--slim", f"copies the run as it is and trains nothing, so {', '.join(ignored)} "
                                        "would be ignored: give them when the copy resumes (gnwarp rl -o DEST ...)")
        run = Path(_out(args))
        dest = slim_run(run, args.slim)
        size = sum(f.stat().st_size for f in Path(dest).iterdir() if f.is_file())
        print(f"wrote {dest}: the run in {run} without its replay buffer's transitions ({size / 2**20:.1f} MiB); "
              f"gnwarp rl -o {dest} rebuilds them and trains on")
        return 0
    cfg = rl_config(args)
    from gnwarp.rl.run import run_rl
    r = run_rl(cfg)
    ev = r["last_eval"]
    last = f"; last evaluation: median return {sorted(ev)[len(ev) // 2]:.1f} of {len(ev)} episodes" if ev else ""
    print(f"{r['env_steps']} of {cfg.env_steps} env steps ({r['stop']}), {r['updates']} updates, "
          f"{r['seconds']:.1f} s this call{last}; records in {r['records']}")
    if r["stop"] != "done":
        print(f"stopped by --{'budget-seconds' if r['stop'] == 'budget' else 'chunk'}: run again to go on")
    return 0
