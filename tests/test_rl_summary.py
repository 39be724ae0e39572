"""bench/rl_summary.py: summary.json rows and learning-curve plots from synthetic RL records."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import rl_summary as rs  # noqa: E402
from gnwarp.eval.records import ResultRecord, write_records  # noqa: E402


def _rec(agent, seed, env_steps, returns, preset="spinningup", networks="mlp", experiment="rl", utd=None,
         ahead=None, settings=None, dynamics="true_mjwarp", eval_seed=None):
    return ResultRecord(experiment=experiment, task="dmc-swimmer-swimmer6", planner="policy",
                        dynamics=dynamics, variant=f"{agent}/{preset}/{networks}", episodes=len(returns),
                        episode_steps=1000, returns=list(map(float, returns)), seed=seed, env_steps=env_steps,
                        config=dict(agent=agent, preset=preset, networks=networks)
                        | ({} if utd is None else {"utd": utd}) | ({} if eval_seed is None else {"eval_seed": eval_seed})
                        | ({} if ahead is None and settings is None else
                           {"agent_settings": ({} if ahead is None else {"act_ahead": ahead}) | (settings or {})}))


def test_point_statistics_against_numpy():
    v = [100.0, 300.0, 200.0, 400.0]
    p = rs.point(v)
    assert p["median"] == 250.0 and p["q25"] == 175.0 and p["q75"] == 325.0 and p["mean"] == 250.0
    assert p["se"] == pytest.approx(np.std(v, ddof=1) / 2)
    assert rs.point([5.0])["se"] is None
    with pytest.raises(ValueError, match="finite"):
        rs.point([])


def test_difference_is_welchs_interval():
    a, b = [400.0, 420.0, 380.0, 410.0], [100.0, 160.0, 90.0]
    d, lo, hi = rs.difference(a, b)
    va, vb = np.var(a, ddof=1) / 4, np.var(b, ddof=1) / 3
    df = (va + vb) ** 2 / (va ** 2 / 3 + vb ** 2 / 2)          # 2.6: t at 2 degrees of freedom
    assert 2 < df < 3 and d == pytest.approx(np.mean(a) - np.mean(b))
    assert (lo, hi) == pytest.approx((d - 4.302653 * np.sqrt(va + vb), d + 4.302653 * np.sqrt(va + vb)), rel=2e-4)
    assert lo > 0                      # separated runs: the interval excludes 0
    stats = pytest.importorskip("scipy.stats")
    wide = stats.ttest_ind(a, b, equal_var=False).confidence_interval()   # fractional df: a shade narrower
    assert lo <= wide.low and hi >= wide.high and hi - lo < 1.3 * (wide.high - wide.low)
    d, lo, hi = rs.difference(a, a)
    assert d == 0.0 and lo < 0 < hi    # a run against itself: it contains 0
    assert rs.difference([2.0, 2.0], [1.0, 1.0]) == (1.0, 1.0, 1.0)   # no spread: the difference itself
    with pytest.raises(ValueError, match="at least two finite values a side"):
        rs.difference([1.0], b)
    with pytest.raises(ValueError, match="at least two finite values a side"):
        rs.difference(a, [1.0, float("nan")])


def test_paired_difference_blocks_on_the_shared_seeds():
    a = {0: 300.0, 1: 150.0, 2: 420.0, 5: 999.0}
    b = {0: 280.0, 1: 128.0, 2: 402.0, 3: 0.0}
    d, lo, hi, seeds = rs.paired_difference(a, b)
    assert seeds == [0, 1, 2] and d == pytest.approx(20.0)     # seeds 3 and 5 have no partner
    half = 4.302653 * np.std([20.0, 22.0, 18.0], ddof=1) / np.sqrt(3)   # t at 2 degrees of freedom
    assert (lo, hi) == pytest.approx((20.0 - half, 20.0 + half), rel=2e-4) and lo > 0
    # the seeds' spread cancels: Welch's interval over the same numbers contains 0
    assert rs.difference([a[k] for k in seeds], [b[k] for k in seeds])[1] < 0
    with pytest.raises(ValueError, match="at least two shared seeds"):
        rs.paired_difference({0: 1.0, 1: 2.0}, {1: 1.0, 2: 2.0})
    with pytest.raises(ValueError, match="finite"):
        rs.paired_difference({0: 1.0, 1: float("nan")}, {0: 1.0, 1: 2.0})


def test_seed_means_keep_each_seeds_mean_and_episodes(tmp_path):
    folder = tmp_path / "rl"
    folder.mkdir()
    write_records(folder / "a.jsonl", [_rec("svg1", 0, 1000, [1, 3]), _rec("svg1", 1, 1000, [5, 7, 9]),
                                       _rec("svg1", 0, 1000, [10, 10])])   # a rerun of seed 0: the last stands
    by = rs.seed_means(tmp_path, Path("rl"))
    assert by == {("dmc-swimmer-swimmer6", "svg1", "spinningup", "mlp", 1.0, False, "", None, 1000): {0: (10.0, 2, "true_mjwarp", 0.0), 1: (7.0, 3, "true_mjwarp", 4.0 / 3)}}


def test_rows_group_seeds_per_point_and_skip_other_files(tmp_path):
    folder = tmp_path / rs.RL
    (folder / "svg1-s0").mkdir(parents=True)
    (folder / "svg1-s1").mkdir()
    write_records(folder / "svg1-s0" / "records.jsonl", [
        _rec("svg1", 0, 0, [1.0, 3.0]), _rec("svg1", 0, 1000, [10.0, 30.0]), _rec("svg1", 0, 1000, [40.0, 60.0])])
    write_records(folder / "svg1-s1" / "records.jsonl", [
        _rec("svg1", 1, 0, [5.0, 7.0, 9.0]), _rec("svg1", 1, 1000, [70.0, 90.0], dynamics="true_mujoco_c"),
        _rec("ddpg", 1, 1000, [1.0, 2.0]), _rec("svg1", 1, 1000, [1.0, 1.0], experiment="control"),
        _rec("svg1", 1, 1000, [200.0, 400.0], utd=3),    # another curve: 3 updates an env step
        _rec("svg1", 1, 1000, [500.0, 700.0], ahead=True),
        _rec("svg1", 1, 1000, [900.0, 900.0], settings={"squash_penalty": 1e-3, "seed": 1}),
        _rec("svg1", 0, 1000, [7.0, 7.0], ahead=False, settings={"squash_penalty": 0.0, "hidden": [256, 256]})])
    (folder / "rl_agents_gpu.jsonl").write_text(json.dumps({"agent": "ddpg", "updates_per_s": 200}) + "\n")
    assert rs.main(["--root", str(tmp_path)]) == 0
    summary = json.loads((folder / "summary.json").read_text())
    keys = {"task", "agent", "preset", "networks", "utd", "act_ahead", "settings", "env_steps", "seeds",
            "eval_episodes", "median", "q25", "q75", "mean", "se", "dynamics", "eval_seed"}
    assert all(set(r) == keys for r in summary)
    got = {(r["agent"], r["env_steps"]): r for r in summary
           if r["utd"] == 1 and not r["act_ahead"] and not r["settings"]}
    (tuned,) = [r for r in summary if r["settings"]]   # a setting off its default: a curve of its own
    assert tuned["settings"] == "squash_penalty=0.001" and tuned["mean"] == 900.0
    assert set(got) == {("ddpg", 1000), ("svg1", 0), ("svg1", 1000)}
    (more,) = [r for r in summary if r["utd"] == 3]
    assert more["agent"] == "svg1" and more["seeds"] == 1 and more["mean"] == 300.0 and not more["act_ahead"]
    (ahead,) = [r for r in summary if r["act_ahead"]]   # acting ahead: a curve of its own
    assert ahead["seeds"] == 1 and ahead["mean"] == 600.0 and ahead["utd"] == 1
    # seed 0's last record stands (act_ahead false and defaults said outright: the same curve as
    # unsaid; mean 7);
    # seed 1's mean 80; the control record is skipped
    late = got[("svg1", 1000)]
    assert late["seeds"] == 2 and late["eval_episodes"] == 2
    assert late["dynamics"] == ["true_mjwarp", "true_mujoco_c"]   # one curve, both simulators named
    assert got[("svg1", 0)]["dynamics"] == ["true_mjwarp"]
    assert late["mean"] == 43.5 and late["median"] == 43.5 and late["se"] == pytest.approx(36.5)
    assert got[("svg1", 0)]["eval_episodes"] == 2 and got[("svg1", 0)]["mean"] == 4.5
    assert got[("ddpg", 1000)]["se"] is None
    assert (folder / "learning_curves_dmc-swimmer-swimmer6.png").stat().st_size > 1000
    assert (folder / "learning_curves_dmc-swimmer-swimmer6_variants.png").stat().st_size > 1000   # utd 3, settings
    assert rs.main_curve(("svg1", "spinningup", "mlp", 1.0, True, "", None))             # acting ahead: main
    assert not rs.main_curve(("svg1", "spinningup", "mlp", 3.0, False, "", None))        # 3 updates a step
    assert not rs.main_curve(("svg1", "spinningup", "mlp", 1.0, True, "gamma=0.995", 2))
    assert not rs.main_curve(("svg2", "spinningup", "mlp", 1.0, False, "", None))
    assert rs.main(["--root", str(tmp_path), "--check"]) == 0
    write_records(folder / "svg1-s1" / "records.jsonl", [_rec("svg1", 2, 1000, [0.0, 0.0])])
    assert rs.main(["--root", str(tmp_path), "--check"]) == 1


def test_settings_tags_of_records_of_another_version():
    from gnwarp.rl.settings import settings_tag
    from gnwarp.validation import ConfigError
    assert settings_tag({"agent": "svg1", "preset": "spinningup", "hidden": [256, 256], "seed": 3}) == ""
    old = {"agent": "svg1", "preset": "spinningup", "retired_key": [1, "a"], "gamma": 0.9}
    with pytest.raises(ConfigError, match="retired_key"):
        settings_tag(old)
    assert settings_tag(old, strict=False) == "gamma=0.9,retired_key=1xa"   # tagged, not a crash
    assert settings_tag({"agent": "svg99", "gamma": 0.9}, strict=False) == "gamma=0.9"


def test_seed_lists_of_the_side_by_side_runner():
    from bench import rl_seeds
    assert rl_seeds.seeds_of("0-5") == [0, 1, 2, 3, 4, 5] and rl_seeds.seeds_of("0,2,7") == [0, 2, 7]
    for bad in ("", "1,1", "-1"):
        with pytest.raises(ValueError, match="seeds"):
            rl_seeds.seeds_of(bad)


def test_run_names_of_the_side_by_side_runner():
    from bench.rl_seeds import run_name
    base = dict(agent="svg1", preset="spinningup", networks="mlp")
    assert run_name(base) == "svg1-spinningup-mlp"
    assert run_name({**base, "utd": 3, "act_ahead": True}) == "svg1-spinningup-mlp-utd3-ahead"
    assert run_name({**base, "act_ahead": False, "utd": 1.0}) == "svg1-spinningup-mlp"
    assert run_name({**base, "act_ahead": True, "eval_seed": 0}) == "svg1-spinningup-mlp-ahead-eval0"
    with pytest.raises(ValueError, match="act_ahead=...: true or false, got 'yes'"):
        run_name({**base, "act_ahead": "yes"})
    with pytest.raises(ValueError, match="utd=...: updates per env step"):
        run_name({**base, "utd": "many"})
    # agent settings off their defaults name a run of their own; a default said outright does not
    assert (run_name({**base, "act_ahead": True, "agent_settings": {"squash_penalty": 1e-3, "entropy_weight": 0.0}})
            == "svg1-spinningup-mlp-ahead-squash_penalty0.001")
    assert run_name({**base, "hidden": [64, 64], "agent_settings": {"gamma": 0.98}}) == (   # the run's own keys too
        "svg1-spinningup-mlp-gamma0.98-hidden64x64")
    with pytest.raises(ValueError, match="squash_penalt"):
        run_name({**base, "agent_settings": {"squash_penalt": 1e-3}})
    with pytest.raises(ValueError, match="a JSON object"):
        run_name({**base, "agent_settings": "squash_penalty=1e-3"})


def test_side_by_side_runner_refuses_a_bad_setting_before_any_seed_starts(tmp_path, capsys):
    from bench import rl_seeds
    with pytest.raises(SystemExit) as e:
        rl_seeds.main(["--quick", "--seeds", "0-1", "--runs", str(tmp_path / "runs"), "--results",
                       str(tmp_path / "res"), "--set", "no_such_key=1"])
    assert e.value.code == 2 and "no_such_key" in capsys.readouterr().err
    assert not (tmp_path / "runs").exists()


def test_side_by_side_runner_exports_each_seeds_agent(tmp_path, capsys):
    """``--export``: a seed's process (``_one``, here in this process) writes its trained agent
    alone, loadable where the run folder is not."""
    from bench import rl_seeds
    from gnwarp.rl.run import AGENT_FILE, load_agent
    exp = tmp_path / "exp" / "svg0-spinningup-mlp" / "s0"
    cfg = {**rl_seeds.QUICK, "preset": "spinningup", "networks": "mlp", "progress": False, "seed": 0,
           "out": str(tmp_path / "runs" / "s0"), "export": str(exp)}
    assert rl_seeds._one(json.dumps(cfg)) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["stop"] == "done"
    assert (exp / AGENT_FILE).is_file() and not (exp / "checkpoint.pt").exists()
    agent, saved, _ = load_agent(exp, "cpu")
    assert saved.seed == 0 and agent.env_steps == rl_seeds.QUICK["env_steps"]


def test_goals_table_compares_each_svg1_loop_with_svg0_in_turn(tmp_path):
    """rl-goals: SVG(1) in turn and acting ahead each against SVG(0) in turn, two seeds or more a
    side; runs with other agent settings stay out."""
    from bench import results_tables as rt
    folder = tmp_path / rs.RL
    folder.mkdir(parents=True)
    recs = [_rec("svg0", s, 250000, [100.0 + 10 * s] * 2) for s in (0, 1, 2)]
    recs += [_rec("svg1", s, 250000, [300.0 + 10 * s] * 2, ahead=True) for s in (0, 1)]
    recs += [_rec("svg1", s, 250000, [900.0] * 2, settings={"squash_penalty": 1e-3}) for s in (0, 1)]
    recs += [_rec("svg1", 0, 250000, [50.0] * 2)]   # in turn: one seed, no row
    # on shared evaluation states: against SVG(0) of the same loop and states (not SVG(0) in turn)
    recs += [_rec("svg1", s, 250000, [600.0 + s] * 2, ahead=True, eval_seed=0) for s in (4, 5)]
    recs += [_rec("svg0", s, 250000, [500.0 + 20 * s] * 2, ahead=True, eval_seed=0) for s in (4, 5)]
    recs += [_rec("svg0", s, 250000, [0.0] * 2, ahead=True) for s in (6, 7)]   # own states: compared with nothing
    write_records(folder / "records.jsonl", recs)
    lines = rt.rl_goals(tmp_path, None)
    rows = [ln for ln in lines if ln.startswith("| swimmer")]
    assert len(rows) == 2, lines
    cells = [c.strip() for c in rows[0].strip("|").split("|")]
    assert cells[:3] == ["swimmer-swimmer6", "acting ahead", "250k"]
    assert cells[3].startswith("305 +- 5 (seeds 0-1)") and cells[4].startswith("110 +- 6 (seeds 0-2)")
    assert cells[5] == "+195" and cells[7] == "yes"
    cells = [c.strip() for c in rows[1].strip("|").split("|")]
    assert cells[:3] == ["swimmer-swimmer6", "acting ahead, both on the states of eval_seed 0", "250k"]
    assert cells[3].startswith("604 +- 0 (seeds 4-5)") and cells[4].startswith("590 +- 10 (seeds 4-5)")
    assert cells[5] == "+14"
    summary = rs.rows(tmp_path)
    assert {r["eval_seed"] for r in summary} == {None, 0}   # a curve of its own


def test_paired_goals_table_pairs_each_seed_on_its_own_states(tmp_path):
    """rl-goals-paired: SVG(1) seed k against SVG(0) seed k (in turn) over the seeds both have with
    as many evaluation episodes; a seed without a partner, or evaluated on other episodes, stays
    out; runs on shared states (eval_seed) pair with SVG(0) of the same loop and states only."""
    from bench import results_tables as rt
    folder = tmp_path / rs.RL
    folder.mkdir(parents=True)
    recs = [_rec("svg0", s, 250000, [100.0 * s] * 2) for s in (0, 1, 2, 3)]
    recs += [_rec("svg1", s, 250000, [100.0 * s + 10 + s] * 2) for s in (0, 1, 2)]   # +10, +11, +12
    recs += [_rec("svg1", 3, 250000, [999.0] * 3)]           # three episodes against two: not a pair
    recs += [_rec("svg1", 7, 250000, [999.0] * 2)]           # no SVG(0) seed 7
    recs += [_rec("svg1", s, 250000, [5.0] * 2, eval_seed=0) for s in (0, 1)]   # shared states, in turn: no partner
    recs += [_rec("svg1", s, 250000, [50.0 + 4 * s] * 2, ahead=True, eval_seed=0) for s in (4, 5)]   # 66, 70
    recs += [_rec("svg0", s, 250000, [50.0 + 20 * s - 80] * 2, ahead=True, eval_seed=0) for s in (4, 5)]   # 50, 70
    write_records(folder / "records.jsonl", recs)
    rows = [ln for ln in rt.rl_goals_paired(tmp_path, None) if ln.startswith("| swimmer")]
    assert len(rows) == 2, rows
    cells = [c.strip() for c in rows[0].strip("|").split("|")]
    half = 4.302653 * 1.0 / np.sqrt(3)          # differences 10, 11, 12: sd 1, t at 2 degrees of freedom
    assert cells[:6] == ["swimmer-swimmer6", "in turn", "250k", "0-2", "111", "100"]
    assert cells[6:] == ["+11", f"[{11 - half:+.0f}, {11 + half:+.0f}]", "yes"]
    cells = [c.strip() for c in rows[1].strip("|").split("|")]
    half = 12.706205 * np.std([16.0, 0.0], ddof=1) / np.sqrt(2)   # differences 16, 0; t at 1 degree of freedom
    assert cells[:6] == ["swimmer-swimmer6", "acting ahead, both on the states of eval_seed 0", "250k", "4-5", "68", "60"]
    assert cells[6:] == ["+8", f"[{8 - half:+.0f}, {8 + half:+.0f}]", "no"]


def test_gamma_table_pairs_each_discount_with_gamma_099_on_their_shared_seeds(tmp_path):
    """rl-gamma: SVG(1) acting ahead on shared states at each discount set alone (0.98, 0.995,
    0.999) against 0.99 (default settings) on the seeds the two share (a 0.99 row on those seeds
    above, one for a seed set shared in a row); the difference paired on the seed; the window row
    averages each seed's evaluations of 300-500k; bands pool the episodes; a run with a second
    setting off its default stays out."""
    from bench import results_tables as rt
    folder = tmp_path / rs.RL
    folder.mkdir(parents=True)
    base = {0: 100.0, 1: 200.0, 2: 300.0}
    recs = [_rec("svg1", s, 250000, [v, v], ahead=True, eval_seed=2) for s, v in base.items()]
    recs += [_rec("svg1", s, 250000, [base[s] + 10 + 2 * s] * 2, ahead=True, eval_seed=2,
                  settings={"gamma": 0.995}) for s in (0, 1, 2)]                                # +10, +12, +14
    recs += [_rec("svg1", s, 250000, [0.0, 1000.0], ahead=True, eval_seed=2, settings={"gamma": 0.999})
             for s in (0, 1)]                                                                   # seeds 0-1 only
    recs += [_rec("svg1", s, 250000, [999.0, 999.0], ahead=True, eval_seed=2,
                  settings={"gamma": 0.9, "squash_penalty": 1e-3}) for s in (0, 1)]           # two settings off: out
    recs += [_rec("svg1", s, 250000, [base[s] - 50] * 2, ahead=True, eval_seed=2, settings={"gamma": 0.98})
             for s in (0, 1)]                                                                   # any discount alone
    for g, add in ((None, 0.0), (0.995, 30.0), (0.999, 60.0)):                                  # the window's five points
        recs += [_rec("svg1", s, k * 50000, [add + k, add + k], ahead=True, eval_seed=2,
                      settings=None if g is None else {"gamma": g}) for s in (0, 1) for k in range(6, 11)]
    write_records(folder / "records.jsonl", recs)
    (folder / "eval_targets_swimmer6.jsonl").write_text(
        json.dumps({"eval_seed": 2, "episodes": 2, "distances": [0.5, 2.0]}) + "\n")
    rows = [[c.strip() for c in ln.strip("|").split("|")] for ln in rt.rl_gamma(tmp_path, None) if ln.startswith("| 2 ")]
    assert [r[1:6] for r in rows[:6]] == [["0.99", "250k", "0-1", "100 / 200", "**150**"],
                                          ["0.98", "250k", "0-1", "50 / 150", "**100**"],
                                          ["0.99", "250k", "0-2", "100 / 200 / 300", "**200**"],
                                          ["0.995", "250k", "0-2", "110 / 212 / 314", "**212**"],
                                          ["0.99", "250k", "0-1", "100 / 200", "**150**"],
                                          ["0.999", "250k", "0-1", "500 / 500", "**500**"]]
    half = 4.302653 * np.std([10.0, 12.0, 14.0], ddof=1) / np.sqrt(3)   # t at 2 degrees of freedom
    assert rows[1][6] == "-50 [-50, -50]" and rows[2][6] == "" and rows[3][6] == f"+12 [{12 - half:+.0f}, {12 + half:+.0f}]"
    h2 = 12.706205 * np.std([400.0, 300.0], ddof=1) / np.sqrt(2)
    assert rows[5][6] == f"+350 [{350 - h2:+.0f}, {350 + h2:+.0f}]" and rows[5][7:] == ["0", "", "", "1000"]   # near 0, far 1000
    window = [r for r in rows if r[2] == "mean of 300-500k"]
    assert [r[1] for r in window] == ["0.99", "0.995", "0.999"]   # the same seeds (0-1): one 0.99 row
    assert [r[5] for r in window] == ["**8**", "**38**", "**68**"] and window[1][6].startswith("+30 [+30, +30]")
    assert [r[4] for r in rows if r[2] == "500k"] == ["10 / 10", "40 / 40", "70 / 70"]   # the window's last point

def test_fastest_1m_run_is_the_one_with_the_fewest_training_seconds(tmp_path):
    from bench import results_tables as rt
    for name, secs, steps in (("slow", 2000.0, 1000000), ("fast", 700.0, 1000500), ("short", 10.0, 500000)):
        d = tmp_path / rs.RL / name   # "fast" ends past 1M (rounds of 1500 steps): its first row there counts
        d.mkdir(parents=True)
        (d / "progress.csv").write_text(f"env_steps,seconds\n10000,1.0\n{steps},{secs}\n{steps + 1500},{secs + 1}\n")
        write_records(d / "records.jsonl", [_rec("svg1", 0, steps, [1.0])])
    secs, rec = rt._fastest_1m(tmp_path)
    assert secs == 700.0 and rec.env_steps == 1000500
    assert rt._fastest_1m(tmp_path / "none") is None


def test_eval_noise_table_against_hand_computed_variances(tmp_path):
    """rl-eval-noise: the mean of the seeds' (episode variance / episodes) over the variance of the
    seeds' means, per curve, at 250k (three seeds or more)."""
    from bench import results_tables as rt
    folder = tmp_path / rs.RL
    folder.mkdir(parents=True)
    eps = {0: [0.0, 2.0], 1: [4.0, 8.0], 2: [10.0, 10.0]}   # means 1, 6, 10; (var / 2): 1, 4, 0
    recs = [_rec("svg1", s, 250000, v) for s, v in eps.items()]
    recs += [_rec("svg0", s, 250000, v) for s, v in list(eps.items())[:2]]   # two seeds: no row
    write_records(folder / "records.jsonl", recs)
    (folder / "eval_targets_swimmer6.jsonl").write_text("".join(   # one near and one far target a seed:
        json.dumps({"eval_seed": s, "episodes": 2, "distances": [0.1, 2.0]}) + "\n" for s in eps))   # too few to stratify
    (folder / "eval_states_swimmer6.jsonl").write_text(
        json.dumps({"eval_seed": None, "episodes": 4000, "near": 1.25, "share": 0.45}) + "\n")
    # DDPG, 4 episodes a seed, two near targets and two far: stratified
    four = {3: [10.0, 30.0, 0.0, 0.0], 4: [100.0, 100.0, 20.0, 0.0], 5: [50.0, 70.0, 10.0, 30.0]}
    write_records(folder / "records.jsonl", [_rec("ddpg", s, 250000, v) for s, v in four.items()])
    with open(folder / "eval_targets_swimmer6.jsonl", "a") as f:
        f.writelines(json.dumps({"eval_seed": s, "episodes": 4, "distances": [0.1, 0.2, 2.0, 2.0]}) + "\n" for s in four)
    rows = [ln for ln in rt.rl_eval_noise(tmp_path, None) if ln.startswith(("| SVG", "| DDPG"))]
    within, between = (1 + 4 + 0) / 3, np.var([1.0, 6.0, 10.0], ddof=1)
    strat = [0.45 * np.mean(v[:2]) + 0.55 * np.mean(v[2:]) for v in four.values()]
    raw = [np.mean(v) for v in four.values()]
    w4 = np.mean([np.var(v, ddof=1) / 4 for v in four.values()])
    assert rows == [f"| DDPG, in turn | {w4:.0f} / {np.var(raw, ddof=1):.0f} (**{w4 / np.var(raw, ddof=1):.2f}**; 3 seeds) | "
                    f"{np.var(strat, ddof=1):.0f} ({np.var(strat, ddof=1) / np.var(raw, ddof=1):.2f}) |  |  |",
                    f"| SVG(1), in turn | {within:.0f} / {between:.0f} (**{within / between:.2f}**; 3 seeds) | "
                    f"{between:.0f} (1.00) |  |  |"], rows


