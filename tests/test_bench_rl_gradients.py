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
    torch.testing.assert_close(g["g_true"], g["g_model"], rtol=1e-3, atol=1e-4 * float(g["g_model"].abs().max()))
    x = states["obs"]
    a = agent.squash(agent.policy(x)[0]).detach().requires_grad_(True)
    (dq,) = torch.autograd.grad(agent.q(x, a).sum(), a)
    torch.testing.assert_close(g["g_zero"], dq)


def test_true_simulator_steps_from_each_visited_state(swimmer):
    """``true_next`` puts each world back in its visited state (the reset observes exactly the
    stored observation, target included) and steps it once: what the visiting env itself gives
    for the same action one step on."""
    from gnwarp.control.vector_env import make_vector_env
    agent, task, obs_fn, _ = swimmer
    visit = make_vector_env(task, 2, backend="mujoco", output="torch", observation=obs_fn)
    again = make_vector_env(task, 2, backend="mujoco", output="torch", observation=obs_fn)
    try:
        states = rg.visited_states(agent, visit, 3, 3, seed=4)   # the visiting env's current states
        a = agent.squash(agent.policy(states["obs"])[0]).detach()
        want, _, _, _, _ = visit.step(a)
        rows = torch.tensor([1, 0])
        back, _ = again.reset(options={"qpos": states["qpos"][rows], "qvel": states["qvel"][rows],
                                       "targets": states["targets"][rows]})
        assert torch.equal(back, states["obs"][rows])
        assert torch.equal(rg.true_next(again, states, rows, a[rows]), want[rows])
    finally:
        visit.close()
        again.close()


def test_one_sided_differences_at_the_action_bounds(swimmer):
    """A mean action on the box's bound (the policy pushed far past it): the differences step
    inward only, and through an exact simulator still match autograd's gradient there."""
    import copy

    agent, _, _, states = swimmer
    agent = copy.deepcopy(agent)
    for net in (agent.policy, agent.q, agent.model):
        net.double()
    for k in ("low", "high", "mid", "half"):
        setattr(agent, k, getattr(agent, k).double())
    inner = agent.policy

    class Pushed(torch.nn.Module):   # component 0 of the mean far above the bound, 1 far below
        def forward(self, x):
            mean, log_std = inner(x)
            return mean + torch.tensor([1e6, -1e6, 0.0, 0.0, 0.0], dtype=mean.dtype), log_std
    agent.policy = Pushed()
    states = {**states, "obs": states["obs"].double()}
    a = agent.squash(agent.policy(states["obs"])[0])
    assert bool((a[:, 0] == agent.high[0]).all()) and bool((a[:, 1] == agent.low[1]).all())
    g = rg.action_gradients(agent, states, lambda rows, act: agent.model(states["obs"][rows], act).detach(), h=1e-5)
    scale = g["g_model"].abs().max()
    torch.testing.assert_close(g["g_true"], g["g_model"], rtol=1e-3, atol=1e-4 * float(scale))   # each component


def test_only_svg1_agents_are_measured(monkeypatch, tmp_path):
    from gnwarp.rl import run as rl_run
    real = rl_run.load_agent

    def as_svg2(folder, device):
        agent, cfg, obs_fn = real(folder, device)
        agent.horizon = 2
        return agent, cfg, obs_fn
    monkeypatch.setattr(rl_run, "load_agent", as_svg2)
    with pytest.raises(SystemExit, match="SVG\\(1\\) only"):
        rg.measure(AGENT, 2, 2, 2, 1e-2, 0, 1)


def test_script_writes_records_and_readme(tmp_path, capsys):
    assert rg.main([str(AGENT), "--envs", "2", "--steps", "4", "--every", "2", "--out", str(tmp_path)]) == 0
    rec = json.loads((tmp_path / rg.RECORDS).read_text())
    assert rec["states"] == 4 and len(rec["cos_g_model_g_true"]) == 4 and rec["task"] == "dmc-swimmer-swimmer6"
    assert all(-1.0 <= c <= 1.0 for c in rec["cos_g_zero_g_true"])
    assert "| svg1-spinningup-mlp-s0 | swimmer-swimmer6 | 700k | 4 (2) | 0.01 |" in (tmp_path / "README.md").read_text()
    assert rec["world"] == [0, 1, 0, 1] and rec["machine"].startswith("CPU (")
    assert rg.main([str(AGENT), "--envs", "2", "--steps", "4", "--every", "2", "--out", str(tmp_path)]) == 0
    assert len((tmp_path / rg.RECORDS).read_text().splitlines()) == 1   # measured again: replaced
    with pytest.raises(SystemExit):
        rg.main([str(AGENT), "--steps", "1", "--every", "2", "--out", str(tmp_path)])

