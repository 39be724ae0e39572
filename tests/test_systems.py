"""Tests of gnwarp.sim.systems: the paper's systems (section B), their parameterized variants, MJCF."""
import math

import mujoco
import numpy as np
import pytest

from gnwarp.sim import builders, systems

# name: (bodies incl. world, nq, nv, nu, data timestep) -- the reference table.
TABLE = {
    "pendulum": (2, 1, 1, 1, 0.02),
    "cartpole": (3, 2, 2, 1, 0.01),
    "acrobot": (3, 2, 2, 1, 0.01),
    "swimmer3": (4, 5, 5, 2, 0.02),
    "swimmer6": (7, 8, 8, 5, 0.02),
    "swimmer15": (16, 17, 17, 14, 0.02),
    "cheetah": (8, 9, 9, 6, 0.01),
    "walker": (8, 9, 9, 6, 0.0025),
    "jaco": (10, 9, 9, 9, 0.1),
}
CONTACT_FREE = ["pendulum", "cartpole", "acrobot", "swimmer6", "jaco"]
PARAMETERIZED = ["pendulum", "cartpole", "swimmer", "swimmer6", "cheetah", "jaco"]


def rollout(system, seconds, seed=0, ctrl=None):
    """Steps the system with MuJoCo C under random (or given constant) controls; returns data."""
    model = system.model
    data = mujoco.MjData(model)
    rng = np.random.default_rng(seed)
    low, high = model.actuator_ctrlrange.T
    for _ in range(int(round(seconds / system.dt))):
        data.ctrl[:] = rng.uniform(low, high) if ctrl is None else ctrl
        for _ in range(system.substeps):
            mujoco.mj_step(model, data)
    return data


def model_arrays(model):
    return [model.body_mass, model.body_inertia, model.body_pos, model.body_quat,
            model.geom_size, model.geom_pos, model.actuator_gear]


# ------------------------------------------------------------------------------------------------
# Fixed systems.


def test_names():
    assert systems.names() == ["pendulum", "cartpole", "acrobot", "swimmer", "cheetah", "walker",
                               "jaco"]


@pytest.mark.parametrize("name", list(TABLE))
def test_sizes_and_timesteps(name):
    nbody, nq, nv, nu, dt = TABLE[name]
    system = systems.make(name)
    assert (system.nbody, system.nq, system.nv, system.nu) == (nbody, nq, nv, nu)
    assert system.name == name
    assert system.dt == pytest.approx(dt)
    assert system.timestep * system.substeps == pytest.approx(dt)
    assert system.model.opt.timestep == pytest.approx(dt / system.substeps)
    assert not system.parameterized and system.params == {}


def test_swimmer_default_and_all_sizes():
    assert systems.make("swimmer").name == "swimmer6"
    for n in range(3, 16):
        system = systems.make(f"swimmer{n}")
        assert (system.nbody, system.nq, system.nu) == (n + 1, n + 2, n - 1)
    assert systems.make("swimmer").timestep == pytest.approx(0.002)  # dm_control's 2 ms


@pytest.mark.parametrize("name", list(TABLE))
def test_fixed_systems_step_one_second(name):
    system = systems.make(name)
    data = rollout(system, 1.0)
    assert np.isfinite(data.qpos).all() and np.isfinite(data.qvel).all()
    assert data.time == pytest.approx(1.0)
    assert np.abs(data.qvel).max() < 100


@pytest.mark.parametrize("name", CONTACT_FREE)
def test_contact_free_systems_disable_contacts(name):
    system = systems.make(name)
    assert system.model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT
    assert not system.contacts


@pytest.mark.parametrize("name", ["cheetah", "walker"])
def test_legged_systems_touch_the_floor(name):
    system = systems.make(name)
    assert system.contacts
    data = rollout(system, 1.0)  # falls onto the floor within a second
    assert data.ncon > 0
    floor = mujoco.mj_name2id(system.model, mujoco.mjtObj.mjOBJ_GEOM, "floor")
    touching = {int(g) for c in data.contact[: data.ncon] for g in (c.geom1, c.geom2)}
    assert floor in touching


