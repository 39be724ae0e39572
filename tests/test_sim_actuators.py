"""The actuators' record (``gnwarp.sim.actuators``): one reading of control ranges for every user,
and random actions of an actuator without limits (MuJoCo's default range [0, 0])."""
import mujoco
import numpy as np
import pytest
import torch

from gnwarp import sim
from gnwarp.control import identify_on_env
from gnwarp.control.sampling import RandomPlanner
from gnwarp.sim.actuators import UNLIMITED_SAMPLE_RANGE, Actuators

# a hinge pendulum whose motor has no ctrlrange: ctrllimited compiles to false, range [0, 0]
UNLIMITED = """<mujoco>
  <option timestep="0.01"/>
  <worldbody>
    <body name="pole">
      <joint name="hinge" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.05" mass="1"/>
    </body>
  </worldbody>
  <actuator><motor name="torque" joint="hinge"/></actuator>
</mujoco>"""


@pytest.fixture
def unlimited(tmp_path):
    path = tmp_path / "unlimited.xml"
    path.write_text(UNLIMITED)
    return sim.from_mjcf(path)


@pytest.mark.parametrize("name", ["pendulum", "cartpole", "walker", "jaco"])
def test_limited_actuators_read_their_range(name):
    m = sim.make(name).model
    act = sim.make(name).actuators
    cr = np.asarray(m.actuator_ctrlrange, dtype=np.float64)
    assert act.limited.all() and act.clamped.all()
    np.testing.assert_array_equal(np.stack([act.low, act.high], 1), cr)
    np.testing.assert_array_equal(act.sample_range(), cr)
    np.testing.assert_array_equal(np.stack(act.clamp_bounds(), 1), cr)
    np.testing.assert_array_equal(sim.control_range(m), cr)


def test_clamping_disabled_keeps_the_box_but_does_not_clamp():
    s = sim.make("pendulum")
    s.model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CLAMPCTRL)
    act = s.actuators
    assert act.limited.all() and not act.clamped.any()
    assert (act.low, act.high) == (-1.0, 1.0)
    assert np.isinf(act.clamp_bounds()[1]).all()


def test_unlimited_actuator_record(unlimited):
    m = unlimited.model
    assert not m.actuator_ctrllimited[0] and tuple(m.actuator_ctrlrange[0]) == (0.0, 0.0)
    act = unlimited.actuators
    assert act.low[0] == -np.inf and act.high[0] == np.inf and not act.clamped[0]
    np.testing.assert_array_equal(act.sample_range(), [UNLIMITED_SAMPLE_RANGE])
    assert act.mid_half() == (0.0, np.inf)
    env = sim.make_env(unlimited, 2, backend="mujoco")
    np.testing.assert_array_equal(env.ctrlrange.numpy(), [UNLIMITED_SAMPLE_RANGE])
    assert isinstance(env.actuators, Actuators)


def test_random_actions_of_an_unlimited_actuator_are_not_zero(unlimited):
    """``identify_on_env``'s random window drives an unlimited actuator in [-1, 1], and the env
    applies those controls as they are (no clamp to the raw range [0, 0])."""
    n, window = 4, 25

    class Identify:  # what identify_on_env needs of a system-ID model
        def identify(self, states, actions, instance):
            self.seen = actions
            return torch.zeros(states.shape[0], 1)

        def with_fixed_gid(self, g_id):
            return self

    model = Identify()
    model.window = window
    env = sim.make_env(unlimited, n, backend="mujoco")
    _, after, out = identify_on_env(model, env, seed=3, qpos0=np.zeros((n, 1)))
    a = out["actions"]          # the controls the env applied
    lo, hi = UNLIMITED_SAMPLE_RANGE
    assert a.shape == (n, window, 1) and bool((a >= lo).all() and (a <= hi).all())
    assert float(a.abs().min()) > 0 and float(a.min()) < -0.5 and float(a.max()) > 0.5
    torch.testing.assert_close(model.seen, a[:, :window])
    # the pole moved under those torques (zero controls would leave it hanging at rest)
    assert float(after[:, 1, 10:13].abs().max()) > 1e-3
    # the same planner straight from the record
    u = RandomPlanner(env.actuators, n, seed=0).step(None)
    assert bool((u != 0).all() and (u >= lo).all() and (u <= hi).all())


def test_random_planner_refuses_an_infinite_range():
    with pytest.raises(ValueError, match="ctrlrange must be finite"):
        RandomPlanner([[-np.inf, np.inf]], 2)


def _template(system):
    from gnwarp.data.builder import GraphTemplate, graph_builder
    from gnwarp.data.convert import static_arrays
    _, layout, _ = static_arrays([system])
    return GraphTemplate(graph_builder(layout, system), torch.zeros(2, dtype=torch.long)), layout


def test_rollout_clamp_reads_the_systems_actuator_record(unlimited):
    """A model bound to Systems clamps controls to their ``Actuators`` record: a limited actuator
    to its range, an unlimited one not at all; a dataset's template (no record) reads the same
    range from its static edge features."""
    from gnwarp.data.builder import GraphBuilder, GraphTemplate
    from gnwarp.data.convert import static_arrays
    from gnwarp.models.rollout import RolloutInputs
    big = torch.tensor([[[50.0], [-50.0], [0.25]]] * 2)                     # [N=2, T=3, U=1]
    tmpl, layout = _template(sim.make("pendulum"))
    assert tmpl.actuators is not None and tmpl.actuators[0].limited.all()
    inp = RolloutInputs(tmpl, layout)
    still = torch.zeros(2, tmpl.B, 13)
    still[..., 3] = 1.0   # bodies at rest, unit quaternions
    assert torch.equal(inp.values(still, big), big.clamp(-1.0, 1.0))
    # the record decides, not the features: a narrower record range clamps there
    tmpl, layout = _template(sim.make("pendulum"))
    rec = tmpl.actuators[0]
    tmpl.actuators = [Actuators(low=rec.low / 2, high=rec.high / 2, limited=rec.limited, clamped=rec.clamped)] * 2
    x0 = still
    assert torch.equal(RolloutInputs(tmpl, layout).values(x0, big), big.clamp(-0.5, 0.5))
    # a dataset's graphs (no System at hand): the static features hold the same range
    static, layout, _ = static_arrays([sim.make("pendulum")])
    ds_tmpl = GraphTemplate(GraphBuilder(static), torch.zeros(2, dtype=torch.long))
    assert ds_tmpl.actuators is None
    assert torch.equal(RolloutInputs(ds_tmpl, layout).values(x0, big), big.clamp(-1.0, 1.0))
    # an unlimited actuator (MuJoCo's default range [0, 0]) is not clamped, not even to [0, 0]
    tmpl, layout = _template(unlimited)
    assert not tmpl.actuators[0].limited.any()
    inp = RolloutInputs(tmpl, layout)
    assert inp.ranges is None
    assert torch.equal(inp.values(still, big), big)
    # and "error" has nothing to refuse: the same controls pass
    assert torch.equal(RolloutInputs(tmpl, layout, ctrl_policy="error").values(still, big), big)
