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

from gnwarp.cli.common import IMPLS, Help
from gnwarp.cli.data import add_check, add_generate, add_systems
from gnwarp.cli.evaluate import add_demo, add_evaluate
from gnwarp.cli.mpc import add_mpc
from gnwarp.cli.rl import add_rl
from gnwarp.cli.train import add_train

# each command's module imports what the command needs inside its function, so --help loads
# neither torch nor Warp
__all__ = ["main", "build_parser", "IMPLS"]


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The command line's parser. ``command``: the command about to run; the train command's
    config-key list and system-ID options (which import the training stack) and the loop and rl
    commands' flags (LoopConfig's, RLConfig's) are added only for that command or for None (every
    command in full)."""
    p = argparse.ArgumentParser(prog="gnwarp", description=__doc__, formatter_class=Help)
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    add_systems(sub)
    add_generate(sub)
    add_train(sub, full=command in (None, "train"))
    add_evaluate(sub)
    add_demo(sub)
    add_check(sub)
    add_mpc(sub)
    lp = sub.add_parser("loop", help="the data loop: plan on the true simulator, add the data, train on, repeat")
    if command in (None, "loop"):   # its flags are LoopConfig's, whose module loads torch
        import gnwarp.rl.planner  # noqa: F401 - registers planner "policy" (a trained gnwarp rl agent)
        from gnwarp.control.loop_command import add_loop_arguments
        add_loop_arguments(lp)
    add_rl(sub, full=command in (None, "rl"))   # its flags are RLConfig's
    for name, action in sub.choices.items():  # every command: its defaults shown, a description
        action.formatter_class = Help
        action.description = action.description or next(a.help for a in sub._choices_actions if a.dest == name)
    return p


def command_of(argv: list[str]) -> str:
    """The command named in ``argv`` (its first word not starting with "-"), or "" for none."""
    return next((a for a in argv if not a.startswith("-")), "")


# commands that split their work over torchrun's ranks; the others run in one process
RANKED = ("generate", "train", "mpc", "loop")
ONE_PROCESS_HINTS = {"rl": "; several seeds over ranks: torchrun --nproc_per_node N bench/rl_seeds.py --seeds 0-5 ..."}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser(command_of(argv)).parse_args(argv)
    from gnwarp.distributed import launched
    if launched() and args.command not in RANKED:   # every rank would do the same work, write the same files
        print(f"gnwarp {args.command}: error: runs in one process, not under torchrun (under torchrun: "
              f"{', '.join(RANKED)}; docs/distributed.md){ONE_PROCESS_HINTS.get(args.command, '')}", file=sys.stderr)
        return 2
    from gnwarp.distributed import DistributedError, close
    try:
        code = args.func(args)
    except (ValueError, OSError, FloatingPointError, RuntimeError, TypeError) as e:
        print(f"gnwarp {args.command}: error: {e}", file=sys.stderr)
        if not isinstance(e, DistributedError):   # a broken group is left as it is
            close()
        return 2
    close(sync=True)   # under torchrun: leave the process group before exit (else gloo may abort the process)
    return code


if __name__ == "__main__":
    sys.exit(main())
