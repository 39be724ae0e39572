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
