"""Training, checkpoints, evaluation, the CLI and the demo, at tiny sizes on the CPU."""
import csv
import json
import math

import numpy as np
import pytest
import torch

import gnwarp
from gnwarp import data
from gnwarp import eval as ev
from gnwarp.data.layout import LayoutMismatchError, merge_layouts
from gnwarp.interop import warp
from gnwarp.gn import RunOptions
from gnwarp.models import GNCoreConfig, ModelConfig
from oracles import TruthModel
from gnwarp.train import CheckpointError, FlatAdam, TrainConfig, Trainer, load_model, train

warp()

TINY = dict(latent=8, edge_hidden=(16,), node_hidden=(16,), global_hidden=(16,))


@pytest.fixture(scope="module")
def pendulum():
    return data.generate("pendulum", (20, 3, 4), num_steps=20, seed=0, backend="mujoco", progress=False)


def config(tmp_path, name="run", impl="torch", **kw):
    base = dict(out=str(tmp_path / name), model=ModelConfig(gn=GNCoreConfig(**TINY), run=RunOptions(impl=impl)),
                steps=60, batch_size=32, lr=3e-3, lr_decay_steps=1000, valid_every=30, valid_sequences=3,
                log_every=10, checkpoint_every=30, normalizer_warmup=2, progress=False, device="cpu")
    base.update(kw)
    return TrainConfig(**base)


