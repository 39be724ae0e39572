"""DMC systems (gnwarp.sim.dmc): the suite's own MJCF through the MJCF checks at DMC's control
timestep, the graph pipeline on them, MuJoCo-Warp on Warp's CPU beside MuJoCo C."""
import importlib
import sys
import warnings

import mujoco
import numpy as np
import pytest

from gnwarp.sim import dmc, make_env, systems

pytest.importorskip("dm_control")
pytestmark = pytest.mark.filterwarnings("ignore:.*DISPLAY environment variable")


@pytest.fixture(scope="module")
def built():
    return {name: systems.make(name) for name in dmc.dmc_names()}


def test_timesteps_and_episode_lengths_are_the_suites(built):
    """dt = the suite module's control timestep (its _CONTROL_TIMESTEP, else the model's timestep),
    substeps = control / physics timestep, 1000-step episodes (its _DEFAULT_TIME_LIMIT / dt)."""
    for name, system in built.items():
        d = dmc.domain(name)
        module = importlib.import_module(f"dm_control.suite.{d.module}")
        xml, assets = module.get_model_and_assets(*d.args)
        physics_dt = mujoco.MjModel.from_xml_string(xml if isinstance(xml, str) else xml.decode(), assets).opt.timestep
        control_dt = getattr(module, "_CONTROL_TIMESTEP", physics_dt)
        assert system.dt == pytest.approx(control_dt, rel=1e-12), name
        assert system.timestep == pytest.approx(physics_dt, rel=1e-12), name
        assert system.substeps == round(control_dt / physics_dt) and system.substeps * system.timestep == \
            pytest.approx(system.dt), name
        assert d.episode_steps == round(module._DEFAULT_TIME_LIMIT / control_dt) == 1000, name
        assert system.source == "dm_control" and system.name == name
        assert system.translation_invariant == (d.module in ("cheetah", "walker", "hopper", "swimmer"))
        assert system.translation_axes == systems.translation_axes(name) == \
            {"swimmer": (0, 1)}.get(d.module, (0,) if system.translation_invariant else ()), name
    assert (built["dmc-walker"].dt, built["dmc-walker"].substeps) == (0.025, 10)
    assert (built["dmc-swimmer6"].nu, built["dmc-swimmer6"].nbody) == (5, 7)


def test_the_model_is_the_suites(built):
    """Same bodies, masses (the cheetah's settotalmass folded into explicit inertials), joints and
    actuators as MuJoCo's compile of the suite's XML; recompiling the spec changes nothing."""
    for name, system in built.items():
        xml, assets = dmc.model_source(name)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ref = mujoco.MjModel.from_xml_string(xml, assets)
        m = system.model
        assert (m.nbody, m.nq, m.nv, m.nu, m.ngeom, m.nsite) == (ref.nbody, ref.nq, ref.nv, ref.nu, ref.ngeom, ref.nsite)
        for field in ("body_mass", "body_inertia", "body_ipos", "body_pos", "jnt_range", "actuator_gear", "geom_size"):
            np.testing.assert_allclose(getattr(m, field), getattr(ref, field), rtol=1e-12, atol=1e-15, err_msg=name)
        with warnings.catch_warnings():
            warnings.simplefilter("error")   # no deprecation warning from the folded spec
            again = system.spec.compile()
        np.testing.assert_array_equal(again.body_mass, m.body_mass)
    assert built["dmc-cheetah"].model.body_mass.sum() == pytest.approx(14.0)


def test_dmc_names_are_refused_where_they_do_not_fit():
    with pytest.raises(ValueError, match="no parameterized variant"):
        systems.make("dmc-cheetah", seed=1)
    with pytest.raises(ValueError, match="DMC systems: dmc-cheetah"):
        systems.make("dmc-quadruped")
    assert systems.param_ranges("dmc-walker") == {}
    assert set(dmc.dmc_names()).isdisjoint(systems.names())


def test_missing_dm_control_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "dm_control.suite", None)   # import fails as when not installed
    with pytest.raises(ImportError, match=r'pip install -e "\.\[dmc\]"'):
        systems.make("dmc-pendulum")


