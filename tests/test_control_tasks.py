"""Control tasks (F.2): each reward against hand-computed states, the registry's errors."""
import math

import numpy as np
import pytest
import torch

from gnwarp import control, systems
from gnwarp.control.tasks import Task, TaskError, body_index, get_task, sample_targets, upright_angle
from gnwarp.state import quat_axis_angle

I = torch.tensor([1.0, 0.0, 0.0, 0.0])


def q(axis, angle):
    return torch.tensor(quat_axis_angle(axis, angle), dtype=torch.float32)


def states(T, B):
    """[1, T+1, B, 13] at rest, every body at identity orientation."""
    s = torch.zeros(1, T + 1, B, 13)
    s[..., 3] = 1.0
    return s


def test_balance_tasks_sum_minus_the_angles_from_upright():
    s = states(2, 2)
    s[0, 0, 1, 3:7] = q([0, 1, 0], math.pi)        # state 0 (where planning starts) is not scored
    s[0, 1, 1, 3:7] = q([0, 1, 0], math.pi / 2)
    s[0, 2, 1, 3:7] = q([1, 0, 0], -0.3)
    r = get_task("pendulum-balance").reward(s, torch.zeros(1, 2, 1))
    assert r.shape == (1,) and r.item() == pytest.approx(-(math.pi / 2 + 0.3), abs=1e-5)
    c = states(1, 3)
    c[0, 1, 1, 3:7] = q([0, 1, 0], 1.0)              # the cart turning does not count; the pole does
    c[0, 1, 2, 3:7] = -q([0, 1, 0], 0.5)             # q and -q are one orientation
    assert get_task("cartpole-balance").reward(c, None).item() == pytest.approx(-0.5, abs=1e-5)
    a = states(1, 3)
    a[0, 1, 1, 3:7] = q([0, 1, 0], 0.2)
    a[0, 1, 2, 3:7] = q([0, 1, 0], math.pi)
    assert get_task("acrobot-swingup").reward(a, None).item() == pytest.approx(-(0.2 + math.pi), abs=1e-5)
    w = states(1, 8)
    for b, ang in zip(body_index("walker", "torso", "right_thigh", "left_leg", "right_foot"), (0.1, 0.2, 0.3, 1.0)):
        w[0, 1, b, 3:7] = q([0, 1, 0], ang)          # feet are not scored
    assert get_task("walker-verticality").reward(w, None).item() == pytest.approx(-0.6, abs=1e-5)


def test_upright_angle_has_finite_gradients_at_upright():
    x = I.clone().requires_grad_(True)
    upright_angle(x).backward()
    assert torch.isfinite(x.grad).all()
    assert upright_angle(q([0, 0, 1], 0.7), q([0, 0, 1], 0.2)).item() == pytest.approx(0.5, abs=1e-5)


def test_swimmer_reach_projects_the_head_displacement_on_the_target_direction():
    s = states(2, 7)
    s[0, :, 1, :2] = torch.tensor([[1.0, 1.0], [1.1, 1.2], [1.3, 1.2]])   # head
    s[0, :, 3, :2] = 5.0                                                   # other links do not count
    target = torch.tensor([[11.0, 1.0, 0.0]])                              # direction +x from the start
    r = get_task("swimmer-reach").reward(s, None, target)
    assert r.item() == pytest.approx((0.1 + 0.2) - 0.01 * (0.2 ** 2 + 0.2 ** 2), abs=1e-6)
    with pytest.raises(TaskError, match="needs target"):
        get_task("swimmer-reach").reward(s, None)
    assert get_task("swimmer-reach", "swimmer6").system == "swimmer"       # any SwimmerN fits