def test_translation_invariance_flags():
    invariant = {n for n in TABLE if systems.make(n).translation_invariant}
    assert invariant == {"swimmer3", "swimmer6", "swimmer15", "cheetah", "walker"}
    for n in TABLE:   # one record: the family's axes, read the same way without building the system
        s = systems.make(n)
        assert s.translation_axes == systems.translation_axes(n) == {"cheetah": (0,), "walker": (0,)}.get(
            n, (0, 1) if n.startswith("swimmer") else ()), n
    assert systems.translation_axes("my_robot") == ()
    with pytest.raises(ValueError, match="translation_axes must hold distinct horizontal axes"):
        systems.from_mjcf_string("<mujoco/>", translation_axes=(2,))


def test_dm_control_details():
    pendulum = systems.make("pendulum").model
    assert pendulum.body_mass[1] == pytest.approx(1.0)
    assert pendulum.dof_damping[0] == pytest.approx(0.1)
    cartpole = systems.make("cartpole").model
    assert cartpole.body_mass[1:] == pytest.approx([1.0, 0.1])
    assert cartpole.actuator_gear[0, 0] == pytest.approx(10)
    assert cartpole.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4
    acrobot = systems.make("acrobot").model
    assert acrobot.actuator_trnid[0, 0] == mujoco.mj_name2id(acrobot, mujoco.mjtObj.mjOBJ_JOINT,
                                                             "elbow")
    assert acrobot.actuator_gear[0, 0] == pytest.approx(2)
    cheetah = systems.make("cheetah").model
    assert cheetah.body_mass.sum() == pytest.approx(14.0)  # dm_control's settotalmass
    assert cheetah.actuator_gear[:, 0] == pytest.approx([120, 90, 60, 90, 60, 30])
    walker = systems.make("walker").model
    assert walker.actuator_gear[:, 0] == pytest.approx([100, 50, 20, 100, 50, 20])
    swimmer = systems.make("swimmer6").model
    assert swimmer.opt.density == pytest.approx(3000)
    assert swimmer.body_mass[1:] == pytest.approx([0.01] * 6)
    assert swimmer.jnt_range[3:, 1] == pytest.approx([2 * math.pi / 6] * 5)


def test_jaco_structure():
    system = systems.make("jaco")
    model = system.model
    assert (model.jnt_type == mujoco.mjtJoint.mjJNT_HINGE).all()
    assert model.njnt == 9
    # 6 arm joints in a chain, 3 finger joints on the hand.
    hand = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "hand")
    assert list(model.body_parentid[1:7]) == [0, 1, 2, 3, 4, 5]
    assert list(model.body_parentid[7:]) == [hand] * 3
    assert systems.describe(system)["actuators"] == "velocity"
    # qpos0 is inside every joint's limits.
    for j in range(model.njnt):
        if model.jnt_limited[j]:
            low, high = model.jnt_range[j]
            assert low < model.qpos0[model.jnt_qposadr[j]] < high
    # Gravity is on; the upright pose needs little torque to hold.
    assert model.opt.gravity[2] < 0
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    assert np.abs(data.qfrc_bias).max() < 0.1


@pytest.mark.parametrize("gear", [1.0, 1.5])
def test_jaco_velocity_actuators_track_targets(gear):
    params = {f"gear_{a}": gear for a in builders.JACO_ACTUATOR_NAMES}
    system = systems.make("jaco", params=params)
    high = system.model.actuator_ctrlrange[:, 1]
    target = 0.5 * high
    target[6:] = 0.5  # fingers: 0.5 rad/s for 0.5 s stays inside their 0.15..1.35 range
    data = rollout(system, 0.5, ctrl=target)
    # A velocity actuator drives gear * qvel to its control.
    expected = target / gear
    error = np.abs(data.qvel - expected)
    assert (error[:6] < 0.05 * np.abs(expected[:6]) + 0.01).all(), (data.qvel, expected)
    # Fingers lose ~10% to their damping and friction (dm_control's values).
    assert (error[6:] < 0.15 * np.abs(expected[6:])).all(), (data.qvel, expected)


