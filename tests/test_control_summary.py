"""bench/control_summary.py: summary.json rows from control records (intervals, protocols, pairing)."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import control_summary as cs  # noqa: E402
from gnwarp.eval.records import ResultRecord, write_records  # noqa: E402


def _rec(planner, returns, seed=0, experiment="control", dynamics=None, env_steps=0, task="cheetah-forward"):
    dyn = dynamics or {"ilqg": "true_mujoco_c", "random": "none"}.get(planner, "learned")
    return ResultRecord(experiment=experiment, task=task, planner=planner, dynamics=dyn, episodes=len(returns),
                        episode_steps=10, returns=list(map(float, returns)), seed=seed, env_steps=env_steps)


def test_bootstrap_interval_covers_the_mean_and_narrows_with_more_values():
    rng = np.random.default_rng(1)
    small, large = rng.normal(5, 1, 10), rng.normal(5, 1, 1000)
    lo, hi = cs.bootstrap_ci(small)
    assert lo < small.mean() < hi
    lo2, hi2 = cs.bootstrap_ci(large)
    assert hi2 - lo2 < (hi - lo) / 3
    with pytest.raises(ValueError, match="two finite"):
        cs.bootstrap_ci([1.0])


def test_rows_seeds_protocols_and_paired_comparisons(tmp_path):
    folder = tmp_path / cs.CONTROL
    folder.mkdir(parents=True)
    ilqg = [10.0, 12, 11, 13, 9, 10]
    write_records(folder / "results.jsonl", [
        _rec("ilqg", ilqg), _rec("random", [0.0, 1, -1, 0.5, 0, 0.2]),
        _rec("gradient", [x - 1 for x in ilqg]),                  # 1 below iLQG on every initial state
        _rec("gradient", [3.0, 4, 5], seed=1, experiment="loop", env_steps=600),
        _rec("gradient", [5.0, 6, 7], seed=2, experiment="loop", env_steps=600)])
    rows = cs.rows(tmp_path)
    by = {(r["planner"], r["protocol"]): r for r in rows}
    paper = by[("gradient", "paper")]
    assert paper["over"] == "episodes" and paper["seeds"] == 1
    assert paper["minus_ilqg_ci95"] == [-1.0, -1.0]                # paired: the constant difference
    assert paper["discriminative"] is True
    loop = by[("gradient", "loop")]
    assert loop["seeds"] == 2 and loop["episodes"] == 6 and loop["over"] == "seeds" and loop["env_steps"] == 600
    assert loop["mean"] == pytest.approx(5.0)
    assert loop["ci95"][0] == pytest.approx(4.0) and loop["ci95"][1] == pytest.approx(6.0)   # the two seed means
    assert "minus_ilqg_ci95" not in loop                          # other seeds: no pairing


def test_not_discriminative_where_ilqg_is_no_better_than_random(tmp_path):
    folder = tmp_path / cs.CONTROL
    folder.mkdir(parents=True)
    same = [1.0, -1, 2, -2, 0.5, -0.5]
    write_records(folder / "r.jsonl", [_rec("ilqg", same), _rec("random", same[::-1]), _rec("gradient", same)])
    row = next(r for r in cs.rows(tmp_path) if r["planner"] == "gradient")
    assert row["discriminative"] is False


def test_committed_summary_is_current():
    assert cs.main(["--check"]) == 0, "bench/results/control/summary.json differs: run bench/control_summary.py"
    rows = json.loads((ROOT / cs.CONTROL / "summary.json").read_text())
    need = {"task", "planner", "dynamics", "protocol", "env_steps", "seeds", "episodes", "mean", "ci95"}
    assert rows and all(need <= set(r) for r in rows)


def test_a_diverged_episode_is_named_not_summarized(tmp_path):
    folder = tmp_path / cs.CONTROL
    folder.mkdir(parents=True)
    write_records(folder / "results.jsonl", [_rec("gradient", [1.0, float("nan"), 2.0], seed=3)])
    with pytest.raises(ValueError, match=r"results\.jsonl: cheetah-forward / gradient / learned: the returns of "
                                         r"seed\(s\) \[3\] hold NaN"):
        cs.rows(tmp_path)


def test_loop_value_and_ensemble_rows_do_not_pool(tmp_path):
    folder = tmp_path / cs.CONTROL
    folder.mkdir(parents=True)
    recs = []
    for value, ensemble, rets in ((None, 1, [1.0, 2.0]), ({"gamma": 0.99}, 1, [5.0, 6.0]), (None, 2, [9.0, 9.5])):
        r = _rec("sampling", rets, experiment="loop", env_steps=100)
        r.variant, r.config = "loop", {"protocol": "loop", "loop": {"value": value, "ensemble": ensemble}}
        recs.append(r)
    write_records(folder / "records.jsonl", recs)
    got = {r["variant"]: r["mean"] for r in cs.rows(tmp_path)}
    assert got == {"loop": 1.5, "loop, terminal value": 5.5, "loop, ensemble of 2": 9.25}


def test_pairing_stays_within_the_protocol_and_prefers_ilqg_on_mujoco_c(tmp_path, capsys):
    """A loop row pairs with the loop's iLQG / random records, not the paper protocol's of the
    same task and episode length; of iLQG on two dynamics, the true MuJoCo C one pairs; a file
    of no results records is named on stderr."""
    folder = tmp_path / cs.CONTROL
    folder.mkdir(parents=True)
    base = [10.0, 12, 11, 13, 9, 10]
    write_records(folder / "results.jsonl", [
        _rec("ilqg", [x + 5 for x in base], dynamics="true_mjwarp"),   # listed first, not preferred
        _rec("ilqg", base), _rec("random", [0.0, 1, -1, 0.5, 0, 0.2]),
        _rec("gradient", [x - 1 for x in base]),
        _rec("gradient", [x - 2 for x in base], experiment="loop", env_steps=600),
        _rec("ilqg", [x - 4 for x in base], experiment="loop"),
        _rec("random", [x - 4 for x in base], experiment="loop")])
    (folder / "timings.jsonl").write_text('{"batch": 8, "ms": 1.5}\n')
    rows = cs.rows(tmp_path)
    assert "skipped " + str(Path(cs.CONTROL) / "timings.jsonl") in capsys.readouterr().err
    by = {(r["planner"], r["protocol"], r["dynamics"]): r for r in rows}
    assert by[("gradient", "paper", "learned")]["minus_ilqg_ci95"] == [-1.0, -1.0]     # MuJoCo C's iLQG
    assert by[("gradient", "paper", "learned")]["discriminative"] is True
    loop = by[("gradient", "loop", "learned")]
    assert loop["minus_ilqg_ci95"] == [2.0, 2.0]                                       # the loop's iLQG
    assert loop["discriminative"] is False                                             # its iLQG = its random
