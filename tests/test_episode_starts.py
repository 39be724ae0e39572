"""Initial states and targets of control episodes: drawn from one seed, yet independent."""
import warnings

import numpy as np
import pytest

pytest.importorskip("dm_control")
warnings.filterwarnings("ignore", message=".*glfw.*")

from gnwarp.control import episode_starts, get_task  # noqa: E402
from gnwarp.sim import systems  # noqa: E402


def _angle_gap(qpos, targets):
    """Target angle minus shoulder angle, wrapped to [-pi, pi)."""
    angle = np.arctan2(targets[:, 0], targets[:, 1])
    return (angle - qpos[:, 0] + np.pi) % (2 * np.pi) - np.pi


def test_reacher_targets_independent_of_initial_states():
    task, system = get_task("reacher-easy"), systems.make("dmc-reacher")
    qpos, qvel, targets = episode_starts(task, system, 64, seed=3)
    assert qpos.shape == (64, system.model.nq) and qvel.shape == (64, system.model.nv)
    assert targets.shape == (64, 3)
    gap = _angle_gap(qpos, targets.numpy())
    # one seed for both draws would put every target at the shoulder angle + pi (gap -pi, spread 0)
    assert gap.std() > 1.0
    again = episode_starts(task, system, 64, seed=3)
    np.testing.assert_array_equal(again[0], qpos)
    np.testing.assert_array_equal(again[2].numpy(), targets.numpy())


def test_task_without_targets_gives_none():
    task, system = get_task("pendulum-swingup"), systems.make("dmc-pendulum")
    qpos, qvel, targets = episode_starts(task, system, 4, seed=0)
    assert targets is None and qpos.shape == (4, system.model.nq)


def test_mpc_command_draws_targets_with_episode_starts():
    import inspect

    from gnwarp.cli import mpc
    src = inspect.getsource(mpc.mpc_command)
    assert "episode_starts(" in src and "sample_targets(" not in src


def test_vector_env_draws_each_env_as_episode_starts_of_its_seed():
    from gnwarp.control import make_vector_env
    env = make_vector_env("reacher-easy", 3, backend="mujoco")
    env.reset(seed=11)
    q = env.observe().qpos.double().numpy()
    for i in range(3):
        qpos, _, target = episode_starts(env.task, env.system, 1, seed=11 + i)
        np.testing.assert_allclose(q[i], qpos[0], atol=1e-6)
        np.testing.assert_array_equal(env.targets[i].numpy(), target[0].numpy())
    env.close()