def read_log(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def test_training_reduces_the_loss(tmp_path, pendulum):
    r = train(config(tmp_path, impl="warp", steps=150, valid_every=50), [pendulum])
    rows = [x for x in read_log(tmp_path / "run" / "log.csv") if x["loss"]]
    first, last = float(rows[0]["loss"]), np.mean([float(x["loss"]) for x in rows[-3:]])
    assert last < 0.5 * first, (first, last)
    assert r["steps"] == 150 and r["stop"] == "steps" and math.isfinite(r["best_error"])
    valid = [float(x["valid_error"]) for x in read_log(tmp_path / "run" / "log.csv") if x["valid_error"]]
    assert len(valid) == 3 and r["best_error"] == min(valid)
    assert (tmp_path / "run" / "best" / "model.pt").is_file()
    m = load_model(r["best"])
    assert m.options.impl == "warp" and m.config.recenter is False  # pendulum: no re-centring (D.4)


def test_checkpoint_round_trip_gives_identical_predictions(tmp_path, pendulum):
    r = train(config(tmp_path, steps=30), [pendulum])
    a = load_model(r["last"], device="cpu")
    b = load_model(r["last"], device="cpu")
    for k, v in a.state_dict().items():
        assert torch.equal(v, b.state_dict()[k]), k
    assert a.norm_nodes.count.dtype == torch.float64 and float(a.norm_nodes.count) > 0
    sp = pendulum["test"]
    x0, u = torch.as_tensor(sp.body[:, 0]), torch.as_tensor(sp.ctrl)
    pa = a.bind(pendulum).rollout(x0, u)
    pb = b.bind(pendulum).rollout(x0, u)
    assert torch.equal(pa, pb)
    # saving a loaded model again and reloading changes nothing
    gnwarp.train.save_checkpoint(tmp_path / "again", a)
    c = load_model(tmp_path / "again", device="cpu").bind(pendulum)
    assert torch.equal(c.rollout(x0, u), pa)
    cfg = json.loads((tmp_path / "run" / "last" / "config.json").read_text())
    assert cfg["format"] == "gnwarp-model" and cfg["layout"] == pendulum.layout.to_dict()
    assert cfg["train"]["steps"] == 30 and cfg["data"][0]["system"] == "pendulum"


def test_resume_continues_exactly(tmp_path, pendulum):
    full = train(config(tmp_path, "full", steps=40, valid_every=20, checkpoint_every=20), [pendulum])
    train(config(tmp_path, "half", steps=20, valid_every=20, checkpoint_every=20), [pendulum])
    resumed = train(config(tmp_path, "half", steps=40, valid_every=20, checkpoint_every=20), [pendulum])
    assert resumed["steps"] == 40 and resumed["steps_this_call"] == 20
    # the rate is the run's: its steps over its seconds, all calls counted
    assert resumed["steps_per_second"] == pytest.approx(40 / resumed["seconds"])
    again = train(config(tmp_path, "half", steps=40, valid_every=20, checkpoint_every=20), [pendulum])
    assert again["steps_this_call"] == 0 and again["seconds"] == resumed["seconds"]
    assert again["steps_per_second"] == resumed["steps_per_second"]
    a, b = load_model(full["last"], device="cpu"), load_model(resumed["last"], device="cpu")
    for k, v in a.state_dict().items():
        torch.testing.assert_close(v, b.state_dict()[k], rtol=1e-6, atol=1e-7, msg=k)
    steps = [int(x["step"]) for x in read_log(tmp_path / "half" / "log.csv")]
    assert steps == sorted(steps) and steps[-1] == 40


def test_corrupt_checkpoints_give_clear_errors(tmp_path, pendulum):
    train(config(tmp_path, steps=10, valid_every=10), [pendulum])
    import shutil
    good = tmp_path / "run" / "last"
    with pytest.raises(CheckpointError, match="no checkpoint"):
        load_model(tmp_path / "nowhere")
    bad = tmp_path / "flipped"
    shutil.copytree(good, bad)
    raw = bytearray((bad / "model.pt").read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    (bad / "model.pt").write_bytes(bytes(raw))
    with pytest.raises(CheckpointError, match="model.pt is corrupt"):
        load_model(bad)
    bad = tmp_path / "truncated"
    shutil.copytree(good, bad)
    (bad / "model.pt").unlink()
    with pytest.raises(CheckpointError, match="model.pt is missing"):
        load_model(bad)
    bad = tmp_path / "json"
    shutil.copytree(good, bad)
    (bad / "manifest.json").write_text("{not json")
    with pytest.raises(CheckpointError, match="JSON"):
        load_model(bad)
    # weights of another architecture under a consistent manifest
    bad = tmp_path / "other"
    shutil.copytree(good, bad)
    cfg = json.loads((bad / "config.json").read_text())
    cfg["model"]["gn"]["latent"] = 9
    (bad / "config.json").write_text(json.dumps(cfg))
    man = json.loads((bad / "manifest.json").read_text())
    man["config.json"] = gnwarp.files.sha256_file(bad / "config.json")
    (bad / "manifest.json").write_text(json.dumps(man))
    with pytest.raises(CheckpointError, match="cannot load the weights"):
        load_model(bad)
    assert not any(p.name.startswith(".") for p in (tmp_path / "run").iterdir())  # no temporary folders left


def _rewrite_config(folder, edit):
    """Edit a checkpoint's config.json and re-sign it in the manifest."""
    cfg = json.loads((folder / "config.json").read_text())
    edit(cfg)
    (folder / "config.json").write_text(json.dumps(cfg))
    man = json.loads((folder / "manifest.json").read_text())
    man["config.json"] = gnwarp.files.sha256_file(folder / "config.json")
    (folder / "manifest.json").write_text(json.dumps(man))


def test_load_model_overrides_run_options_not_weights(tmp_path, pendulum):
    """``load_model(path, impl=..., precision=...)`` changes how the model runs, not its weights:
    the Warp implementation in float64 ("fp64") predicts what the saved torch fp32 model does, and
    ``set_options`` goes back to float32 with the same weights bit for bit."""
    r = train(config(tmp_path, steps=20, valid_every=20), [pendulum])
    a = load_model(r["last"], device="cpu")
    b = load_model(r["last"], device="cpu", impl="warp", precision="fp64")
    assert (a.options.impl, a.options.precision, a.dtype) == ("torch", "fp32", torch.float32)
    assert (b.options.impl, b.options.precision, b.dtype) == ("warp", "fp64", torch.float64)
    for (k, p), q in zip(a.named_parameters(), b.parameters()):
        assert torch.equal(p.double(), q), k
    sp = pendulum["test"]
    x0, u = torch.as_tensor(sp.body[:, 0]), torch.as_tensor(sp.ctrl[:, :10])
    pa, pb = a.bind(pendulum).rollout(x0, u), b.bind(pendulum).rollout(x0, u)
    assert pb.dtype == torch.float64 and (pa.double() - pb).abs().max() < 1e-4
    b.set_options(precision="fp32", impl="torch")
    assert b.dtype == torch.float32 and all(torch.equal(p, q) for p, q in zip(a.parameters(), b.parameters()))
    with pytest.raises(TypeError, match="unknown run options"):
        load_model(r["last"], device="cpu", precison="tf32")
    with pytest.raises(ValueError, match="precision"):
        load_model(r["last"], device="cpu", precision="fp8")


def test_checkpoints_of_earlier_versions_load(tmp_path, pendulum):
    """Configs written before run options had their own home (``model.gn.backend`` / ``path`` /
    ``precision``, ``path="split"``, ``train.dtype``) load with the same meaning."""
    r = train(config(tmp_path, steps=10, valid_every=10), [pendulum])
    old = tmp_path / "old"
    import shutil
    shutil.copytree(r["last"], old)

    def old_model(model, precision):
        run = model.pop("run")
        model["gn"].update(backend=run["impl"], path="split", precision=precision, deterministic=True)

    def to_old(cfg):
        old_model(cfg["model"], "tf32")
        old_model(cfg["train"]["model"], "fp32")  # every old config spelled out gn.precision
        cfg["train"]["dtype"] = "float64"
    _rewrite_config(old, to_old)
    m = load_model(old, device="cpu")
    assert (m.options.impl, m.options.path, m.options.precision, m.options.deterministic) == (
        "torch", "blas", "tf32", True)
    # the old train config: float64 training is precision "fp64", whatever gn.precision said
    cfg = TrainConfig.from_dict(json.loads((old / "config.json").read_text())["train"])
    assert (cfg.model.run.precision, cfg.model.run.impl, cfg.model.run.path) == ("fp64", "torch", "blas")
    with pytest.raises(ValueError, match="dtype"):
        TrainConfig.from_dict({"dtype": "float16"})
    # a saved config's earlier key is read; as a keyword of load_model it is an unknown option
    with pytest.raises(TypeError, match=r"unknown run options \['backend'\]"):
        load_model(r["last"], device="cpu", backend="torch")


def test_trainer_seams(tmp_path, pendulum):
    """The Trainer's seams: a subclass replaces where batches come from, callbacks see every log
    row, validation and checkpoint, and ``step`` alone runs one optimization step."""
    events = []

    class Counting(gnwarp.Trainer):
        batches = 0

        def sample(self):
            Counting.batches += 1
            return super().sample()
    t = Counting(config(tmp_path, steps=20, valid_every=10, log_every=10, checkpoint_every=20, normalizer_warmup=2),
                 [pendulum], callbacks=[lambda tr, event, info: events.append((event, info))])
    p0 = [p.detach().clone() for p in t.model.parameters()]
    r = t.run()
    assert Counting.batches == 20 + 2  # the steps and the normalizer warm-up
    kinds = [e for e, _ in events]
    assert kinds.count("log") == 2 and kinds.count("validate") == 2 and kinds[-1] == "end"
    assert [i["name"] for e, i in events if e == "checkpoint"][-1] == "last"
    assert [i["row"]["step"] for e, i in events if e == "log"] == [10, 20]
    assert next(i for e, i in events if e == "validate")["error"] == float(read_log(tmp_path / "run" / "log.csv")[0]
                                                                          ["valid_error"])
    assert r["steps"] == 20 and not all(torch.equal(a, b) for a, b in zip(p0, t.model.parameters()))
    terms = t.step()  # one more step, outside the loop: the count and the schedule advance
    assert set(terms) == {"loss", "pos", "quat", "linvel", "angvel"} and terms["loss"].requires_grad
    assert t.state["step"] == 21 and t.optimizer.param_groups[0]["lr"] == t.config.lr_at(20)


def test_trainer_runs_a_given_model_as_its_config_says(tmp_path, pendulum):
    """A model passed to the Trainer runs as ``config.model.run`` says ("fp64": float64), and
    changing a model's options leaves other models built from the same config alone."""
    cfg = config(tmp_path, steps=2, valid_every=2)
    other = gnwarp.models.build_model(cfg.model, [pendulum])
    m = gnwarp.models.build_model(cfg.model, [pendulum])
    cfg.model.run = cfg.model.run.replace(precision="fp64")
    t = gnwarp.Trainer(cfg, [pendulum], model=m)
    assert t.model.dtype == torch.float64 and t.model.options.precision == "fp64"
    assert other.options.precision == "fp32" and other.dtype == torch.float32
    a, b = (gnwarp.ForwardModel(other.config, pendulum.layout) for _ in range(2))  # one config object
    a.set_options(precision="tf32")
    assert b.options.precision == "fp32" and other.options.precision == "fp32"
    t.run()
    assert load_model(t.out / "last", device="cpu").dtype == torch.float64


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("optimizer,ema", [("adam", 0.0), ("flat_adam", 0.0), ("adam", 0.9), ("flat_adam", 0.9)])
def test_cuda_captured_training_matches_uncaptured(tmp_path, pendulum, optimizer, ema):
    """The training step replayed from one CUDA graph (sampling, noise, normalizers, loss,
    backward, clipping, update, running sums) after two eager steps, and the validation rollouts
    replayed too, give what uncaptured steps give: the same parameters bit for bit in
    deterministic mode with torch's Adam (FlatAdam's norm reduction adds blocks in any order: to
    float tolerance), the same losses and validation errors."""
    model = ModelConfig(gn=GNCoreConfig(**TINY), run=RunOptions(impl="warp", deterministic=True))
    kw = dict(steps=12, valid_every=6, log_every=3, checkpoint_every=12, device="cuda", optimizer=optimizer,
              model=model, ema=ema)
    runs = {}
    for capture in (True, False):
        t = gnwarp.Trainer(config(tmp_path, f"cap{capture}", capture=capture, **kw), [pendulum])
        t.run()
        assert (t.captured is not None and t.captured.graph is not None) == capture
        runs[capture] = t
    a, b = runs[True], runs[False]
    for p, q in zip(a.model.parameters(), b.model.parameters()):
        if optimizer == "adam":
            assert torch.equal(p, q)
        else:
            torch.testing.assert_close(p, q, rtol=1e-5, atol=1e-6)
    la, lb = read_log(a.out / "log.csv"), read_log(b.out / "log.csv")
    for ra, rb in zip(la, lb):
        for k in ("loss", "valid_error"):
            if ra[k]:
                assert math.isclose(float(ra[k]), float(rb[k]), rel_tol=1e-4), (k, ra, rb)
    assert a._valid_engines and a._valid_engines[0]._fwd.graph is not None


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_captured_training_of_several_systems(tmp_path, pendulum):
    """Batches mixing two systems are captured too (node offsets known on the host) and train as
    the uncaptured steps do."""
    cart = data.generate("cartpole", (10, 2, 2), num_steps=10, seed=0, backend="mujoco", progress=False)
    model = ModelConfig(gn=GNCoreConfig(**TINY), run=RunOptions(impl="warp", deterministic=True))
    runs = {}
    for capture in (True, False):
        t = gnwarp.Trainer(config(tmp_path, f"multi{capture}", capture=capture, steps=8, valid_every=8,
                                  batch_size=30, device="cuda", optimizer="adam", model=model), [pendulum, cart])
        t.run()
        assert (t.captured is not None and t.captured.graph is not None) == capture
        runs[capture] = t
    for p, q in zip(runs[True].model.parameters(), runs[False].model.parameters()):
        assert torch.equal(p, q)


def test_mismatched_dataset_gives_a_clear_error(tmp_path, pendulum):
    r = train(config(tmp_path, steps=5, valid_every=5), [pendulum])
    m = load_model(r["best"], device="cpu")
    cart = data.generate("cartpole", (2, 1, 2), num_steps=5, seed=0, backend="mujoco", progress=False)
    with pytest.raises(LayoutMismatchError, match="do not match the model's feature layout"):
        ev.evaluate(m, cart)
    with pytest.raises(LayoutMismatchError), pytest.warns(UserWarning, match="layout differs"):
        train(config(tmp_path, steps=10, valid_every=5), [cart])   # resuming a pendulum run on cartpole data


def test_mixed_batches_need_no_host_read(pendulum):
    """A batch mixing several datasets offsets its edges by node rows, shapes known on the host
    (a device read would break a captured step), and equals the parts batched one by one."""
    from gnwarp.graphs import batch
    from gnwarp.models import ForwardModel
    from gnwarp.train.sampler import BatchSampler
    cart = data.generate("cartpole", (6, 1, 1), num_steps=6, seed=0, backend="mujoco", progress=False)
    model = ForwardModel(ModelConfig(gn=GNCoreConfig(**TINY)), merge_layouts([pendulum.layout, cart.layout]))
    s = BatchSampler([pendulum, cart], model, "cpu")
    assert s.static_shapes
    g, target = s.sample(7, torch.Generator().manual_seed(0))
    gen = torch.Generator().manual_seed(0)
    parts = [p.sample(n, gen) for p, n in zip(s.parts, (4, 3))]   # the same draws, in the same order
    ref = batch([q for q, _ in parts])
    for a, b in zip(g, ref):
        assert torch.equal(a, b)
    assert torch.equal(target, torch.cat([t for _, t in parts]))
    assert int(g.senders[-1]) >= 4 * 2                               # cartpole's edges offset past pendulum's nodes
    # no device read: node counts that cannot be read back (meta tensors) are never needed
    meta = [q._replace(n_node=q.n_node.to("meta"), n_edge=q.n_edge.to("meta")) for q, _ in parts]
    blind = batch(meta)
    assert torch.equal(blind.senders, ref.senders) and torch.equal(blind.receivers, ref.receivers)


@pytest.mark.parametrize("system", ["pendulum", "cheetah"])
def test_fused_batch_kernel_matches_the_graph_builder(pendulum, system):
    """A batch of one topology written by the sampler's Warp kernel equals the graph builder's
    batch of the same draws (static features in the model's layout, routed controls, targets)."""
    from gnwarp.models import ForwardModel
    from gnwarp.train.sampler import SplitSampler
    ds = pendulum if system == "pendulum" else data.generate("cheetah", (5, 1, 1), num_steps=6, seed=0,
                                                             backend="mujoco", progress=False)
    for dtype in (torch.float32, torch.float64):
        model = ForwardModel(ModelConfig(gn=GNCoreConfig(**TINY)), ds.layout).to(dtype=dtype)
        s = SplitSampler(ds, model, "cpu")
        assert s.fused
        got = s.sample(9, torch.Generator().manual_seed(1))
        s.fused = False
        ref = s.sample(9, torch.Generator().manual_seed(1))
        for a, b in zip(got[0], ref[0]):
            assert a.dtype == b.dtype and torch.equal(a, b)
        assert torch.equal(got[1], ref[1])


def test_several_systems_in_one_model(tmp_path, pendulum):
    cart = data.generate("cartpole", (10, 2, 2), num_steps=10, seed=0, backend="mujoco", progress=False)
    lay = merge_layouts([pendulum.layout, cart.layout])
    assert "timestep" in lay.global_names                  # constant in each, different between them
    assert set(pendulum.layout.node_names) <= set(lay.node_names)
    r = train(config(tmp_path, "multi", steps=20, valid_every=20, batch_size=30), [pendulum, cart])
    m = load_model(r["best"], device="cpu")
    assert m.config.recenter is False
    for d in (pendulum, cart):
        res = ev.evaluate(m, d, sequences=2, horizons=(5,))
        assert math.isfinite(res["rollout_5"]["mean"])


def test_mlp_baseline_trains(tmp_path, pendulum):
    r = train(config(tmp_path, "mlp", steps=20, valid_every=20,
                     model=ModelConfig(core="mlp", mlp={"layers": 3, "width": 128})), [pendulum])
    m = load_model(r["best"], device="cpu")
    assert m.config.mlp.n_node == 2 and m.config.mlp.n_edge == 2


def test_evaluation_metrics(pendulum):
    res = ev.evaluate(TruthModel(pendulum), pendulum, horizons=(5, 20))
    for k in ("one_step", "rollout_5", "rollout_20"):
        assert res[k]["mean"] == 0.0
        assert math.isnan(res[k]["pos"])     # the pendulum's frame sits on its hinge: nothing to compare
    # the constant prediction scores 1 by construction, sign flips of quaternions cost nothing
    true = np.asarray(pendulum["test"].body[...])
    const = np.broadcast_to(true[:, :1], true.shape)
    mask = ev.movable_mask(pendulum, pendulum["test"].instance[...])
    r = ev.normalized_errors(const[:, 1:], true[:, 1:], const[:, 1:], mask)
    assert r["mean"] == 1.0
    flipped = true.copy()
    flipped[..., 3:7] *= -1
    r = ev.normalized_errors(flipped[:, 1:], true[:, 1:], const[:, 1:], mask)
    assert r["quat"] == 0.0


def test_sequence_shares_decompose_the_error(pendulum):
    """Each sequence's share of the normalized error: the shares add up to the error (over the
    groups with a ratio: the pendulum's position has none), and noise added to one sequence
    raises that sequence's share alone."""
    true = np.asarray(pendulum["test"].body[...], dtype=np.float64)
    const = np.broadcast_to(true[:, :1], true.shape)
    mask = ev.movable_mask(pendulum, pendulum["test"].instance[...])
    rng = np.random.default_rng(0)
    pred = true + 0.01 * rng.standard_normal(true.shape)
    base = ev.sequence_shares(pred[:, 1:], true[:, 1:], const[:, 1:], mask)
    assert base.shape == (true.shape[0],) and (base > 0).all()
    assert base.sum() == pytest.approx(ev.normalized_errors(pred[:, 1:], true[:, 1:], const[:, 1:], mask)["mean"],
                                       rel=1e-12)
    worse = pred.copy()
    worse[1] += 0.1 * rng.standard_normal(worse[1].shape)
    shares = ev.sequence_shares(worse[:, 1:], true[:, 1:], const[:, 1:], mask)
    assert shares[1] > 10 * base[1]
    np.testing.assert_allclose(np.delete(shares, 1), np.delete(base, 1), rtol=1e-12)
    assert shares.sum() == pytest.approx(ev.normalized_errors(worse[:, 1:], true[:, 1:], const[:, 1:], mask)["mean"],
                                         rel=1e-12)
    for group in (slice(0, 3), slice(3, 7)):   # position (no ratio on the pendulum) and orientation
        bad = pred.copy()
        bad[2, 5, 1, group] = np.nan
        shares = ev.sequence_shares(bad[:, 1:], true[:, 1:], const[:, 1:], mask)
        assert np.isposinf(shares[2]) and np.isfinite(np.delete(shares, 2)).all()
        assert ev.normalized_errors(bad[:, 1:], true[:, 1:], const[:, 1:], mask)["mean"] == math.inf


def test_cli_train_and_evaluate(tmp_path, pendulum, capsys):
    from gnwarp.cli import main
    path = tmp_path / "pend.h5"
    pendulum.save(path)
    (tmp_path / "cfg.toml").write_text(
        'steps = 10\nbatch_size = 16\nvalid_every = 10\nvalid_sequences = 2\nprogress = false\n'
        'device = "cpu"\nnormalizer_warmup = 1\n[model.gn]\nlatent = 8\nedge_hidden = [16]\n'
        'node_hidden = [16]\nglobal_hidden = [16]\n')
    out = tmp_path / "cli"
    assert main(["train", str(tmp_path / "cfg.toml"), "--data", str(path), "--out", str(out),
                 "--set", "model.run.impl=torch", "--set", "lr=0.002", "--set", "ema=0.99"]) == 0
    saved = json.loads((out / "best" / "config.json").read_text())
    assert saved["train"]["lr"] == 0.002 and saved["model"]["run"]["impl"] == "torch" and saved["train"]["ema"] == 0.99
    assert "average" in torch.load(out / "last" / "training.pt", weights_only=True)
    assert main(["evaluate", str(out / "best"), "--data", str(path), "--horizons", "5", "10",
                 "--out", str(tmp_path / "ev")]) == 0
    assert "| cli |" in capsys.readouterr().out
    for f in ("errors.md", "errors.png", "states.png", "rollouts.gif", "results.json"):
        assert (tmp_path / "ev" / f).is_file(), f
    assert main(["train", "--set", "nosuchkey=1", "--data", str(path)]) == 2   # a clear error, not a traceback
    assert main(["train", "--set", "ema=1", "--data", str(path)]) == 2
    assert "ema: must be a finite number >= 0 and < 1" in capsys.readouterr().err


def test_demo_end_to_end_tiny(tmp_path):
    from gnwarp.demo import DemoConfig, run_demo
    s = run_demo(DemoConfig(out=str(tmp_path / "demo"), train_sequences=8, valid_sequences=2, test_sequences=2,
                            num_steps=12, gn=GNCoreConfig(**TINY), mlp_size="3x128", train_steps=20,
                            train_seconds=None, batch_size=16, valid_every=10, animate_rollouts=2, progress=False))
    for f in ("report.md", "errors.png", "states.png", "rollouts.gif", "training.png", "results.json",
              "pendulum.h5", "gn/best/model.pt", "mlp/best/model.pt", "gn/log.csv"):
        assert (tmp_path / "demo" / f).is_file(), f
    assert s["gn"]["steps"] == 20 and s["mlp"]["steps"] == 20
    for name in ("GN", "MLP 3x128"):
        assert s["results"][name]["rollout_100"]["steps"] == 12   # cut to the sequences' length
        assert s["results"][name]["one_step"]["mean"] is not None
    assert "| GN |" in (tmp_path / "demo" / "report.md").read_text()


@pytest.mark.parametrize("impl", ["warp", "torch"])
def test_flat_adam_trains_like_torch_adam(tmp_path, pendulum, impl):
    """optimizer="flat_adam" (Warp kernels; gradients through main_grad on the Warp implementation,
    through p.grad on the torch one) ends where torch's Adam + clip_grad_norm_ does."""
    kw = dict(impl=impl, steps=20, valid_every=20, checkpoint_every=20, grad_clip=0.5)
    a = train(config(tmp_path, "adam", **kw), [pendulum])
    b = train(config(tmp_path, "flat", optimizer="flat_adam", **kw), [pendulum])
    ma, mb = load_model(a["last"], device="cpu"), load_model(b["last"], device="cpu")
    for (k, v), w in zip(ma.state_dict().items(), mb.state_dict().values()):
        torch.testing.assert_close(v, w, rtol=2e-4, atol=2e-5, msg=k)
    # not vacuous: training moved the parameters away from their (seeded) start
    assert any(not torch.allclose(p, q) for p, q in zip(mb.parameters(), _fresh_params(tmp_path, pendulum, impl)))
    with pytest.raises(CheckpointError, match="optimizer state does not fit"):
        train(config(tmp_path, "flat", optimizer="adam", **{**kw, "steps": 30}), [pendulum])


def test_auto_optimizer_is_adam_on_cpu_and_resumes_the_saved_kind(tmp_path, pendulum):
    """optimizer="auto" (the default): torch's Adam on the CPU; a run saved with FlatAdam state
    resumes with FlatAdam under "auto" instead of failing on the other kind's state."""
    assert TrainConfig().optimizer == "auto"
    t = Trainer(config(tmp_path, "auto", steps=4, valid_every=4, checkpoint_every=4), [pendulum])
    assert type(t.optimizer) is torch.optim.Adam
    t.run()
    flat = config(tmp_path, "flat", optimizer="flat_adam", steps=4, valid_every=4, checkpoint_every=4)
    train(flat, [pendulum])
    resumed = Trainer(config(tmp_path, "flat", steps=8, valid_every=4, checkpoint_every=4), [pendulum])
    assert isinstance(resumed.optimizer, FlatAdam) and resumed.state["step"] == 4
    assert resumed.run()["steps"] == 8


class _Recording(Trainer):
    """A Trainer that keeps the live weights after every step (``history[0]``: the initial ones)."""

    def step(self):
        if not hasattr(self, "history"):
            self.history = [[p.detach().clone() for p in self.model.parameters()]]
        terms = super().step()
        self.history.append([p.detach().clone() for p in self.model.parameters()])
        return terms


@pytest.mark.parametrize("optimizer", ["adam", "flat_adam"])
def test_ema_validates_and_saves_the_averaged_weights(tmp_path, pendulum, optimizer):
    """ema=0.9: the checkpoints' model is the moving average of the live weights of every step
    (a reference loop over them), the logged validation error is the averaged model's, and the
    live weights (what the optimizer steps) are the last step's, as without averaging."""
    cfg = config(tmp_path, "ema", steps=20, valid_every=20, checkpoint_every=20, ema=0.9, optimizer=optimizer)
    t = _Recording(cfg, [pendulum])
    t.run()
    ref = t.history[0]
    for k, w in enumerate(t.history[1:], 1):
        d = min(0.9, (1 + k) / (10 + k))
        ref = [d * r + (1 - d) * x for r, x in zip(ref, w)]
    saved = load_model(t.out / "last", device="cpu")
    for p, r in zip(saved.parameters(), ref):
        torch.testing.assert_close(p, r, rtol=1e-5, atol=1e-6)
    assert all(torch.equal(p, x) for p, x in zip(t.model.parameters(), t.history[-1]))
    assert any(not torch.allclose(p, r, atol=1e-4) for p, r in zip(t.model.parameters(), ref))  # not vacuous
    valid = [float(x["valid_error"]) for x in read_log(t.out / "log.csv") if x["valid_error"]]
    best = load_model(t.out / "best", device="cpu").bind(pendulum)
    assert math.isclose(valid[-1], ev.rollout_error(best, pendulum, "valid", cfg.valid_horizon, cfg.valid_sequences),
                        rel_tol=1e-5)
    live = load_model(t.out / "best", device="cpu").bind(pendulum)
    with torch.no_grad():
        for p, x in zip(live.parameters(), t.history[-1]):
            p.copy_(x)
    assert not math.isclose(valid[-1], ev.rollout_error(live, pendulum, "valid", cfg.valid_horizon,
                                                          cfg.valid_sequences), rel_tol=1e-5)


def test_ema_resume_continues_exactly(tmp_path, pendulum):
    """A run with ema resumed from its checkpoint ends where an uninterrupted one does (averages
    and live weights); resumed with ema=0 it continues from the live weights, not the averages
    its checkpoint's model holds."""
    kw = dict(valid_every=20, checkpoint_every=20)
    full = _Recording(config(tmp_path, "full", steps=40, ema=0.9, **kw), [pendulum])
    full.run()
    train(config(tmp_path, "half", steps=20, ema=0.9, **kw), [pendulum])
    resumed = _Recording(config(tmp_path, "half", steps=40, ema=0.9, **kw), [pendulum])
    assert resumed.state["step"] == 20
    for p, x in zip(resumed.model.parameters(), full.history[20]):   # the live weights came back
        torch.testing.assert_close(p, x, rtol=1e-6, atol=1e-7)
    resumed.run()
    a, b = load_model(full.out / "last", device="cpu"), load_model(resumed.out / "last", device="cpu")
    for k, v in a.state_dict().items():
        torch.testing.assert_close(v, b.state_dict()[k], rtol=1e-6, atol=1e-7, msg=k)
    for p, q in zip(full.model.parameters(), resumed.model.parameters()):
        torch.testing.assert_close(p, q, rtol=1e-6, atol=1e-7)
    # the same run resumed without averaging: the live weights of step 20 go on
    train(config(tmp_path, "off", steps=20, ema=0.9, **kw), [pendulum])
    off = Trainer(config(tmp_path, "off", steps=40, **kw), [pendulum])
    assert off.average is None
    for p, x in zip(off.model.parameters(), full.history[20]):
        torch.testing.assert_close(p, x, rtol=1e-6, atol=1e-7)


def test_ema_checkpoint_with_a_bad_average_state_is_refused(tmp_path, pendulum):
    """A training state whose average does not fit the model: a CheckpointError naming it."""
    from gnwarp.files import sha256_file
    from gnwarp.train.checkpoint import MANIFEST, load_training
    kw = dict(valid_every=10, checkpoint_every=10, ema=0.9)
    train(config(tmp_path, "bad", steps=10, **kw), [pendulum])
    last = tmp_path / "bad" / "last"
    training = load_training(last)
    training["average"]["weights"] = training["average"]["weights"][:-1]
    torch.save(training, last / "training.pt")
    manifest = json.loads((last / MANIFEST).read_text())
    manifest["training.pt"] = sha256_file(last / "training.pt")   # a consistent file: its content is what is wrong
    (last / MANIFEST).write_text(json.dumps(manifest))
    with pytest.raises(CheckpointError, match="WeightAverage state holds"):
        Trainer(config(tmp_path, "bad", steps=20, **kw), [pendulum])


def _fresh_params(tmp_path, pendulum, impl):
    r = train(config(tmp_path, "zero", impl=impl, steps=0, valid_every=20), [pendulum])
    return list(load_model(r["last"], device="cpu").parameters())


def test_training_without_a_valid_split_says_so(tmp_path):
    """Data without valid sequences trains (its best/ is the last model), with a warning that
    nothing was validated, instead of in silence."""
    ds = data.generate("pendulum", (6, 0, 1), num_steps=6, seed=0, backend="mujoco", progress=False)
    with pytest.warns(UserWarning, match="no dataset has a valid split: nothing is validated"):
        r = train(config(tmp_path, steps=4, log_every=2, checkpoint_every=4), [ds])
    assert r["best_step"] == -1 and (tmp_path / "run" / "best" / "model.pt").is_file()


def test_cli_names_the_validation_horizon_it_used(tmp_path, pendulum, capsys):
    """The closing line names the horizon validated (the config's, cut to the valid sequences'
    length), not a fixed 20."""
    from gnwarp.cli import main
    path = tmp_path / "p.h5"
    pendulum.save(path)
    sets = ["steps=4", "valid_every=2", "valid_sequences=2", "batch_size=8", "device=cpu", "model.gn.latent=8",
            "model.gn.edge_hidden=[8]", "model.gn.node_hidden=[8]", "model.gn.global_hidden=[8]",
            "model.run.impl=torch"]
    for horizon, said in ((3, 3), (1000, 20)):
        argv = ["train", "--data", str(path), "-o", str(tmp_path / f"r{horizon}"), "-q",
                "--set", f"valid_horizon={horizon}"]
        assert main(argv + [a for kv in sets for a in ("--set", kv)]) == 0
        assert f"best {said}-step validation error" in capsys.readouterr().out
