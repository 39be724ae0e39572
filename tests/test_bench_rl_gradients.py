"""bench/rl_gradients.py: SVG(1)'s action gradient through the learned model against the same
through the true simulator (finite differences of MuJoCo C) and SVG(0)'s."""
import json
from pathlib import Path

import pytest
import torch

from bench import rl_gradients as rg

AGENT = Path(__file__).resolve().parents[1] / "bench" / "results" / "rl" / "agents" / "svg1-spinningup-mlp-s0"


@pytest.fixture(scope="module")
def swimmer():
    from gnwarp.control.vector_env import make_vector_env
    from gnwarp.rl.run import check_task, load_agent
    agent, cfg, obs_fn = load_agent(AGENT, "cpu")
    task = check_task(cfg)
    env = make_vector_env(task, 2, backend="mujoco", output="torch", observation=obs_fn)
    try:
        states = rg.visited_states(agent, env, 6, 3, seed=1)
    finally:
        env.close()
    return agent, task, obs_fn, states


def test_differences_through_an_exact_simulator_equal_the_models_gradient(swimmer):
    """With the learned model standing in for the simulator, the 'true' gradient is the model's
    own differenced: it must match autograd's (which catches a perturbation sent to the wrong
    state or component), and SVG(0)'s gradient is dQ/da."""
    import copy
    agent, _, _, states = swimmer
    assert states["obs"].shape == (4, 25) and states["qpos"].shape[0] == 4 and states["targets"].shape[0] == 4
    agent = copy.deepcopy(agent)   # in float64: the differences' rounding out of the comparison
    for net in (agent.policy, agent.q, agent.model):
        net.double()
    for k in ("low", "high", "mid", "half"):
        setattr(agent, k, getattr(agent, k).double())
    states = {**states, "obs": states["obs"].double()}

    def exact(rows, actions):
        with torch.no_grad():
            return agent.model(states["obs"][rows], actions)
    g = rg.action_gradients(agent, states, exact, h=1e-5)
    assert torch.equal(g["g_true"], g["g_model_fd"])
    cos = torch.nn.functional.cosine_similarity(g["g_true"], g["g_model"], dim=1)
    assert bool((cos > 0.9999).all()), cos
    x = states["obs"]
    a = agent.squash(agent.policy(x)[0]).detach().requires_grad_(True)
    (dq,) = torch.autograd.grad(agent.q(x, a).sum(), a)
    torch.testing.assert_close(g["g_zero"], dq)
    assert torch.allclose(g["model_error"], torch.zeros(4, dtype=torch.float64))   # the model against itself


def test_true_simulator_steps_from_each_visited_state(swimmer):
    """``true_next`` resets each world to its visited state: the mean action's next observation
    there differs from the state's own by one control step, and is the same for a row twice."""
    from gnwarp.control.vector_env import make_vector_env
    agent, task, obs_fn, states = swimmer
    env = make_vector_env(task, 3, backend="mujoco", output="torch", observation=obs_fn)
    try:
        rows = torch.tensor([0, 2, 0])
        a = agent.squash(agent.policy(states["obs"][rows])[0]).detach()
        nxt = rg.true_next(env, states, rows, a)
    finally:
        env.close()
    assert torch.equal(nxt[0], nxt[2]) and not torch.equal(nxt[0], nxt[1])
    step = (nxt - states["obs"][rows]).norm(dim=1)
    assert bool((step > 1e-4).all()) and bool((step < 0.5 * states["obs"][rows].norm(dim=1)).all())


def test_script_writes_records_and_readme(tmp_path, capsys):
    assert rg.main([str(AGENT), "--envs", "2", "--steps", "4", "--every", "2", "--out", str(tmp_path)]) == 0
    rec = json.loads((tmp_path / rg.RECORDS).read_text())
    assert rec["states"] == 4 and len(rec["cos_g_model_g_true"]) == 4 and rec["task"] == "dmc-swimmer-swimmer6"
    assert all(-1.0 <= c <= 1.0 for c in rec["cos_g_zero_g_true"])
    assert "| svg1-spinningup-mlp-s0 | swimmer-swimmer6 | 700k | 4 | 0.01 |" in (tmp_path / "README.md").read_text()
    with pytest.raises(SystemExit):
        rg.main([str(AGENT), "--steps", "1", "--every", "2", "--out", str(tmp_path)])