def test_reach_table_splits_episodes_by_their_targets_distance(tmp_path):
    """rl-reach: each band's mean over the episodes whose target started in it, pooled over seeds;
    a seed's rerun at the same env steps replaces it; other settings stay out."""
    from bench import results_tables as rt
    folder = tmp_path / rs.RL
    folder.mkdir(parents=True)
    recs = [_rec("svg1", 0, 250000, [900.0, 500.0, 100.0, 10.0]),
            _rec("svg1", 1, 250000, [0.0, 0.0, 0.0, 0.0]),            # replaced by its rerun below
            _rec("svg1", 1, 250000, [800.0, 300.0, 50.0, 20.0]),
            _rec("svg1", 2, 250000, [999.0] * 4, settings={"squash_penalty": 1e-3}),   # another curve
            _rec("svg1", 3, 250000, [600.0, 0.0, 0.0, 0.0], ahead=True),             # pooled with in turn
            _rec("svg1", 0, 300000, [999.0] * 4)]                                    # not a table point
    write_records(folder / "records.jsonl", recs)
    dist = {0: [0.5, 1.0, 1.4, 2.0], 1: [2.0, 1.4, 1.0, 0.5], 2: [0.5] * 4, 3: [0.1, 2.0, 2.0, 2.0]}
    (folder / "eval_targets_swimmer6.jsonl").write_text("".join(   # each seed's evaluation set its own
        json.dumps({"eval_seed": s, "episodes": 4, "distances": d}) + "\n" for s, d in dist.items()))
    rows = [ln for ln in rt.rl_reach(tmp_path, None) if ln.startswith("| SVG")]
    # 0-0.75 m: 900, 20, 600; 0.75-1.25: 500, 50; 1.25-1.6: 100, 300; >= 1.6: 10, 800, 0, 0, 0
    assert rows == ["| SVG(1) | 250k | 3 | 507 (3) | 275 (2) | 200 (2) | 162 (5) |"], rows


