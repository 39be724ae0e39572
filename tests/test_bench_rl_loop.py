"""bench/rl_loop.py: both ways of the loop timed in one process, their rows and table (CPU, tiny)."""
from __future__ import annotations

import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import rl_loop  # noqa: E402


def test_both_ways_timed_with_the_same_schedule(tmp_path):
    rl_loop.main(["--quick", "--profile", "--out", str(tmp_path)])
    (jsonl,) = tmp_path.glob("rl_loop_*_quick.jsonl")
    rows = [json.loads(line) for line in jsonl.read_text().splitlines()]
    assert [r["way"] for r in rows] == ["in turn", "ahead"] and [r["act_ahead"] for r in rows] == [False, True]
    assert all(r["env_steps_per_s"] > 0 and len(r["env_steps_per_s_each"]) == r["reps"] == 1 for r in rows)
    # the same updates a repetition either way: updates / s over env steps / s is the schedule's ratio
    ratios = {round(r["updates_per_s"] / r["env_steps_per_s"], 6) for r in rows}
    assert ratios == {1.0}
    assert {r["torch_compile"] for r in rows} == {"none"}   # "auto" on the CPU: eager
    assert rows[0]["ahead_over_in_turn"] == round(rows[1]["env_steps_per_s"] / rows[0]["env_steps_per_s"], 3)
    md = jsonl.with_suffix(".md").read_text()
    assert "ahead / in turn" in md and md.count("| pendulum-balance |") == 1
    # the table holds every run of the file: a second run's line beside the first, --summarize alike
    with jsonl.open("a") as f:   # another simulator, then the same settings again: each a line, whole
        for r in rows:
            f.write(json.dumps({**r, "backend": "mujoco_warp", "env_steps_per_s": 2 * r["env_steps_per_s"]}) + "\n")
        for r in rows:
            f.write(json.dumps(r) + "\n")
    rl_loop.main(["--summarize", str(jsonl)])
    lines = [ln for ln in jsonl.with_suffix(".md").read_text().splitlines() if "| pendulum-balance |" in ln]
    assert [ln.split(" | ")[3] for ln in lines] == ["2 on mujoco", "2 on mujoco_warp", "2 on mujoco"], lines
    assert lines[0] == lines[2] and " - " not in lines[2], lines
    ratio = rows[1]["env_steps_per_s"] / rows[0]["env_steps_per_s"]
    assert all(f"**{ratio:.2f}x**" in ln for ln in lines), lines
    # --profile: each way's operator table, the loop's named ranges (act, env step, store, updates) in it,
    # switched on for the profiled repetition only
    from gnwarp.rl import loop
    assert loop.PROFILE_RANGES is False
    for way in ("in_turn", "ahead"):
        (prof,) = tmp_path.glob(f"rl_loop_profile_*_{way}.txt")
        text = prof.read_text()
        assert text.startswith("3 vector steps of 2 envs in ") and all(
            f"rl.{part}" in text for part in ("act", "env_step", "store", "updates")), text[:400]


def test_device_ops_counts_kernels_an_update_but_not_the_loops_ranges():
    from types import SimpleNamespace

    from torch.autograd import DeviceType
    cuda, cpu = DeviceType.CUDA, DeviceType.CPU
    table = [SimpleNamespace(key="rl.updates", device_type=cuda, count=10, self_device_time_total=9e6),
             SimpleNamespace(key="sgemm", device_type=cuda, count=40, self_device_time_total=400.0),
             SimpleNamespace(key="elementwise", device_type=cuda, count=160, self_device_time_total=200.0),
             SimpleNamespace(key="aten::mul", device_type=cpu, count=500, self_device_time_total=0.0)]
    line = rl_loop.device_ops(table, updates=10)
    assert line == ("device operations: 200 (20 an update), 0.6 ms of device time "
                    "(3.00 us each, 0.060 ms an update)"), line
    assert rl_loop.device_ops(table[:1], updates=10) == "no device operations recorded"
