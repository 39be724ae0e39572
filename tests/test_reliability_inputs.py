"""Bad inputs give one clear error: typed configurations (the
Python API, config files and ``gnwarp train --set`` alike), ``gnwarp evaluate``'s arguments and
non-finite reports, the GN block's index, rollout inputs and control clamping; and a property test
of GraphsTuple batch / unbatch round trips. CPU, tiny sizes."""
import dataclasses
import math
import pickle

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from gnwarp import cli, data
from gnwarp.eval import metrics
from gnwarp.eval.report import markdown_table
from gnwarp.gn import GNBlockConfig, GraphNetwork, RunOptions
from gnwarp.validation import ConfigError
from gnwarp.gn.index import check_index, graph_index
from gnwarp.graphs import GraphsTuple, batch, unbatch, validate
from gnwarp.models import ForwardModel, GNCoreConfig, ModelConfig
from gnwarp.models.rollout import RolloutInputError
from gnwarp.train import TrainConfig
from oracles import TruthModel

TINY = GNCoreConfig(latent=8, edge_hidden=(16,), node_hidden=(16,), global_hidden=(16,))


# -- configurations: one ConfigError naming the key path and the allowed values --------------------
# (raw config dict, --set item, key path, words of the allowed values)
CONFIG_CASES = [
    ({"steps": "abc"}, "steps=abc", "steps", "an integer >= 0"),
    ({"batch_size": 1.5}, "batch_size=1.5", "batch_size", "an integer from 1"),
    ({"valid_every": 0}, "valid_every=0", "valid_every", "an integer >= 1"),
    ({"lr_decay_steps": 0}, "lr_decay_steps=0", "lr_decay_steps", "'fast'"),
    ({"valid_horizon": 0}, "valid_horizon=0", "valid_horizon", "an integer >= 1"),
    ({"grad_clip": -1}, "grad_clip=-1", "grad_clip", "> 0 or None"),
    ({"seed": -1}, "seed=-1", "seed", "an integer from 0"),
    ({"checkpoint_every": -5}, "checkpoint_every=-5", "checkpoint_every", ">= 1"),
    ({"lr": 0}, "lr=0", "lr", "> 0"),
    ({"lr": float("nan")}, "lr=NaN", "lr", "finite"),
    ({"steps": True}, "steps=true", "steps", "an integer"),
    ({"optimizer": "sgd"}, "optimizer=sgd", "optimizer", "'adam', 'flat_adam'"),
    ({"device": "gpu"}, "device=gpu", "device", "'cuda:N'"),
    ({"capture": "yes"}, "capture=yes", "capture", "true or false"),
    ({"model": {"gn": {"edge_hidden": 5}}}, "model.gn.edge_hidden=5", "model.gn.edge_hidden", "layer widths"),
    ({"model": {"gn": {"latent": 0}}}, "model.gn.latent=0", "model.gn.latent", "an integer from 1 to 65536"),
    ({"model": {"gn": {"node_hidden": [64, -1]}}}, "model.gn.node_hidden=[64,-1]", "model.gn.node_hidden",
     "layer widths"),
    ({"model": {"core": "cnn"}}, "model.core=cnn", "model.core", "'gn', 'mlp'"),
    ({"model": {"mlp": {"width": 0}}}, "model.mlp.width=0", "model.mlp.width", "from 1"),
    ({"model": {"run": {"precision": "fp8"}}}, "model.run.precision=fp8", "model.run.precision", "'fp16'"),
    ({"model": {"gn": {"latnet": 8}}}, "model.gn.latnet=8", "model.gn.latnet", "latent"),
    ({"model": 3}, "model=3", "model", "ModelConfig"),
    ({"stpes": 10}, "stpes=10", "stpes", "unknown"),
]


def _one_error(exc: ConfigError, path: str, words: str):
    assert isinstance(exc, ValueError) and exc.path == path, (exc.path, str(exc))
    assert str(exc).startswith(f"{path}: ") and words in str(exc), str(exc)