def test_rl_targets_distance_and_reach(tmp_path, capsys):
    """bench/rl_targets.py: each episode's target distance from the head's start, the farthest
    reached and the nearest missed; a record without targets is refused by name."""
    from bench import rl_targets
    rec = ResultRecord(experiment="mpc", task="dmc-swimmer-swimmer6", planner="policy", dynamics="none",
                       episodes=3, episode_steps=1000, returns=[990.0, 10.0, 700.0], seed=0,
                       config=dict(policy="agents/a", backend="mujoco",
                                   targets=[[0.3, 0.4, 0.05], [2.0, 0.0, 0.05], [1.0, 1.0, 0.05]],
                                   initial_qpos=[[0.0] * 8, [0.0] * 8, [1.0, 0.0] + [0.0] * 6]))
    import mujoco
    from gnwarp.rl.observations import DMCObservation
    model = DMCObservation("swimmer6").system.model
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    nose0 = data.geom("nose").xpos[:2]   # the root's slides move the nose rigidly
    start = np.array([[0.0, 0.0], [0.0, 0.0], [1.0, 0.0]]) + nose0
    want = np.linalg.norm(np.array([[0.3, 0.4], [2.0, 0.0], [1.0, 1.0]]) - start, axis=1)
    d, r = rl_targets.episodes(rec)
    assert np.allclose(d, want) and r.tolist() == [990.0, 10.0, 700.0]
    assert abs(nose0[1]) > 0.01 or abs(nose0[0]) > 0.01   # the nose is not the root's origin
    write_records(tmp_path / "p.jsonl", [rec])
    assert rl_targets.main([str(tmp_path / "p.jsonl"), "--out", str(tmp_path / "t.png")]) == 0
    out = capsys.readouterr().out
    assert f"reached 2 of 3, the farthest at {max(want[0], want[2]):.2f} m; the nearest missed at {want[1]:.2f} m" in out
    assert (tmp_path / "t.png").stat().st_size > 1000
    import dataclasses
    with pytest.raises(ValueError, match="targets"):
        rl_targets.episodes(dataclasses.replace(rec, config={"policy": "agents/a"}))


