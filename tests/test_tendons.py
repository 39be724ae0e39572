"""Actuators on fixed tendons on the graph (their control times each joint's coefficient on that
joint's edges), and actuators the graph cannot carry refused by generate before any simulation."""
import warnings

import h5py
import mujoco
import numpy as np
import pytest
import torch

from gnwarp import cli, data
from gnwarp.data import generation
from gnwarp.data.builder import GraphTemplate
from gnwarp.data.convert import UnsupportedActuatorError, edge_controls, static_arrays, topology
from gnwarp.data.layout import FeatureLayout
from gnwarp.gn import RunOptions
from gnwarp.interop import warp
from gnwarp.models import ForwardModel, GNCoreConfig, ModelConfig, SysIDConfig, SysIDModel
from gnwarp.models.fused_step import FusedStep
from gnwarp.sim.systems import from_mjcf
from gnwarp.train import TrainConfig, load_model, train

warp()

TINY = dict(latent=8, edge_hidden=(16,), node_hidden=(16,), global_hidden=(16,))
LINK = '<geom type="capsule" fromto="0 0 0 0 0 -0.4" size="0.04"/>'

# three hinges; tendon "couple" = 0.5 h1 - 1.5 h2 driven by "pull" (gear 2); "elbow" drives h2
COUPLED = f"""<mujoco><option timestep="0.01"/><worldbody>
<body name="a" pos="0 0 1"><joint name="h1" axis="0 1 0" damping="0.1"/>{LINK}
 <body name="b" pos="0 0 -0.4"><joint name="h2" axis="0 1 0" damping="0.1"/>{LINK}
  <body name="c" pos="0 0 -0.4"><joint name="h3" axis="0 1 0" damping="0.1"/>{LINK}</body></body></body>
</worldbody>
<tendon><fixed name="couple"><joint joint="h1" coef="0.5"/><joint joint="h2" coef="-1.5"/></fixed></tendon>
<actuator><motor name="pull" tendon="couple" gear="2" ctrlrange="-1 1"/>
<motor name="elbow" joint="h2" ctrlrange="-1 1"/></actuator></mujoco>"""

SITE = f"""<mujoco><worldbody><body name="a" pos="0 0 1"><joint name="h1" axis="0 1 0"/>{LINK}
<site name="tip" pos="0 0 -0.4"/></body></worldbody>
<actuator><motor name="elbow" joint="h1"/><general name="thruster" site="tip" gear="1 0 0 0 0 0"/></actuator>
</mujoco>"""

SPATIAL = f"""<mujoco><worldbody><site name="anchor" pos="0.3 0 1"/>
<body name="a" pos="0 0 1"><joint name="h1" axis="0 1 0"/>{LINK}<site name="tip" pos="0 0 -0.4"/></body>
</worldbody><tendon><spatial name="cable"><site site="anchor"/><site site="tip"/></spatial></tendon>
<actuator><motor name="winch" tendon="cable" ctrlrange="-1 1"/></actuator></mujoco>"""


def _system(tmp_path, xml, name="robot"):
    path = tmp_path / f"{name}.xml"
    path.write_text(xml)
    return from_mjcf(path, dt=0.02, substeps=2), path


@pytest.fixture(scope="module")
def coupled(tmp_path_factory):
    sys_, _ = _system(tmp_path_factory.mktemp("mjcf"), COUPLED)
    return sys_, data.generate(sys_, (6, 2, 2), num_steps=8, seed=0, backend="mujoco", progress=False)


def _moment(model, qpos):
    """[nu, nv] MuJoCo's actuator moments (d length / d qpos: gear times tendon coefficient) at qpos."""
    d = mujoco.MjData(model)
    d.qpos[:] = qpos
    mujoco.mj_forward(model, d)
    dense = np.zeros((model.nu, model.nv))
    mujoco.mju_sparse2dense(dense, d.actuator_moment, d.moment_rownnz, d.moment_rowadr, d.moment_colind)
    return dense


def _check_against_moments(model, edge_ctrl, ctrl, edges):
    """Per edge of joint j: sum over slots of (edge control x its actuator's gear) equals MuJoCo's
    generalized actuator input sum_a moment[a, dof(j)] ctrl[a] (hinge and slide joints)."""
    gear = np.asarray(model.actuator_gear[:, 0])
    want = ctrl @ _moment(model, model.qpos0)                       # [S, nv]
    nj = model.njnt
    for e in range(2 * nj):
        j = e % nj
        if model.jnt_type[j] not in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
            continue
        idx = edge_ctrl[e]
        got = (edges[:, e] * np.where(idx >= 0, gear[np.maximum(idx, 0)], 0.0)).sum(-1)
        np.testing.assert_allclose(got, want[:, model.jnt_dofadr[j]], rtol=1e-5, atol=1e-6, err_msg=f"edge {e}")


