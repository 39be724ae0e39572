"""bench/rl_agents.py at CPU size: a row per agent, with the compiled losses timed beside the
eager updates (torch.compile's "aot_eager": no compiler needed)."""
import json

import pytest

from bench import rl_agents


def test_quick_run_times_compiled_updates_beside_eager_ones(tmp_path, capsys):
    rl_agents.main(["--quick", "--agents", "ddpg,svg1", "--compile", "aot_eager", "--out", str(tmp_path)])
    (jsonl,) = tmp_path.glob("rl_agents_*_quick.jsonl")
    rows = [json.loads(x) for x in jsonl.read_text().splitlines()]
    assert [r["agent"] for r in rows] == ["ddpg", "svg1"]
    for r in rows:
        assert r["compile_backend"] == "aot_eager" and r["compiled_updates_per_s"] > 0
        assert r["first_compiled_s"] > 0 and r["graph_updates_per_s"] is None   # no CUDA graph on a CPU
        ratio = r["compiled_updates_per_s"] / r["updater_updates_per_s"]   # against the uncaptured Updater
        assert r["compiled_speedup"] == pytest.approx(ratio, abs=0.02)
    md = jsonl.with_suffix(".md").read_text()
    assert "compiled losses" in md and 'compile_update("aot_eager")' in md
