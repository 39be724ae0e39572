"""The DMC observations from body states against the suite's own ``get_observation`` on MuJoCo C
trajectories (float64), and the joint coordinates against MuJoCo's qpos / qvel."""
from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest
import torch

from gnwarp.control import dmc as cdmc
from gnwarp.control.tasks import get_task, sample_targets
from gnwarp.rl.obs_reward import ObservationReward, forward_kinematics
from gnwarp.rl.observations import DMCObservation, joint_coordinates, observation_domain, wrap_angle
from gnwarp.sim import systems
from gnwarp.sim.body_state import body_states

pytest.importorskip("dm_control")


SUITE_TASKS = {
    "dmc-swimmer-swimmer6": lambda m: m.Swimmer(random=0),
    "dmc-cheetah-run": lambda m: m.Cheetah(random=0),
    "dmc-walker-walk": lambda m: m.PlanarWalker(move_speed=1, random=0),
}


def _trajectories(name, suite_physics, E=3, T=8, seed=0):
    """Body states [E, T+1, B, 13], qpos [E, T+1, nq], qvel, targets [E, 3] (or None) and the suite's
    flat observations [E, T+1, D] (its dict order) at the same states."""
    rng = np.random.default_rng(seed)
    task = get_task(name)
    system = systems.make(task.system)
    m, d = system.model, mujoco.MjData(system.model)
    module, physics = suite_physics(task.system)
    suite_task = SUITE_TASKS[name](module)
    qpos0, qvel0 = task.initial(system, E, rng)
    qvel0 = qvel0 + rng.normal(0, 1.0, qvel0.shape)       # moving from the start: every velocity nonzero
    target = sample_targets(task, system, E, seed=seed)
    target = None if target is None else target.double().numpy()
    body, qp, qv, ref = [], [], [], []
    for k in range(E):
        if target is not None:
            physics.named.model.geom_pos["target", "x"] = target[k, 0]
            physics.named.model.geom_pos["target", "y"] = target[k, 1]
        mujoco.mj_resetData(m, d)
        d.qpos[:], d.qvel[:] = qpos0[k], qvel0[k]
        mujoco.mj_forward(m, d)
        b, p, v, o = [], [], [], []
        for t in range(T + 1):
            if t:
                d.ctrl[:] = rng.uniform(-1, 1, m.nu)
                mujoco.mj_step(m, d, system.substeps)
                mujoco.mj_forward(m, d)
            b.append(body_states(m, d))
            p.append(d.qpos.copy())
            v.append(d.qvel.copy())
            physics.data.qpos[:], physics.data.qvel[:] = d.qpos, d.qvel
            physics.forward()
            o.append(np.concatenate([np.atleast_1d(x).ravel() for x in suite_task.get_observation(physics).values()]
                                    + [[suite_task.get_reward(physics)]]))
        body.append(b)
        qp.append(p)
        qv.append(v)
        ref.append(o)
    t = None if target is None else torch.tensor(target)
    ref = torch.tensor(np.array(ref))
    return (torch.tensor(np.array(body)), torch.tensor(np.array(qp)), torch.tensor(np.array(qv)), t,
            ref[..., :-1], ref[..., -1])


@pytest.mark.parametrize("name", list(SUITE_TASKS))
def test_observation_equals_the_suites(suite_physics, name):
    body, qpos, qvel, target, ref, _ = _trajectories(name, suite_physics)
    obs = DMCObservation(name)
    out = obs(body, target)                        # [E, T+1, B, 13] with targets [E, 3]
    assert out.dtype == torch.float64 and out.shape == ref.shape == (*body.shape[:2], obs.size)
    assert len(obs.names) == obs.size
    diff = out - ref
    if obs.domain == "cheetah":                    # rooty, an unlimited hinge: equal up to 2 pi turns
        i = obs.names.index("position.rooty")
        diff[..., i] = wrap_angle(diff[..., i])
    assert diff.abs().max() < 1e-10, (name, diff.abs().amax((0, 1)))
    # the same per step, with the target given per env
    flat = obs(body[:, 3], None if target is None else target[:, :2])
    assert torch.allclose(flat, out[:, 3], atol=1e-12)
    assert ref.abs().amax((0, 1)).min() > 1e-4     # no entry is trivially zero on these trajectories


