"""The scripts of examples/ run at small sizes on a CPU (so they never rot)."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SMALL = {
    "quickstart.py": ["--sequences", "20", "--steps", "10"],
    "own_mjcf.py": ["--sequences", "20", "--steps", "5"],
    "system_id.py": ["--sequences", "16", "--steps", "10"],
    "mpc.py": ["--steps", "10", "--episodes", "2", "--control-steps", "3"],
}


def test_every_example_is_tested():
    assert sorted(p.name for p in (ROOT / "examples").glob("*.py")) == sorted(SMALL)


@pytest.mark.parametrize("script", sorted(SMALL))
def test_example_runs(script, tmp_path):
    env = dict(os.environ, CUDA_VISIBLE_DEVICES="")
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    r = subprocess.run([sys.executable, str(ROOT / "examples" / script), "--out", str(tmp_path / "out"),
                        *SMALL[script]], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, f"{script} exited {r.returncode}:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    assert r.stdout.strip(), f"{script} printed nothing"
