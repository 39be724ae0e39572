"""Sampling MPC: predictive sampling and MPPI on the true dynamics beat random actions
on pendulum balance; planned actions stay in range; the sampler runs through a learned model."""
import numpy as np
import pytest
import torch

from gnwarp import data
from gnwarp.sim.env import make_env
from gnwarp.control.episodes import run_episodes
from gnwarp.control.sampling import (ModelDynamics, RandomPlanner, SamplingConfig, SamplingPlanner, spline_basis,
                                     true_dynamics)
from gnwarp.interop import warp
from gnwarp.models import MLPForwardModel

warp()


def upright(states, actions):
    """Pendulum balance: the pole's z axis . world z, summed over the steps after the first."""
    q = states[:, 1:, 1, 3:7]
    return (1 - 2 * (q[..., 1] ** 2 + q[..., 2] ** 2)).sum(1)


Q0 = np.array([[0.1], [-0.15], [0.15]])   # within ~0.2 rad the 1 N m motor can hold the pole up


@pytest.mark.parametrize("method,interp", [("best", "zero"), ("mppi", "cubic")])
def test_sampling_mpc_beats_random_actions(method, interp):
    N, K = 3, 32
    env = make_env("pendulum", N, backend="mujoco")
    cfg = SamplingConfig(horizon=15, samples=K, knots=3, interpolation=interp, method=method)
    planner = SamplingPlanner(true_dynamics("pendulum", N, K, backend="mujoco"), upright, env.ctrlrange, N, cfg)
    mpc = run_episodes(planner, env, upright, 40, qpos0=Q0)
    rnd = run_episodes(RandomPlanner(env.ctrlrange, N, seed=1), env, upright, 40, qpos0=Q0)
    assert mpc["states"].shape == (N, 41, 2, 13) and mpc["actions"].shape == (N, 40, 1)
    assert mpc["plan_seconds"].shape == (40,)
    assert (mpc["returns"] > rnd["returns"] + 2.0).all(), (mpc["returns"], rnd["returns"])
    q = mpc["states"][:, -1, 1, 3:7]
    assert ((1 - 2 * (q[:, 1] ** 2 + q[:, 2] ** 2)) > 0.9).all()   # still balanced at the end


def test_planned_actions_stay_in_range_and_nominal_shifts():
    N, K = 2, 16
    env = make_env("cartpole", N, backend="mujoco")
    env.reset(np.zeros((N, 2)))
    lo, hi = env.ctrlrange[:, 0], env.ctrlrange[:, 1]
    # a reward that wants ever larger forces: the clamp is what holds the actions in the range
    greedy = lambda s, a: a.abs().sum((1, 2)) * 100.0   # noqa: E731
    cfg = SamplingConfig(horizon=6, samples=K, knots=6, noise=5.0, interpolation="cubic", seed=3)
    planner = SamplingPlanner(true_dynamics("cartpole", N, K, backend="mujoco", source=env), greedy,
                              env.ctrlrange, N, cfg)
    for t in range(4):
        before = planner.nominal()
        # the true state as an Observation, or body states only (qpos / qvel then read from the source env)
        a = planner.step(env.observe() if t % 2 else env.body_states())
        assert a.shape == (N, 1) and (a >= lo).all() and (a <= hi).all()
        assert (planner.candidates() >= lo).all() and (planner.candidates() <= hi).all()
        env.step(a)
    # piecewise-constant knots, one per step: the shift moves the sequence one step earlier
    cfg = SamplingConfig(horizon=5, samples=4, knots=5, noise=0.0)
    p = SamplingPlanner(true_dynamics("cartpole", N, 4, backend="mujoco"), greedy, env.ctrlrange, N, cfg)
    p.knots = torch.arange(5.0).reshape(1, 5, 1).expand(N, 5, 1) * 0.1
    with pytest.raises(ValueError, match="true qpos / qvel"):
        p.step(env.body_states())
    p.step(env.observe())
    torch.testing.assert_close(p.nominal()[:, :, 0], torch.tensor([[0.1, 0.2, 0.3, 0.4, 0.4]] * N))
    assert before.shape == (N, 6, 1)


def test_spline_basis_and_config_checks():
    t = np.array([0.0, 0.5, 1.0, 2.0, 5.0])
    for kind in ("zero", "linear", "cubic"):
        w = spline_basis(kind, 3, t)
        np.testing.assert_allclose(w.sum(1), 1.0)   # constants stay constant
    np.testing.assert_allclose(spline_basis("linear", 3, t)[1], [0.5, 0.5, 0.0])
    with pytest.raises(ValueError, match="knots"):
        SamplingConfig(horizon=4, knots=5)
    with pytest.raises(ValueError, match="method"):
        SamplingConfig(method="cem")


def test_sampler_through_a_learned_model():
    ds = data.generate("pendulum", (4, 1, 1), num_steps=6, seed=0, backend="mujoco", progress=False)
    torch.manual_seed(0)
    model = MLPForwardModel(ds.layout, n_node=2, n_edge=2, size="3x128").bind(ds)
    N, K = 2, 8
    env = make_env("pendulum", N, backend="mujoco")
    cfg = SamplingConfig(horizon=5, samples=K, knots=2, interpolation="linear")
    planner = SamplingPlanner(ModelDynamics(model.rollout), upright, env.ctrlrange, N, cfg)
    out = run_episodes(planner, env, upright, 3, qpos0=Q0[:N])
    assert out["returns"].shape == (N,) and planner.last_rewards.shape == (N, K)
    assert (out["actions"].abs() <= 1.0).all()