def test_describe_rows():
    row = systems.describe(systems.make("swimmer6"))
    assert row["name"] == "swimmer6" and row["bodies"] == 7 and row["nq"] == 8
    assert row["nv"] == 8 and row["nu"] == 5 and row["actuators"] == "motor"
    assert row["timestep"] == pytest.approx(0.002) and row["dt"] == pytest.approx(0.02)
    assert row["substeps"] == 10 and row["contacts"] is False
    assert row["parameters"] == {"n_links": (3, 9), "link_length_*": (0.3, 2.0),
                                 "link_thickness_*": (0.5, 5.0)}
    assert systems.describe(systems.make("walker"))["parameters"] == {}
    assert systems.describe(systems.make("cheetah"))["contacts"] is True


# ------------------------------------------------------------------------------------------------
# Parameterized variants.


def test_param_ranges():
    assert systems.param_ranges("pendulum") == {"length": (0.2, 1.0), "mass": (0.5, 3.0)}
    assert systems.param_ranges("cartpole") == {"cart_mass": (0.2, 2.0),
                                                "pole_length": (0.3, 1.0),
                                                "pole_thickness": (0.4, 2.2)}
    assert systems.param_ranges("acrobot") == {} and systems.param_ranges("walker") == {}
    swimmer = systems.param_ranges("swimmer")
    assert swimmer["n_links"] == (3, 9)
    assert swimmer["link_length_8"] == (0.3, 2.0) and swimmer["link_thickness_0"] == (0.5, 5.0)
    assert systems.param_ranges("swimmer6")["n_links"] == (6, 6)
    cheetah = systems.param_ranges("cheetah")
    assert cheetah["base_angle_bthigh"] == (-0.1, 0.1) and cheetah["length_torso"] == (0.5, 2.0)
    assert len(cheetah) == 6 + 7 + 7
    jaco = systems.param_ranges("jaco")
    assert len(jaco) == 18 and jaco["mass_hand"] == (0.5, 1.5)
    assert jaco["gear_finger_3"] == (0.5, 1.5)


@pytest.mark.parametrize("name", PARAMETERIZED)
def test_sampled_params_inside_ranges_and_recorded(name):
    ranges = systems.param_ranges(name)
    for seed in range(5):
        system = systems.make(name, seed=seed)
        assert system.parameterized
        assert system.params == systems.sample_params(name, np.random.default_rng(seed))
        assert set(system.params) <= set(ranges)
        for key, value in system.params.items():
            low, high = ranges[key]
            assert low <= value <= high, (key, value)
        data = rollout(system, 0.5, seed=seed)
        assert np.isfinite(data.qpos).all() and np.isfinite(data.qvel).all()


def test_swimmer_samples_its_number_of_links():
    counts = set()
    for seed in range(40):
        system = systems.make("swimmer", seed=seed)
        n = int(system.params["n_links"])
        assert system.params["n_links"] == n and 3 <= n <= 9
        assert system.name == f"swimmer{n}" and system.nbody == n + 1 and system.nu == n - 1
        assert {k for k in system.params if k.startswith("link_")} == {
            f"link_{what}_{i}" for what in ("length", "thickness") for i in range(n)}
        counts.add(n)
    assert counts == set(range(3, 10))
    fixed_n = systems.make("swimmer6", seed=0)
    assert fixed_n.params["n_links"] == 6 and fixed_n.nbody == 7


@pytest.mark.parametrize("name", PARAMETERIZED)
def test_seeds_are_reproducible(name):
    a, b, c = (systems.make(name, seed=s) for s in (7, 7, 8))
    assert a.params == b.params and a.params != c.params
    for x, y in zip(model_arrays(a.model), model_arrays(b.model)):
        np.testing.assert_array_equal(x, y)
    if a.model.nbody == c.model.nbody:
        assert not np.array_equal(a.model.body_mass, c.model.body_mass) or not np.array_equal(
            a.model.actuator_gear, c.model.actuator_gear)


def test_explicit_params_fill_defaults():
    system = systems.make("cartpole", params={"pole_length": 0.5})
    assert system.params == {"cart_mass": 1.0, "pole_length": 0.5, "pole_thickness": 1.0}
    assert systems.make("pendulum", params={}).params == {"length": 1.0, "mass": 1.0}
    # A recorded parameter dict rebuilds the same model.
    sampled = systems.make("swimmer", seed=3)
    again = systems.make("swimmer", params=sampled.params)
    for x, y in zip(model_arrays(sampled.model), model_arrays(again.model)):
        np.testing.assert_array_equal(x, y)