def test_tendon_actuator_controls_on_the_edges_of_its_joints(coupled):
    system, ds = coupled
    m = system.model
    assert ds.layout.n_global_ctrl == 0 and ds.layout.n_ctrl_slots == 2
    ec, gain = ds.static["edge_ctrl"][0], ds.static["edge_ctrl_gain"][0]
    # h1: pull x 0.5; h2: elbow, then pull x -1.5; h3: nothing (both directions alike)
    for e0 in (0, 3):
        assert ec[e0].tolist() == [0, -1] and gain[e0].tolist() == [0.5, 0.0]
        assert ec[e0 + 1].tolist() == [1, 0] and gain[e0 + 1].tolist() == [1.0, -1.5]
        assert ec[e0 + 2].tolist() == [-1, -1]
    sp = ds["train"]
    S, T = sp.ctrl.shape[:2]
    seq = torch.arange(S).repeat_interleave(T)
    t = torch.arange(T).repeat(S)
    ctrl = np.asarray(sp.ctrl).reshape(S * T, -1).astype(np.float64)
    b = data.GraphBuilder(ds.static, dtype=torch.float32)
    inst, body, u = (torch.as_tensor(np.asarray(x)) for x in (sp.instance, sp.body, sp.ctrl))
    fused, _ = b.sequence_batch(inst, body, u, seq, t, fused=True)
    plain, _ = b.sequence_batch(inst, body, u, seq, t, fused=False)
    general = b(inst[seq], body[seq, t], u[seq, t])
    b.fixed_topology = False                                        # the per-instance path of mixed topologies
    per_instance = b(inst[seq], body[seq, t], u[seq, t])
    tmpl = GraphTemplate(data.GraphBuilder(ds.static), inst[seq])
    templ = tmpl.graph(body[seq, t].double(), u[seq, t].double())
    E, K = ec.shape
    ref = edge_controls(topology(m), ctrl)                          # numpy reference [S*T, E, K]
    _check_against_moments(m, ec, ctrl, ref)
    for g in (fused, plain, general, per_instance, templ):
        got = g.edges[:, -K:].reshape(S * T, E, K).double().numpy()
        np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(ref[:, 0, 0], 0.5 * ctrl[:, 0])
    np.testing.assert_allclose(ref[:, 1], np.stack([ctrl[:, 1], -1.5 * ctrl[:, 0]], -1))
    assert torch.equal(fused.edges, plain.edges)                    # one launch and the torch ops: same bits


def test_tendon_model_trains_and_its_rollout_differentiates_the_tendon_control(tmp_path, coupled):
    _, ds = coupled
    cfg = TrainConfig(out=str(tmp_path / "run"), model=ModelConfig(gn=GNCoreConfig(**TINY), run=RunOptions(impl="torch")),
                      steps=4, batch_size=8, lr=1e-3, valid_every=4, valid_sequences=2, log_every=2,
                      checkpoint_every=4, normalizer_warmup=1, progress=False, device="cpu")
    r = train(cfg, [ds])
    assert r["steps"] == 4 and np.isfinite(r["best_error"])
    model = load_model(r["last"], device="cpu").to(dtype=torch.float64).bind(ds)
    assert model.layout.n_ctrl_slots == 2
    sp = ds["test"]
    x0 = torch.as_tensor(np.asarray(sp.body[:, 0]), dtype=torch.float64)
    u = torch.as_tensor(np.asarray(sp.ctrl), dtype=torch.float64).requires_grad_(True)
    weights = torch.randn(x0.shape[0], u.shape[1] + 1, *x0.shape[1:], dtype=torch.float64,
                          generator=torch.Generator().manual_seed(0))
    (model.rollout(x0, u) * weights).sum().backward()               # adjoint rollout
    g_adj = u.grad.clone()
    u.grad = None
    (model.rollout(x0, u, adjoint=False) * weights).sum().backward()
    torch.testing.assert_close(g_adj, u.grad)
    assert g_adj[..., 0].abs().min() > 0                            # every step's tendon control matters
    # the control reaches the graph only through its tendon's weights: scaling "pull" by 2 equals
    # feeding the edges twice the control, which differs from the unscaled rollout
    with torch.no_grad():
        a = model.rollout(x0, u[:, :1])
        twice = u[:, :1].clone()
        twice[..., 0] *= 2
        assert not torch.allclose(a, model.rollout(x0, twice))
    tmpl = model.template(torch.zeros(2, dtype=torch.int64))
    why = FusedStep.unsupported(model, tmpl)
    assert why is not None and "tendons" in why
    with pytest.raises(ValueError, match="tendons"):
        model.rollout_engine(torch.zeros(2, dtype=torch.int64), 3, fused=True)
    eng = model.rollout_engine(torch.zeros(2, dtype=torch.int64), 3, graphs=False)   # unfused: runs
    with torch.no_grad():
        out = eng.rollout(x0[:2], u[:2, :3].detach())
    torch.testing.assert_close(out, model.rollout(x0[:2], u[:2, :3].detach()))