def test_core_imports_do_not_need_dm_control(monkeypatch):
    """No module imports dm_control at its top; the DMC tasks register and resolve without it."""
    import ast
    import pathlib
    import gnwarp
    root = pathlib.Path(gnwarp.__file__).parent
    for path in root.rglob("*.py"):
        for node in ast.parse(path.read_text()).body:   # module level only: lazy imports are fine
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            assert not any(n.startswith("dm_control") for n in names), path
    from gnwarp.control import dmc as control_dmc
    from gnwarp.control.tasks import get_task

    def refuse(*a, **k):
        raise ImportError("dm_control missing")
    monkeypatch.setattr(dmc, "require_dm_control", refuse)
    assert len(control_dmc.dmc_tasks()) == 13 and get_task("cheetah-run").name == "dmc-cheetah-run"


def test_from_mjcf_string_checks_like_from_mjcf():
    xml = ('<mujoco><worldbody><body><joint type="hinge"/><geom size="0.1" mass="nan"/></body></worldbody>'
           '<actuator><motor joint="0"/></actuator></mujoco>')
    with pytest.raises(ValueError, match="mine:.*not finite"):
        systems.from_mjcf_string(xml.replace('joint="0"', 'joint="j"').replace('type="hinge"', 'name="j"'),
                                 name="mine")
    ok = xml.replace(' mass="nan"', "").replace('joint="0"', 'joint="j"').replace('type="hinge"', 'name="j"')
    s = systems.from_mjcf_string(ok, name="mine", dt=0.02, substeps=4)
    assert (s.dt, s.substeps, s.timestep, s.source) == (0.02, 4, 0.005, "string")
    with pytest.raises(ValueError, match="mine: the model has no actuators"):
        systems.from_mjcf_string(ok.replace('<actuator><motor joint="j"/></actuator>', ""), name="mine")


def test_graph_pipeline_takes_every_domain(built):
    """Static graph features of every domain, and a tiny dataset generated by name."""
    from gnwarp.data.convert import static_arrays
    from gnwarp.data.generation import generate
    for name, system in built.items():
        static, layout, meta = static_arrays([system])
        assert static["n_node"][0] == system.nbody, name
        assert np.isfinite(static["senders"]).all()
    ds = generate("dmc-cartpole", (2, 1, 0), num_steps=3, seed=0, backend="mujoco", progress=False)
    assert ds.meta["system"] == "dmc-cartpole" and ds.meta["dt"] == 0.01 and ds.meta["substeps"] == 1
    assert np.isfinite(ds["train"].body[:]).all() and ds["train"].body.shape == (2, 4, 3, 13)


def test_make_env_by_name_steps_at_the_control_timestep(built):
    """make_env("dmc-walker", n) steps 10 physics steps of 2.5 ms per control step."""
    system = built["dmc-walker"]
    env = make_env("dmc-walker", 2, backend="mujoco")
    assert env.dt == 0.025 and env.substeps == 10
    rng = np.random.default_rng(0)
    qpos = np.tile(system.model.qpos0, (2, 1)) + rng.uniform(-0.1, 0.1, (2, system.nq))
    u = rng.uniform(-1, 1, (2, 3, system.nu))
    env.reset(qpos)
    body = env.rollout(u).numpy()
    m, d = system.model, mujoco.MjData(system.model)
    d.qpos[:] = qpos[1]
    for t in range(3):
        d.ctrl[:] = u[1, t]
        mujoco.mj_step(m, d, 10)
    mujoco.mj_forward(m, d)
    np.testing.assert_allclose(body[1, -1, :, :3], d.xpos, atol=1e-5)


def test_mujoco_warp_cpu_agrees_with_mujoco_c(built):
    system = built["dmc-cartpole"]   # RK4, as the suite's cartpole and acrobot
    rng = np.random.default_rng(1)
    qpos = np.tile(system.model.qpos0, (2, 1)) + rng.uniform(-0.3, 0.3, (2, system.nq))
    u = rng.uniform(-1, 1, (2, 4, system.nu))
    out = {}
    for backend in ("mujoco", "mujoco_warp_cpu"):
        env = make_env(system, 2, backend=backend)
        env.reset(qpos)
        out[backend] = env.rollout(u).double().numpy()
    assert np.abs(out["mujoco"][:, -1] - out["mujoco"][:, 0]).max() > 1e-2   # it moved
    np.testing.assert_allclose(out["mujoco_warp_cpu"], out["mujoco"], atol=1e-4)