def test_pendulum_mass_and_length():
    fixed = systems.make("pendulum").model
    system = systems.make("pendulum", params={"mass": 2.5, "length": 0.4}).model
    assert system.body_mass[1] == pytest.approx(2.5 * fixed.body_mass[1])
    assert system.body_ipos[1, 2] == pytest.approx(0.4 * fixed.body_ipos[1, 2])  # bob moved in


def test_cartpole_masses_follow_sizes():
    fixed = systems.make("cartpole").model
    system = systems.make("cartpole", params={"cart_mass": 0.2, "pole_length": 0.5,
                                              "pole_thickness": 2.0}).model
    assert system.body_mass[1] == pytest.approx(0.2)

    def capsule_volume(radius, length):
        return math.pi * radius**2 * length + 4 / 3 * math.pi * radius**3

    ratio = capsule_volume(0.09, 0.5) / capsule_volume(0.045, 1.0)
    assert system.body_mass[2] == pytest.approx(fixed.body_mass[2] * ratio)


def test_swimmer_masses_follow_sizes():
    fixed = systems.make("swimmer6").model
    system = systems.make("swimmer6", params={"link_length_2": 2.0, "link_thickness_4": 2.0})
    mass = system.model.body_mass
    assert mass[3] == pytest.approx(2 * fixed.body_mass[3])  # twice as long
    assert mass[5] == pytest.approx(4 * fixed.body_mass[5])  # twice as thick (cross-section)
    assert mass[[1, 2, 4, 6]] == pytest.approx(fixed.body_mass[[1, 2, 4, 6]])
    # The long link's largest moment, m/3 (b^2 + c^2) of its .002 x .1 x .02 m box, follows.
    b, c = 0.05, 0.01
    ratio = 2 * ((2 * b) ** 2 + c**2) / (b**2 + c**2)
    assert system.model.body_inertia[3].max() == pytest.approx(
        ratio * fixed.body_inertia[3].max())


def test_cheetah_masses_follow_sizes():
    fixed = systems.make("cheetah").model
    thigh = mujoco.mj_name2id(fixed, mujoco.mjtObj.mjOBJ_BODY, "bthigh")
    longer = systems.make("cheetah", params={"length_bthigh": 2.0}).model
    ratio = longer.body_mass[thigh] / fixed.body_mass[thigh]
    assert 1.7 < ratio < 2.0  # a capsule: the cylinder doubles, the end caps do not
    assert longer.body_inertia[thigh].max() > 4 * fixed.body_inertia[thigh].max()
    thicker = systems.make("cheetah", params={"thickness_bthigh": 2.0}).model
    assert 4.0 < thicker.body_mass[thigh] / fixed.body_mass[thigh] < 8.0
    # Other bodies keep their masses: density, not total mass, is constant.
    others = [b for b in range(1, fixed.nbody) if b != thigh]
    assert longer.body_mass[others] == pytest.approx(fixed.body_mass[others])


def test_jaco_mass_and_gear_factors():
    fixed = systems.make("jaco").model
    system = systems.make("jaco", params={"mass_arm": 1.5, "gear_joint_3": 0.5}).model
    arm = mujoco.mj_name2id(fixed, mujoco.mjtObj.mjOBJ_BODY, "arm")
    assert system.body_mass[arm] == pytest.approx(1.5 * fixed.body_mass[arm])
    assert system.body_inertia[arm] == pytest.approx(1.5 * fixed.body_inertia[arm])
    assert system.actuator_gear[2, 0] == pytest.approx(0.5)
    assert np.delete(system.actuator_gear[:, 0], 2) == pytest.approx(1.0)


def test_swimmer_chain_stays_connected():
    rng = np.random.default_rng(0)
    params = {f"link_length_{i}": float(rng.uniform(0.3, 2.0)) for i in range(6)}
    system = systems.make("swimmer6", params=params)
    model, data = system.model, mujoco.MjData(system.model)
    data.qpos[3:] = rng.uniform(-0.5, 0.5, size=5)
    mujoco.mj_kinematics(model, data)
    for i in range(1, 6):  # body i+1's joint sits at the far end of link i
        half = 0.05 * params[f"link_length_{i - 1}"]
        end = data.xpos[i] + data.xmat[i].reshape(3, 3) @ np.array([0.0, half, 0.0])
        joint = model.body_jntadr[i + 1]
        np.testing.assert_allclose(data.xanchor[joint], end, atol=1e-9)