@pytest.mark.parametrize("name", list(SUITE_TASKS))
def test_joint_coordinates_are_mujocos(suite_physics, name):
    body, qpos, qvel, _, _, _ = _trajectories(name, suite_physics, E=2, T=4, seed=1)
    m = systems.make(get_task(name).system).model
    p, v = joint_coordinates(m, body)
    hinge = torch.tensor(m.jnt_type == mujoco.mjtJoint.mjJNT_HINGE)
    dp = torch.where(hinge, wrap_angle(p - qpos), p - qpos)
    assert dp.abs().max() < 1e-10 and (v - qvel).abs().max() < 1e-10

    fk = forward_kinematics(m, qpos, qvel)
    assert (fk[..., 1:, :] - body[..., 1:, :]).abs().max() < 1e-10


@pytest.mark.parametrize("name", list(SUITE_TASKS))
def test_reward_from_the_observation_is_the_suites(suite_physics, name):
    body, _, _, target, ref, reward = _trajectories(name, suite_physics, seed=3)
    obs = DMCObservation(name)
    x = obs(body, target).flatten(0, 1)
    x.requires_grad_(True)
    r = ObservationReward(name, obs)(x, None, x)
    assert (r.detach() - reward.flatten()).abs().max() < 1e-9, name
    assert reward.max() > 1e-3                     # not all zero on these trajectories
    r.sum().backward()
    assert torch.isfinite(x.grad).all()
    # from the suite's own observation vector too (the walker's pitch from its orientations)
    assert (ObservationReward(name)(ref.flatten(0, 1), None, ref.flatten(0, 1)) - reward.flatten()).abs().max() < 1e-9


def test_joint_coordinates_of_a_model_without_joints_or_bodies():
    """A world alone, and a body without joints: empty coordinates, no error."""
    from gnwarp.rl.observations import JointCoordinates
    for xml in ("<mujoco/>", "<mujoco><worldbody><body><geom size='.1'/></body></worldbody></mujoco>"):
        m = mujoco.MjModel.from_xml_string(xml)
        p, v = JointCoordinates(m)(torch.zeros(3, m.nbody, 13))
        assert p.shape == (3, 0) and v.shape == (3, 0)


def test_float32_and_a_learned_models_batch_shape():
    obs = DMCObservation("dmc-walker")
    m = obs.system.model
    d = mujoco.MjData(m)
    rng = np.random.default_rng(2)
    d.qpos[:] = cdmc.randomize_joints(m, 1, rng)[0]
    d.qvel[:] = rng.normal(0, 1, m.nv)
    mujoco.mj_forward(m, d)
    b = torch.tensor(body_states(m, d))
    x64 = obs(b[None])
    x32 = obs(b[None].float())
    assert x32.dtype == torch.float32 and torch.allclose(x32.double(), x64, atol=1e-5)


def test_names_and_errors():
    assert observation_domain("swimmer6") == observation_domain("dmc-swimmer6") == "swimmer6"
    assert observation_domain("dmc-walker-run") == "walker"
    assert DMCObservation("cheetah").size == 17 and DMCObservation("walker").size == 24
    sw = DMCObservation("dmc-swimmer-swimmer6")
    assert sw.size == 25 and sw.parts["to_target"] == slice(5, 7)
    with pytest.raises(ValueError, match="no DMC observation"):
        DMCObservation("hopper")
    with pytest.raises(ValueError, match="needs the episode's target"):
        sw(torch.zeros(2, 7, 13))
    with pytest.raises(ValueError, match=r"\[\.\.\., 7, 13\]"):
        sw(torch.zeros(2, 6, 13), torch.zeros(2, 3))
    ball = mujoco.MjModel.from_xml_string(
        "<mujoco><worldbody><body><joint type='ball'/><geom size='.1'/></body></worldbody></mujoco>")
    with pytest.raises(ValueError, match="neither a slide nor a hinge"):
        joint_coordinates(ball, torch.zeros(2, 13))
    with pytest.raises(ValueError, match="needs the walker observation, got cheetah"):
        ObservationReward("walker-stand", DMCObservation("cheetah"))
    with pytest.raises(ValueError, match="no DMC observation"):
        ObservationReward("reacher-easy")
    assert math.isclose(float(wrap_angle(torch.tensor(3 * math.pi / 2, dtype=torch.float64))), -math.pi / 2)


