"""bench/mpc_latency.py on the CPU at tiny sizes: one configuration measured in a fresh process,
its record, and the summary JSON and README generated from the records (not typed)."""
import json

import numpy as np
import pytest

from bench import mpc_latency as ml
from gnwarp.eval.records import read_records, write_records

ARGS = ["--quick", "--systems", "pendulum", "--configs", "1x3x1", "--paths", "torch_graph", "--steps", "3",
        "--cold", "none"]


def test_quick_run_records_and_summary_follow_the_records(tmp_path, capsys):
    out = tmp_path / "mpc_latency"
    assert ml.main(ARGS + ["--out", str(out)]) == 0
    (rec_file,) = out.glob("mpc_latency_*.jsonl")
    (rec,) = read_records(rec_file)
    m = rec.metrics
    assert "error" not in rec.config, rec.config
    assert (rec.system, rec.episodes, rec.config["horizon"], rec.config["iterations"], rec.config["path"]) == (
        "pendulum", 1, 3, 1, "torch_graph")
    assert m["model_evals_per_step"] == 3 and m["measured_evals_per_step"] == 3   # every step ran 1 x 3
    assert len(m["plan_ms"]) == 4 and m["first_step_ms"] == pytest.approx(m["plan_ms"][0])
    assert m["steady_ms"] == pytest.approx(float(np.median(m["plan_ms"][3:])))       # after the first three
    assert m["real_time_factor"] == pytest.approx(20.0 / m["steady_ms"])
    (summary,) = tmp_path.glob("mpc_latency_*.json")
    (row,) = json.loads(summary.read_text())
    assert set(ml.ROW_KEYS) <= set(row) and row["path"] == "torch_graph" and row["gpu"] == rec.gpu
    assert row["steady_ms"] == pytest.approx(m["steady_ms"], rel=1e-3)
    assert row["model_step_us"] == pytest.approx(1e3 * m["steady_ms"] / 3, rel=1e-3)
    assert row["first_step_cold_ms"] is None and row["control_dt_ms"] == pytest.approx(20.0)

    assert rec.config["precision"] == row["precision"] == "fp32"   # TF32 runs as IEEE fp32 off CUDA

    # change the record, regenerate: the JSON and the README follow it
    d = json.loads(rec_file.read_text().splitlines()[0])
    d["metrics"].update(steady_ms=123.0, model_step_us=41000.0)
    rec_file.write_text(json.dumps(d) + "\n")
    assert ml.main(["--summarize", "--out", str(out)]) == 0
    (row2,) = json.loads(summary.read_text())
    assert row2["steady_ms"] == 123.0 != row["steady_ms"] and row2["model_step_us"] == 41000.0
    assert "| pendulum | 1 | 3 | 1 | torch_graph | fp32 |" in (out / "README.md").read_text()
    # a record of another precision is a row of its own; one without the field reads as fp32
    d2 = dict(d, config=dict(d["config"], precision="tf32"), metrics=dict(d["metrics"], steady_ms=7.0))
    d["config"].pop("precision")
    rec_file.write_text(json.dumps(d) + "\n" + json.dumps(d2) + "\n")
    assert ml.main(["--summarize", "--out", str(out)]) == 0
    rows = {r["precision"]: r["steady_ms"] for r in json.loads(summary.read_text())}
    assert rows == {"fp32": 123.0, "tf32": 7.0}
    rec_file.write_text(json.dumps(dict(d, config=dict(d["config"], precision="fp32"))) + "\n")

    # resume: the recorded configuration is skipped
    capsys.readouterr()
    assert ml.main(ARGS + ["--out", str(out)]) == 0
    assert "recorded, skipped" in capsys.readouterr().out and len(read_records(rec_file)) == 1


def test_rows_keep_the_latest_record_and_errors(tmp_path):
    warm = {"first_step_ms": 900.0, "steady_ms": 20.0, "model_step_us": 80.0, "model_evals_per_step": 250,
            "real_time_factor": 1.0, "episode_steps_per_s": 50.0}
    a = ml.make_record("pendulum", 1, 50, 5, "unfused", "GPU X", warm, {"first_step_ms": 5000.0}, 30, False, "default")
    b = ml.make_record("pendulum", 1, 50, 5, "unfused", "GPU X", {**warm, "steady_ms": 10.0}, None, 30, False,
                       "default", "none")
    c = ml.make_record("cheetah", 1, 50, 5, "torch_compile", "GPU X", {"error": "BackendCompilerFailed: x"},
                       {"first_step_ms": 1.0}, 30, False, "default")
    write_records(tmp_path / "mpc_latency_gpu-x.jsonl", [a, b, c])
    rows = ml.summary_rows(read_records(tmp_path / "mpc_latency_gpu-x.jsonl"))
    assert [(r["system"], r["path"]) for r in rows] == [("pendulum", "unfused"), ("cheetah", "torch_compile")]
    assert rows[0]["steady_ms"] == 10.0 and rows[0]["first_step_cold_ms"] is None   # the latest record
    assert rows[1]["steady_ms"] is None and "BackendCompilerFailed" in rows[1]["error"]
    assert "error: warm: BackendCompilerFailed" in ml.markdown(rows)
    assert ml.parse_configs("1x50x5, 16x50x5") == [(1, 50, 5), (16, 50, 5)]
    with pytest.raises(ValueError, match="EPISODESxHORIZONxITERATIONS"):
        ml.parse_configs("1x50")


def test_quick_is_a_small_grid_and_the_full_one_the_default():
    """--quick without grid flags is a smoke test (pendulum, the Warp paths, no cold process: well
    under a minute on a CPU), not the whole grid of 100 processes; given flags are kept."""
    from types import SimpleNamespace
    a = SimpleNamespace(quick=True, systems=None, paths=None, cold=None)
    ml.resolve_defaults(a)
    assert (a.systems, a.paths, a.cold) == ("pendulum", "unfused,fused", "none")
    a = SimpleNamespace(quick=False, systems=None, paths=None, cold=None)
    ml.resolve_defaults(a)
    assert (a.systems.split(","), a.paths.split(","), a.cold) == (list(ml.TASKS), list(ml.PATHS), "all")
    a = SimpleNamespace(quick=True, systems="cheetah", paths="torch_graph", cold="once")
    ml.resolve_defaults(a)
    assert (a.systems, a.paths, a.cold) == ("cheetah", "torch_graph", "once")
