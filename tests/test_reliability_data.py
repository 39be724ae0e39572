"""Reliability of what datasets and MJCF files feed the pipeline:
checksummed, validated datasets, refused meaningless models, and `gnwarp check`."""
import os
import re
import shutil
import sys
import tempfile
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gnwarp import cli, data
from gnwarp.data.checks import MAX_ABS
from gnwarp.data.dataset import check
from gnwarp.data.format import DatasetWarning
from gnwarp.data.layout import FeatureLayout
from gnwarp.sim import systems

SETTINGS = settings(max_examples=25, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])


# -- a small dataset and its corruptions ---------------------------------------------------------

@pytest.fixture(scope="module")
def good(tmp_path_factory):
    """(dataset in memory, path of its file): cartpole, 3 bodies, 4 edges, 1 control."""
    ds = data.generate("cartpole", (6, 2, 2), num_steps=15, seed=5, backend="mujoco", progress=False)
    path = ds.save(tmp_path_factory.mktemp("reliability") / "good.h5")
    return ds, path


def _mutated(good, tmp_path, fn, name="bad.h5") -> Path:
    """A copy of the good file changed through h5py (checksums stay consistent: only validation can tell)."""
    p = tmp_path / name
    shutil.copy(good[1], p)
    with h5py.File(p, "r+") as f:
        fn(f)
    return p


def _set(key, idx, value):
    def fn(f):
        a = f[key][...]
        a[idx] = value
        f[key][...] = a
    return fn


def _retype(key, dtype):
    def fn(f):
        a = f[key][...]
        del f[key]
        f.create_dataset(key, data=a.astype(dtype), fletcher32=True)
    return fn


def _load_all(p):
    """Load lazily and read every split the way training and evaluation do."""
    ds = data.load(p)
    try:
        for k in data.SPLITS:
            sp = ds[k]
            np.asarray(sp.body[...]), np.asarray(sp.ctrl[...]), sp.load()
    finally:
        ds.close()


def test_save_writes_checksums_and_clean_file_checks(good):
    _, p = good
    with h5py.File(p) as f:
        for g in ("static", *data.SPLITS):
            for k in f[g]:
                assert f[g][k].fletcher32, f"/{g}/{k} has no checksum"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a checksummed file loads without a warning
        _load_all(p)
    lines = check(p)
    assert len(lines) == 1 and lines[0].startswith("ok:") and "Fletcher-32" in lines[0], lines


def test_flipped_bytes_in_states_detected(good, tmp_path):
    ds, p = good
    raw = bytearray(p.read_bytes())
    pat = ds["train"].body[2].tobytes()[:64]
    at = raw.find(pat)
    assert at > 0 and raw.find(pat, at + 1) < 0
    raw[at + 200] ^= 0x10  # one bit inside sequence 2's stored states
    bad = tmp_path / "flipped.h5"
    bad.write_bytes(bytes(raw))
    back = data.load(bad)  # static arrays are intact: opens
    g = back.graphs("train", [1, 3], [0, 4])  # other sequences still read
    assert g.n_graph == 2
    for read in (lambda: back["train"].body[...], lambda: np.asarray(back["train"].body),
                 lambda: back.graphs("train", [2], [3]), lambda: back["train"].load()):
        with pytest.raises(data.DatasetError, match=r"flipped.h5: /train/body \(sequence 2\) fails its Fletcher-32"):
            read()
    back.close()
    errors = [x for x in check(bad) if x.startswith("error:")]
    assert len(errors) == 1 and "/train/body (sequence 2)" in errors[0] and "checksum" in errors[0]