@pytest.mark.parametrize("domain", ["cheetah", "walker"])
def test_planar_chain_is_the_general_kinematics(domain):
    """The planar fast path (what cheetah's and walker's rewards run) against the body-by-body
    composition, at random joint coordinates far from the data: states and their gradients
    (float64), and the same in float32."""
    from gnwarp.rl.planar_fk import planar_chain
    obs = DMCObservation(domain)
    m, coords = obs.system.model, obs.coords
    assert planar_chain(coords) is not None and planar_chain(coords) is planar_chain(coords)   # made once
    g = torch.Generator().manual_seed(4)
    qpos = (3 * torch.randn(2, 5, m.nq, generator=g, dtype=torch.float64)).requires_grad_(True)
    qvel = (3 * torch.randn(2, 5, m.nv, generator=g, dtype=torch.float64)).requires_grad_(True)
    fast = planar_chain(coords)(qpos, qvel)
    assert torch.equal(forward_kinematics(m, qpos, qvel, coords), fast)   # what the rewards run
    slow = forward_kinematics(m, qpos, qvel, coords, planar=False)
    assert fast.shape == slow.shape == (2, 5, m.nbody, 13)
    assert (fast - slow).abs().max() < 1e-12
    w = torch.randn(fast.shape, generator=g, dtype=torch.float64)
    gf = torch.autograd.grad((fast * w).sum(), (qpos, qvel))
    gs = torch.autograd.grad((slow * w).sum(), (qpos, qvel))
    assert all((a - b).abs().max() < 1e-11 for a, b in zip(gf, gs))
    f32 = forward_kinematics(m, qpos.detach().float(), qvel.detach().float(), coords)
    assert f32.dtype == torch.float32 and (f32.double() - slow).abs().max() < 1e-4
    task = {"cheetah": "cheetah-run", "walker": "walker-walk"}[domain]   # the reward on either path
    x = torch.randn(6, obs.size, generator=g, dtype=torch.float64)
    r_fast, r_slow = ObservationReward(task, obs)(x, None, x), ObservationReward(task, obs, planar=False)(x, None, x)
    assert (r_fast - r_slow).abs().max() < 1e-12 and r_fast.abs().max() > 0


@pytest.mark.parametrize("domain", ["cheetah", "walker"])
def test_planar_chain_in_real_pairs_is_the_complex_one(domain):
    """The chain's complex numbers as pairs of real tensors (what runs inside torch.compile) give
    the complex tensors' states and gradients (float64)."""
    from gnwarp.rl.planar_fk import planar_chain
    obs = DMCObservation(domain)
    m, chain = obs.system.model, planar_chain(obs.coords)
    g = torch.Generator().manual_seed(7)
    qpos = (3 * torch.randn(4, m.nq, generator=g, dtype=torch.float64)).requires_grad_(True)
    qvel = (3 * torch.randn(4, m.nv, generator=g, dtype=torch.float64)).requires_grad_(True)
    cx, pr = chain(qpos, qvel), chain(qpos, qvel, pairs=True)
    assert pr.shape == cx.shape and (pr - cx).abs().max() < 1e-12
    w = torch.randn(cx.shape, generator=g, dtype=torch.float64)
    gc = torch.autograd.grad((cx * w).sum(), (qpos, qvel))
    gp = torch.autograd.grad((pr * w).sum(), (qpos, qvel))
    assert all((a - b).abs().max() < 1e-11 for a, b in zip(gc, gp))


def test_the_planar_reward_traces_whole_for_torch_compile():
    """Walker's reward (its planar kinematics included) traces into one graph: no graph break, so
    an update compiled by inductor fuses it; the traced function computes the eager reward."""
    import torch._dynamo
    obs = DMCObservation("walker")
    reward = ObservationReward("walker-walk", obs)
    x = torch.randn(5, obs.size, generator=torch.Generator().manual_seed(2))
    eager = reward(x, None, x)
    torch._dynamo.reset()
    explained = torch._dynamo.explain(lambda o: reward(o, None, o))(x)
    assert explained.graph_break_count == 0 and explained.graph_count == 1, explained.break_reasons
    traced = torch.compile(lambda o: reward(o, None, o), backend="aot_eager", fullgraph=True)(x)
    assert (traced - eager).abs().max() < 1e-5