@pytest.mark.parametrize("raw,item,path,words", CONFIG_CASES, ids=[c[1] for c in CONFIG_CASES])
def test_config_errors_name_the_key_alike_everywhere(raw, item, path, words, tmp_path, capsys):
    """The same error from the Python API, a TOML or JSON config file and ``--set``, before any
    data is read (the dataset named does not exist)."""
    with pytest.raises(ConfigError) as api:
        TrainConfig.from_dict(raw)
    _one_error(api.value, path, words)
    # --set: one line naming the same key, exit status 2
    assert cli.main(["train", "--data", str(tmp_path / "none.h5"), "--set", item]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith(f"gnwarp train: error: {api.value}") and f"--set {item}" in err, err
    # a config file (JSON; TOML for what TOML can spell)
    import json
    f = tmp_path / "cfg.json"
    f.write_text(json.dumps(raw))
    assert cli.main(["train", str(f), "--data", str(tmp_path / "none.h5")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"gnwarp train: error: {api.value} (from {f})", err


def test_toml_config_values_and_syntax_errors(tmp_path, capsys):
    good = tmp_path / "good.toml"
    good.write_text('steps = 10\nlr_decay_steps = "slow"\n[model.gn]\nlatent = 16\nedge_hidden = [32, 32]\n')
    raw = cli.common.read_config(str(good))
    cfg = TrainConfig.from_dict(raw)
    assert cfg.model.gn.edge_hidden == (32, 32) and cfg.decay_steps == 200_000
    bad = tmp_path / "bad.toml"
    bad.write_text('steps = 10\nbatch_size = \nlr = 1e-3\n')
    assert cli.main(["train", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and str(bad) in err and "line 2" in err, err
    vals = tmp_path / "vals.toml"
    vals.write_text("[model.gn]\nlatent = -4\n")
    assert cli.main(["train", str(vals), "--data", "x.h5"]) == 2
    err = capsys.readouterr().err.strip()
    assert "model.gn.latent: must be an integer from 1 to 65536, got -4" in err and str(vals) in err
    # a key set by --set over the file is named as from --set
    assert cli.main(["train", str(good), "--data", "x.h5", "--set", "model.gn.latent=abc"]) == 2
    assert "(from --set model.gn.latent=abc)" in capsys.readouterr().err
    lst = tmp_path / "list.json"
    lst.write_text("[1, 2]")
    with pytest.raises(ConfigError, match="a table of TrainConfig keys"):
        cli.common.read_config(str(lst))
    for item, words in (("steps", "KEY=VALUE"), ("model..gn=1", "malformed key"), ("steps.x=1", "steps")):
        with pytest.raises(ConfigError, match=words):
            TrainConfig.from_dict(cli.common.apply_overrides({}, [item]))


def test_configs_keep_their_python_api():
    """Keywords, to_dict / from_dict, dataclasses.replace (validated too), lists read as tuples,
    integral floats (--set steps=1e5) as ints, None where allowed."""
    c = TrainConfig(data="a.h5", steps=1e5, model={"gn": {"latent": 8, "edge_hidden": [16]}}, grad_clip=None,
                    patience=None, lr_decay_steps=3)
    assert c.data == ["a.h5"] and c.steps == 100_000 and isinstance(c.steps, int)
    assert c.model.gn.edge_hidden == (16,) and c.grad_clip is None and c.decay_steps == 3
    assert TrainConfig.from_dict(c.to_dict()) == c
    assert dataclasses.replace(c, valid_every=7).valid_every == 7
    with pytest.raises(ConfigError, match="valid_every: must be an integer >= 1, got 0"):
        dataclasses.replace(c, valid_every=0)
    m = ModelConfig(gn=TINY)
    assert ModelConfig.from_dict(m.to_dict()) == m
    with pytest.raises(ConfigError, match="^latent: "):
        dataclasses.replace(TINY, latent=0)
    with pytest.raises(ConfigError, match="^gn.latent: "):
        ModelConfig(gn={"latent": 0})
    # an earlier version's keys still load
    old = TrainConfig.from_dict({"dtype": "float64", "model": {"gn": {"latent": 8, "backend": "torch"}}})
    assert (old.model.run.precision, old.model.run.impl) == ("fp64", "torch")
    # the error pickles (multiprocessing hands it back whole)
    e = pickle.loads(pickle.dumps(ConfigError("model.gn.latent", "must be ...")))
    assert (e.path, e.reason, str(e)) == ("model.gn.latent", "must be ...", "model.gn.latent: must be ...")


def test_gn_block_config_and_run_options_are_validated():
    for kw, path in ((dict(edge_hidden=5), "edge_hidden"), (dict(node_out=0), "node_out"),
                     (dict(node_size=-1), "node_size"), (dict(update_globals=1), "update_globals"),
                     (dict(edge_block={"use_edges": "no"}), "edge_block.use_edges")):
        with pytest.raises(ConfigError) as e:
            GNBlockConfig(**{"node_size": 4, "edge_size": 3, "global_size": 2, **kw})
        assert e.value.path == path, str(e.value)
    assert GNBlockConfig(4, 3, 2, edge_hidden=[8, 8]).edge_hidden == (8, 8)
    for kw, path in ((dict(precision="fp8"), "precision"), (dict(deterministic="yes"), "deterministic"),
                     (dict(emulate_min=(1, 2, 3)), "emulate_min")):
        with pytest.raises(ConfigError) as e:
            RunOptions(**kw)
        assert e.value.path == path
    with pytest.raises(ConfigError, match="unknown run options"):
        RunOptions.from_dict({"precison": "fp16"})


# -- gnwarp evaluate: arguments, and predictions that leave the finite range -----------------------
@pytest.mark.parametrize("args,words", [(["-n", "0"], "-n/--sequences must be an integer >= 1, got '0'"),
                                        (["-n", "-1"], "got '-1'"), (["-n", "abc"], "got 'abc'"),
                                        (["--horizons", "0"], "--horizons must be an integer >= 1, got '0'"),
                                        (["--horizons", "20", "-5"], "got '-5'"),
                                        (["--horizons", "2x0"], "got '2x0'")])
def test_evaluate_refuses_bad_counts(args, words, tmp_path, capsys):
    """Refused before anything is loaded (the checkpoint and dataset named do not exist)."""
    assert cli.main(["evaluate", str(tmp_path / "ck"), "--data", str(tmp_path / "none.h5"), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"gnwarp evaluate: error: {words}" or (words in err and "\n" not in err), err


@pytest.fixture(scope="module")
def pendulum():
    return data.generate("pendulum", (4, 2, 3), num_steps=8, seed=0, backend="mujoco", progress=False)



def test_evaluate_reports_the_first_nonfinite_step(pendulum, tmp_path, monkeypatch, capsys):
    r = metrics.evaluate(TruthModel(pendulum, 3), pendulum, "test", horizons=(2, 5))
    assert r["rollout_2"]["first_nonfinite_step"] is None and math.isfinite(r["rollout_2"]["mean"])
    assert r["rollout_5"]["first_nonfinite_step"] == 3 and r["rollout_5"]["nonfinite_sequences"] == 1
    assert r["rollout_5"]["mean"] == math.inf and r["first_nonfinite_step"] == 3 and not r["finite"]
    table = markdown_table({"GN": r}, "pendulum")
    row = next(line for line in table.splitlines() if line.startswith("| GN |"))
    assert "non-finite" in row and "3 (1 of 3 sequences)" in row and "n/a" not in row, row
    # the command: the table says where, the exit status says that something diverged
    import gnwarp.data.dataset as dataset_module
    import gnwarp.train as train_module
    monkeypatch.setattr(dataset_module, "load", lambda path: pendulum)
    monkeypatch.setattr(train_module, "load_model", lambda path, **kw: TruthModel(pendulum, 3))
    assert cli.main(["evaluate", "ck", "--names", "GN", "--data", "x.h5", "--horizons", "2,5"]) == 1
    out = capsys.readouterr()
    assert "3 (1 of 3 sequences)" in out.out
    assert out.err.strip() == ("gnwarp evaluate: error: predictions left the finite range: GN: rollouts not "
                               "finite from step 3 (1 of 3 sequences)")
    monkeypatch.setattr(train_module, "load_model", lambda path, **kw: TruthModel(pendulum, 99))
    assert cli.main(["evaluate", "ck", "--data", "x.h5", "--horizons", "5", "-n", "2"]) == 0
    assert "| none |" in capsys.readouterr().out


def test_evaluate_names_the_steps_a_short_dataset_allows_and_refuses_what_it_would_drop(pendulum, monkeypatch,
                                                                                        capsys):
    """A horizon longer than the data's sequences is labelled with the steps used (not as a
    rollout of its own length); --names must name every checkpoint; system-identification and
    forward checkpoints are not mixed (the forward ones were dropped) and sysid takes no -o."""
    import gnwarp.data.dataset as dataset_module
    import gnwarp.train as train_module
    import gnwarp.train.checkpoint as checkpoint_module
    monkeypatch.setattr(dataset_module, "load", lambda path: pendulum)
    monkeypatch.setattr(train_module, "load_model", lambda path, **kw: TruthModel(pendulum, 99))
    assert cli.main(["evaluate", "ck", "--data", "x.h5", "--horizons", "3", "1000"]) == 0
    head = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("| model |"))
    assert "| 3-step rollout |" in head and "| 8-step rollout (1000 asked: the data's length) |" in head, head
    assert cli.main(["evaluate", "a", "b", "--names", "A", "--data", "x.h5"]) == 2
    assert "--names gives 1 names for 2 checkpoints" in capsys.readouterr().err
    monkeypatch.setattr(checkpoint_module, "checkpoint_config", lambda p: {"kind": "sysid" if p == "sid" else "forward"})
    assert cli.main(["evaluate", "sid", "fwd", "--data", "x.h5"]) == 2
    assert "(sid) and forward models (fwd) are evaluated apart" in capsys.readouterr().err
    assert cli.main(["evaluate", "sid", "--data", "x.h5", "-o", "out"]) == 2
    assert "-o/--out: not taken for system-identification checkpoints" in capsys.readouterr().err


# -- the GN block's index --------------------------------------------------------------------------
def _two_graphs(senders=(0, 1, 2, 3)):
    return GraphsTuple(nodes=torch.randn(4, 4), edges=torch.randn(4, 3), receivers=torch.tensor([1, 0, 3, 2]),
                       senders=torch.tensor(senders), globals=torch.randn(2, 2), n_node=torch.tensor([2, 2]),
                       n_edge=torch.tensor([2, 2]))


@pytest.fixture
def block():
    torch.manual_seed(0)
    return GraphNetwork(GNBlockConfig(4, 3, 2, 8, 8, 8, (8,), (8,), (8,)), check_inputs=False)


@pytest.mark.parametrize("bad", [1000, 10**9, -1, 4])
def test_bad_sender_is_refused_at_index_build(bad, block):
    """With ``check_inputs=False`` too: the index is where values are validated, so no kernel
    ever reads out of bounds."""
    g = _two_graphs((0, bad, 2, 3))
    with pytest.raises(ValueError, match="senders index out of range"):
        graph_index(g)
    with pytest.raises(ValueError, match="senders index out of range"):
        block(g)
    with pytest.raises(ValueError, match="senders index out of range"):
        block.graph_index(g)


@pytest.mark.parametrize("change,words", [
    (dict(n_node=torch.tensor([2, 3])), "n_node sums to 5"),
    (dict(n_node=torch.tensor([-1, 5])), "non-negative"),
    (dict(n_edge=torch.tensor([2, 3])), "n_edge sums to 5"),
    (dict(n_edge=torch.tensor([2])), "n_node has 2 graphs but n_edge has 1"),
    (dict(receivers=torch.tensor([1, 0, 3])), "receivers 3"),
    (dict(senders=torch.tensor([0.0, 1.0, 2.0, 3.0])), "int32 or int64"),
    (dict(senders=torch.tensor([0, 2, 2, 3])), "different graph"),
])
def test_graph_index_validates_counts(change, words, block):
    g = _two_graphs()._replace(**change)
    with pytest.raises((ValueError, TypeError), match=words):
        graph_index(g)
    with pytest.raises((ValueError, TypeError), match=words):
        block(g)


def test_index_of_another_topology_raises(block):
    g = _two_graphs()
    index = block.graph_index(g)
    assert block(g, index).nodes.shape == (4, 8)
    # other counts: found from shapes alone, with input checks off
    three = GraphsTuple(nodes=torch.randn(6, 4), edges=torch.randn(4, 3), receivers=torch.tensor([1, 0, 3, 2]),
                        senders=torch.tensor([0, 1, 2, 3]), globals=torch.randn(2, 2), n_node=torch.tensor([2, 4]),
                        n_edge=torch.tensor([2, 2]))
    with pytest.raises(ValueError, match="another topology.*6 nodes"):
        block(three, index)
    one = graph_index(_two_graphs())._replace(n_graphs=1)
    with pytest.raises(ValueError, match="another topology"):
        check_index(one, g)
    # same counts, other edges: with input checks on the arrays are compared too
    swapped = g._replace(senders=torch.tensor([1, 0, 3, 2]), receivers=torch.tensor([0, 1, 2, 3]))
    block(swapped, index)   # shapes agree: accepted without a host sync
    block.check_inputs = True
    with pytest.raises(ValueError, match="another topology: its senders, receivers differ"):
        block(swapped, index)
    with pytest.raises(ValueError, match="another topology"):
        block(three, index)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_index_topology_check_needs_no_host_sync(block):
    """With input checks off, a prebuilt index is compared with the graph from shapes alone: the
    block's call makes no host synchronization, and another topology still raises."""
    block = block.cuda()
    g = GraphsTuple(*(None if x is None else x.cuda() for x in _two_graphs()))
    index = block.graph_index(g)
    block(g, index)   # compiles the kernels
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        out = block(g, index)
        with pytest.raises(ValueError, match="another topology"):
            block(g._replace(nodes=torch.randn(5, 4, device="cuda")), index)
    finally:
        torch.cuda.set_sync_debug_mode(0)
    assert torch.isfinite(out.nodes).all()


# -- rollouts: shapes, instances, finiteness, control ranges ----------------------------------------
@pytest.fixture(scope="module")
def model(pendulum):
    torch.manual_seed(0)
    m = ForwardModel(ModelConfig(gn=TINY, run=RunOptions(impl="warp")), pendulum.layout).bind(pendulum)
    return m


def _inputs(pendulum):
    sp = pendulum["test"]
    return torch.as_tensor(sp.body[:2, 0]), torch.as_tensor(sp.ctrl[:2, :3])


def _scaled_quat(x, at, factor):
    x = x.clone()
    x[at][3:7] *= factor
    return x


def _nan_at(x, index):
    x = x.clone()
    x[index] = float("nan")
    return x


ROLLOUT_CASES = [
    ("NaN in the initial state", lambda x, u: dict(initial_body=_nan_at(x, (1, 1, 4))), "initial_body\\[1, 1\\]"),
    ("zero quaternion", lambda x, u: dict(initial_body=x.clone().index_fill_(2, torch.arange(3, 7), 0.0)),
     "initial_body\\[0, 0\\] has an orientation quaternion of norm 0 "),
    ("quaternion of norm 0.05", lambda x, u: dict(initial_body=_scaled_quat(x, (1, 1), 0.05)),
     "initial_body\\[1, 1\\] has an orientation quaternion of norm 0.05 "),
    ("Inf in the controls", lambda x, u: dict(ctrl=_nan_at(u, (0, 2, 0)).nan_to_num(posinf=math.inf, nan=math.inf)),
     "ctrl contains NaN or Inf \\(at ctrl\\[0, 2, 0\\]\\)"),
    ("two controls for one actuator", lambda x, u: dict(ctrl=torch.zeros(2, 3, 2)), "got shape \\(2, 3, 2\\).*1 control"),
    ("more control sequences than states", lambda x, u: dict(ctrl=torch.zeros(3, 3, 1)), "number of sequences"),
    ("empty controls", lambda x, u: dict(ctrl=torch.zeros(2, 0, 1)), "no steps"),
    ("state width", lambda x, u: dict(initial_body=torch.zeros(2, 2, 7)), "initial_body must be \\[N, B, 13\\]"),
    ("bodies", lambda x, u: dict(initial_body=torch.zeros(2, 3, 13)), "= \\[2, 2, 13\\]"),
    ("instance -1", lambda x, u: dict(instance=torch.tensor([0, -1])), "instance -1 is out of range"),
    ("instance 7", lambda x, u: dict(instance=[7, 0]), "instance 7 is out of range.*1 system instance"),
    ("float instance", lambda x, u: dict(instance=torch.tensor([0.0, 0.0])), "integers"),
    ("instance count", lambda x, u: dict(instance=[0, 0, 0]), "instance has 3 entries"),
    ("ctrl outside the range, refused", lambda x, u: dict(ctrl=u * 100, ctrl_policy="error"), "control range \\[-1, 1\\]"),
    ("unknown ctrl_policy", lambda x, u: dict(ctrl_policy="wrap"), "ctrl_policy must be one of"),
]


@pytest.mark.parametrize("case", ROLLOUT_CASES, ids=[c[0] for c in ROLLOUT_CASES])
def test_rollout_inputs_are_checked_before_any_launch(case, model, pendulum, monkeypatch):
    import warp as wp
    _, make, words = case
    x0, u = _inputs(pendulum)
    kw = dict(initial_body=x0, ctrl=u)
    kw.update(make(x0, u))

    def no_launch(*a, **k):
        raise AssertionError("a kernel was launched before the inputs were checked")
    monkeypatch.setattr(wp, "launch", no_launch)
    with pytest.raises(ValueError, match=words):
        model.rollout(**kw)


def test_rollout_engine_and_predict_inputs(model, pendulum):
    x0, u = _inputs(pendulum)
    for kw, words in ((dict(instance=[0, 2], horizon=3), "instance 2"), (dict(instance=[0, 0], horizon=0), "horizon"),
                      (dict(instance=[0.5, 0], horizon=3), "integers")):
        with pytest.raises(RolloutInputError, match=words):
            model.rollout_engine(**kw)
    engine = model.rollout_engine([0, 0], 3)
    with pytest.raises(RolloutInputError, match="ctrl contains NaN"):
        engine.rollout(x0, _nan_at(u, (1, 1, 0)))
    with pytest.raises(RolloutInputError, match="holds x0"):
        engine.rollout(x0, torch.zeros(2, 3, 2))
    with pytest.raises(RolloutInputError, match="predict's ctrl must be \\[N, U\\]"):
        model.predict(x0, u)
    # checks off: NaN goes through (and comes out), as asked
    assert torch.isnan(model.rollout(x0, _nan_at(u, (0, 0, 0)), check=False)).any()


def test_controls_are_clamped_to_the_actuator_range_as_mujoco_does(model, pendulum):
    """Pendulum's motor has ctrlrange [-1, 1] (ctrllimited): 100x controls roll out as the range's
    ends, in the eager rollout, one-step predictions and the engine alike; "none" keeps them."""
    x0, u = _inputs(pendulum)
    big = torch.where(u >= 0, 100.0, -100.0) * torch.ones_like(u)
    ends = torch.where(u >= 0, 1.0, -1.0) * torch.ones_like(u)
    with torch.no_grad():
        clamped = model.rollout(x0, big)
        assert torch.equal(clamped, model.rollout(x0, ends))
        assert not torch.equal(clamped, model.rollout(x0, big, ctrl_policy="none"))
        assert torch.equal(model.predict(x0, big[:, 0]), clamped[:, 1])
        assert torch.equal(model.rollout_engine([0, 0], 3).rollout(x0, big), clamped)
    # inside the range nothing changes, and gradients flow where the controls are inside it
    w = u.clone().requires_grad_()
    model.rollout(x0, w).sum().backward()
    assert w.grad.abs().sum() > 0
    v = big.clone().requires_grad_()
    model.rollout(x0, v).sum().backward()
    assert torch.equal(v.grad, torch.zeros_like(v))   # MuJoCo's clamped controls have no effect either


def test_clamping_matches_mujoco(pendulum):
    """The reference: MuJoCo itself clamps the pendulum's motor control to [-1, 1]."""
    import mujoco

    from gnwarp.sim import systems
    s = systems.make("pendulum")
    m, d = s.model, mujoco.MjData(s.model)
    assert m.actuator_ctrllimited[0] and tuple(m.actuator_ctrlrange[0]) == (-1.0, 1.0)
    out = []
    for c in (1.0, 100.0):
        mujoco.mj_resetData(m, d)
        d.ctrl[:] = c
        mujoco.mj_step(m, d)
        out.append(d.qvel.copy())
    np.testing.assert_array_equal(out[0], out[1])


# -- GraphsTuple: batch / unbatch round trips (property test) ---------------------------------------
@st.composite
def _graphs(draw):
    n = draw(st.integers(1, 5))
    seed = draw(st.integers(0, 2**32 - 1))
    with_nodes, with_edges, with_globals = draw(st.booleans()), draw(st.booleans()), draw(st.booleans())
    rng = np.random.default_rng(seed)
    gs = []
    for _ in range(n):
        nv = int(rng.integers(0, 6))
        ne = int(rng.integers(0, 7)) if nv else 0
        gs.append(GraphsTuple(
            nodes=rng.normal(size=(nv, 3)) if with_nodes else None,
            edges=rng.normal(size=(ne, 2)) if with_edges else None,
            globals=rng.normal(size=(1, 4)) if with_globals else None,
            senders=rng.integers(0, max(nv, 1), ne), receivers=rng.integers(0, max(nv, 1), ne),
            n_node=np.array([nv]), n_edge=np.array([ne])))
    return gs


def _same(a, b):
    for x, y in zip(a, b):
        assert (x is None) == (y is None)
        if x is not None:
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


@settings(max_examples=40, deadline=None)
@given(_graphs(), st.booleans())
def test_batch_unbatch_round_trip_property(gs, to_torch):
    if to_torch:
        gs = [g.to_torch() for g in gs]
    b = batch(gs)
    validate(b)
    assert b.total_nodes == sum(g.total_nodes for g in gs) and b.total_edges == sum(g.total_edges for g in gs)
    parts = unbatch(b)
    assert len(parts) == len(gs)
    for g, p in zip(gs, parts):
        _same(g, p)
    _same(batch(parts), b)
    # batching batches: the same as batching all at once
    k = len(gs) // 2
    if 0 < k < len(gs):
        _same(batch([batch(gs[:k]), batch(gs[k:])]), b)


@pytest.mark.skipif(torch.cuda.is_available(), reason="asks for CUDA where torch sees none")
@pytest.mark.parametrize("command", [["evaluate", "{ck}", "--data", "{data}"], ["mpc", "--model", "{ck}", "--task",
                                     "pendulum-balance", "--video", "none", "--records", "{tmp}/r.jsonl"],
                                     ["train", "--data", "{data}", "--quick", "-o", "{tmp}/t"]])
def test_a_device_that_is_not_here_is_one_clear_error(command, tmp_path, capsys):
    """--device cuda on a CPU-only torch (and a misspelt device) end in one line naming the device,
    before any work (no checkpoint or dataset is even read: none exists here)."""
    from gnwarp.interop import resolve_device
    fill = dict(ck=str(tmp_path / "ck"), data=str(tmp_path / "d.h5"), tmp=str(tmp_path))
    args = [a.format(**fill) for a in command]
    args += ["--set", "device=cuda"] if command[0] == "train" else ["--device", "cuda"]
    assert cli.main(args) == 2
    err = capsys.readouterr().err
    assert "device 'cuda' asked for, but torch sees no CUDA device" in err and "Traceback" not in err
    with pytest.raises(ValueError, match="'cdua' is not a device"):
        resolve_device("cdua")
    assert resolve_device("auto") == torch.device("cpu") and resolve_device("cpu") == torch.device("cpu")


def test_generate_refuses_dt_and_substeps_for_a_built_in_system(tmp_path, capsys):
    """--dt and --substeps shape an MJCF's data; a built-in system keeps its own timestep, so
    they are refused there instead of ignored (the data would not have the dt asked for)."""
    for flag in (["--dt", "0.01"], ["--substeps", "0"]):
        out = tmp_path / "b.h5"
        assert cli.main(["generate", "pendulum", "-n", "3", "--steps", "5", *flag, "-o", str(out), "-q"]) == 2
        assert "--dt and --substeps apply to --mjcf only" in capsys.readouterr().err and not out.exists()


def test_resolve_device_refuses_a_gpu_index_beyond_those_visible(monkeypatch):
    """Any machine: with one CUDA device visible (patched), cuda:3 is refused naming the count;
    cuda:0, torch.device objects and the CPU pass."""
    from gnwarp.interop import resolve_device
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    with pytest.raises(ValueError, match="'cuda:3': only 1 CUDA device"):
        resolve_device("cuda:3")
    assert resolve_device("cuda:0") == torch.device("cuda", 0)
    assert resolve_device(torch.device("cpu")) == torch.device("cpu")
    with pytest.raises(ValueError, match="runs on cpu or cuda"):
        resolve_device("xla")


def test_sysid_table_names_the_steps_each_models_window_leaves(monkeypatch, capsys):
    """Sysid checkpoints of different windows roll out for different steps at a long horizon: the
    column says so and each cell names its own steps (the label once showed the shortest)."""
    from types import SimpleNamespace

    import gnwarp.eval.sysid as eval_sysid
    import gnwarp.train.sysid as train_sysid
    from gnwarp.cli.evaluate import evaluate_sysid
    models = {"a/ck": SimpleNamespace(window=4), "b/ck": SimpleNamespace(window=10)}
    monkeypatch.setattr(train_sysid, "load_sysid", lambda path, device=None: models[path])
    monkeypatch.setattr(train_sysid, "trained_param_stats", lambda m, system: None)
    monkeypatch.setattr(eval_sysid, "sysid_error_rows",
                        lambda m, ds, split, hs, n, oracle: [("same instance", [0.5 * m.window] * len(hs))])

    class Data(dict):
        system = "pendulum"
    ds = Data(test=SimpleNamespace(ctrl=np.zeros((3, 20, 1))))
    assert evaluate_sysid(["a/ck", "b/ck"], ds, SimpleNamespace(device="cpu", split="test", names=["A", "B"]),
                          None, (5, 12, 30)) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == ("| model | identified from | 5-step rollout | 12-step rollout (fewer where a model's "
                        "window leaves fewer steps: in its cells) | 30-step rollout (fewer where a model's window "
                        "leaves fewer steps: in its cells) |"), lines[0]
    assert lines[2] == "| A | same instance | 2 | 2 | 2 (16 steps) |", lines[2]
    assert lines[3] == "| B | same instance | 5 | 5 (10 steps) | 5 (10 steps) |", lines[3]
    # one window: the steps used in the header, as for forward models
    assert evaluate_sysid(["b/ck"], ds, SimpleNamespace(device="cpu", split="test", names=None), None, (12,)) == 0
    assert "| 10-step rollout (12 asked: the data's length) |" in capsys.readouterr().out
