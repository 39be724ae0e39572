"""Graph conversion, simulation backends and datasets."""
import os

import h5py
import mujoco
import numpy as np
import pytest
import torch

from gnwarp import data
from gnwarp.data.convert import edge_controls, static_graph, topology
from gnwarp.sim.body_state import body_states
from gnwarp.data.layout import FeatureLayout
from gnwarp.interop import cuda_available
from gnwarp.sim import systems
from gnwarp.sim.excitation import control_range, random_spline_controls
from gnwarp.sim.backends import simulate
from gnwarp.state import DYN_NODE_SIZE


def _reference_rollout(system, q0, v0, u):
    """Plain MuJoCo C stepping in Python, reading node states with mj_objectVelocity."""
    m = system.model
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = q0, v0
    out = []
    for t in range(u.shape[0] + 1):
        mujoco.mj_forward(m, d)
        out.append(body_states(m, d))
        if t < u.shape[0]:
            d.ctrl[:] = u[t]
            for _ in range(system.substeps):
                mujoco.mj_step(m, d)
    return np.array(out)


def test_topology_cheetah():
    s = systems.make("cheetah")
    topo = topology(s.model)
    assert s.model.nbody == 8 and topo.n_edge == 18  # 9 joints, both directions
    # every joint gives one parent->child and one child->parent edge
    jb = s.model.jnt_bodyid
    par = s.model.body_parentid[jb]
    np.testing.assert_array_equal(topo.senders[:9], par)
    np.testing.assert_array_equal(topo.receivers[:9], jb)
    np.testing.assert_array_equal(topo.senders[9:], jb)
    # the three root joints of the torso give three edge pairs between world and torso
    assert np.sum((topo.senders == 0) & (topo.receivers == jb[0])) == 3
    # 6 motorized joints -> 12 motorized edges; the controls land on the right edges
    sg = static_graph(s.model)
    mot = sg.edges[:, sg.edge_names.index("motorized")]
    assert mot.sum() == 12
    ctrl = np.arange(1, 7, dtype=float)
    ec = edge_controls(topo, ctrl)[:, 0]
    for a in range(6):
        j = s.model.actuator_trnid[a, 0]
        assert ec[j] == ctrl[a] and ec[j + 9] == ctrl[a]
    assert np.all(ec[mot == 0] == 0)
    d = sg.edges[:, sg.edge_names.index("direction")]
    np.testing.assert_array_equal(d, np.r_[np.ones(9), -np.ones(9)])


def test_static_features_follow_model():
    s = systems.make("pendulum")
    sg = static_graph(s.model)
    i = sg.node_names.index("body_mass")
    np.testing.assert_allclose(sg.nodes[:, i], s.model.body_mass)
    g = sg.global_names.index("gravity_2")
    assert sg.globals[g] == pytest.approx(s.model.opt.gravity[2])
    assert sg.globals[sg.global_names.index("timestep")] == pytest.approx(s.model.opt.timestep)
    # contact-free systems say so in the disable-flag bits
    assert sg.globals[sg.global_names.index(f"disableflags_{int(np.log2(int(mujoco.mjtDisableBit.mjDSBL_CONTACT)))}")] == 1


@pytest.mark.parametrize("name", ["pendulum", "cartpole", "acrobot", "swimmer6", "cheetah", "walker", "jaco"])
def test_mujoco_c_backend_matches_reference_stepping(name):
    s = systems.make(name)
    rng = np.random.default_rng(0)
    q0, v0 = data.initial_states(s, 3, rng)
    u = random_spline_controls(3, 12, control_range(s.model), rng)
    tr = simulate(s, q0, v0, u, backend="mujoco")
    assert tr.body.shape == (3, 13, s.model.nbody, DYN_NODE_SIZE)
    ref = _reference_rollout(s, q0[1], v0[1], u[1])
    np.testing.assert_allclose(tr.body[1], ref, atol=2e-5 * max(1.0, np.abs(ref).max()))
    np.testing.assert_allclose(tr.qpos[1, 0], q0[1], atol=1e-6)


# MuJoCo-Warp (Warp's CPU device) against MuJoCo C from the same initial states and controls.
# Float32 (MJWarp) vs float64 (C) over 20 data steps: relative tolerance on the state scale.
WARP_BACKENDS = ["mujoco_warp_cpu"] + (["mujoco_warp"] if cuda_available() else [])