def test_rl_targets_eval_states_are_the_runs_own(tmp_path):
    """--eval-states: the nose-to-target distances (MuJoCo's kinematics of the simulator's qpos) of
    the states a run with that eval_seed evaluates from, against the norm of the observation's
    to_target that the run's agent sees there; the share of near ones written as rows."""
    from bench import rl_targets
    from gnwarp.rl.config import RLConfig
    from gnwarp.rl.observations import DMCObservation
    from gnwarp.rl.run import eval_reset_seed, evaluation_env
    six = rl_targets.eval_distances(6, 0)
    cfg = RLConfig(task="swimmer6", agent="svg1", eval_episodes=6, eval_seed=0, backend="mujoco", device="cpu",
                   out="unused")
    env = evaluation_env(cfg)
    obs, _ = env.reset(seed=eval_reset_seed(cfg))
    env.close()
    names = DMCObservation("swimmer6").names
    seen = np.linalg.norm(np.asarray(obs, dtype=np.float64)[:, [names.index("to_target.x"), names.index("to_target.y")]],
                          axis=1)
    assert np.allclose(six, seen, atol=1e-5), (six, seen)
    assert not np.allclose(rl_targets.eval_distances(6, 1), six)
    out = tmp_path / "e.jsonl"
    assert rl_targets.main(["--eval-states", "6", "--eval-seeds", "0", "--population", "8", "--near", "1.25",
                            "--out", str(out)]) == 0
    rows = [json.loads(x) for x in out.read_text().splitlines()]
    assert [r["episodes"] for r in rows] == [8, 6] and rows[1]["share"] == round(float((seen < 1.25).mean()), 4)


