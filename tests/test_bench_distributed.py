"""bench/distributed.py's summary: the time to error read from validation curves (no GPU, no ranks)."""
import argparse
import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import distributed as bd  # noqa: E402


def row(run, gpus, curve, step_ms):
    return {"gpus": gpus, "mode": "weak", "per_gpu_batch": 200, "train_graphs_per_s": 200 * gpus / step_ms * 1e3,
            "gpu": "X", "nccl": None, "run": run, "step_ms": step_ms, "tte_curve": curve}


def curve(times, errors):
    return [[t, i, e] for i, (t, e) in enumerate(zip(times, errors))]


def summarize(tmp_path, records, run_id, target):
    rec = tmp_path / "rec.jsonl"
    rec.write_text("".join(json.dumps(r) + "\n" for r in records))
    out = tmp_path / "sum.json"
    a = argparse.Namespace(records=str(rec), run_id=run_id, summary=str(out),
                           tte_window=3, tte_target=target)
    bd.summarize(a)
    return json.loads(out.read_text())


def test_moving_median_and_time_to_error_with_either_target(tmp_path):
    t, e = bd.smoothed(curve([1, 2, 3, 4], [4.0, 1.0, 3.0, 2.0]), 3)
    assert t == [1, 2, 3, 4] and e == [4.0, 2.5, 3.0, 2.0]
    one = row("r", 1, curve([10, 20, 30, 40], [0.9, 0.5, 0.3, 0.2]), 1.0)      # ends (smoothed) at 0.3
    two = row("r", 2, curve([5, 10, 15, 20], [0.8, 0.4, 0.35, 0.34]), 1.1)    # ends at 0.35: worse
    end = {x["gpus"]: x for x in summarize(tmp_path, [one, two], "r", "one_gpu_end")}
    assert end[1]["time_to_error_s"] == 40 and end[2]["time_to_error_s"] is None   # never reaches 0.3
    both = {x["gpus"]: x for x in summarize(tmp_path, [one, two], "r", "all_reach")}
    assert both[2]["target_smoothed_error"] == 0.35
    # smoothed: 1 GPU 0.9, 0.7, 0.5, 0.3 (reaches 0.35 at 40); 2 GPUs 0.8, 0.6, 0.4, 0.35 (at 20)
    assert both[1]["time_to_error_s"] == 40 and both[2]["time_to_error_s"] == 20
    assert both[2]["time_to_error_ratio"] == pytest.approx(0.5)
    assert both[2]["train_efficiency"] == pytest.approx(1 / 1.1)


def test_several_runs_in_one_summary_each_row_named(tmp_path):
    a = [row("a", 1, curve([1, 2], [0.5, 0.4]), 1.0), row("a", 2, curve([1, 2], [0.5, 0.3]), 1.0)]
    b = [row("b", 1, curve([1, 2], [0.5, 0.2]), 2.0)]
    out = summarize(tmp_path, a + b, "a,b", "all_reach")
    assert [(x["run"], x["gpus"]) for x in out] == [("a", 1), ("a", 2), ("b", 1)]
    assert out[2]["train_efficiency"] == 1.0 and out[1]["train_efficiency"] == pytest.approx(1.0)
    with pytest.raises(SystemExit, match="no rows of run 'c'"):
        summarize(tmp_path, a, "a,c", "all_reach")


def test_a_run_on_a_fixed_number_of_graphs_declares_its_own_target(tmp_path):
    one = row("r", 1, curve([10, 20, 30, 40], [0.9, 0.5, 0.3, 0.2]), 1.0)
    two = row("r", 2, curve([5, 10, 15, 20], [0.8, 0.4, 0.35, 0.34]), 1.1)
    old = {x["gpus"]: x for x in summarize(tmp_path, [one, two], "r", None)}   # a time-budget run: one GPU's end
    assert old[2]["tte_target"] == "one_gpu_end" and old[2]["time_to_error_s"] is None
    for x in (one, two):
        x["tte_protocol"] = {"samples_steps": 8}
    new = {x["gpus"]: x for x in summarize(tmp_path, [one, two], " r ", None)}
    assert new[2]["tte_target"] == "all_reach" and new[2]["time_to_error_s"] == 20