@pytest.mark.parametrize("backend", WARP_BACKENDS)
@pytest.mark.parametrize("name", ["pendulum", "cartpole", "acrobot", "swimmer6", "cheetah", "walker", "jaco"])
def test_mujoco_warp_matches_mujoco_c(name, backend):
    s = systems.make(name)
    rng = np.random.default_rng(1)
    q0, v0 = data.initial_states(s, 4, rng)
    u = random_spline_controls(4, 20, control_range(s.model), rng)
    c = simulate(s, q0, v0, u, backend="mujoco")
    w = simulate(s, q0, v0, u, backend=backend)
    scale = np.abs(c.body).reshape(-1, DYN_NODE_SIZE).max(0) + 1.0
    err = (np.abs(c.body - w.body) / scale).max()
    # contacts (cheetah, walker) amplify float32 rounding; chaotic systems diverge slowly
    tol = 2e-3 if s.contacts else 2e-4
    assert err < tol, f"{name}: max scaled error {err:.2e}"
    np.testing.assert_allclose(w.qpos[:, 0], q0, atol=1e-6)


@pytest.fixture(scope="module")
def small_dataset():
    return data.generate("cartpole", (6, 2, 2), num_steps=15, seed=5, backend="mujoco", progress=False)


def test_generate_layout_and_roundtrip(small_dataset, tmp_path):
    ds = small_dataset
    assert {k: len(ds[k]) for k in data.SPLITS} == {"train": 6, "valid": 2, "test": 2}
    assert ds["train"].body.shape == (6, 16, 3, DYN_NODE_SIZE)
    assert ds["train"].ctrl.shape == (6, 15, 1)
    # world body stays at rest
    np.testing.assert_array_equal(ds["train"].body[:, :, 0, 3], 1.0)
    lay = ds.layout
    # constant static features are dropped and recorded; varying ones kept
    assert "body_mass" in lay.node_names and "timestep" in lay.dropped["globals"]
    assert ds.static["globals"].shape[-1] == len(lay.global_names)
    p = ds.save(tmp_path / "cp.h5")
    back = data.load(p)
    for k in data.SPLITS:
        for a in ("body", "ctrl", "qpos", "qvel", "instance"):
            np.testing.assert_array_equal(np.asarray(getattr(back[k], a)[...]), getattr(ds[k], a))
    assert back.meta == ds.meta
    # lazy: arrays are h5py datasets until read
    assert isinstance(back["train"].body, h5py.Dataset)
    g = back.graphs("train", [3, 0, 3], [4, 0, 14])
    g.validate()
    assert g.n_graph == 3 and g.nodes.shape == (9, len(lay.node_names) + DYN_NODE_SIZE)
    np.testing.assert_allclose(g.nodes[3:6, -DYN_NODE_SIZE:].numpy(), ds["train"].body[0, 0])
    np.testing.assert_allclose(g.nodes[6:9, -DYN_NODE_SIZE:].numpy(), ds["train"].body[3, 14])
    # the cart's motorized edges carry the control of that step
    ectrl = g.edges[:, -1].numpy()
    mot = g.edges[:, lay.edge_names.index("motorized")].numpy() > 0.5
    assert np.allclose(ectrl[:4][mot[:4]], ds["train"].ctrl[3, 4, 0])
    back.close()


def test_generate_reproducible_and_seeded():
    a = data.generate("pendulum", (3, 1, 1), num_steps=5, seed=1, backend="mujoco", progress=False)
    b = data.generate("pendulum", (3, 1, 1), num_steps=5, seed=1, backend="mujoco", progress=False)
    c = data.generate("pendulum", (3, 1, 1), num_steps=5, seed=2, backend="mujoco", progress=False)
    np.testing.assert_array_equal(a["train"].body, b["train"].body)
    assert not np.array_equal(a["train"].body, c["train"].body)


def test_parameterized_dataset_swimmer_mixed_topologies(tmp_path):
    ds = data.generate("swimmer", (8, 2, 2), num_steps=5, seed=3, parameterized=True, backend="mujoco",
                       progress=False)
    n_node = ds.static["n_node"]
    assert len(np.unique(n_node)) > 1  # several N in one dataset
    assert ds.static["params"].shape[0] == 12 and "n_links" in ds.meta["param_names"]
    nl = ds.static["params"][:, ds.meta["param_names"].index("n_links")]
    np.testing.assert_array_equal(n_node, nl + 1)
    # padded bodies stay zero, real ones move
    tr = ds["train"]
    i = int(np.argmin(n_node[tr.instance]))
    nb = n_node[tr.instance[i]]
    assert np.all(tr.body[i, :, nb:] == 0) and np.abs(tr.body[i, -1, 1:nb, :3]).sum() > 0
    g = ds.graphs("train", np.arange(8), np.zeros(8, int))
    g.validate()
    assert g.total_nodes == int(n_node[tr.instance].sum())
    # static parameters vary, so their columns are kept
    assert "body_mass" in ds.layout.node_names
    ds.save(tmp_path / "sw.h5")
    assert data.load(tmp_path / "sw.h5").static["params"].shape == ds.static["params"].shape