def test_post_stratified_seed_means(tmp_path):
    """seed_means(stratify=...): share x mean(near) + (1 - share) x mean(far), its variance
    likewise; the raw mean where a stratum has fewer than two episodes; results_tables'
    swimmer6 strata from the evaluation sets' distances and the population's share."""
    import dataclasses
    from bench import results_tables as rt
    folder = tmp_path / rs.RL
    folder.mkdir(parents=True)
    write_records(folder / "r.jsonl", [_rec("svg1", 0, 1000, [900.0, 1000.0, 10.0, 20.0, 30.0, 40.0]),
                                       _rec("svg1", 1, 1000, [900.0, 10.0, 20.0])])
    masks = {0: [True, True, False, False, False, False], 1: [True, False, False]}
    by = rs.seed_means(tmp_path, rs.RL, stratify=lambda r: (masks[r.seed], 0.5))
    (seeds,) = by.values()
    mean, _, _, var = seeds[0]
    assert mean == pytest.approx(0.5 * 950 + 0.5 * 25)
    assert var == pytest.approx(0.25 * np.var([900, 1000], ddof=1) / 2 + 0.25 * np.var([10, 20, 30, 40], ddof=1) / 4)
    assert seeds[1][0] == pytest.approx(310.0)   # one near episode: not stratified
    # the swimmer6 strata: distances of the run's own evaluation set, the population's share
    (folder / "eval_targets_swimmer6.jsonl").write_text(
        json.dumps({"eval_seed": 0, "episodes": 6, "distances": [0.2, 1.0, 1.3, 2.0, 2.5, 1.6]}) + "\n")
    (folder / "eval_states_swimmer6.jsonl").write_text(
        json.dumps({"eval_seed": None, "episodes": 4000, "near": 1.25, "share": 0.45}) + "\n")
    with open(folder / "eval_targets_swimmer6.jsonl", "a") as f:   # a shared set: eval_seed 9, 3 episodes
        f.write(json.dumps({"eval_seed": 9, "episodes": 3, "distances": [2.0, 0.5, 1.0]}) + "\n")
    strata = rt._swimmer_strata(tmp_path)
    rec = _rec("svg1", 0, 1000, [1.0] * 6)
    mask, share = strata(rec)
    assert mask.tolist() == [True, True, False, False, False, False] and share == 0.45
    mask, _ = strata(_rec("svg1", 0, 1000, [1.0] * 3, eval_seed=9))   # its eval_seed's set, not its seed's
    assert mask.tolist() == [False, True, True]
    with pytest.raises(LookupError, match=r"\(5, 6\)"):   # no distances for its set: refused, not left raw
        strata(_rec("svg1", 5, 1000, [1.0] * 6))
    assert strata(dataclasses.replace(rec, task="dmc-cheetah-run")) is None