@pytest.mark.parametrize("mutation, match", [
    (_set("train/body", (1, 3, 1, 0), np.nan), r"/train/body holds a non-finite value, NaN, at sequence 1, step 3, "
                                               r"body 1, pos_x"),
    (_set("train/body", (4, 7, 2, 9), -np.inf), r"/train/body holds a non-finite value, -Inf, at sequence 4, step 7"),
    (_set("train/ctrl", (3, 2, 0), np.inf), r"/train/ctrl holds a non-finite value, Inf, at sequence 3, step 2, "
                                            r"actuator 0"),
    (_set("train/ctrl", (3, 2, 0), np.nan), r"/train/ctrl holds a non-finite value, NaN"),
    (_set("valid/qvel", (1, 2, 0), 1e30), r"/valid/qvel holds an absurd value \(\|x\| > 1e\+06\), 1e\+30, at sequence 1"),
    (_set("train/body", (0, 5, 1, 0), 1e30), r"/train/body holds an absurd value .*1e\+30, at sequence 0, step 5"),
    (_set("train/body", (0, 0, 2, 3), 0.0), r"/train/body: sequence 0, step 0, body 2 has an orientation quaternion"),
])
def test_bad_values_in_splits_are_clear_errors(good, tmp_path, mutation, match):
    p = _mutated(good, tmp_path, mutation)
    with pytest.raises(data.DatasetError, match="bad.h5: " + match):
        _load_all(p)
    with pytest.raises(data.DatasetError, match=match):
        data.load(p, lazy=False)
    errors = [x for x in check(p) if x.startswith("error:")]
    assert len(errors) == 1 and re.search(match, errors[0]), errors


@pytest.mark.parametrize("mutation, match", [
    (_retype("train/body", np.int32), r"/train/body has dtype int32, expected float32"),
    (_retype("test/ctrl", np.int64), r"/test/ctrl has dtype int64, expected float32"),
    (_retype("static/senders", np.float32), r"/static/senders has dtype float32, expected int64"),
    (_set("static/senders", (0, 0), 10**9), r"/static/senders: instance 0, edge 0 holds body index 1000000000, "
                                            r"outside \[0, 3\)"),
    (_set("static/senders", (0, 1), 99), r"/static/senders: instance 0, edge 1 holds body index 99"),
    (_set("static/senders", (0, 1), -1), r"/static/senders: instance 0, edge 1 holds body index -1, outside"),
    (_set("static/receivers", (0, 2), -7), r"/static/receivers: instance 0, edge 2 holds body index -7"),
    (_set("static/n_node", 0, 2), r"body index 2, outside \[0, 2\)"),
    (_set("static/n_node", 0, 7), r"/static/n_node of instance 0 is 7, outside \[1, 3\]"),
    (_set("static/n_node", 0, 0), r"/static/n_node of instance 0 is 0, outside \[1, 3\]"),
    (_set("static/n_edge", 0, 2), r"beyond n_edge = 2, where the format has -1 \(padding\): n_edge does not match"),
    (_set("static/n_edge", 0, 9), r"/static/n_edge of instance 0 is 9, outside \[0, 4\]"),
    (_set("static/edge_ctrl", (0, 0, 0), 5), r"/static/edge_ctrl: instance 0, edge 0, slot 0 holds control index 5, "
                                             r"outside \[-1, 1\)"),
    (_set("static/edge_ctrl", (0, 1, 0), -2), r"/static/edge_ctrl: instance 0, edge 1, slot 0 holds control index -2"),
    (_set("static/nodes", (0, 1, 0), np.nan), r"/static/nodes holds a non-finite value, NaN, at instance 0, body 1"),
    (_set("test/instance", 1, 7), r"/test/instance of sequence 1 is 7, outside \[0, 1\)"),
])
def test_bad_static_and_layout_refused_at_load(good, tmp_path, mutation, match):
    p = _mutated(good, tmp_path, mutation)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DatasetWarning)
        with pytest.raises(data.DatasetError, match="bad.h5: .*" + match):
            data.load(p)  # lazily: refused before any split is read
        lines = check(p)
    assert any(x.startswith("error:") and re.search(match, x) for x in lines), lines


def test_sender_1e9_never_reaches_the_graph_builder(good, tmp_path):
    """A stored sender of 1e9 (which, unchecked, segfaults in the GN block) is refused."""
    p = _mutated(good, tmp_path, _set("static/senders", (0, 3), 10**9))
    with pytest.raises(data.DatasetError, match=r"/static/senders.*1000000000"):
        data.load(p)
    # a Dataset built in memory is checked before its first graphs
    ds = good[0]
    bad = data.Dataset(ds.meta, {**ds.static, "senders": np.where(np.arange(4) == 3, 10**9, ds.static["senders"])},
                       ds.splits)
    with pytest.raises(data.DatasetError, match=r"/static/senders: instance 0, edge 3 holds body index 1000000000"):
        bad.graphs("train", [0], [0])