def test_a_system_and_its_dataset_give_one_graph(coupled):
    system, ds = coupled
    static, layout, meta = static_arrays([system])
    assert layout.to_dict() == ds.layout.to_dict() and meta["n_global_ctrl"] == 0
    for k, v in static.items():
        np.testing.assert_array_equal(v, ds.static[k], err_msg=k)


def test_the_control_weights_survive_the_file_and_are_validated(tmp_path, coupled):
    _, ds = coupled
    path = tmp_path / "coupled.h5"
    ds.save(path)
    back = data.load(path)
    np.testing.assert_array_equal(back.static["edge_ctrl_gain"], ds.static["edge_ctrl_gain"])
    seq, t = [0, 3], [2, 5]
    torch.testing.assert_close(back.graphs("train", seq=seq, t=t).edges, ds.graphs("train", seq=seq, t=t).edges)
    back.close()
    with h5py.File(path, "r+") as f:
        g = f["static/edge_ctrl_gain"][...]
        g[0, 1, 1] = np.nan
        f["static/edge_ctrl_gain"][...] = g
    with pytest.raises(data.DatasetError, match=r"/static/edge_ctrl_gain: instance 0, edge 1, slot 1 holds nan"):
        data.load(path)


@pytest.mark.parametrize("xml, actuator, what", [
    (SITE, "actuator 1 'thruster'", "site transmission"),
    (SPATIAL, "actuator 0 'winch'", "spatial tendon 0 'cable'"),
], ids=["site", "spatial_tendon"])
def test_generate_refuses_an_actuator_the_graph_cannot_carry_before_simulating(tmp_path, monkeypatch, xml, actuator,
                                                                                what):
    system, path = _system(tmp_path, xml)

    def simulated(*a, **k):
        raise AssertionError("simulated")

    monkeypatch.setattr(generation, "simulate", simulated)
    with pytest.raises(UnsupportedActuatorError, match=f"{actuator}.*{what}") as err:
        data.generate(system, (2, 1, 1), num_steps=3, backend="mujoco", progress=False)
    assert "robot" in str(err.value) and "fixed tendons" in str(err.value)
    with pytest.raises(UnsupportedActuatorError, match=actuator):
        topology(system.model)                                      # binding a model to it: the same error
    out = tmp_path / "out.h5"
    assert cli.main(["generate", "--mjcf", str(path), "-n", "3", "--steps", "3", "-q", "--backend", "mujoco",
                     "-o", str(out)]) == 2
    assert not out.exists()


def test_a_layout_with_controls_on_the_globals_is_refused_by_name():
    lay = FeatureLayout(["timestep"], ["body_mass"], ["direction"], n_global_ctrl=2)
    with pytest.raises(ValueError, match="2 controls of actuators not on a joint edge.*regenerate"):
        ForwardModel(ModelConfig(gn=GNCoreConfig(**TINY)), lay)
    with pytest.raises(ValueError, match="2 on the globals.*regenerate"):
        SysIDModel(SysIDConfig(), lay)


def test_dmc_quadruped_tendon_actuators_are_carried():
    pytest.importorskip("dm_control")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from dm_control.suite import common, quadruped
    m = mujoco.MjModel.from_xml_string(quadruped.make_model(floor_size=10), common.ASSETS)
    topo = topology(m)
    assert topo.edge_ctrl.shape[1] == 2 and topo.edge_ctrl_gain is not None
    assert set(topo.edge_ctrl[topo.edge_ctrl >= 0].tolist()) == set(range(m.nu))   # all 12 actuators
    ctrl = np.random.default_rng(0).uniform(-1, 1, (5, m.nu))
    _check_against_moments(m, topo.edge_ctrl, ctrl, edge_controls(topo, ctrl))