def test_run_eval_sets_name_each_runs_evaluation_states(tmp_path):
    from bench import rl_targets
    write_records(tmp_path / "a.jsonl", [_rec("svg1", 3, 0, [1.0] * 4), _rec("svg1", 3, 1000, [1.0] * 4),
                                         _rec("svg0", 4, 0, [1.0] * 5, eval_seed=2),
                                         _rec("svg0", 5, 0, [1.0] * 5, experiment="control")])
    assert rl_targets.run_eval_sets(tmp_path) == {(2, 5): None, (3, 4): None}


def test_rl_targets_runs_refuses_states_that_differ_from_the_records(tmp_path):
    """--runs draws each set again; a run that recorded its states (its first record) must get
    the same distances, else the sampler changed since and the file is not written."""
    from bench import rl_targets
    rec = _rec("svg1", 0, 0, [1.0] * 3, eval_seed=0)
    rec.config.update(initial_qpos=[[0.0] * 8] * 3, targets=[[3.0, 3.0, 0.05]] * 3)   # not eval_seed 0's
    write_records(tmp_path / "r.jsonl", [rec])
    out = tmp_path / "t.jsonl"
    assert rl_targets.main(["--runs", str(tmp_path), "--out", str(out)]) == 1 and not out.exists()
    from gnwarp.rl.config import RLConfig
    from gnwarp.rl.observations import DMCObservation
    from gnwarp.rl.run import eval_reset_seed, evaluation_env, evaluation_states
    cfg = RLConfig(task="swimmer6", agent="svg1", eval_episodes=3, eval_seed=0, backend="mujoco", device="cpu",
                   out="unused")
    env = evaluation_env(cfg)
    obs, _ = env.reset(seed=eval_reset_seed(cfg))
    rec.config.update(evaluation_states(env))   # what a run records
    env.close()
    # the distances the agent's observation saw there (to_target: target minus nose, in the head's frame)
    names = DMCObservation("swimmer6").names
    good = np.linalg.norm(np.asarray(obs)[:, [names.index("to_target.x"), names.index("to_target.y")]], axis=1)
    assert np.allclose(rl_targets.nose_distances(rec.config["initial_qpos"], rec.config["targets"]), good, atol=1e-3)
    write_records(tmp_path / "r.jsonl", [rec])
    assert rl_targets.main(["--runs", str(tmp_path), "--out", str(out)]) == 0
    (row,) = [json.loads(x) for x in out.read_text().splitlines()]
    assert row["eval_seed"] == 0 and np.allclose(row["distances"], good, atol=1e-3)