def test_layout_mapping_between_datasets():
    a = FeatureLayout(["x", "y"], ["m"], ["d"])
    b = FeatureLayout(["y"], ["m"], ["d"], dropped={"globals": {"x": 7.0}, "nodes": {}, "edges": {}})
    vals = np.array([[3.0]])
    np.testing.assert_array_equal(a.map_static(b, "globals", vals), [[7.0, 3.0]])
    c = FeatureLayout(["y"], ["m"], ["d"])
    with pytest.raises(ValueError, match="'x'"):
        a.map_static(c, "globals", vals)


def test_bad_input_errors(tmp_path, small_dataset):
    with pytest.raises(ValueError, match="unknown|Unknown"):
        data.generate("nosuchsystem", 3, num_steps=3, progress=False)
    with pytest.raises(ValueError, match="backend"):
        data.generate("pendulum", 3, num_steps=3, backend="bullet", progress=False)
    p = tmp_path / "x.h5"
    p.write_bytes(b"not an hdf5 file")
    with pytest.raises(FileExistsError):
        small_dataset.save(p)
    assert p.read_bytes() == b"not an hdf5 file"  # nothing already written is lost
    with pytest.raises(data.DatasetError, match="corrupt|truncated"):
        data.load(p)
    with pytest.raises(FileNotFoundError):
        data.load(tmp_path / "missing.h5")
    with pytest.raises(FileNotFoundError):
        small_dataset.save(tmp_path / "no" / "such" / "dir.h5")
    # truncated file
    good = small_dataset.save(tmp_path / "good.h5")
    raw = good.read_bytes()
    (tmp_path / "trunc.h5").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(data.DatasetError):
        data.load(tmp_path / "trunc.h5")
    # a file of another layout
    with h5py.File(tmp_path / "other.h5", "w") as f:
        f.attrs["format"] = "something-else"
    with pytest.raises(data.DatasetError, match="not a gnwarp dataset"):
        data.load(tmp_path / "other.h5")


def test_failed_save_leaves_nothing(tmp_path, small_dataset, monkeypatch):
    def boom(*a, **k):
        raise OSError("disk full")
    monkeypatch.setattr(h5py.Group, "create_dataset", boom)
    with pytest.raises(OSError, match="disk full"):
        small_dataset.save(tmp_path / "d.h5")
    assert os.listdir(tmp_path) == []


def test_unstable_simulation_reported(monkeypatch):
    s = systems.make("pendulum")
    s.model.dof_damping[:] = -1e8  # negative damping: velocities grow until they overflow
    with pytest.raises((FloatingPointError, ValueError)):
        data.generate(s, (2, 1, 1), num_steps=20, backend="mujoco", progress=False)


def test_graph_builder_torch_device_roundtrip(small_dataset):
    b = data.GraphBuilder(small_dataset.static, dtype=torch.float64)
    sp = small_dataset["valid"]
    g = b(torch.as_tensor(sp.instance), torch.as_tensor(sp.body[:, 3]), torch.as_tensor(sp.ctrl[:, 3]))
    g.validate()
    assert g.nodes.dtype == torch.float64 and g.n_graph == 2


@pytest.mark.parametrize("backend", WARP_BACKENDS)
def test_mujoco_warp_per_world_parameters_match_mujoco_c(backend):
    """Parameterized instances in one batch: MuJoCo-Warp's batched Model fields against one
    MuJoCo C model per sequence."""
    insts = [systems.make("cartpole", seed=k) for k in range(3)]
    masses = [float(s.model.body_mass[1]) for s in insts]
    assert len(set(masses)) == 3  # the instances really differ
    rng = np.random.default_rng(4)
    q0, v0 = data.initial_states(insts[0], 3, rng)
    u = random_spline_controls(3, 15, control_range(insts[0].model), rng)
    c = simulate(insts, q0, v0, u, backend="mujoco")
    w = simulate(insts, q0, v0, u, backend=backend)
    scale = np.abs(c.body).reshape(-1, DYN_NODE_SIZE).max(0) + 1.0
    assert (np.abs(c.body - w.body) / scale).max() < 2e-4
    # and each sequence really used its own parameters: simulating all with instance 0 differs
    w0 = simulate(insts[0], q0, v0, u, backend="mujoco")
    assert np.abs(w0.body[1:] - c.body[1:]).max() > 1e-3
