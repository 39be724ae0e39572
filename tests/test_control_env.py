"""The closed-loop environments: MuJoCo-Warp (Warp's CPU device) against MuJoCo C
stepping the same actions from the same states; shapes, resets, control clamping, bad inputs."""
import numpy as np
import pytest
import torch

from gnwarp import data, sim
from gnwarp.sim.env import EnvInputError, dataset_states, make_env
from gnwarp.interop import cuda_available, warp
from gnwarp.state import DYN_NODE_SIZE

warp()

WARP_BACKENDS = ["mujoco_warp_cpu"] + (["mujoco_warp"] if cuda_available() else [])


def _start(system, n, seed=0):
    return data.initial_states(system, n, np.random.default_rng(seed))


@pytest.mark.parametrize("backend", WARP_BACKENDS)
@pytest.mark.parametrize("name", ["cartpole", "swimmer3"])   # RK4; sub-steps
def test_mujoco_warp_env_matches_mujoco_c(name, backend):
    s = sim.make(name)
    q0, v0 = _start(s, 3)
    u = sim.random_spline_controls(3, 6, sim.control_range(s.model), rng=1)
    envs = [make_env(s, 3, backend="mujoco"), make_env(s, 3, backend=backend)]
    outs = []
    for env in envs:
        body = [env.reset(q0, v0)]
        body += [env.step(torch.as_tensor(u[:, t])) for t in range(3)]
        body.append(env.rollout(u[:, 3:])[:, 1:])   # the rest in one call, from where step left it
        outs.append((torch.cat([torch.stack(body[:4], 1), body[4]], 1).cpu(), env.qpos.cpu(), env.qvel.cpu()))
    (bc, qc, vc), (bw, qw, vw) = outs
    assert bc.shape == (3, 7, s.model.nbody, DYN_NODE_SIZE) and qc.dtype == torch.float64
    scale = bc.abs().reshape(-1, DYN_NODE_SIZE).amax(0) + 1.0
    assert ((bc - bw).abs() / scale).max() < 2e-4
    np.testing.assert_allclose(qw.double(), qc, atol=1e-4)
    np.testing.assert_allclose(vw.double(), vc, atol=1e-3)
    # the same states as the dataset simulator
    ref = sim.simulate(s, q0, v0, u, backend="mujoco")
    np.testing.assert_allclose(bc.numpy(), ref.body, atol=1e-5)


@pytest.mark.parametrize("backend", ["mujoco"] + WARP_BACKENDS)
def test_reset_step_shapes_and_dataset_states(backend):
    ds = data.generate("pendulum", (2, 1, 3), num_steps=5, seed=2, backend="mujoco", progress=False)
    env = make_env("pendulum", 3, backend=backend)
    assert (env.n_worlds, env.nu, env.dt) == (3, 1, sim.make("pendulum").dt)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros((3, 1)))
    q0, v0 = dataset_states(ds, "test", [2, 0, 1])
    for seqs, t, words in (([5], 0, "must be in \\[0, 3\\)"), ([-1], 0, "must be in"), ([0], 6, "step 6 outside"),
                           ([], 0, "no sequences")):
        with pytest.raises(IndexError, match=words):
            dataset_states(ds, "test", seqs, t)
    body = env.reset(q0, v0)
    sp = ds["test"]
    order = [2, 0, 1]
    assert body.shape == (3, 2, DYN_NODE_SIZE)
    np.testing.assert_allclose(body.cpu().numpy(), sp.body[order, 0], atol=1e-5)
    traj = env.rollout(sp.ctrl[order])
    assert traj.shape == (3, 6, 2, DYN_NODE_SIZE)
    np.testing.assert_allclose(traj.cpu().numpy(), sp.body[order], atol=1e-4)
    np.testing.assert_allclose(env.body_states().cpu().numpy(), sp.body[order, -1], atol=1e-4)
    obs = env.observe()
    assert obs.qpos.shape == (3, 1) and obs.qvel.shape == (3, 1) and obs.body.shape == (3, 2, DYN_NODE_SIZE)
    assert env.step(np.zeros((3, 1))).shape == (3, 2, DYN_NODE_SIZE)


def test_bad_states_and_controls_raise():
    env = make_env("cartpole", 2, backend="mujoco")
    q0, v0 = np.zeros((2, 2)), np.zeros((2, 2))
    bad = q0.copy()
    bad[1, 1] = np.nan
    with pytest.raises(EnvInputError, match=r"qpos holds NaN or Inf \(world 1, coordinate 1\)"):
        env.reset(bad, v0)
    with pytest.raises(EnvInputError, match="qvel holds NaN"):
        env.reset(q0, np.full((2, 2), np.inf))
    with pytest.raises(EnvInputError, match=r"qpos \[N=2, nq=2\]"):
        env.reset(np.zeros((3, 2)))
    env.reset(q0)   # qvel defaults to zeros
    with pytest.raises(EnvInputError, match="controls must be"):
        env.step(np.zeros((2, 3)))
    with pytest.raises(EnvInputError, match="NaN"):
        env.step(np.array([[0.0], [np.nan]]))
    with pytest.raises(ValueError, match="ctrl_policy"):
        make_env("cartpole", 2, backend="mujoco", ctrl_policy="wrap")
    with pytest.raises(ValueError, match="unknown backend"):
        make_env("cartpole", 2, backend="bullet")


@pytest.mark.parametrize("backend", ["mujoco"] + WARP_BACKENDS)
def test_controls_outside_the_range_are_clamped_or_refused(backend):
    s = sim.make("pendulum")
    lo, hi = s.model.actuator_ctrlrange[0]
    q0 = np.array([[0.3], [0.3]])
    env = make_env(s, 2, backend=backend)
    env.reset(q0)
    far = env.rollout(np.array([[[10 * hi]] * 4, [[hi]] * 4]))   # world 0 asks for 10x the range
    torch.testing.assert_close(far[0], far[1])                   # both run at the limit
    assert env.last_ctrl[:, 0].tolist() == [hi, hi]
    strict = make_env(s, 2, backend=backend, ctrl_policy="error")
    strict.reset(q0)
    with pytest.raises(EnvInputError, match=r"actuator 0 .* outside its range"):
        strict.step(np.array([[lo - 0.5], [0.0]]))
    strict.step(np.array([[lo], [hi]]))   # the bounds themselves are fine