def test_torso_tasks_of_cheetah_and_walker():
    s = states(2, 8)
    s[0, 1:, 1, 7:10] = torch.tensor([[2.0, 0.0, 1.0], [3.0, 0.0, -2.0]])  # torso velocity
    s[0, 1:, 1, 10:13] = torch.tensor([[0.0, 1.0, 0.0], [0.0, -2.0, 2.0]])
    s[0, 1:, 1, 2] = torch.tensor([0.5, 0.7])
    s[0, 1:, 2, 7] = 100.0                                                  # a thigh: not the torso
    expect = {"cheetah-forward": 5.0, "walker-forward": 5.0, "cheetah-height": 1.2, "walker-height": 1.2,
              "cheetah-vspeed": 1.0 + 4.0, "cheetah-spin": 1.0 + 8.0}
    for name, want in expect.items():
        assert get_task(name).reward(s, None).item() == pytest.approx(want, abs=1e-5), name


def test_walker_feet_to_head():
    s = states(2, 8)
    rf, lf = body_index("walker", "right_foot", "left_foot")
    s[0, 1:, 1, 2] = 1.0                              # torso frame at 1 m: head 0.3 m above it
    s[0, 1:, rf, 2], s[0, 1:, lf, 2] = 0.1, 0.2
    s[0, 2, 1, 3:7] = q([0, 1, 0], math.pi / 2)       # step 2: torso horizontal, head at the torso's height
    want = (1.2 ** 2 + 1.1 ** 2) + (0.9 ** 2 + 0.8 ** 2)
    assert get_task("walker-feet-to-head").reward(s, None).item() == pytest.approx(want, abs=1e-5)


def test_jaco_pose_tasks_are_minus_the_pose_loss():
    s = states(1, 10)
    palm = body_index("jaco", "hand")[0]
    assert palm == 6
    s[0, 1, palm, 3:7] = q([0, 0, 1], math.pi / 2)
    target = torch.zeros(1, 10, 7)
    target[..., 3] = 1.0
    target[0, palm, 0] = 1.0
    # palm: |dp|^2 = 1, 1 - cos^2(45 deg) = 0.5
    assert get_task("jaco-palm-pose").reward(s, None, target[:, palm]).item() == pytest.approx(-1.5, abs=1e-5)
    s[0, 1, 2, :3] = torch.tensor([0.0, 2.0, 0.0])   # another body 2 m off; the world body never counts
    target[0, 0, :3] = 9.0
    assert get_task("jaco-full-pose").reward(s, None, target).item() == pytest.approx(-5.5, abs=1e-5)
    with pytest.raises(TaskError, match=r"\[N, 10, >= 7\]"):
        get_task("jaco-full-pose").reward(s, None, target[:, palm])


def test_registry_errors_and_user_tasks():
    with pytest.raises(TaskError, match="unknown task 'pendulum-swing'.*pendulum-balance"):
        get_task("pendulum-swing")
    with pytest.raises(TaskError, match="task 'cartpole-balance' is for cartpole, but the system is pendulum"):
        get_task("cartpole-balance", "pendulum")
    spin = Task("spin", "pendulum", 10, lambda s, a, target=None: s[:, 1:, 1, 11].sum(1))
    assert get_task(spin, "pendulum") is spin
    with pytest.raises(TaskError, match="horizon"):
        Task("bad", "pendulum", 0, spin.reward)
    with pytest.raises(TaskError, match="callable"):
        Task("bad", "pendulum", 5, 3.0)
    assert set(control.TASKS) >= {"pendulum-balance", "swimmer-reach", "jaco-full-pose"}


def test_sample_targets():
    assert sample_targets(get_task("pendulum-balance"), systems.make("pendulum"), 3) is None
    t = sample_targets(get_task("swimmer-reach"), systems.make("swimmer6"), 4, seed=1)
    assert t.shape == (4, 3) and np.allclose(t[:, :2].norm(dim=1), 1.0)
    jaco = systems.make("jaco")
    full = sample_targets(get_task("jaco-full-pose"), jaco, 2)
    palm = sample_targets(get_task("jaco-palm-pose"), jaco, 2)
    assert full.shape == (2, 10, 13) and torch.allclose(palm, full[:, 6])
    s = full[:, None].repeat(1, 2, 1, 1)               # at the target: no loss
    assert torch.allclose(get_task("jaco-full-pose").reward(s, None, full), torch.zeros(2), atol=1e-5)
