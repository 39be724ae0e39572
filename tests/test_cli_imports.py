"""The command line starts without the heavy stack: ``import gnwarp.cli`` and ``gnwarp --help``
load neither torch nor Warp nor MuJoCo(-Warp); each command imports what it needs when it runs."""
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("torch", "warp", "mujoco", "mujoco_warp", "dm_control")


def _loaded(code: str) -> list[str]:
    """The heavy modules loaded after running ``code`` in a fresh interpreter."""
    probe = f"{code}\nimport sys\nprint(' '.join(m for m in {HEAVY!r} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True, timeout=120,
                         env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr
    return out.stdout.split("\n")[-2].split()


def test_import_cli_and_top_level_help_load_no_heavy_module():
    assert _loaded("import gnwarp.cli") == []
    assert _loaded("import gnwarp") == []
    help_code = ("import contextlib, io\nfrom gnwarp.cli import main\n"
                 "for argv in (['--help'], ['mpc', '--help'], ['generate', '--help'], ['systems', '--help']):\n"
                 "    with contextlib.redirect_stdout(io.StringIO()):\n"
                 "        try:\n            main(argv)\n        except SystemExit:\n            pass")
    assert _loaded(help_code) == []


def test_lazy_public_names_resolve():
    import gnwarp
    from gnwarp.gn import GraphNetwork
    from gnwarp.gn.options import IMPLS
    from gnwarp.cli import IMPLS as CLI_IMPLS
    assert CLI_IMPLS == IMPLS  # the command line's copy of the implementations' names
    from gnwarp.cli.mpc import PLANNERS as CLI_PLANNERS
    from gnwarp.control.planner import MODEL_PLANNERS
    assert CLI_PLANNERS == MODEL_PLANNERS  # and of the planners through a model
    assert gnwarp.GraphNetwork is GraphNetwork
    assert gnwarp.systems.names() and gnwarp.data.__name__ == "gnwarp.data"
    assert set(gnwarp.__all__) <= set(dir(gnwarp))
    import pytest
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        gnwarp.nope


def test_train_help_still_lists_config_keys_and_sysid_options(capsys):
    from gnwarp.cli import build_parser, main
    import pytest
    with pytest.raises(SystemExit):
        main(["train", "--help"])
    text = capsys.readouterr().out
    assert "steps=100000" in text and "--sysid" in text and "system identification" in text
    assert "system identification" not in build_parser("mpc").format_help()


def test_python_m_gnwarp_runs_the_command():
    """``python -m gnwarp`` is the ``gnwarp`` command (its help and exit codes)."""
    env = {"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"}
    out = subprocess.run([sys.executable, "-m", "gnwarp", "--help"], cwd=ROOT, capture_output=True, text=True,
                         timeout=120, env=env)
    assert out.returncode == 0 and "usage: gnwarp" in out.stdout, out.stderr
    bad = subprocess.run([sys.executable, "-m", "gnwarp", "no-such-command"], cwd=ROOT, capture_output=True,
                         text=True, timeout=120, env=env)
    assert bad.returncode == 2 and "no-such-command" in bad.stderr
