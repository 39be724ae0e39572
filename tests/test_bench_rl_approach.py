"""bench/rl_approach.py: how a trained swimmer6 agent approaches near and far targets."""
import json
from pathlib import Path

import pytest

AGENT = Path(__file__).resolve().parents[1] / "bench" / "results" / "rl" / "agents" / "svg1-spinningup-mlp-s0"


def test_approach_records_distances_from_the_evaluation_states(tmp_path):
    """bench/rl_approach.py: the nose-to-target distance of each evaluation episode over time,
    starting where the run's evaluation env starts (eval_seed 2's states)."""
    import dataclasses

    from bench import rl_approach
    from gnwarp.rl.run import check_task, eval_reset_seed, evaluation_env, load_agent
    assert rl_approach.main([str(AGENT), "--episodes", "2", "--steps", "20", "--every", "5",
                             "--out", str(tmp_path)]) == 0
    rec = json.loads((tmp_path / rl_approach.RECORDS).read_text())
    assert rec["episodes"] == 2 and rec["eval_seed"] == 2 and len(rec["distance"][0]) == 5
    assert rec["machine"].startswith("CPU (") and f"Machines: {rec['machine']}." in (tmp_path / "README.md").read_text()
    assert rec["times"] == pytest.approx([0.0, 0.15, 0.3, 0.45, 0.6])
    agent, cfg, obs_fn = load_agent(AGENT, "cpu")
    cfg = dataclasses.replace(cfg, eval_episodes=2, eval_seed=2, backend="mujoco")
    env = evaluation_env(cfg, check_task(cfg), obs_fn)
    try:
        obs, _ = env.reset(seed=eval_reset_seed(cfg))
    finally:
        env.close()
    nose_to_target = obs[:, obs_fn.parts["to_target"]].norm(dim=1)
    assert rec["start"] == pytest.approx(nose_to_target.tolist(), abs=1e-4)
    assert rec["least"] == pytest.approx([min(d) for d in rec["distance"]], abs=1e-4)
    assert rec["reached"] == [x <= rec["target_radius"] for x in rec["least"]] and 0 < rec["target_radius"] < 1
    # a window longer than the episode: the fastest approach is the whole episode's
    assert rec["speed"] == pytest.approx([(a - b) / 0.6 for a, b in zip(rec["start"], rec["last"])], abs=1e-3)
    assert (tmp_path / "approach_swimmer6.png").stat().st_size > 1000


def test_fastest_approach_over_a_window_and_the_returns_gnwarp_rl_scores(tmp_path):
    """A window of two recorded points (0.3 s) in an episode of 22 steps whose last point (0.66 s)
    is off the grid: the fastest fall over 0.3 s, brute force over the pairs exactly 0.3 s apart;
    the returns are what gnwarp rl's evaluation scores over the same 22 steps."""
    import dataclasses

    import numpy as np

    from bench import rl_approach
    from gnwarp.rl.run import check_task, eval_reset_seed, evaluate_policy, evaluation_env, load_agent
    assert rl_approach.main([str(AGENT), "--episodes", "3", "--steps", "22", "--every", "5", "--window", "0.3",
                             "--out", str(tmp_path)]) == 0
    rec = json.loads((tmp_path / rl_approach.RECORDS).read_text())
    t = rec["times"]
    assert t == pytest.approx([0.0, 0.15, 0.3, 0.45, 0.6, 0.66])
    for d, v in zip(rec["distance"], rec["speed"]):
        falls = [(d[i] - d[j]) / 0.3 for i in range(len(t)) for j in range(i + 1, len(t))
                 if abs(t[j] - t[i] - 0.3) < 1e-9]
        assert len(falls) == 3 and v == pytest.approx(max(falls), abs=1e-3)
    agent, cfg, obs_fn = load_agent(AGENT, "cpu")
    cfg = dataclasses.replace(cfg, eval_episodes=3, eval_seed=2, backend="mujoco", episode_steps=22)
    env = evaluation_env(cfg, check_task(cfg), obs_fn)
    try:
        want = evaluate_policy(agent, env, eval_reset_seed(cfg))
    finally:
        env.close()
    assert np.allclose(rec["returns"], want, rtol=1e-5, atol=1e-4), (rec["returns"], want)
    with pytest.raises(SystemExit, match="different --window"):   # one table, one window
        rl_approach.main([str(AGENT), "--episodes", "2", "--steps", "20", "--every", "5", "--out", str(tmp_path)])


def test_fastest_approach_leaves_out_the_off_grid_last_point():
    import numpy as np

    from bench.rl_approach import fastest_approach
    times = np.array([0.0, 0.15, 0.3, 0.45, 0.6, 0.66])
    d = np.array([[2.0, 1.9, 1.8, 1.7, 1.6, 0.0],      # a plunge into the last, closer point: not a 0.3 s fall
                  [2.0, 2.0, 1.0, 1.0, 1.0, 1.0]])
    speed, span = fastest_approach(d, times, 0.3)
    assert span == 0.3 and speed == pytest.approx([0.2 / 0.3, 1.0 / 0.3])
    speed, span = fastest_approach(d, times, 100.0)   # a window past the episode: first point to last
    assert span == pytest.approx(0.66) and speed == pytest.approx([2.0 / 0.66, 1.0 / 0.66])
    speed, span = fastest_approach(d, times, 0.6)     # 0.6 s: the pair (0.15, 0.66) is 0.51 s apart, left out
    assert span == pytest.approx(0.6) and speed == pytest.approx([0.4 / 0.6, 1.0 / 0.6])
    speed, span = fastest_approach(d, times, 0.01)    # shorter than a step: one step
    assert span == pytest.approx(0.15) and speed == pytest.approx([0.1 / 0.15, 1.0 / 0.15])