def test_cheetah_chain_scales_with_parent_length():
    fixed = systems.make("cheetah").model
    params = {"length_torso": 1.5, "length_bthigh": 0.6, "length_fshin": 2.0}
    system = systems.make("cheetah", params=params).model
    for body in range(2, fixed.nbody):
        parent = fixed.body_parentid[body]
        name = mujoco.mj_id2name(fixed, mujoco.mjtObj.mjOBJ_BODY, parent)
        scale = params.get(f"length_{name}", 1.0)
        np.testing.assert_allclose(system.body_pos[body], scale * fixed.body_pos[body])


def test_cheetah_keeps_its_floor_clearance():
    def lowest(model):
        return builders._lowest_point(model)

    fixed = lowest(systems.make("cheetah").model)
    assert fixed > 0
    for seed in range(3):
        assert lowest(systems.make("cheetah", seed=seed).model) == pytest.approx(fixed)


def test_cheetah_base_angles_turn_bodies():
    system = systems.make("cheetah", params={"base_angle_fshin": 0.1}).model
    fshin = mujoco.mj_name2id(system, mujoco.mjtObj.mjOBJ_BODY, "fshin")
    quat = system.body_quat[fshin]
    assert quat == pytest.approx([math.cos(0.05), 0.0, math.sin(0.05), 0.0])


# ------------------------------------------------------------------------------------------------
# Bad input.


def test_unknown_system_lists_valid_names():
    with pytest.raises(ValueError, match="unknown system 'hopper'.*pendulum.*jaco"):
        systems.make("hopper")


@pytest.mark.parametrize("name", ["swimmer2", "swimmer16", "swimmer0"])
def test_swimmer_size_out_of_range(name):
    with pytest.raises(ValueError, match="3 to 15 links"):
        systems.make(name)


@pytest.mark.parametrize("name", ["acrobot", "walker"])
def test_no_parameterized_variant(name):
    with pytest.raises(ValueError, match="no parameterized variant"):
        systems.make(name, seed=0)
    with pytest.raises(ValueError, match="no parameterized variant"):
        systems.make(name, params={"length": 1.0})
    with pytest.raises(ValueError, match="no parameterized variant"):
        systems.sample_params(name, np.random.default_rng(0))


@pytest.mark.parametrize("name, params, match", [
    ("pendulum", {"lenght": 0.5}, "unknown parameter.*'lenght'"),
    ("pendulum", {"length": 1.5}, r"'length'=1.5 is outside its range \[0.2, 1.0\]"),
    ("pendulum", {"mass": float("nan")}, "'mass'"),
    ("pendulum", {"mass": "heavy"}, "'mass' must be a number"),
    ("cheetah", {"base_angle_bthigh": 0.2}, "'base_angle_bthigh'"),
    ("jaco", {"gear_joint_1": 0.4}, "'gear_joint_1'"),
    ("swimmer", {"n_links": 4.5}, "'n_links' must be an integer"),
    ("swimmer", {"n_links": 12}, "'n_links'=12"),
    ("swimmer6", {"n_links": 4}, "varies the number of links"),
    ("swimmer", {"n_links": 4, "link_length_5": 1.0}, "beyond the swimmer's 4 links"),
    ("swimmer6", {"link_length_6": 1.0}, "unknown parameter"),
])
def test_bad_params(name, params, match):
    with pytest.raises(ValueError, match=match):
        systems.make(name, params=params)


def test_params_and_seed_together():
    with pytest.raises(ValueError, match="not both"):
        systems.make("pendulum", params={"mass": 1.0}, seed=0)


PENDULUM_XML = """
<mujoco model="user">
  <option timestep="0.005"/>
  <worldbody>
    <body name="pole" pos="0 0 1">
      <joint name="hinge" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0 0 0.5" size="0.02"/>
    </body>
  </worldbody>
  <actuator><motor joint="hinge" ctrlrange="-1 1"/></actuator>
</mujoco>
"""