def test_graphs_index_ranges(good):
    ds = good[0]
    with pytest.raises(IndexError, match="sequence index 6 outside split 'train' of 6"):
        ds.graphs("train", [6], [0])
    with pytest.raises(IndexError, match="sequence index -1"):
        ds.graphs("train", [-1], [0])
    with pytest.raises(IndexError, match=r"step 16 outside \[0, 15\]"):
        ds.graphs("train", [0], [16])
    assert ds.graphs("train", [5], [15]).n_graph == 1


def _without_checksums(src: Path, dst: Path):
    with h5py.File(src) as a, h5py.File(dst, "w") as b:
        for k, v in a.attrs.items():
            b.attrs[k] = v
        for g in a:
            for k in a[g]:
                b.create_dataset(f"{g}/{k}", data=a[g][k][...])


def test_old_file_without_checksums_loads_with_a_warning(good, tmp_path):
    old = tmp_path / "old.h5"
    _without_checksums(good[1], old)
    with pytest.warns(DatasetWarning, match="without per-array checksums"):
        back = data.load(old)
    np.testing.assert_array_equal(back["train"].body[...], good[0]["train"].body)
    back.close()
    lines = check(old)
    assert [x.split(":")[0] for x in lines] == ["warning", "ok"], lines
    assert cli.main(["check", str(old)]) == 0
    # its values are still validated
    with h5py.File(old, "r+") as f:
        f["train/ctrl"][0, 0, 0] = np.nan
    with pytest.warns(DatasetWarning), pytest.raises(data.DatasetError, match="/train/ctrl holds a non-finite"):
        _load_all(old)


def test_metadata_is_checksummed_and_its_values_checked(good, tmp_path):
    """The metadata (system, dt, ...) has a SHA-256 beside it: a changed byte is detected; values
    no reader can use (dt <= 0) are refused even where the checksum matches; a file from before
    the metadata had a checksum still loads."""
    import json
    import shutil

    from gnwarp.data.format import meta_digest
    cases = {"changed": (lambda m: m.update(system="acrobot"), False, "metadata was changed or damaged"),
             "dt": (lambda m: m.update(dt=-1), True, "metadata 'dt' must be the data timestep"),
             "steps": (lambda m: m.update(num_steps=0), True, "metadata 'num_steps' must be an integer >= 1"),
             "older": (lambda m: None, None, None)}
    for name, (change, rehash, words) in cases.items():
        p = tmp_path / f"{name}.h5"
        shutil.copy(good[1], p)
        with h5py.File(p, "r+") as f:
            m = json.loads(f.attrs["meta"])
            change(m)
            text = json.dumps(m)
            f.attrs["meta"] = text
            if rehash:
                f.attrs["meta_sha256"] = meta_digest(text)
            elif rehash is None:   # as written before the checksum existed
                del f.attrs["meta_sha256"]
        if words is None:
            data.load(p).close()
            assert check(p)[-1].startswith("ok:")
            continue
        with pytest.raises(data.DatasetError, match=words):
            data.load(p)
        assert any(x.startswith("error:") and words in x for x in check(p)), check(p)


