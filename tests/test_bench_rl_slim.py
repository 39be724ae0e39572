"""bench/rl_slim.py: a slim copy measured beside its run's checkpoint (CPU, tiny)."""
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench import rl_slim  # noqa: E402


def test_slim_copy_is_smaller_and_rebuilds(tmp_path):
    rl_slim.main(["--quick", "--out", str(tmp_path)])
    (jsonl,) = tmp_path.glob("rl_slim_*_quick.jsonl")
    (row,) = [json.loads(line) for line in jsonl.read_text().splitlines()]
    assert row["task"] == "pendulum-balance" and row["transitions"] == 3 * 2 * 10
    assert 0 < row["slim_mb"] < row["full_mb"] and row["slim_mb_at_1m"] < row["full_mb_at_1m"]
    assert row["rebuild_steps_per_s"] > 0
    assert "| pendulum-balance | 60 |" in jsonl.with_suffix(".md").read_text()