def test_from_mjcf(tmp_path):
    path = tmp_path / "my_pendulum.xml"
    path.write_text(PENDULUM_XML)
    system = systems.from_mjcf(path)
    assert system.name == "my_pendulum" and system.source == str(path)
    assert (system.nbody, system.nq, system.nu) == (2, 1, 1)
    assert system.dt == pytest.approx(0.005) and system.substeps == 1
    assert not system.parameterized and system.params == {}
    system = systems.from_mjcf(str(path), substeps=4)
    assert system.dt == pytest.approx(0.02) and system.timestep == pytest.approx(0.005)
    system = systems.from_mjcf(path, dt=0.03, substeps=3)
    assert system.dt == pytest.approx(0.03) and system.timestep == pytest.approx(0.01)
    assert np.isfinite(rollout(system, 0.3).qpos).all()
    assert systems.describe(system)["parameters"] == {}


def test_from_mjcf_warns_of_actuator_activations_the_graphs_do_not_hold(tmp_path):
    """An actuator with its own state (dyntype filter) makes the data non-Markov in body states:
    loading it warns, naming the actuator; a plain motor loads silently."""
    import warnings
    lagged = PENDULUM_XML.replace('<motor joint="hinge" ctrlrange="-1 1"/>',
                                  '<general name="lag" joint="hinge" ctrlrange="-1 1" dyntype="filter" dynprm="0.2"/>')
    with pytest.warns(UserWarning, match=r"actuator 'lag' carries an activation state \(MuJoCo's act, 1 in all"):
        system = systems.from_mjcf_string(lagged, name="lagged")
    assert system.model.na == 1
    path = tmp_path / "lagged.xml"
    path.write_text(lagged)
    with pytest.warns(UserWarning, match="lagged.xml: actuator 'lag' carries"):
        systems.from_mjcf(path)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        systems.from_mjcf_string(PENDULUM_XML, name="plain")


def test_from_mjcf_missing_file(tmp_path):
    missing = tmp_path / "nope.xml"
    with pytest.raises(FileNotFoundError, match="nope.xml"):
        systems.from_mjcf(missing)


@pytest.mark.parametrize("text", [
    "<mujoco><worldbody><body><geom size='1'/></body></worldbody",   # truncated
    "<mujoco><worldbody><body><geom sze='1'/></body></worldbody></mujoco>",  # bad attribute
    "not xml at all",
])
def test_from_mjcf_malformed(tmp_path, text):
    path = tmp_path / "broken.xml"
    path.write_text(text)
    with pytest.raises(ValueError, match="broken.xml: not a valid MJCF model"):
        systems.from_mjcf(path)


def test_from_mjcf_needs_joints_and_actuators(tmp_path):
    no_joint = tmp_path / "statue.xml"
    no_joint.write_text("<mujoco><worldbody><body><geom size='0.1'/></body></worldbody></mujoco>")
    with pytest.raises(ValueError, match="statue.xml: the model has no joints"):
        systems.from_mjcf(no_joint)
    no_actuator = tmp_path / "passive.xml"
    no_actuator.write_text(PENDULUM_XML.replace(
        '<actuator><motor joint="hinge" ctrlrange="-1 1"/></actuator>', ""))
    with pytest.raises(ValueError, match="passive.xml: the model has no actuators"):
        systems.from_mjcf(no_actuator)


@pytest.mark.parametrize("kwargs", [{"dt": 0.0}, {"dt": -1.0}, {"substeps": 0},
                                    {"substeps": 1.5}])
def test_from_mjcf_bad_timesteps(tmp_path, kwargs):
    path = tmp_path / "pendulum.xml"
    path.write_text(PENDULUM_XML)
    with pytest.raises(ValueError):
        systems.from_mjcf(path, **kwargs)


@pytest.mark.parametrize("name", ["cheetah", "swimmer", "jaco"])
def test_spec_compiles_to_the_model(name):
    system = systems.make(name, seed=2)
    again = system.spec.compile()
    for x, y in zip(model_arrays(system.model), model_arrays(again)):
        np.testing.assert_array_equal(x, y)
    assert again.opt.timestep == system.model.opt.timestep