def test_unreadable_files_are_dataset_errors(good, tmp_path):
    (tmp_path / "folder.h5").mkdir()
    with pytest.raises(data.DatasetError, match="is a folder"):
        data.load(tmp_path / "folder.h5")
    raw = good[1].read_bytes()
    (tmp_path / "trunc.h5").write_bytes(raw[: len(raw) // 3])
    assert check(tmp_path / "trunc.h5")[0].startswith("error:")
    assert check(tmp_path / "missing.h5")[0].startswith("error:")


def test_save_refuses_a_full_disk(good, tmp_path, monkeypatch):
    import collections
    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(10**6, 10**6 - 100, 100))
    with pytest.raises(OSError, match=r"not enough disk space for .*full.h5: the dataset needs .* GiB"):
        good[0].save(tmp_path / "full.h5")
    assert os.listdir(tmp_path) == []


# -- `gnwarp check` ------------------------------------------------------------------------------

def test_cli_check_clean_and_corrupt(good, tmp_path, capsys):
    assert cli.main(["check", str(good[1])]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and out[0].startswith("ok: ") and "cartpole" in out[0]

    def several(f):
        _set("train/body", (1, 3, 1, 0), np.nan)(f)
        _set("valid/ctrl", (0, 0, 0), 1e30)(f)
    p = _mutated(good, tmp_path, several)
    assert cli.main(["check", str(p)]) == 1
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 2 and all(x.startswith("error: ") and "bad.h5" in x for x in out), out
    assert "/train/body" in out[0] and "/valid/ctrl" in out[1]

    p = _mutated(good, tmp_path, _set("static/senders", (0, 0), 10**9), "snd.h5")
    assert cli.main(["check", str(p)]) == 1
    out = capsys.readouterr().out
    assert "/static/senders" in out and "1000000000" in out

    assert cli.main(["check", str(tmp_path / "nothing.h5")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nothing.h5" in err[0]


def test_cli_check_checkpoint_folder(tmp_path, capsys):
    """A folder goes to gnwarp.train.checkpoint.check_checkpoint: an empty one is no checkpoint."""
    code = cli.main(["check", str(tmp_path)])
    out = capsys.readouterr()
    assert code == 1 and any(x.startswith("error:") for x in out.out.splitlines()), out


# -- generation refuses what cannot work ---------------------------------------------------------

def test_generate_refuses_impossible_sizes_and_seeds(tmp_path, capsys):
    with pytest.raises(ValueError, match=r"too large: .*1000000000 steps.* GiB"):
        data.generate("cheetah", 3, num_steps=1_000_000_000, backend="mujoco", progress=False)
    with pytest.raises(ValueError, match="seed must be a non-negative integer, got -1"):
        data.generate("pendulum", 3, num_steps=3, seed=-1, backend="mujoco", progress=False)
    with pytest.raises(ValueError, match="num_steps must be an integer"):
        data.generate("pendulum", 3, num_steps=2.5, backend="mujoco", progress=False)
    out = tmp_path / "big.h5"
    assert cli.main(["generate", "cheetah", "--steps", "1000000000", "-o", str(out), "-q", "--backend", "mujoco"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "GiB" in err[0] and "Traceback" not in err[0]
    assert cli.main(["generate", "pendulum", "--seed", "-3", "-n", "3", "--steps", "3", "-o", str(out), "-q",
                     "--backend", "mujoco"]) == 2
    assert "seed must be a non-negative integer, got -3" in capsys.readouterr().err
    assert not out.exists() and os.listdir(tmp_path) == []


# -- MJCF models the pipeline cannot use ----------------------------------------------------------

MJCF = """<mujoco model="user">
  <option timestep="{timestep}"/>
  <worldbody>
    <body name="pole" pos="0 0 1">
      <joint name="hinge" type="hinge" axis="0 1 0" damping="{damping}"/>
      <geom name="rod" type="capsule" fromto="0 0 0 0 0 0.5" size="{size}" {mass}/>
      <body name="tip" pos="0 0 0.5">
        <joint name="elbow" type="hinge" axis="0 1 0"/>
        <inertial pos="0 0 0" mass="{tip_mass}" diaginertia="{tip_inertia}"/>
      </body>
    </body>
    <body name="marker" pos="0 0 2"/>
  </worldbody>
  <actuator><motor name="torque" joint="hinge" ctrlrange="-1 1" gear="{gear}"/></actuator>
</mujoco>
"""
GOOD = dict(timestep="0.005", damping="0.1", size="0.02", mass="", tip_mass="0.1", tip_inertia="0.001 0.001 0.001",
            gear="1")


def _mjcf(tmp_path, **changes) -> Path:
    p = tmp_path / "robot.xml"
    p.write_text(MJCF.format(**{**GOOD, **changes}))
    return p


def test_good_mjcf_with_massless_frame_body_loads(tmp_path):
    s = systems.from_mjcf(_mjcf(tmp_path))
    assert s.model.nbody == 4 and s.model.body_mass[3] == 0  # the jointless marker may be massless


@pytest.mark.parametrize("changes, match", [
    ({"mass": 'mass="nan"'}, r"<geom 'rod'> attribute mass=\"nan\" \(line 6\) is not finite"),
    ({"tip_mass": "nan"}, r"(<inertial> attribute mass=\"nan\"|Element name 'tip')"),
    ({"timestep": "0"}, r"option timestep is 0.0; it must be a finite positive"),
    ({"timestep": "-0.01"}, r"option timestep is -0.01"),
    ({"timestep": "nan"}, r"<option> attribute timestep=\"nan\""),
    ({"timestep": "inf"}, r"<option> attribute timestep=\"inf\""),
    ({"mass": 'mass="1e30"'}, r"body 'pole' has mass 1e\+30, outside \[1e-06, 1e\+06\] kg"),
    ({"tip_mass": "1e30"}, r"body 'tip' has mass 1e\+30"),
    ({"size": "1e30"}, r"geom 'rod' of body 'pole' has size \[1e\+30, 0.25, 0.0\], outside \[1e-06, 1e\+06\] m"),
    ({"tip_inertia": "1e30 1e30 1e30"}, r"body 'tip' has inertia \[1e\+30, 1e\+30, 1e\+30\], outside"),
    ({"damping": "nan"}, r"<joint 'hinge'> attribute damping=\"nan\""),
    ({"gear": "inf"}, r"<motor 'torque'> attribute gear=\"inf\""),
])
def test_meaningless_mjcf_refused_naming_body_or_option(tmp_path, changes, match):
    p = _mjcf(tmp_path, **changes)
    with pytest.raises(ValueError, match="(?s)robot.xml: .*" + match):
        systems.from_mjcf(p)


def test_cli_generate_refuses_bad_mjcf(tmp_path, capsys):
    p = _mjcf(tmp_path, mass='mass="1e30"')
    out = tmp_path / "out.h5"
    assert cli.main(["generate", "--mjcf", str(p), "-n", "3", "--steps", "3", "-q", "--backend", "mujoco",
                     "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "body 'pole' has mass 1e+30" in err[0]
    assert not out.exists()


def test_check_model_on_built_and_mutated_systems():
    for name in systems.names():
        systems.check_model(systems.make(name).model, name)
    s = systems.make("cartpole")
    s.model.body_mass[2] = np.nan
    with pytest.raises(ValueError, match=r"system 'cartpole': body 'pole_1' has mass nan"):
        data.generate(s, (2, 1, 1), num_steps=3, backend="mujoco", progress=False)
    s = systems.make("pendulum")
    s.model.opt.timestep = 0.0
    with pytest.raises(ValueError, match="option timestep is 0.0"):
        data.generate(s, (2, 1, 1), num_steps=3, backend="mujoco", progress=False)


_NUMBERS = st.one_of(
    st.sampled_from([float("nan"), float("inf"), float("-inf"), 0.0, -1.0, 1e30, -1e30, 1e-30, 1e7, 1e-7]),
    st.floats(allow_nan=True, allow_infinity=True, width=64),
    st.floats(min_value=1e-3, max_value=10.0),
)
_FIELDS = {"timestep": 1, "damping": 1, "size": 1, "mass": 1, "tip_mass": 1, "tip_inertia": 3, "gear": 1}


@SETTINGS
@given(field=st.sampled_from(sorted(_FIELDS)), values=st.lists(_NUMBERS, min_size=3, max_size=3))
def test_random_mjcf_numeric_mutations(field, values):
    """Any number in any of these attributes: a clear ValueError naming the file, or a model whose
    timestep, masses, inertias and sizes the pipeline can use; never another exception."""
    text = " ".join(repr(v) for v in values[:_FIELDS[field]])
    change = {field: f'mass="{text}"' if field == "mass" else text}
    with tempfile.TemporaryDirectory() as d:
        p = _mjcf(Path(d), **change)
        try:
            s = systems.from_mjcf(p)
        except ValueError as e:
            assert "robot.xml" in str(e)
            return
    m = s.model
    assert np.isfinite(m.opt.timestep) and m.opt.timestep > 0
    moving = np.asarray(m.body_dofnum)[1:] > 0
    mass = np.asarray(m.body_mass)[1:]
    assert np.all(np.isfinite(mass)) and np.all(mass[moving] >= 1e-6) and np.all(mass <= 1e6)
    assert np.all(np.isfinite(m.body_inertia)) and np.all(m.body_inertia <= systems.INERTIA_MAX)
    assert np.all(np.isfinite(m.geom_size)) and np.all(m.geom_size <= 1e6)
    assert np.all(np.isfinite(m.dof_damping)) and np.all(np.isfinite(m.actuator_gear))


# -- round trips ---------------------------------------------------------------------------------

def _synthetic(rng, I, B, E, K, U, T, sizes, Fg, Fv, Fe, P, dtype) -> data.Dataset:
    """A valid dataset of the format, from random numbers (not a simulation)."""
    n_node = rng.integers(1, B + 1, I)
    n_edge = rng.integers(0, E + 1, I)
    n_node[0], n_edge[0] = B, E
    snd, rcv = -np.ones((I, E), np.int64), -np.ones((I, E), np.int64)
    ectrl = -np.ones((I, E, K), np.int64)
    nodes, edges = np.zeros((I, B, Fv), np.float32), np.zeros((I, E, Fe), np.float32)
    for i in range(I):
        ne, nb = n_edge[i], n_node[i]
        snd[i, :ne], rcv[i, :ne] = rng.integers(0, nb, ne), rng.integers(0, nb, ne)
        ectrl[i, :ne] = rng.integers(-1, U, (ne, K))
        nodes[i, :nb] = rng.normal(size=(nb, Fv))
        edges[i, :ne] = rng.normal(size=(ne, Fe))
    static = {"globals": rng.normal(size=(I, Fg)).astype(np.float32), "nodes": nodes, "edges": edges,
              "senders": snd, "receivers": rcv, "n_node": n_node, "n_edge": n_edge, "edge_ctrl": ectrl,
              "params": rng.uniform(0.5, 2, (I, P))}
    splits = {}
    for name, S in sizes.items():
        inst = rng.integers(0, I, S)
        body = np.zeros((S, T + 1, B, 13), dtype)
        real = np.broadcast_to((np.arange(B)[None] < n_node[inst][:, None])[:, None], (S, T + 1, B))
        x = rng.normal(size=(S, T + 1, B, 13))
        x[..., 3:7] /= np.linalg.norm(x[..., 3:7], axis=-1, keepdims=True)
        body[real] = x[real]
        splits[name] = data.Split(body, rng.uniform(-1, 1, (S, T, U)).astype(dtype),
                                  rng.normal(size=(S, T + 1, 2)).astype(dtype),
                                  rng.normal(size=(S, T + 1, 2)).astype(dtype), inst)
    lay = FeatureLayout([f"g{j}" for j in range(Fg)], [f"v{j}" for j in range(Fv)], [f"e{j}" for j in range(Fe)],
                        n_ctrl_slots=K)
    meta = {"system": "synthetic", "dt": 0.01, "num_steps": T, "splits": sizes, "param_names": [f"p{j}" for j in range(P)],
            "layout": lay.to_dict(), "max_bodies": B, "max_edges": E, "nq": 2, "nv": 2, "nu": U}
    return data.Dataset(meta, static, splits)


_SHAPES = st.fixed_dictionaries({
    "I": st.integers(1, 4), "B": st.integers(1, 5), "E": st.integers(0, 6), "K": st.integers(1, 2),
    "U": st.integers(1, 3), "T": st.integers(1, 5), "Fg": st.integers(0, 3), "Fv": st.integers(0, 3),
    "Fe": st.integers(0, 3), "P": st.integers(0, 2), "dtype": st.sampled_from([np.float32, np.float64]),
    "sizes": st.fixed_dictionaries({k: st.integers(0, 3) for k in data.SPLITS}),
})


@SETTINGS
@given(shape=_SHAPES, seed=st.integers(0, 2**32 - 1), corrupt=st.booleans(), pick=st.integers(0, 10**6))
def test_dataset_roundtrip_property(shape, seed, corrupt, pick):
    """Any valid dataset reads back exactly (lazily and eagerly) and checks clean; one NaN put
    anywhere into its states or controls is found and located."""
    rng = np.random.default_rng(seed)
    ds = _synthetic(rng, **shape)
    with tempfile.TemporaryDirectory() as d:
        p = ds.save(Path(d) / "syn.h5")
        for lazy in (True, False):
            back = data.load(p, lazy=lazy)
            for k in data.SPLITS:
                for a in ("body", "ctrl", "qpos", "qvel", "instance"):
                    got = np.asarray(getattr(back[k], a)[...])
                    want = getattr(ds[k], a)
                    assert got.dtype == want.dtype
                    np.testing.assert_array_equal(got, want)
            for k, v in ds.static.items():
                np.testing.assert_array_equal(back.static[k], v)
            assert back.meta == ds.meta
            sp = back["train"]
            if len(sp):
                g = back.graphs("train", np.arange(len(sp)), np.zeros(len(sp), np.int64))
                assert g.n_graph == len(sp)
            back.close()
        assert check(p)[-1].startswith("ok:")
        arrays = [(k, a) for k in data.SPLITS for a in ("body", "ctrl", "qpos", "qvel") if getattr(ds[k], a).size]
        if corrupt and arrays:
            k, a = arrays[pick % len(arrays)]
            with h5py.File(p, "r+") as f:
                x = f[k][a][...]
                idx = np.unravel_index(pick % x.size, x.shape)
                x[idx] = np.nan
                f[k][a][...] = x
            with pytest.raises(data.DatasetError, match=f"/{k}/{a} holds a non-finite value, NaN, at sequence {idx[0]}, "
                                                        f"step {idx[1]}"):
                data.load(p, lazy=False)
            errors = [x for x in check(p) if x.startswith("error:")]
            assert len(errors) == 1 and f"/{k}/{a}" in errors[0]


def test_max_abs_matches_generation():
    from gnwarp.data import generation
    assert generation._MAXVAL == MAX_ABS


# -- atomic writes (gnwarp.files) ---------------------------------------------------------------
def test_atomic_write_replaces_whole_or_not_at_all(tmp_path):
    from gnwarp.files import atomic_write, temporary_of
    path = tmp_path / "a.txt"
    path.write_text("old")
    with pytest.raises(RuntimeError, match="disk full"):
        with atomic_write(path) as tmp:
            tmp.write_text("half")
            raise RuntimeError("disk full")
    assert path.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]
    with atomic_write(path) as tmp:
        assert tmp == temporary_of(path) and tmp.parent == path.parent
        tmp.write_text("new")
        assert path.read_text() == "old"          # in place only once the block ends
    assert path.read_text() == "new" and sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]
    folder = tmp_path / "ck"
    for text in ("one", "two"):                   # a folder, and a folder replacing it
        with atomic_write(folder, folder=True) as tmp:
            (tmp / "x").write_text(text)
        assert (folder / "x").read_text() == text
    with pytest.raises(KeyError):
        with atomic_write(folder, folder=True) as tmp:
            (tmp / "x").write_text("three")
            raise KeyError("x")
    assert (folder / "x").read_text() == "two" and sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "ck"]


def test_stale_temporaries_of_dead_writers_only_are_removed(tmp_path):
    import subprocess
    from gnwarp.files import remove_stale_temporaries, temporary_of
    path = tmp_path / "d.h5"
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    stale, live = temporary_of(path, pid=int(dead.stdout)), temporary_of(path, pid=os.getppid())
    other = temporary_of(tmp_path / "e.h5", pid=int(dead.stdout))   # another file's: not this path's
    for p in (stale, live, other):
        p.write_bytes(b"")
    assert remove_stale_temporaries(path) == [stale]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([live.name, other.name])


def test_generate_refuses_split_names_counts_and_systems_it_would_misread():
    """A misspelt split would silently leave the valid split empty; 2.5 sequences would become 2;
    a system that is neither a name nor a System failed deep inside: each is a clear error first."""
    for sizes, words in (({"train": 3, "val": 1, "test": 1}, "unknown splits \\['val'\\]"),
                         (2.5, "num_sequences must be a whole number of sequences, got 2.5"),
                         ((2, 1.5, 1), "num_sequences' valid must be a whole number")):
        with pytest.raises(ValueError, match=words):
            data.generate("pendulum", sizes, num_steps=3, backend="mujoco", progress=False)
    with pytest.raises(TypeError, match="system must be a built-in system's name or a System"):
        data.generate(3, 3, num_steps=3)
    assert data.split_sizes({"train": np.int64(2), "test": 1}, False) == {"train": 2, "valid": 0, "test": 1}


def test_graphs_of_no_sequences_is_a_clear_error(good):
    with pytest.raises(ValueError, match="no sequences asked for"):
        data.load(good[1]).graphs("train", [], [])