def test_planar_chain_refuses_other_models():
    from gnwarp.rl.observations import JointCoordinates
    from gnwarp.rl.planar_fk import PlanarChain, not_planar, planar_chain
    swimmer = DMCObservation("swimmer6").coords            # moves in the x-y plane
    assert "out of the x-z plane" in not_planar(swimmer) and planar_chain(swimmer) is None
    hinge_z = mujoco.MjModel.from_xml_string(
        "<mujoco><worldbody><body><joint axis='0 0 1'/><geom size='.1'/></body></worldbody></mujoco>")
    assert "hinge axis is not +-y" in not_planar(JointCoordinates(hinge_z))
    side = mujoco.MjModel.from_xml_string(
        "<mujoco><worldbody><body><joint type='slide' axis='0 1 0'/><geom size='.1'/></body></worldbody></mujoco>")
    assert "out of the x-z plane" in not_planar(JointCoordinates(side))
    tilted = mujoco.MjModel.from_xml_string(
        "<mujoco><worldbody><body quat='1 1 0 0'><joint axis='0 1 0'/><geom size='.1'/></body></worldbody></mujoco>")
    with pytest.raises(ValueError, match="not a rotation about y"):
        PlanarChain(JointCoordinates(tilted))
    # the general path still serves them: the swimmer's bodies from its coordinates
    m = DMCObservation("swimmer6").system.model
    body = forward_kinematics(m, torch.zeros(1, m.nq, dtype=torch.float64), torch.zeros(1, m.nv, dtype=torch.float64))
    assert body.shape == (1, m.nbody, 13) and torch.isfinite(body).all()


# a planar chain with what DMC's models lack: body frames rotated about y, slides off the root and
# along an oblique axis, hinges about -y with offset anchors and references, a body without joints,
# levels mixing all of these, and a second tree
MIXED_PLANAR = """<mujoco><worldbody>
  <body pos=".1 .2 .3" quat=".9238795 0 .3826834 0">
    <joint type="slide" axis=".8 0 -.6" ref=".1"/><joint type="slide" axis=".6 0 .8"/>
    <joint type="hinge" axis="0 1 0" pos=".05 .1 -.02" ref=".2"/><geom size=".05"/>
    <body pos=".3 -.1 .1"><joint type="hinge" axis="0 -1 0" pos=".1 0 .05"/><geom size=".05"/>
      <body pos="0 .05 -.2" quat=".7071068 0 -.7071068 0"><joint type="slide" axis="0 0 1" ref="-.3"/>
        <geom size=".05"/></body></body>
    <body pos="-.2 0 .1"><geom size=".05"/></body>
  </body>
  <body pos="1 0 0"><joint type="hinge" axis="0 1 0"/><geom size=".05"/></body>
</worldbody></mujoco>"""


def test_kinematics_of_a_mixed_planar_chain_are_mujocos():
    """Both kinematics paths against MuJoCo's own body states on the chain above (a slide on a
    rotating parent moves with it), and a non-finite coordinate stays in its own body."""
    from gnwarp.rl.observations import JointCoordinates
    from gnwarp.rl.planar_fk import planar_chain
    m = mujoco.MjModel.from_xml_string(MIXED_PLANAR)
    coords = JointCoordinates(m)
    chain = planar_chain(coords)
    assert chain is not None
    d = mujoco.MjData(m)
    rng = np.random.default_rng(5)
    for _ in range(3):
        d.qpos[:] = rng.normal(0, 1, m.nq)
        d.qvel[:] = rng.normal(0, 2, m.nv)
        mujoco.mj_forward(m, d)
        ref = torch.tensor(body_states(m, d))
        qpos, qvel = torch.tensor(d.qpos.copy())[None], torch.tensor(d.qvel.copy())[None]
        for body in (chain(qpos, qvel)[0], chain(qpos, qvel, pairs=True)[0],
                     forward_kinematics(m, qpos, qvel, coords, planar=False)[0]):
            assert (body[1:] - ref[1:]).abs().max() < 1e-10
    bad = qpos.clone()
    bad[0, -1] = float("nan")                      # the second tree's hinge
    body = chain(bad, qvel)[0]
    assert torch.isfinite(body[:-1]).all() and not torch.isfinite(body[-1]).all()
