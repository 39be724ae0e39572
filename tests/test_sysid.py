"""System identification (Algorithms D.2, D.4): end-to-end training lowers the loss, a saved G_ID
reproduces rollouts, bad identification windows are refused by name, and gradients through the
window match finite differences."""
import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from gnwarp import TrainConfig, data
from gnwarp.dynamics import Dynamics
from gnwarp.sim import systems
from gnwarp.state import state_delta
from gnwarp.gn import RunOptions
from gnwarp.interop import warp
from gnwarp.models import GNCoreConfig, ModelConfig
from gnwarp.models.recurrent import RecurrentGNConfig
from gnwarp.graphs import GraphsTuple
from gnwarp.models.rollout import RolloutEngine, RolloutInputError
from gnwarp.models.gid import GIDError, load_gid, save_gid
from gnwarp.models import SysIDConfig, SysIDModel
from gnwarp.train.checkpoint import CheckpointError, load_model
from gnwarp.eval.sysid import sysid_rollout_error
from gnwarp.train.sysid import SysIDTrainer, load_sysid
from gnwarp.train.sysid_config import SysIDTrainConfig
from gnwarp.validation import ConfigError

warp()

W = 5
TINY = GNCoreConfig(latent=8, edge_hidden=(16,), node_hidden=(16,), global_hidden=(16,))
ID = RecurrentGNConfig(latent=8, hidden_edges=4, hidden_nodes=4, hidden_globals=4, edge_mlp=(16,), node_mlp=(16,),
                       global_mlp=(16,), out_edges=3, out_nodes=3, out_globals=3)


@pytest.fixture(scope="module")
def pendulum():
    return data.generate("pendulum", (16, 2, 2), num_steps=30, seed=0, backend="mujoco", parameterized=True,
                         progress=False)


@pytest.fixture(scope="module")
def trained(pendulum, tmp_path_factory):
    out = tmp_path_factory.mktemp("sysid")
    cfg = TrainConfig(out=str(out), model=ModelConfig(gn=TINY, run=RunOptions(impl="torch")), steps=40, batch_size=16,
                      lr=3e-3, valid_every=20, valid_sequences=2, log_every=10, checkpoint_every=20, progress=False,
                      device="cpu", normalizer_warmup=5)
    rows = []
    tr = SysIDTrainer(cfg, SysIDConfig(identifier=ID, window=W), datasets=[pendulum],
                      callbacks=[lambda t, event, info: rows.append(info["row"]) if event == "log" else None])
    summary = tr.run()
    return tr, rows, summary


def test_training_lowers_the_loss_and_checkpoints_load(trained, pendulum):
    tr, rows, summary = trained
    losses = [r["loss"] for r in rows if r.get("loss") not in (None, "")]
    assert len(losses) == 4 and losses[-1] < 0.8 * losses[0], losses
    assert np.isfinite(summary["best_error"])
    m = load_sysid(summary["last"]).bind(pendulum)
    assert sysid_rollout_error(m, pendulum, "valid", 10) == pytest.approx(
        sysid_rollout_error(tr.model, pendulum, "valid", 10), rel=1e-6)
    with pytest.raises(CheckpointError, match="does not describe a model"):
        load_model(summary["last"])


def _window(ds, split="test", start=0):
    sp = ds[split]
    return (torch.as_tensor(sp.body[:, start:start + W]), torch.as_tensor(sp.ctrl[:, start:start + W]),
            torch.as_tensor(sp.instance[:]))


def test_saved_gid_reproduces_rollouts(trained, pendulum, tmp_path):
    m = trained[0].model.bind(pendulum)
    body, ctrl, inst = _window(pendulum)
    sp = pendulum["test"]
    g_id = m.identify(body, ctrl, inst)
    assert g_id.nodes.shape == (4, 3) and g_id.edges.shape == (4, 3) and g_id.globals.shape == (2, 3)
    x0, u = torch.as_tensor(sp.body[:, W]), torch.as_tensor(sp.ctrl[:, W:W + 8])
    with torch.no_grad():
        a = m.rollout(x0, u, g_id, inst)
        b = m.rollout(x0, u, load_gid(save_gid(tmp_path / "gid.pt", g_id)), inst)
        # from new initial states, G_ID reused: the same as identifying again
        c = m.rollout(torch.as_tensor(sp.body[:, 15]), u, load_gid(tmp_path / "gid.pt"), inst)
        d = m.rollout(torch.as_tensor(sp.body[:, 15]), u, m.identify(body, ctrl, inst), inst)
    assert a.shape == (2, 9, 2, 13) and torch.isfinite(a).all()
    assert torch.equal(a, b) and torch.equal(c, d)
    # a changed byte of the file is refused
    p = torch.load(tmp_path / "gid.pt", weights_only=True)
    p["tensors"]["nodes"][0, 0] += 1
    torch.save(p, tmp_path / "bad.pt")
    with pytest.raises(GIDError, match="checksum"):
        load_gid(tmp_path / "bad.pt")
    with pytest.raises(GIDError, match="cannot read"):
        load_gid(tmp_path / "missing.pt")


def test_bad_identification_windows_are_refused(trained, pendulum):
    m = trained[0].model.bind(pendulum)
    body, ctrl, inst = _window(pendulum)
    with pytest.raises(RolloutInputError, match=f"window has 3 steps; this model identifies systems from {W}"):
        m.identify(body[:, :3], ctrl[:, :3], inst)
    bad = body.clone()
    bad[1, 2, 1, 4] = float("nan")
    with pytest.raises(RolloutInputError, match=r"window_body contains NaN or Inf \(first at window_body\[1, 2, 1, 4"):
        m.identify(bad, ctrl, inst)
    cart = data.generate("cartpole", (2, 1, 1), num_steps=W, seed=0, backend="mujoco", progress=False)["train"]
    with pytest.raises(RolloutInputError, match="another graph layout"):
        m.identify(cart.body[:, :W], cart.ctrl[:, :W], inst)
    # a G_ID of another topology is refused by the rollout
    g_id = m.identify(body, ctrl, inst)
    x0, u = torch.as_tensor(pendulum["test"].body[:1, W]), torch.as_tensor(pendulum["test"].ctrl[:1, W:W + 2])
    with pytest.raises(GIDError, match="another layout"):
        m.rollout(x0, u, g_id, inst[:1])


@pytest.mark.parametrize("impl", ["torch", "warp"])
def test_gradients_through_the_identification_window(pendulum, impl):
    torch.manual_seed(0)
    cfg = SysIDConfig(forward=ModelConfig(gn=TINY, run=RunOptions(impl=impl, precision="fp64")), identifier=ID,
                      window=3)
    m = SysIDModel(cfg, pendulum.layout).bind(pendulum)
    assert m.dtype == torch.float64
    sp = pendulum["test"]
    body = torch.as_tensor(sp.body[:, :3], dtype=torch.float64)
    ctrl = torch.as_tensor(sp.ctrl[:, :3], dtype=torch.float64)
    x0, u = torch.as_tensor(sp.body[:, 3], dtype=torch.float64), torch.as_tensor(sp.ctrl[:, 3:5], dtype=torch.float64)

    def f(moving, window_ctrl):   # the moving body's states in the window, and the window's controls
        window = torch.cat([body[:, :, :1], moving[:, :, None]], 2)
        g_id = m.identify(window, window_ctrl, sp.instance[:])
        return m.rollout(x0, u, g_id, sp.instance[:])[:, 1:, 1].sum(-1)
    args = (body[:, :, 1].clone().requires_grad_(), ctrl.clone().requires_grad_())
    f(*args).sum().backward()
    assert all(bool(a.grad.abs().sum() > 0) for a in args)   # the window does reach the prediction
    assert torch.autograd.gradcheck(f, tuple(a.detach().requires_grad_() for a in args), eps=1e-6, atol=1e-5,
                                    rtol=1e-4)


def test_cli_trains_and_evaluates_system_identification(pendulum, tmp_path, capsys):
    """`gnwarp train --sysid` trains a SysIDModel; `gnwarp evaluate` recognizes its checkpoint and
    reports rollout errors with G_ID from the same and from another instance's window."""
    from gnwarp.cli import main
    path = tmp_path / "p.h5"
    pendulum.save(path)
    sets = ["steps=4", "valid_every=2", "valid_sequences=2", "batch_size=8", "device=cpu", "model.gn.latent=8",
            "model.gn.edge_hidden=[8]", "model.gn.node_hidden=[8]", "model.gn.global_hidden=[8]",
            "model.run.impl=torch"]
    argv = ["train", "--data", str(path), "--sysid", "-o", str(tmp_path / "run"), "-q"]
    for kv in sets:
        argv += ["--set", kv]
    assert main(argv) == 0
    assert load_sysid(tmp_path / "run" / "best").window == SysIDConfig().window
    capsys.readouterr()
    assert main(["evaluate", str(tmp_path / "run" / "best"), "--data", str(path), "--horizons", "5"]) == 0
    out = capsys.readouterr().out
    assert "same instance" in out and "another instance" in out
    # gnwarp check reads it as what it is (it used to call it a checkpoint that describes no model)
    assert main(["check", str(tmp_path / "run" / "best")]) == 0
    assert "a system-identification checkpoint (window" in capsys.readouterr().out
    weights = tmp_path / "run" / "best" / "model.pt"
    good = weights.read_bytes()
    weights.write_bytes(good[:-9] + bytes([good[-9] ^ 1]) + good[-8:])
    assert main(["check", str(tmp_path / "run" / "best")]) == 1
    assert "error:" in capsys.readouterr().out
    weights.write_bytes(good)
    assert load_sysid(tmp_path / "run" / "best").config.transitions is False
    assert main(["train", "--data", str(path), "--sysid", "--transitions", "--readout", "ridge", "--ridge-head", "8",
                 "--ridge-features", "3", "--param-loss", "1", "--param-teacher", "1", "-o", str(tmp_path / "run-t"),
                 "-q"] + [a for kv in sets for a in ("--set", kv)]) == 0
    ridge = load_sysid(tmp_path / "run-t" / "best").config
    assert (ridge.transitions, ridge.readout, ridge.ridge_head, ridge.ridge_features) == (True, "ridge", 8, 3)
    saved = json.loads((tmp_path / "run-t" / "best" / "config.json").read_text())["sysid_train"]
    assert (saved["param_loss"], saved["param_teacher"]) == (1.0, 1.0)
    capsys.readouterr()
    assert main(["train", "--data", str(path), "--sysid", "--ridge-features", "3", "-o", str(tmp_path / "run-f"),
                 "-q"]) == 2
    assert "--ridge-features: ridge_features splits GN_p's outputs for readout 'ridge'" in capsys.readouterr().err
    assert main(["train", "--data", str(path), "--sysid", "--param-teacher", "0.5", "-o", str(tmp_path / "run-q"),
                 "-q"] + [a for kv in sets for a in ("--set", kv)]) == 2
    assert "needs param_loss" in capsys.readouterr().err and not (tmp_path / "run-q" / "best").exists()
    assert main(["train", "--data", str(path), "--sysid", "--readout", "mean", "--start-windows", "0.5",
                 "--consistency", "0.3", "-o", str(tmp_path / "run-m"), "-q"] + [a for kv in sets for a in ("--set", kv)]) == 0
    assert load_sysid(tmp_path / "run-m" / "best").config.readout == "mean"
    assert main(["train", "--data", str(path), "--sysid", "--readout", "dynamics", "-o", str(tmp_path / "run-d"), "-q"]
                + [a for kv in sets for a in ("--set", kv)]) == 0
    dyn = load_sysid(tmp_path / "run-d" / "best")
    assert (dyn.config.readout, dyn.gid_sizes["nodes"]) == ("dynamics", 6 * SysIDConfig().identifier.out_nodes)
    capsys.readouterr()
    assert main(["train", "--data", str(path), "--sysid", "--transitions", "--readout", "dynamics", "-o",
                 str(tmp_path / "run-dt"), "-q"] + [a for kv in sets for a in ("--set", kv)]) == 2
    assert "transitions=True is refused" in capsys.readouterr().err
    assert main(["train", "--data", str(path), "--sysid", "--ridge-head", "8", "-o", str(tmp_path / "run-h"), "-q"]
                + [a for kv in sets for a in ("--set", kv)]) == 2
    assert "ridge_head" in capsys.readouterr().err and not (tmp_path / "run-h" / "best").exists()
    saved = json.loads((tmp_path / "run-m" / "best" / "config.json").read_text())["sysid_train"]
    assert (saved["start_windows"], saved["consistency"]) == (0.5, 0.3)
    assert main(["train", "--data", str(path), "--sysid", "--param-loss", "2", "-o", str(tmp_path / "run-p"), "-q"]
                + [a for kv in sets for a in ("--set", kv)]) == 0
    saved = json.loads((tmp_path / "run-p" / "best" / "config.json").read_text())
    assert saved["sysid_train"]["param_loss"] == 2.0 and "param_stats" in saved
    assert main(["train", "--data", str(path), "--sysid", "--param-loss", "1", "--local-params", "-o",
                 str(tmp_path / "run-l"), "-q"] + [a for kv in sets for a in ("--set", kv)]) == 0
    local = load_sysid(tmp_path / "run-l" / "best").config
    assert local.local_params and local.param_places == (("nodes", (1,)), ("nodes", (1,)))
    assert main(["train", "--data", str(path), "--sysid", "--nominal-static", "-o", str(tmp_path / "run-n"), "-q"]
                + [a for kv in sets for a in ("--set", kv)]) == 0
    nominal = load_sysid(tmp_path / "run-n" / "best").config
    assert nominal.nominal_static and nominal.nominal.node_names == tuple(data.load(path).layout.node_names)
    assert main(["train", "--data", str(path), "--sysid", "--gid-globals", "6", "-o", str(tmp_path / "run-g"), "-q"]
                + [a for kv in sets for a in ("--set", kv)]) == 0
    ident = load_sysid(tmp_path / "run-g" / "best").config.identifier
    assert (ident.out_globals, ident.hidden_globals, ident.out_nodes) == (6, 6, SysIDConfig().identifier.out_nodes)
    capsys.readouterr()
    assert main(["train", "--data", str(path), "--sysid", "--gid-globals", "0", "-o", str(tmp_path / "run-g0"),
                 "-q"]) == 2
    assert "--gid-globals: must be an integer from 1" in capsys.readouterr().err
    assert main(["train", "--data", str(path), "--sysid", "--local-params", "-o", str(tmp_path / "run-l0"), "-q"]
                + [a for kv in sets for a in ("--set", kv)]) == 2
    assert "needs param_loss" in capsys.readouterr().err
    assert load_sysid(tmp_path / "run-p" / "best").config.readout == "last"
    capsys.readouterr()   # a supervised checkpoint's evaluation adds the oracle row; the paper's has none
    assert main(["evaluate", str(tmp_path / "run-p" / "best"), str(tmp_path / "run" / "best"), "--data", str(path),
                 "--horizons", "5"]) == 0
    rows = [r for r in capsys.readouterr().out.splitlines() if "true parameter columns" in r]
    assert len(rows) == 1 and rows[0].startswith("| run-p |")
    for flag in (["--transitions"], ["--readout", "mean"], ["--start-windows", "0.5"], ["--consistency", "1"],
                 ["--param-loss", "1"], ["--ridge-head", "8"], ["--param-teacher", "0.5"], ["--ridge-features", "3"],
                 ["--local-params"], ["--nominal-static"], ["--gid-globals", "18"]):
        with pytest.raises(SystemExit, match=f"train: {flag[0]} apply to .*--sysid"):
            main(["train", "--data", str(path), *flag, "-o", str(tmp_path / "run-x"), "-q"])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("options", [{}, {"readout": "mean", "transitions": True, "start_windows": 0.5,
                                          "consistency": 0.5}, {"readout": "ridge", "ridge_features": 2,
                                                                "param_loss": 1.0, "ridge_head": 8},
                                     {"readout": "dynamics", "param_loss": 1.0, "param_teacher": 0.5},
                                     {"readout": "ridge", "ridge_features": 2, "ridge_head": 8, "param_loss": 1.0,
                                      "param_teacher": 0.5, "local_params": True, "nominal_static": True},
                                     {"readout": "ridge", "ridge_features": 2, "ridge_head": 8, "param_loss": 1.0,
                                      "transitions": True, "stateless": True}],
                         ids=["paper", "mean-transitions-start-consistency", "ridge-head-param_loss", "dynamics-teacher",
                              "local-params-nominal", "stateless"])
def test_cuda_captured_sysid_training_matches_uncaptured(pendulum, tmp_path, options):
    """The system-identification step (window sampling, GN_p over the window, the forward loss,
    backward, update) replayed from one CUDA graph gives the parameters and losses of eager steps:
    bit for bit in deterministic mode with torch's Adam; also with the options beyond the paper."""
    options = dict(options)
    start = options.pop("start_windows", 0.0)
    consistency = options.pop("consistency", 0.0)
    param_loss = options.pop("param_loss", 0.0)
    teacher = options.pop("param_teacher", 0.0)
    runs = {}
    for capture in (True, False):
        cfg = TrainConfig(out=str(tmp_path / f"cap{capture}"), steps=10, batch_size=16, lr=3e-3, valid_every=5,
                          valid_sequences=2, log_every=5, checkpoint_every=10, progress=False, device="cuda",
                          normalizer_warmup=3, capture=capture, optimizer="adam",
                          model=ModelConfig(gn=TINY, run=RunOptions(impl="warp", deterministic=True)))
        rows = []
        tr = SysIDTrainer(cfg, SysIDConfig(identifier=ID, window=W, **options), datasets=[pendulum],
                          callbacks=[lambda t, event, info: rows.append(info["row"]) if event == "log" else None],
                              options=SysIDTrainConfig(start_windows=start, consistency=consistency,
                                                       param_loss=param_loss, param_teacher=teacher))
        tr.run()
        assert (tr.captured is not None and tr.captured.graph is not None) == capture
        runs[capture] = (tr, rows)
    (a, ra), (b, rb) = runs[True], runs[False]
    for p, q in zip(a.model.parameters(), b.model.parameters()):
        assert torch.equal(p, q)
    for x, y in zip(ra, rb):
        for k in ("loss", "valid_error", "window_spread", "param_error"):
            if x.get(k) not in (None, ""):
                assert float(x[k]) == pytest.approx(float(y[k]), rel=1e-4), (k, x, y)
    assert ("window_spread" in ra[0]) == (consistency > 0)
    assert ("param_error" in ra[0]) == (param_loss > 0)


def test_planning_through_an_identified_system(trained, pendulum):
    """Figure 10's system-ID variant: W random actions on the true env, G_ID from them, then a
    rollout engine and gradient MPC on the fixed G_ID; the engine rolls out what
    ``SysIDModel.rollout`` does with that G_ID, and planning raises the planned reward."""
    from gnwarp.control import GradientMPC, GradientMPCConfig, identify_on_env
    from gnwarp.sim import make_env
    m = trained[0].model.bind(pendulum)
    env = make_env("pendulum", 3, backend="mujoco")
    qpos, qvel = np.array([[0.3], [2.0], [-1.0]]), np.zeros((3, 1))
    fixed, x, window = identify_on_env(m, env, seed=1, qpos0=qpos, qvel0=qvel)
    assert window["states"].shape == (3, W + 1, 2, 13) and torch.equal(x, window["states"][:, W])
    torch.testing.assert_close(x, torch.as_tensor(env.body_states()).float())   # the env is where x says
    u = torch.rand(3, 6, 1) * 2 - 1
    eng = fixed.rollout_engine(torch.zeros(3, dtype=torch.int64), 6)
    with torch.no_grad():
        ref = m.rollout(x, u, fixed.g_id, torch.zeros(3, dtype=torch.int64))
    torch.testing.assert_close(eng.rollout(x, u), ref)
    p = GradientMPC(fixed, "pendulum-balance", "pendulum", n=3, config=GradientMPCConfig(horizon=6, lr=0.05))
    xs = p.check_state(x)
    before = p.planned_reward(xs)
    p.iterate(xs, 10)
    assert p.planned_reward(xs).sum() > before.sum()
    # the first state's proposal on a G_ID fixed to 3 graphs: one sequence per episode at a time
    p.reset()
    start = p.planned_reward(xs)
    best = p.propose(xs)
    assert p.proposal_evals == 32 * 6 and (best >= start - 1e-5).all()
    torch.testing.assert_close(p.planned_reward(xs), best)
    # a G_ID of other graphs is refused when the engine is made
    with pytest.raises(GIDError, match="another layout"):
        fixed.rollout_engine(torch.zeros(2, dtype=torch.int64), 6)


def test_planning_with_each_episodes_true_parameters(pendulum):
    """Figure 10's parameterized variant: a model trained on parameterized data, given each
    episode's true static graph (a list of Systems, one per episode). The planner's engine rolls
    out what the model does bound to those instances, which differs from giving every episode
    the first one's parameters."""
    from gnwarp.control import GradientMPC, GradientMPCConfig, PlanningError
    from gnwarp.models import ForwardModel
    from gnwarp.sim import systems
    torch.manual_seed(0)
    m = ForwardModel(ModelConfig(gn=TINY, run=RunOptions(impl="torch")), pendulum.layout).double()
    with torch.no_grad():
        for p in m.parameters():
            p.normal_(0, 0.3)
    rng = np.random.default_rng(4)
    insts = [systems.make("pendulum", systems.sample_params("pendulum", rng)) for _ in range(3)]
    assert len({s.model.body_mass[1] for s in insts}) == 3 or len({s.model.geom_size[1, 1] for s in insts}) == 3
    x = torch.as_tensor(np.asarray(pendulum["test"].body[:1, 0]), dtype=torch.float64).repeat(3, 1, 1)
    x[:, 1, 3:7] = torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=torch.float64)
    cfg = GradientMPCConfig(horizon=5, lr=0.05)
    p = GradientMPC(m, "pendulum-balance", insts, n=3, config=cfg)
    u = torch.rand(3, 5, 1, dtype=torch.float64) * 2 - 1
    with torch.no_grad():
        got = p.engine.rollout(x, u)
        ref = ForwardModel.rollout(m.bind(insts), x, u, instance=torch.arange(3))
        same = ForwardModel.rollout(m.bind(insts[0]), x, u)
    torch.testing.assert_close(got, ref)
    assert (got - same).abs().max() > 1e-6          # each episode's parameters reach the model
    xs = p.check_state(x)
    before = p.planned_reward(xs)
    p.iterate(xs, 10)
    assert p.planned_reward(xs).sum() > before.sum()
    p.reset()                                       # the proposal rolls each episode's instance out too
    start = p.planned_reward(xs)
    best = p.propose(xs)
    assert p.proposal_evals == 32 * 5 and (best >= start - 1e-9).all()
    torch.testing.assert_close(p.planned_reward(xs), best)
    with pytest.raises(PlanningError, match="one per episode"):
        GradientMPC(m, "pendulum-balance", insts[:2], n=3, config=cfg)
    with pytest.raises(PlanningError, match="differs from system 0"):
        GradientMPC(m, "pendulum-balance", [insts[0], insts[1], systems.make("cartpole")], n=3, config=cfg)


@pytest.mark.parametrize("ema", [0.0, 0.9])
def test_sysid_resume_continues_exactly(pendulum, tmp_path, ema):
    """A rerun into the same out resumes from <out>/last: 20 + 20 steps give the weights of 40
    straight (with ``ema``: the averages saved and the live weights trained on); a sysid run
    refuses a forward-model checkpoint in its folder, and one of another window."""
    def cfg(name, steps):
        return TrainConfig(out=str(tmp_path / name), model=ModelConfig(gn=TINY, run=RunOptions(impl="torch")),
                           steps=steps, batch_size=16, lr=3e-3, valid_every=20, valid_sequences=2, log_every=10,
                           checkpoint_every=20, progress=False, device="cpu", normalizer_warmup=5, ema=ema)
    full = SysIDTrainer(cfg("full", 40), SysIDConfig(identifier=ID, window=W), datasets=[pendulum]).run()
    SysIDTrainer(cfg("half", 20), SysIDConfig(identifier=ID, window=W), datasets=[pendulum]).run()
    resumed = SysIDTrainer(cfg("half", 40), SysIDConfig(identifier=ID, window=W), datasets=[pendulum])
    assert resumed.state["step"] == 20
    r = resumed.run()
    assert r["steps"] == 40
    a, b = load_sysid(full["last"]), load_sysid(r["last"])
    for k, v in a.state_dict().items():
        torch.testing.assert_close(v, b.state_dict()[k], rtol=1e-6, atol=1e-7, msg=k)
    if ema:   # the checkpoint holds the averages (GN_p's, the head's and the forward model's), not the live weights
        assert len(resumed.average.average) == len(list(b.parameters()))
        for p, avg in zip(b.parameters(), resumed.average.average):
            torch.testing.assert_close(p, avg, rtol=1e-6, atol=1e-7)
        assert any(not torch.allclose(p, q, atol=1e-4) for p, q in zip(b.parameters(), resumed.model.parameters()))
    with pytest.raises(CheckpointError, match="model.window"):
        SysIDTrainer(cfg("half", 60), SysIDConfig(identifier=ID, window=W + 1), datasets=[pendulum])
    from gnwarp.train import train
    train(cfg("fwd", 20), [pendulum])
    with pytest.raises(CheckpointError, match="not a system-identification one"):
        SysIDTrainer(cfg("fwd", 40), SysIDConfig(identifier=ID, window=W), datasets=[pendulum])


def _old_format(folder: Path, options: dict | None) -> None:
    """Rewrite a checkpoint's config.json as checkpoints before "sysid_train" were: the training
    options inside its "train" table (``options``; None: no options recorded at all); the
    manifest updated so that it stays a valid checkpoint."""
    from gnwarp.files import sha256_file
    from gnwarp.train.checkpoint import MANIFEST
    cfg = json.loads((folder / "config.json").read_text())
    del cfg["sysid_train"]
    cfg["train"].update(options or {})
    (folder / "config.json").write_text(json.dumps(cfg))
    manifest = json.loads((folder / MANIFEST).read_text())
    manifest["config.json"] = sha256_file(folder / "config.json")
    (folder / MANIFEST).write_text(json.dumps(manifest))


def test_sysid_training_options_round_trip_and_resume_without_side_channel(pendulum, tmp_path):
    """``SysIDTrainConfig`` is saved in config.json ("sysid_train") and read back by
    ``trained_options``; a rerun into the same out with neither the model config nor the options
    resumes as the run started (10 + 10 steps give the weights of 20 straight); checkpoints
    written before the table load with the options their "train" table holds (the defaults,
    the paper's, where it holds none), and a malformed table is refused saying how to fix it."""
    import shutil
    from gnwarp.train.sysid import trained_options

    def cfg(name, steps):
        return TrainConfig(out=str(tmp_path / name), model=ModelConfig(gn=TINY, run=RunOptions(impl="torch")),
                           steps=steps, batch_size=16, lr=3e-3, valid_every=10, valid_sequences=2, log_every=5,
                           checkpoint_every=10, progress=False, device="cpu", normalizer_warmup=5)
    sysid = SysIDConfig(identifier=ID, window=W, readout="mean")
    options = SysIDTrainConfig(targets=2, start_windows=0.5, param_loss=1.0)
    assert SysIDTrainConfig.from_dict(json.loads(json.dumps(options.to_dict()))) == options
    full = SysIDTrainer(cfg("full", 20), sysid, datasets=[pendulum], options=options).run()
    half = SysIDTrainer(cfg("half", 10), sysid, datasets=[pendulum], options=options).run()
    saved = json.loads((Path(half["last"]) / "config.json").read_text())
    assert saved["sysid_train"] == options.to_dict() and "param_loss" not in saved["train"]
    assert trained_options(load_sysid(half["last"])) == options
    shutil.copytree(tmp_path / "half", tmp_path / "old")   # the same run, its checkpoint as written before
    resumed = SysIDTrainer(cfg("half", 20), datasets=[pendulum])   # no sysid, no options: the checkpoint's
    assert resumed.state["step"] == 10 and resumed.options == options and resumed.model.config.readout == "mean"
    r = resumed.run()
    a, b = load_sysid(full["last"]), load_sysid(r["last"])
    for k, v in a.state_dict().items():
        torch.testing.assert_close(v, b.state_dict()[k], rtol=1e-6, atol=1e-7, msg=k)
    assert trained_options(b) == options
    # a new run (nothing to resume) without options trains the paper's way
    assert SysIDTrainer(cfg("new", 10), sysid, datasets=[pendulum]).options == SysIDTrainConfig()

    old = tmp_path / "old" / "last"
    _old_format(old, options.to_dict())
    assert trained_options(load_sysid(old)) == options
    assert SysIDTrainer(cfg("old", 20), datasets=[pendulum]).options == options   # resumes from the old format
    _old_format(tmp_path / "old" / "best", None)       # from before the options: the paper's training
    assert trained_options(load_sysid(tmp_path / "old" / "best")) == SysIDTrainConfig()
    bad = load_sysid(half["last"])
    bad.checkpoint_info = {**bad.checkpoint_info, "sysid_train": {"targets": 0}}
    with pytest.raises(CheckpointError, match="targets: must be an integer >= 1.*fix or remove"):
        trained_options(bad)


def test_sysid_rollouts_clamp_controls_to_the_sources_ranges(trained, pendulum):
    """A system-ID model reads no static feature of the data, but its rollouts (plain and in a
    rollout engine on a fixed G_ID) clamp controls to the bound source's actuator ranges as
    ForwardModel's do; "error" refuses controls outside them, "none" uses them as given."""
    m = trained[0].model.bind(pendulum)
    body, ctrl, inst = _window(pendulum)
    sp = pendulum["test"]
    g_id = m.identify(body, ctrl, inst)
    x0 = torch.as_tensor(sp.body[:, W])
    lo, hi = (float(v) for v in systems.make("pendulum").model.actuator_ctrlrange[0])
    big = torch.full((2, 4, 1), hi + 5.0, dtype=torch.float64)
    edge = torch.full((2, 4, 1), hi, dtype=torch.float64)
    with torch.no_grad():
        a, b = m.rollout(x0, big, g_id, inst), m.rollout(x0, edge, g_id, inst)
        c = m.rollout(x0, big, g_id, inst, ctrl_policy="none")
    assert torch.equal(a, b) and not torch.equal(a, c)
    with pytest.raises(RolloutInputError, match="outside actuator 0's control range"):
        m.rollout(x0, big, g_id, inst, ctrl_policy="error")
    fixed = m.with_fixed_gid(g_id)
    assert isinstance(fixed, Dynamics)   # G_ID held fixed: a one-step model like a ForwardModel
    engine = fixed.rollout_engine(inst, 4)
    assert engine.store.keep == [(), ("nodes",)]    # the forward model's core says what to keep
    with torch.no_grad():
        assert torch.equal(engine.rollout(x0, big), engine.rollout(x0, edge))
        torch.testing.assert_close(engine.rollout(x0, big), a)
    other = m.graph_builder(pendulum)
    with pytest.raises(ValueError, match="bound source"):
        fixed.rollout_engine(inst, 4, builder=other)
    with pytest.raises(ValueError, match="bound source"):
        RolloutEngine(fixed, inst, 4, builder=other)
    with torch.no_grad():   # another source's builder with the controls as given: no ranges read
        torch.testing.assert_close(fixed.rollout_engine(inst, 4, builder=other, ctrl_policy="none").rollout(x0, big),
                                   c)


def _identified_transitions(pendulum, cfg):
    """A model of ``cfg`` (4-step windows of transitions, float64) on pendulum windows: its
    gradients through the window checked against finite differences (before any statistics, where
    finite differences stay accurate), then non-trivial normalizer statistics accumulated. Returns
    (model, its 3 normalized transition graphs built by hand, its G_ID of the windows)."""
    m = SysIDModel(cfg, pendulum.layout).bind(pendulum)
    fm = m.forward_model
    sp = pendulum["train"]
    body, ctrl = torch.as_tensor(sp.body[:6, :8], dtype=torch.float64), torch.as_tensor(sp.ctrl[:6, :8], dtype=torch.float64)
    inst = torch.as_tensor(sp.instance[:6])
    moving = body[:2, :4, 1].clone().requires_grad_()

    def f(mv):
        g = m.identify(torch.cat([body[:2, :4, :1], mv[:, :, None]], 2), ctrl[:2, :4], inst[:2])
        return m.rollout(body[:2, 4], ctrl[:2, 4:6], g, inst[:2])[:, 1:, 1].sum(-1)
    assert torch.autograd.gradcheck(f, (moving,), eps=1e-6, atol=1e-5, rtol=1e-4)
    with torch.no_grad():
        graph = m.with_gid(m.builder(inst, body[:, 0], ctrl[:, 0]), m.identify(body[:, :4], ctrl[:, :4], inst))
        fm.loss(graph, body[:, 1].reshape(-1, 13), accumulate=True)
    # by hand: 3 transitions, each the normalized state and its normalized change, the controls
    st = fm.stats(torch.float64)
    (mn, sn), (me, se), (md, sd) = st["nodes"], st["edges"], st["delta"]
    graphs = [m.builder(inst, body[:, t], ctrl[:, t]) for t in range(4)]
    K = graphs[0].edges.shape[1]   # the normalizers' first columns are G_ID's
    mn, sn, me, se = mn[-13:], sn[-13:], me[-K:], se[-K:]
    inputs = [g._replace(nodes=torch.cat([(g.nodes - mn) / sn, (state_delta(g.nodes, graphs[t + 1].nodes) - md) / sd], -1),
                         edges=(g.edges - me) / se) for t, g in enumerate(graphs[:3])]
    return m, inputs, m.identify(body[:, :4], ctrl[:, :4], inst)


def test_identification_from_transitions(pendulum, tmp_path):
    """``SysIDConfig(transitions=True)``: GN_p reads W - 1 (state, controls, normalized change to
    the next state) steps; it equals running the identifier over those graphs by hand, its
    gradients w.r.t. the window match finite differences, it trains, and the option is saved."""
    torch.manual_seed(0)
    cfg = SysIDConfig(forward=ModelConfig(gn=TINY, run=RunOptions(impl="torch", precision="fp64")), identifier=ID,
                      window=4, transitions=True)
    m, inputs, g_id = _identified_transitions(pendulum, cfg)
    assert m.identifier.sizes["nodes"] == 26
    h = m.identifier.initial_hidden(inputs[0])
    for g in inputs:
        out, h = m.identifier.step(g, h)
    for k in ("nodes", "edges", "globals"):
        torch.testing.assert_close(getattr(g_id, k), getattr(out, k), rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="at least 2 steps"):
        m.identify_graphs([m.builder(torch.zeros(1, dtype=torch.int64), torch.zeros(1, 2, 13), torch.zeros(1, 1))], 1)
    # trains end to end, the option travels in the checkpoint
    tcfg = TrainConfig(out=str(tmp_path / "tr"), model=ModelConfig(gn=TINY, run=RunOptions(impl="torch")), steps=30,
                       batch_size=16, lr=3e-3, valid_every=30, valid_sequences=2, log_every=10, checkpoint_every=30,
                       progress=False, device="cpu", normalizer_warmup=5)
    rows = []
    summary = SysIDTrainer(tcfg, SysIDConfig(identifier=ID, window=W, transitions=True), datasets=[pendulum],
                           callbacks=[lambda t, e, info: rows.append(info["row"]) if e == "log" else None]).run()
    losses = [r["loss"] for r in rows if r.get("loss") not in (None, "")]
    assert losses[-1] < losses[0]
    assert load_sysid(summary["last"]).config.transitions is True


@pytest.mark.parametrize("system", ["pendulum", "swimmer"])
def test_stacked_window_holds_each_steps_graph(pendulum, system):
    """``StackedWindow.build``: W steps of N instances in one builder call; step t is the graph the
    builder makes of that step alone (features and topology), ``head(k)`` the first k steps as
    ``gnwarp.graphs.batch`` lays them out; one topology for every instance (the pendulum) gives the
    builder's shared topology tensors, instances of varied link counts (the swimmer) their own."""
    from gnwarp.data import FeatureLayout, graph_builder
    from gnwarp.graphs import batch
    from gnwarp.models.sysid_graphs import StackedWindow
    ds = pendulum if system == "pendulum" else data.generate("swimmer", (6, 1, 1), num_steps=8, seed=0,
                                                              backend="mujoco", parameterized=True, progress=False)
    b = graph_builder(FeatureLayout([], [], [], n_ctrl_slots=ds.layout.n_ctrl_slots), ds)
    sp = ds["train"]
    inst = torch.as_tensor(sp.instance[:4])
    body = torch.as_tensor(sp.body[:4, 2:7]).transpose(0, 1)     # [W=5, N=4, B, 13]
    ctrl = torch.as_tensor(sp.ctrl[:4, 2:7]).transpose(0, 1)
    w = StackedWindow.build(b, inst, body, ctrl)
    steps = [b(inst, body[t], ctrl[t]) for t in range(5)]
    assert len(w) == 5 and w.graph.n_node.shape[0] == 20
    assert (w.topology.senders is b.topology(4, ctrl.shape[-1])[0]) == (system == "pendulum")
    for t in (0, 3, -1):
        for f in ("nodes", "edges", "globals", "senders", "receivers", "n_node", "n_edge"):
            torch.testing.assert_close(getattr(w[t], f), getattr(steps[t], f), rtol=0, atol=0)
    for f in GraphsTuple._fields:
        torch.testing.assert_close(getattr(w.head(3), f), getattr(batch(steps[:3]), f), rtol=0, atol=0)
    with pytest.raises(IndexError, match="step 5 of a 5-step window"):
        w[5]


def test_another_instances_window_shares_the_graph_topology(pendulum, tmp_path, capsys):
    """``other_instance_windows``: with one topology, each sequence is identified from the one
    before it (the paper's "another instance"); with instances of varied link counts (the
    parameterized swimmer) from the previous sequence of its own topology, so that ``gnwarp
    evaluate`` reports the row instead of refusing a G_ID of another graph layout."""
    from gnwarp.cli import main
    from gnwarp.eval.sysid import other_instance_windows
    np.testing.assert_array_equal(other_instance_windows(pendulum, "train", 7), np.roll(np.arange(7), 1))
    ds = data.generate("swimmer", (12, 1, 8), num_steps=26, seed=0, backend="mujoco", parameterized=True,
                       progress=False)
    src = other_instance_windows(ds, "test", 8)
    inst = np.asarray(ds["test"].instance[:8])
    links = np.asarray(ds.static["n_node"])[inst]
    assert len(set(links.tolist())) > 1                       # the fixture has varied topologies
    np.testing.assert_array_equal(links[src], links)          # each window from its own topology
    shared = np.array([(links == x).sum() > 1 for x in links])
    assert (src != np.arange(8))[shared].all() and (src == np.arange(8))[~shared].all()
    path = tmp_path / "swim.h5"
    ds.save(path)
    assert main(["train", "--data", str(path), "--sysid", "--set", "steps=2", "--set", "batch_size=4",
                 "--set", "valid_every=2", "--set", "valid_sequences=1", "--set", "device=cpu",
                 "-o", str(tmp_path / "run"), "-q"]) == 0
    capsys.readouterr()
    assert main(["evaluate", str(tmp_path / "run" / "best"), "--data", str(path), "--split", "test"]) == 0
    assert "| another instance |" in capsys.readouterr().out


@pytest.mark.parametrize("impl", ["torch", "warp"])
def test_stateless_identifier_reads_each_step_on_its_own(pendulum, tmp_path, impl):
    """``SysIDConfig(stateless=True)``: GN_p reads every step of the window from the empty hidden
    graph, all steps as one batch. G_ID equals running ``RecurrentGNCore.step`` by hand on each
    transition from zero hidden state and solving the ridge fit over them (Warp kernels and torch
    alike); it differs from the recurrent identifier's with the same weights; gradients through
    the window match finite differences; it trains, the option travels in the checkpoint, a
    recurrent run refuses to resume it, and the paper's "last" readout is refused with it."""
    torch.manual_seed(0)
    opts = RunOptions(impl=impl, precision="fp64")
    cfg = SysIDConfig(forward=ModelConfig(gn=TINY, run=opts), identifier=ID, window=4, transitions=True,
                      readout="ridge", ridge_features=2, ridge=0.01, stateless=True)
    m, inputs, g_id = _identified_transitions(pendulum, cfg)
    outs = [m.identifier.step(g, m.identifier.initial_hidden(g))[0] for g in inputs]   # each from zero state
    h, recurrent = m.identifier.initial_hidden(inputs[0]), []
    for g in inputs:
        o, h = m.identifier.step(g, h)
        recurrent.append(o)
    for k in ("nodes", "edges", "globals"):
        x = torch.stack([getattr(o, k) for o in outs])
        torch.testing.assert_close(getattr(g_id, k), _ridge_reference(x[..., :2], x[..., 2:], 0.01),
                                   rtol=1e-10, atol=1e-10)
        xr = torch.stack([getattr(o, k) for o in recurrent])
        assert not torch.allclose(getattr(g_id, k), _ridge_reference(xr[..., :2], xr[..., 2:], 0.01))
    with pytest.raises(ValueError, match="stateless .* needs readout 'mean', 'ridge' or 'dynamics', got 'last'"):
        SysIDConfig(identifier=ID, stateless=True)
    if impl == "warp":
        return
    tcfg = TrainConfig(out=str(tmp_path / "tr"), model=ModelConfig(gn=TINY, run=RunOptions(impl="torch")), steps=30,
                       batch_size=16, lr=3e-3, valid_every=30, valid_sequences=2, log_every=10, checkpoint_every=30,
                       progress=False, device="cpu", normalizer_warmup=5)
    rows = []
    sysid = SysIDConfig(identifier=ID, window=W, transitions=True, readout="mean", stateless=True)
    summary = SysIDTrainer(tcfg, sysid, datasets=[pendulum],
                           callbacks=[lambda t, e, info: rows.append(info["row"]) if e == "log" else None]).run()
    losses = [r["loss"] for r in rows if r.get("loss") not in (None, "")]
    assert losses[-1] < losses[0]
    assert load_sysid(summary["last"]).config.stateless is True
    tcfg.steps = 40
    with pytest.raises(Exception, match="stateless"):
        SysIDTrainer(tcfg, dataclasses.replace(sysid, stateless=False), datasets=[pendulum]).run()


def test_several_targets_per_identification_window(pendulum, tmp_path):
    """``SysIDTrainConfig(targets=K)``: K one-step losses per window, at steps outside it, each with
    the window's G_ID; K=1 draws what the paper's sampling draws; it trains."""
    cfg = TrainConfig(out=str(tmp_path / "k"), model=ModelConfig(gn=TINY, run=RunOptions(impl="torch")), steps=30,
                      batch_size=8, lr=3e-3, valid_every=30, valid_sequences=2, log_every=10, checkpoint_every=30,
                      progress=False, device="cpu", normalizer_warmup=2)
    with pytest.raises(ValueError, match="targets"):
        SysIDTrainer(cfg, SysIDConfig(identifier=ID, window=W), datasets=[pendulum],
                     options=SysIDTrainConfig(targets=0))
    rows = []
    tr = SysIDTrainer(cfg, SysIDConfig(identifier=ID, window=W), datasets=[pendulum],
                      callbacks=[lambda t, e, info: rows.append(info["row"]) if e == "log" else None],
                          options=SysIDTrainConfig(targets=3))
    (parts,) = tr.sample()
    p = parts[0]
    assert p.graph.n_node.shape[0] == 3 * 8 and p.target.shape == (3 * 8 * 2, 13)
    assert len(p.window) == W and p.window[0].n_node.shape[0] == 8
    # each target is the state after its input: its window's sequence, one step later, outside the window
    body = torch.as_tensor(pendulum["train"].body[...])
    x, y = p.graph.nodes.reshape(3 * 8, 2, -1)[:, :, -13:], p.target.reshape(3 * 8, 2, 13)
    w0 = p.window[0].nodes.reshape(8, 2, 13)
    for k in range(3 * 8):
        hits = [(s, t) for s in range(body.shape[0]) for t in range(body.shape[1] - 1)
                if torch.equal(body[s, t], x[k].to(body.dtype)) and torch.equal(body[s, t + 1], y[k].to(body.dtype))]
        assert hits, k
        s, t = hits[0]
        start = [u for u in range(body.shape[1]) if torch.equal(body[s, u], w0[k % 8].to(body.dtype))]
        assert start and not start[0] <= t < start[0] + W     # outside its window
    tr.run()
    losses = [r["loss"] for r in rows if r.get("loss") not in (None, "")]
    assert losses[-1] < losses[0]


def _ridge_reference(phi, psi, ridge):
    """The normal equations of psi ~ B^T phi over the steps, solved directly."""
    S = (phi[..., :, None] * phi[..., None, :]).mean(0)
    R = (phi[..., :, None] * psi[..., None, :]).mean(0)
    lam = ridge * S.diagonal(dim1=-2, dim2=-1).mean(-1)[:, None, None] + 1e-6
    return torch.linalg.solve(S + lam * torch.eye(phi.shape[-1], dtype=phi.dtype), R).reshape(phi.shape[1], -1)


def test_ridge_fit_is_solved_in_float64():
    """``_ridge_solution`` of float32 regressors solves in float64 and returns float32: with nearly
    collinear regressors and a tiny ridge (condition ~1e8), it recovers the coefficients a float64
    solve gives, where a float32 Cholesky would lose them."""
    from gnwarp.models.sysid import _ridge_solution
    g = torch.Generator().manual_seed(0)
    t = torch.linspace(0, 1, 19, dtype=torch.float64)[:, None, None]
    phi = torch.cat([torch.ones_like(t), 1 - 1e-4 * t ** 2, torch.sin(0.3 * t)], -1).expand(19, 5, 3).clone()
    phi[..., 2] += 0.01 * torch.randn(19, 5, generator=g, dtype=torch.float64)
    coef = torch.randn(5, 3, 2, generator=g, dtype=torch.float64)
    psi = torch.einsum("tnf,nfp->tnp", phi, coef)
    got = _ridge_solution(phi.float(), psi.float(), 1e-12)
    assert got.dtype == torch.float32
    want = _ridge_reference(phi.float().double(), psi.float().double(), 1e-12)
    torch.testing.assert_close(got.double(), want, rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize("readout,head", [("mean", 0), ("ridge", 0), ("dynamics", 0), ("ridge", 5), ("dynamics", 5)],
                         ids=["mean", "ridge", "dynamics", "ridge-head", "dynamics-head"])
def test_pooled_readouts_of_the_identifiers_outputs(pendulum, tmp_path, readout, head):
    """``SysIDConfig(readout="mean")``: G_ID is the mean of GN_p's output graphs over the window;
    "ridge": per node, edge and global, the ridge solution of the outputs' last columns on their
    first ``ridge_features`` over the window; "dynamics": the ridge solution of the observed,
    normalized velocity changes (an edge's receiver's, a graph's mean over its moving bodies; the
    fixed world body's zero) on all output columns of the window's first W - 1 steps. Each equals
    running the identifier by hand and solving the normal equations with ``torch.linalg.solve``,
    in float64. With ``ridge_head``, G_ID is the head MLP of that solution, the identifier's
    output width wide. Gradients through it match finite differences; it trains and the options
    travel in the checkpoint, which a run of the other readout (or head) refuses to resume."""
    torch.manual_seed(0)
    fit = {**({"ridge_features": 2} if readout == "ridge" else {}), **({"ridge": 0.01} if readout != "mean" else {})}
    cfg = SysIDConfig(forward=ModelConfig(gn=TINY, run=RunOptions(impl="torch", precision="fp64")), identifier=ID,
                      window=4, readout=readout, ridge_head=head, **fit)
    m = SysIDModel(cfg, pendulum.layout).bind(pendulum)
    sp = pendulum["train"]
    body, ctrl = torch.as_tensor(sp.body[:5, :8], dtype=torch.float64), torch.as_tensor(sp.ctrl[:5, :8], dtype=torch.float64)
    inst = torch.as_tensor(sp.instance[:5])
    g_id = m.identify(body[:, :4], ctrl[:, :4], inst)
    st = m.forward_model.stats(torch.float64)
    (mn, sn), (me, se) = st["nodes"], st["edges"]
    graphs = [m.builder(inst, body[:, t], ctrl[:, t]) for t in range(4)]
    K = graphs[0].edges.shape[1]
    h = m.identifier.initial_hidden(graphs[0])
    outs = []
    for g in graphs[:3] if readout == "dynamics" else graphs:   # "dynamics": the last step is only a target
        out, h = m.identifier.step(g._replace(nodes=(g.nodes - mn[-13:]) / sn[-13:], edges=(g.edges - me[-K:]) / se[-K:]), h)
        outs.append(out)
    if readout == "dynamics":
        md, sd = st["delta"]
        dv = torch.stack([((state_delta(a.nodes, b.nodes) - md) / sd)[:, 7:13] for a, b in zip(graphs, graphs[1:])])
        dv = dv.reshape(3, 5, 2, 6)
        dv[:, :, 0] = 0     # each pendulum's world body
        psi = {"nodes": dv.reshape(3, 10, 6), "edges": dv.reshape(3, 10, 6)[:, graphs[0].receivers.long()],
               "globals": dv[:, :, 1]}    # one moving body per graph: its own
    for k in ("nodes", "edges", "globals"):
        x = torch.stack([getattr(o, k) for o in outs])
        if readout == "mean":
            want = x.mean(0)
        elif readout == "ridge":
            want = _ridge_reference(x[..., :2], x[..., 2:], 0.01)
            assert want.shape[1] == 2 * (ID.out(k) - 2) == m.sysid.fit_size(k)
        else:
            want = _ridge_reference(x, psi[k], 0.01)
            assert want.shape[1] == 6 * ID.out(k) == m.sysid.fit_size(k)
        if head:   # two SiLU layers of width 5, by hand
            a, b, c = m.heads[k].layers
            silu = lambda v: v * torch.sigmoid(v)  # noqa: E731
            want = silu(silu(want @ a.weight.T + a.bias) @ b.weight.T + b.bias) @ c.weight.T + c.bias
            assert a.out_features == 5
        assert want.shape[1] == m.gid_sizes[k] == (ID.out(k) if head or readout == "mean" else m.sysid.fit_size(k))
        torch.testing.assert_close(getattr(g_id, k), want, rtol=1e-10, atol=1e-10)
        assert not torch.allclose(x.mean(0), getattr(outs[-1], k))   # not the last step's output
    if head:   # the head follows the model's dtype when its options change
        m32 = SysIDModel(dataclasses.replace(cfg, forward=ModelConfig(gn=TINY, run=RunOptions(impl="torch"))),
                         pendulum.layout).bind(pendulum)
        assert m32.identify(body[:, :4].float(), ctrl[:, :4].float(), inst).globals.dtype == torch.float32
        m32.set_options(precision="fp64")
        assert m32.identify(body[:, :4], ctrl[:, :4], inst).globals.dtype == torch.float64
    moving = body[:2, :4, 1].clone().requires_grad_()

    def f(mv):
        g = m.identify(torch.cat([body[:2, :4, :1], mv[:, :, None]], 2), ctrl[:2, :4], inst[:2])
        return m.rollout(body[:2, 4], ctrl[:2, 4:6], g, inst[:2])[:, 1:, 1].sum(-1)
    assert torch.autograd.gradcheck(f, (moving,), eps=1e-6, atol=1e-5, rtol=1e-4)
    with pytest.raises(Exception, match="readout"):
        SysIDConfig(readout="max")
    with pytest.raises(ValueError, match="out_"):     # no target columns left
        SysIDConfig(identifier=ID, readout="ridge", ridge_features=3)
    with pytest.raises(ValueError, match="ridge"):
        SysIDConfig(identifier=ID, readout="ridge", ridge_features=2, ridge=0.0)
    with pytest.raises(ValueError, match="transitions"):
        SysIDConfig(identifier=ID, readout="dynamics", transitions=True)
    with pytest.raises(ValueError, match="window must be at least 2"):
        SysIDConfig(identifier=ID, readout="dynamics", window=1)
    for bad in (float("nan"), float("inf"), -1e-3, True, "small"):   # refused whatever the readout
        with pytest.raises(ConfigError, match="ridge: must be a finite number > 0"):
            SysIDConfig(identifier=ID, readout="mean", ridge=bad)
    for other in ("last", "mean"):
        with pytest.raises(ValueError, match="ridge_head .* needs readout"):
            SysIDConfig(identifier=ID, readout=other, ridge_head=4)
        with pytest.raises(ValueError, match="ridge weights the fit"):      # not silently ignored
            SysIDConfig(identifier=ID, readout=other, ridge=1e-5)
    for other in ("last", "mean", "dynamics"):
        with pytest.raises(ValueError, match=f"readout {other!r} does not read it"):
            SysIDConfig(identifier=ID, readout=other, ridge_features=2)
    assert SysIDConfig(identifier=ID, readout="dynamics", ridge=1e-5).ridge == 1e-5
    for bad in (-1, True, 1 << 17, 2.5):
        with pytest.raises(ValueError, match="ridge_head"):
            SysIDConfig(identifier=ID, readout="ridge", ridge_features=2, ridge_head=bad)
    tcfg = TrainConfig(out=str(tmp_path / "tr"), model=ModelConfig(gn=TINY, run=RunOptions(impl="torch")), steps=30,
                       batch_size=16, lr=3e-3, valid_every=30, valid_sequences=2, log_every=10, checkpoint_every=30,
                       progress=False, device="cpu", normalizer_warmup=5)
    rows = []
    tr = SysIDTrainer(tcfg, SysIDConfig(identifier=ID, window=W, readout=readout, ridge_head=head, **fit),
                      datasets=[pendulum], callbacks=[lambda t, e, info: rows.append(info["row"]) if e == "log" else None])
    summary = tr.run()
    losses = [r["loss"] for r in rows if r.get("loss") not in (None, "")]
    assert losses[-1] < losses[0]
    loaded = load_sysid(summary["last"])
    assert loaded.config.readout == readout and (readout != "ridge" or loaded.config.ridge_features == 2)
    assert loaded.config.ridge_head == head
    window = (torch.as_tensor(sp.body[:3, :W]), torch.as_tensor(sp.ctrl[:3, :W]), torch.as_tensor(sp.instance[:3]))
    tr.model.eval()   # the loaded model (its head included) identifies as the trained one did
    got, want = loaded.bind(pendulum).identify(*window), tr.model.bind(pendulum).identify(*window)
    for k in ("nodes", "edges", "globals"):
        torch.testing.assert_close(getattr(got, k), getattr(want, k), rtol=0, atol=0)
    tcfg.steps = 40
    if readout != "mean":   # the other head setting is refused by name
        with pytest.raises(Exception, match="ridge_head"):
            SysIDTrainer(tcfg, SysIDConfig(identifier=ID, window=W, readout=readout, ridge_head=0 if head else 5, **fit),
                         datasets=[pendulum]).run()
    with pytest.raises(Exception, match="readout"):
        SysIDTrainer(tcfg, SysIDConfig(identifier=ID, window=W), datasets=[pendulum]).run()


def test_identification_windows_at_the_sequence_start(pendulum, tmp_path):
    """``SysIDTrainConfig(start_windows=F)``: F = 1 draws every window at its sequence's start, F = 0.5
    about half of them, F = 0 (the paper's) uniform windows; targets stay outside the window;
    values outside [0, 1] are refused by name; the fraction is recorded in the run's config."""
    cfg = TrainConfig(out=str(tmp_path / "s"), model=ModelConfig(gn=TINY, run=RunOptions(impl="torch")), steps=20,
                      batch_size=64, lr=3e-3, valid_every=20, valid_sequences=2, log_every=10, checkpoint_every=20,
                      progress=False, device="cpu", normalizer_warmup=2)
    for bad in (-0.1, 1.5, True, "half"):
        with pytest.raises(ValueError, match="start_windows"):
            SysIDTrainer(cfg, SysIDConfig(identifier=ID, window=W), datasets=[pendulum],
                         options=SysIDTrainConfig(start_windows=bad))
    body = torch.as_tensor(pendulum["train"].body[...])

    def starts(tr, draws=4):
        out = []
        for _ in range(draws):
            (parts,) = tr.sample()
            p = parts[0]
            w0 = p.window[0].nodes.reshape(-1, 2, 13).to(body.dtype)
            x = p.graph.nodes.reshape(-1, 2, p.graph.nodes.shape[-1])[:, :, -13:].to(body.dtype)
            for k in range(w0.shape[0]):
                hits = [(s, t) for s in range(body.shape[0]) for t in range(body.shape[1] - W)
                        if torch.equal(body[s, t], w0[k]) and torch.equal(body[s, t + 1],
                                                                             p.window[1].nodes.reshape(-1, 2, 13)[k].to(body.dtype))]
                assert hits, k
                s, t = hits[0]
                t0 = [u for u in range(body.shape[1]) if torch.equal(body[s, u], x[k])]
                assert t0 and not t <= t0[0] < t + W        # the target lies outside the window
                out.append(t == 0)
        return np.mean(out)
    all_start = SysIDTrainer(cfg, SysIDConfig(identifier=ID, window=W), datasets=[pendulum],
                             options=SysIDTrainConfig(start_windows=1.0))
    assert starts(all_start) == 1.0
    half = SysIDTrainer(cfg, SysIDConfig(identifier=ID, window=W), datasets=[pendulum],
                        options=SysIDTrainConfig(start_windows=0.5))
    assert 0.35 < starts(half) < 0.65
    uniform = SysIDTrainer(cfg, SysIDConfig(identifier=ID, window=W), datasets=[pendulum])
    assert starts(uniform) < 0.2      # 1 in T - W + 1 = 26 windows
    summary = half.run()
    assert json.loads((Path(summary["last"]) / "config.json").read_text())["sysid_train"]["start_windows"] == 0.5


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("options", [{}, {"readout": "mean", "transitions": True}, {"readout": "ridge", "ridge_features": 2},
                                     {"readout": "ridge", "ridge_features": 2, "transitions": True, "stateless": True}],
                         ids=["paper", "mean-transitions", "ridge", "stateless"])
def test_cuda_captured_identification_matches_eager(pendulum, options):
    """``identify`` on CUDA without gradients replays a captured graph: G_ID equals the eager
    identification's, for new windows of the same shape, and after an in-place weight change."""
    torch.manual_seed(0)
    cfg = SysIDConfig(forward=ModelConfig(gn=TINY, run=RunOptions(impl="warp", deterministic=True)), identifier=ID,
                      window=W, **options)
    m = SysIDModel(cfg, pendulum.layout).to("cuda").bind(pendulum)
    sp = pendulum["train"]
    body = torch.as_tensor(sp.body[:8], device="cuda")
    ctrl = torch.as_tensor(sp.ctrl[:8], device="cuda")
    inst = torch.as_tensor(sp.instance[:8])

    def both(s):
        with torch.no_grad():
            a = m.identify(body[:, s:s + W], ctrl[:, s:s + W], inst)
            b = m.identify(body[:, s:s + W], ctrl[:, s:s + W], inst, capture=False)
        return a, b
    from gnwarp.models.sysid import _IDENTIFY_GRAPHS
    for s in (0, 7, 13):
        a, b = both(s)
        for k in ("nodes", "edges", "globals"):
            torch.testing.assert_close(getattr(a, k), getattr(b, k), rtol=1e-6, atol=1e-6)
    assert len(_IDENTIFY_GRAPHS[m]) == 1          # one capture served the three windows
    before = both(0)[0]
    with torch.no_grad():
        m.identifier.out["globals"].bias.add_(0.5)   # in place: the replay reads it
    a, b = both(0)
    torch.testing.assert_close(a.globals, b.globals, rtol=1e-6, atol=1e-6)
    assert not torch.allclose(a.globals, before.globals)
    with pytest.raises(ValueError, match="CUDA"):
        m.cpu().bind(pendulum).identify(body[:, :W].cpu(), ctrl[:, :W].cpu(), inst, capture=True)


def test_window_spread_against_a_hand_computation():
    """``window_spread``: within-pair variance over total variance, summed over G_ID's columns;
    0 for agreeing pairs, about 1 for independent ones; halves of one G_ID or two G_IDs alike."""
    from gnwarp.graphs import GraphsTuple
    from gnwarp.train.sysid import window_spread
    g = torch.Generator().manual_seed(0)
    a = GraphsTuple(nodes=torch.randn(12, 3, generator=g), edges=torch.randn(8, 3, generator=g),
                    globals=torch.randn(4, 2, generator=g), senders=None, receivers=None, n_node=None, n_edge=None)
    b = GraphsTuple(nodes=torch.randn(12, 3, generator=g), edges=torch.randn(8, 3, generator=g),
                    globals=torch.randn(4, 2, generator=g), senders=None, receivers=None, n_node=None, n_edge=None)
    within = total = 0.0
    for x, y in ((a.nodes, b.nodes), (a.edges, b.edges), (a.globals, b.globals)):
        z = np.concatenate([x.numpy(), y.numpy()]).astype(np.float64)
        within += ((x.numpy() - y.numpy()) ** 2).mean(0).sum() / 2
        total += z.var(0).sum()
    assert float(window_spread(a, b)) == pytest.approx(within / total, rel=1e-5)
    both = a._replace(nodes=torch.cat([a.nodes, b.nodes]), edges=torch.cat([a.edges, b.edges]),
                      globals=torch.cat([a.globals, b.globals]))
    assert float(window_spread(both)) == pytest.approx(within / total, rel=1e-5)
    assert float(window_spread(a, a)) == 0.0
    big = GraphsTuple(nodes=torch.randn(4000, 3, generator=g), edges=None, globals=None, senders=None,
                      receivers=None, n_node=None, n_edge=None)
    assert 0.9 < float(window_spread(big)) < 1.1           # independent halves
    with pytest.raises(ValueError, match="nodes"):
        window_spread(a, a._replace(nodes=a.nodes[:6]))


def term_config(out) -> TrainConfig:
    """A 10-step CPU run of the tiny models, for the tests of extra loss terms."""
    return TrainConfig(out=str(out), model=ModelConfig(gn=TINY, run=RunOptions(impl="torch")), steps=10, batch_size=16,
                       lr=3e-3, valid_every=10, valid_sequences=2, log_every=5, checkpoint_every=10, progress=False,
                       device="cpu", normalizer_warmup=2)


def check_added_term(model, terms, name, weight):
    """The loss is the forward model's four terms plus ``weight`` times ``terms[name]``, and
    that term's gradient reaches GN_p (the identifier) only."""
    val = {k: float(v.detach()) for k, v in terms.items()}
    plain = sum(val[k] for k in ("pos", "linvel", "angvel", "quat"))
    assert val["loss"] == pytest.approx(plain + weight * val[name], rel=1e-5)
    model.zero_grad()
    terms[name].backward()
    grads = {n: q.grad for n, q in model.named_parameters()}
    assert any(g is not None and g.abs().sum() > 0 for n, g in grads.items() if n.startswith("identifier."))
    assert all(g is None or g.abs().sum() == 0 for n, g in grads.items() if n.startswith("forward_model."))


def test_window_consistency_term(pendulum, tmp_path):
    """``SysIDTrainConfig(consistency=c)``: a batch's second half re-draws its first half's
    sequences with new windows; the loss adds c times ``window_spread`` of the batch's G_ID
    (recomputed here from the sampled windows), whose gradient reaches GN_p only; bad weights
    and odd shares are refused by name; the weight is recorded in the run's config."""
    from gnwarp.train.sysid import window_spread
    cfg = term_config(tmp_path / "c")
    for bad in (-0.5, math.nan, True, "1"):
        with pytest.raises(ValueError, match="consistency"):
            SysIDTrainer(cfg, SysIDConfig(identifier=ID, window=W), datasets=[pendulum],
                         options=SysIDTrainConfig(consistency=bad))
    cfg.batch_size = 15
    with pytest.raises(ValueError, match="even"):
        SysIDTrainer(cfg, SysIDConfig(identifier=ID, window=W), datasets=[pendulum],
                     options=SysIDTrainConfig(consistency=1.0))
    cfg.batch_size = 16
    tr = SysIDTrainer(cfg, SysIDConfig(identifier=ID, window=W), datasets=[pendulum],
                      options=SysIDTrainConfig(consistency=0.7))
    body = torch.as_tensor(pendulum["train"].body[...])
    (parts,) = tr.sample()
    p = parts[0]
    w0, w1 = (p.window[t].nodes.reshape(-1, 2, 13).to(body.dtype) for t in (0, 1))

    def sequence(k):   # the sequence a window comes from (each holds one system instance)
        hits = {s for s in range(body.shape[0]) for t in range(body.shape[1] - 1)
                if torch.equal(body[s, t], w0[k]) and torch.equal(body[s, t + 1], w1[k])}
        assert len(hits) == 1, k
        return hits.pop()
    seqs = [sequence(k) for k in range(16)]
    assert seqs[:8] == seqs[8:]
    terms = tr.loss(parts, accumulate=False)
    fm = tr.model.forward_model
    g_id = tr.model.identify_graphs(p.window, W, fm.stats(p.graph.nodes.dtype))
    assert float(terms["window_spread"].detach()) == pytest.approx(float(window_spread(g_id).detach()), rel=1e-5)
    check_added_term(tr.model, terms, "window_spread", 0.7)
    summary = tr.run()
    assert json.loads((Path(summary["last"]) / "config.json").read_text())["sysid_train"]["consistency"] == 0.7
    import csv
    with open(Path(summary["out"]) / "log.csv", newline="") as f:
        rows = [r for r in csv.DictReader(f) if r["loss"]]
    assert rows and all(0.0 <= float(r["window_spread"]) < 2.0 for r in rows)
    cfg.steps = 20     # resumed from `last`: the log keeps its columns and gains the new rows
    logged = []
    SysIDTrainer(cfg, SysIDConfig(identifier=ID, window=W), datasets=[pendulum],
                 callbacks=[lambda t, e, info: logged.append(int(info["row"]["step"])) if e == "log" else None],
                     options=SysIDTrainConfig(consistency=0.7)).run()
    assert logged == [15, 20]
    with open(Path(summary["out"]) / "log.csv", newline="") as f:
        text = f.read()
    rows = [r for r in csv.DictReader(text.splitlines()) if r["loss"]]
    assert text.count("window_spread") == 1
    assert [int(r["step"]) for r in rows] == [5, 10, 15, 20] and all(r["window_spread"] for r in rows)


def test_parameter_supervision(pendulum, tmp_path):
    """``SysIDTrainConfig(param_loss=w)``: the loss adds w times the masked mean squared error between
    G_ID's first P global columns and the instances' standardized parameters (recomputed here
    in float64 from the dataset), whose gradient reaches GN_p only; training with it makes
    ``estimate_params`` track the true parameters better than the untrained identifier; bad weights, data without parameters
    and a G_ID too narrow are refused by name; the weight and statistics land in config.json."""

    from gnwarp.models.sysid_params import estimate_params, param_stats
    cfg = term_config(tmp_path / "p")
    for bad in (-1.0, math.inf, True, "1"):
        with pytest.raises(ValueError, match="param_loss"):
            SysIDTrainer(cfg, SysIDConfig(identifier=ID, window=W), datasets=[pendulum],
                         options=SysIDTrainConfig(param_loss=bad))
    narrow = RecurrentGNConfig(latent=8, hidden_edges=4, hidden_nodes=4, hidden_globals=4, edge_mlp=(16,),
                               node_mlp=(16,), global_mlp=(16,), out_edges=3, out_nodes=3, out_globals=1)
    with pytest.raises(ValueError, match="2 parameters but G_ID has 1 global"):
        SysIDTrainer(cfg, SysIDConfig(identifier=narrow, window=W), datasets=[pendulum],
                     options=SysIDTrainConfig(param_loss=1.0))
    fixed = data.generate("pendulum", (4, 1, 1), num_steps=12, seed=0, backend="mujoco", progress=False)
    with pytest.raises(ValueError, match="no instance parameters"):
        SysIDTrainer(cfg, SysIDConfig(identifier=ID, window=W), datasets=[fixed],
                     options=SysIDTrainConfig(param_loss=1.0))

    st = param_stats(pendulum)
    raw = np.asarray(pendulum.static["params"], dtype=np.float64)
    used = raw[np.unique(np.asarray(pendulum["train"].instance[...]))]
    assert st.names == ["length", "mass"] and st.used.all()
    np.testing.assert_allclose(st.mean, used.mean(0), rtol=1e-12)
    np.testing.assert_allclose(st.std, used.std(0), rtol=1e-12)

    Wp = 10   # a window long enough for the tiny identifier to read a length from
    cfg.lr = 1e-2
    tr = SysIDTrainer(cfg, SysIDConfig(identifier=ID, window=Wp), datasets=[pendulum],
                      options=SysIDTrainConfig(param_loss=5.0))
    (parts,) = tr.sample()
    p = parts[0]
    terms = tr.loss(parts, accumulate=False)
    g_id = tr.model.identify_graphs(p.window, Wp, tr.model.forward_model.stats(p.graph.nodes.dtype))
    z = (torch.as_tensor(raw) - torch.as_tensor(st.mean)) / torch.as_tensor(st.std)
    zs = p.params[0].double()
    assert all(any(torch.allclose(r, q, atol=1e-6) for q in z) for r in zs)   # rows are instances' parameters
    want = (g_id.globals[:, :2].double() - zs).square().mean()
    assert float(terms["param_error"].detach()) == pytest.approx(float(want.detach()), rel=1e-5)
    check_added_term(tr.model, terms, "param_error", 5.0)
    tr.model.zero_grad()

    sp = pendulum["train"]
    body = torch.as_tensor(np.asarray(sp.body[...], dtype=np.float32))
    ctrl = torch.as_tensor(np.asarray(sp.ctrl[...], dtype=np.float32))
    inst = np.asarray(sp.instance[...])

    def error():   # rms over the train sequences' first windows and both parameters, in standard deviations
        tr.model.eval().bind(pendulum)
        with torch.no_grad():
            g = tr.model.identify(body[:, :Wp], ctrl[:, :Wp], torch.as_tensor(inst))
        tr.model.train()
        return float(np.sqrt(np.mean(((estimate_params(g, st) - raw[inst]) / st.std) ** 2)))
    before = error()
    cfg.steps, cfg.log_every = 400, 100
    summary = tr.run()
    after = error()
    assert after < 0.8 * before, (before, after)
    saved = json.loads((Path(summary["last"]) / "config.json").read_text())
    assert saved["sysid_train"]["param_loss"] == 5.0
    assert saved["param_stats"]["pendulum"]["names"] == ["length", "mass"]
    np.testing.assert_allclose(saved["param_stats"]["pendulum"]["std"], st.std)


def test_param_stats_masks_missing_and_constant_parameters():
    """``param_stats`` over the train split's instances leaves NaN out of the statistics and
    marks parameters seen once or constant as unused; ``standardize`` zeroes and masks them;
    ``estimate_params`` returns NaN for them and de-standardizes the rest."""
    from types import SimpleNamespace

    from gnwarp.graphs import GraphsTuple
    from gnwarp.models.sysid_params import estimate_params, param_stats
    params = np.array([[1.0, np.nan, 2.0], [3.0, np.nan, 2.0], [5.0, 7.0, 2.0], [100.0, 1.0, 9.0]])

    class Fake(dict):   # a dataset's three attributes param_stats reads; instance 3 is not in train
        system, meta, static = "fake", {"param_names": ["a", "b", "c"]}, {"params": params}
    ds = Fake(train=SimpleNamespace(instance=np.array([0, 1, 2, 2])))
    st = param_stats(ds)
    np.testing.assert_allclose(st.mean[0], 3.0)
    np.testing.assert_allclose(st.std[0], np.std([1.0, 3.0, 5.0]))
    assert st.used.tolist() == [True, False, False]
    z, ok = st.standardize(params)
    np.testing.assert_allclose(z[:, 0], (params[:, 0] - 3.0) / np.std([1.0, 3.0, 5.0]))
    assert not ok[:, 1:].any() and (z[:, 1:] == 0).all()
    g = GraphsTuple(nodes=None, edges=None, globals=torch.as_tensor(np.concatenate([z, np.ones((4, 1))], 1)),
                    senders=None, receivers=None, n_node=None, n_edge=None)
    est = estimate_params(g, st)
    np.testing.assert_allclose(est[:, 0], params[:, 0])
    assert np.isnan(est[:, 1:]).all()
    with pytest.raises(ValueError, match="3 parameters need"):
        estimate_params(g._replace(globals=g.globals[:, :2]), st)
    Fake.meta = {}
    with pytest.raises(ValueError, match="no instance parameters"):
        param_stats(ds)


def test_parameter_teacher_forcing_and_the_oracle_error(pendulum, tmp_path):
    """``SysIDTrainConfig(param_teacher=1)``: the forward model's loss is computed with G_ID's first P
    global columns set to the instances' standardized parameters (recomputed here in float64),
    so its gradient leaves GN_p's rows for those columns untouched; bad fractions, and teacher
    forcing without ``param_loss``, are refused by name; the fraction lands in config.json.
    ``sysid_rollout_error(oracle=param_stats(ds))`` is the error with those columns replaced by
    the true parameters, which differs from the identified G_ID's."""

    from gnwarp.models.sysid_params import param_stats
    cfg = term_config(tmp_path / "q")
    cfg.noise_std = 0.0
    for bad in (-0.1, 1.5, True, "1"):
        with pytest.raises(ValueError, match="param_teacher"):
            SysIDTrainer(cfg, SysIDConfig(identifier=ID, window=W), datasets=[pendulum],
                         options=SysIDTrainConfig(param_loss=1.0, param_teacher=bad))
    with pytest.raises(ValueError, match="needs param_loss"):
        SysIDTrainer(cfg, SysIDConfig(identifier=ID, window=W), datasets=[pendulum],
                     options=SysIDTrainConfig(param_teacher=1.0))
    tr = SysIDTrainer(cfg, SysIDConfig(identifier=ID, window=W), datasets=[pendulum],
                      options=SysIDTrainConfig(param_loss=2.0, param_teacher=1.0))
    (parts,) = tr.sample()
    p = parts[0]
    terms = tr.loss(parts, accumulate=False)
    m, fm = tr.model, tr.model.forward_model
    st = param_stats(pendulum)
    raw = np.asarray(pendulum.static["params"], dtype=np.float64)
    z = p.params[0]
    assert all(any(np.allclose(r, (q - st.mean) / st.std, atol=1e-6) for q in raw) for r in z.double().numpy())
    g_id = m.identify_graphs(p.window, W, fm.stats(p.graph.nodes.dtype))
    forced = g_id._replace(globals=torch.cat([z.to(g_id.globals.dtype), g_id.globals[:, 2:]], 1))
    want = fm.loss(m.with_gid(p.graph, forced), p.target, noise_std=0.0, accumulate=False,
                   rotation_scale=cfg.rotation_loss)
    for k in ("pos", "quat", "linvel", "angvel"):
        assert float(terms[k].detach()) == pytest.approx(float(want[k].detach()), rel=1e-5), k
    m.zero_grad()
    (terms["loss"] - 2.0 * terms["param_error"]).backward()
    w = m.identifier.out["globals"].weight.grad
    assert w[:2].abs().sum() == 0 and w[2:].abs().sum() > 0     # GN_p's estimate is not what the model read
    summary = tr.run()
    assert json.loads((Path(summary["last"]) / "config.json").read_text())["sysid_train"]["param_teacher"] == 1.0

    model = load_sysid(summary["last"]).bind(pendulum)
    inst = np.asarray(pendulum["valid"].instance[...])
    orig = model.identify

    def by_hand(*a, **k):    # G_ID with its first two global columns the true standardized parameters
        g = orig(*a, **k)
        zz = torch.as_tensor((raw[inst] - st.mean) / st.std, dtype=g.globals.dtype)
        return g._replace(globals=torch.cat([zz, g.globals[:, 2:]], 1))
    model.identify = by_hand
    hand = sysid_rollout_error(model, pendulum, "valid", 10)
    del model.identify
    oracle = sysid_rollout_error(model, pendulum, "valid", 10, oracle=st)
    assert oracle == pytest.approx(hand, rel=1e-6)
    assert oracle != pytest.approx(sysid_rollout_error(model, pendulum, "valid", 10), rel=1e-3)
    fixed = data.generate("pendulum", (2, 2, 2), num_steps=12, seed=0, backend="mujoco", progress=False)
    with pytest.raises(ValueError, match="no instance parameters"):
        sysid_rollout_error(model, fixed, "valid", 2, oracle=st)

    # the statistics it was trained with, from its checkpoint, checked
    from gnwarp.models.sysid_params import ParamStats
    from gnwarp.train.sysid import trained_param_stats
    kept = trained_param_stats(model, "pendulum")
    assert kept.names == st.names and np.allclose(kept.mean, st.mean) and np.allclose(kept.std, st.std)
    assert trained_param_stats(model, "cartpole") is None
    good = {"names": ["a", "b"], "mean": [1.0, 2.0], "std": [0.5, 0.0], "used": [True, False]}
    assert ParamStats.from_dict(good).used.tolist() == [True, False]
    for bad in ({**good, "std": [0.0, 1.0]}, {**good, "mean": [1.0, math.nan]}, {**good, "used": [1, 0]},
                {**good, "mean": [1.0]}, {**good, "names": "ab"}, {**good, "mean": ["x", 1]}, {"names": []}):
        with pytest.raises(ValueError, match="parameter statistics"):
            ParamStats.from_dict(bad)


@pytest.mark.parametrize("name", ["pendulum", "cartpole", "swimmer4", "cheetah", "jaco"])
def test_param_places_name_the_graph_element_each_parameter_changes(name):
    """``gnwarp.sim.param_places``: changing one parameter alone changes the static features of
    the node (edges) it is placed at; a mass or a gear changes nothing else."""
    from gnwarp.data.convert import static_graph
    base_sys = systems.make(name, seed=3)
    base = static_graph(base_sys.model)
    places = systems.param_places(base_sys)
    assert len(places) == len(base_sys.params)
    for (key, value), (kind, i) in zip(base_sys.params.items(), places):
        if key == "n_links":
            assert kind == "globals"
            continue
        lo, hi = systems.param_ranges(name)[key]
        step = 0.05 * (hi - lo) * (1 if value < (lo + hi) / 2 else -1)   # inside the range
        moved = static_graph(systems.make(name, params={**base_sys.params, key: value + step}).model)
        changed = {k: np.flatnonzero(np.abs(getattr(moved, k) - getattr(base, k)).max(-1) > 1e-9)
                   for k in ("nodes", "edges")}
        if kind == "nodes":
            assert i in changed["nodes"], (key, i, changed)
        else:
            rows = np.flatnonzero(base.topology.edge_ctrl[:, 0] == i)
            assert len(rows) == 2 and set(changed["edges"]) == set(rows), (key, rows, changed)
        if key.startswith(("mass_", "gear_")):   # JACO: nothing but its own element changes
            assert set(changed["nodes"]) == ({i} if kind == "nodes" else set()), (key, changed)


@pytest.fixture(scope="module")
def jaco():
    return data.generate("jaco", (6, 2, 2), num_steps=8, seed=0, backend="mujoco", parameterized=True,
                         progress=False)


def test_local_params_hand_each_parameter_to_its_node_and_edges(jaco, pendulum, tmp_path):
    """``SysIDConfig(local_params=True)``: the forward model's input holds G_ID's parameter columns
    (its first P globals) on the node of each link mass and on both edges of each gear's joint,
    zero elsewhere; teacher forcing puts the true parameters there; the placement is saved and
    checked against the data bound; misuse is refused by name."""
    from gnwarp.models.sysid_graphs import source_places
    from gnwarp.models.sysid_params import with_params
    idg = dataclasses.replace(ID, out_globals=18, hidden_globals=18)
    cfg = TrainConfig(out=str(tmp_path / "l"), model=ModelConfig(gn=TINY, run=RunOptions(impl="torch")), steps=2,
                      batch_size=4, lr=1e-3, valid_every=2, valid_sequences=2, valid_horizon=2, checkpoint_every=2,
                      progress=False, device="cpu", normalizer_warmup=1)
    sc = SysIDConfig(identifier=idg, window=3, local_params=True)
    tr = SysIDTrainer(cfg, sc, datasets=[jaco], options=SysIDTrainConfig(param_loss=1.0, param_teacher=1.0))
    m = tr.model
    names = jaco.meta["param_names"]
    places = dict(zip(names, m.sysid.param_places))
    assert places["mass_arm"] == ("nodes", (2,)) and places["gear_joint_1"] == ("edges", (0, 9))
    assert m.sysid.param_places == source_places(jaco)
    (parts,) = tr.sample()
    p = parts[0]
    g_id = m.identify_graphs(p.window, 3, m.forward_model.stats(p.graph.nodes.dtype))
    g_id = g_id._replace(globals=torch.randn_like(g_id.globals))
    graph = m.with_gid(p.graph, g_id)
    N, B, E, gn, ge = 4, jaco.meta["max_bodies"], jaco.meta["max_edges"], ID.out_nodes, ID.out_edges
    nodes, edges = graph.nodes[:, gn].reshape(N, B), graph.edges[:, ge].reshape(N, E)
    assert graph.nodes.shape[1] == gn + 1 + 13 and graph.edges.shape[1] == ge + 1 + p.graph.edges.shape[1]
    for j, name in enumerate(names):
        kind, rows = places[name]
        got = (nodes if kind == "nodes" else edges)[:, list(rows)]
        assert torch.equal(got, g_id.globals[:, j:j + 1].expand_as(got)), name
    assert torch.equal(nodes[:, 0], torch.zeros(N))          # the world holds no parameter
    z, ok = p.params
    taught = m.with_gid(p.graph, with_params(g_id, z, ok))
    j = names.index("gear_joint_3")
    assert torch.allclose(taught.edges[:, ge].reshape(N, E)[:, list(places["gear_joint_3"][1])],
                          z[:, j:j + 1].expand(N, 2).to(taught.edges.dtype))

    summary = tr.run()
    back = load_sysid(summary["last"]).bind(jaco)
    assert back.sysid.param_places == m.sysid.param_places
    body, ctrl = torch.as_tensor(jaco["test"].body[:, :3]), torch.as_tensor(jaco["test"].ctrl[:, :3])
    inst = torch.as_tensor(jaco["test"].instance[:])
    with torch.no_grad():
        gid = back.identify(body, ctrl, inst)
        u = torch.as_tensor(jaco["test"].ctrl[:, 3:6])
        roll = back.rollout(body[:, 2], u, gid, inst)
        # by hand: the placed columns recomputed at every step give the rollout's states
        tmpl, fm, x = back._template(inst, inst.shape[0])[0], back.forward_model, body[:, 2]
        ctx = fm.context(back.with_gid(tmpl.graph(x, u[:, 0]), gid))
        for t in range(3):
            x = tmpl.to_body(fm.next_nodes(back.with_gid(tmpl.graph(x, u[:, t]), gid), ctx), x)
            assert torch.allclose(roll[:, t + 1], x, atol=1e-6), t
    assert torch.isfinite(roll).all()
    with pytest.raises(ValueError, match="holds them elsewhere"):
        back.bind(pendulum)
    with pytest.raises(ValueError, match="needs param_loss"):   # (options left out: the resumed run's)
        SysIDTrainer(cfg, sc, datasets=[jaco], options=SysIDTrainConfig())
    with pytest.raises(ValueError, match="widen SysIDConfig.identifier.out_globals"):
        SysIDTrainer(cfg, SysIDConfig(identifier=ID, window=3, local_params=True), datasets=[jaco],
                     options=SysIDTrainConfig(param_loss=1.0))
    with pytest.raises(ValueError, match="set local_params=True"):
        SysIDConfig(param_places=(("nodes", (1,)),))
    with pytest.raises(ValueError, match="a node parameter has one row"):
        SysIDConfig(local_params=True, param_places=(("nodes", (1, 2)),))
    old = data.Dataset({**jaco.meta}, jaco.static, {k: jaco[k] for k in ("train", "valid", "test")})
    del old.meta["param_places"]
    with pytest.raises(ValueError, match="no param_places in its metadata"):
        source_places(old)
    with pytest.raises(ValueError, match="no instance parameters"):
        source_places(systems.make("pendulum"))
    renamed = dataclasses.replace(systems.make("jaco", seed=1), name="my_arm")   # not the registry's: all global
    assert set(systems.param_places(renamed)) == {("globals", 0)}


def test_datasets_with_malformed_param_places_are_refused(pendulum, tmp_path):
    import h5py
    path = tmp_path / "p.h5"
    pendulum.save(path)
    assert data.load(path).meta["param_places"] == [["nodes", 1], ["nodes", 1]]
    for i, bad in enumerate(([["nodes", 0], ["nodes", 1]], [["nodes", 1]], [["edges", 5], ["nodes", 1]],
                             [["bodies", 1], ["nodes", 1]])):
        p2 = tmp_path / f"bad{i}.h5"
        p2.write_bytes(path.read_bytes())
        with h5py.File(p2, "r+") as f:
            meta = json.loads(f.attrs["meta"])
            meta["param_places"] = bad
            f.attrs["meta"] = json.dumps(meta)
            del f.attrs["meta_sha256"]   # as a file written before the metadata's checksum: its values checked
        with pytest.raises(data.DatasetError, match="param_places"):
            data.load(p2)


def test_nominal_static_reads_the_system_as_designed(jaco, pendulum, tmp_path):
    """``SysIDConfig(nominal_static=True)``: the forward model's input holds, after G_ID's columns,
    the training data's static graph at its mean over the train split's instances, the same in
    every graph and normalized as static features are; the nominal graph is saved in the
    checkpoint and validated; another topology, a run resumed on other data and misuse are
    refused by name."""
    from gnwarp.models.sysid_graphs import NominalGraph, nominal_graph
    from gnwarp.validation import ConfigError
    nom = nominal_graph(jaco)
    layout, train = jaco.layout, np.unique(jaco["train"].instance[:])
    assert (nom.node_names, nom.edge_names) == (tuple(layout.node_names), tuple(layout.edge_names))
    for k in ("nodes", "edges"):
        mean = np.asarray(jaco.static[k], dtype=np.float64)[train].mean(0)
        assert np.array_equal(nom.tensors()[k].numpy(), mean[:len(getattr(nom, k))]), k
    assert nom.senders == tuple(jaco.static["senders"][0]) and len(nom.nodes) == jaco.static["n_node"][0]
    assert train.size < jaco.static["n_node"].shape[0]          # the test instances' values are not averaged in
    cfg = TrainConfig(out=str(tmp_path / "n"), model=ModelConfig(gn=TINY, run=RunOptions(impl="torch")), steps=2,
                      batch_size=4, lr=1e-3, valid_every=2, valid_sequences=2, valid_horizon=2, checkpoint_every=2,
                      progress=False, device="cpu", normalizer_warmup=1)
    sc = SysIDConfig(identifier=ID, window=3, nominal_static=True)
    tr = SysIDTrainer(cfg, sc, datasets=[jaco])
    m = tr.model
    assert m.sysid.nominal == nom
    (parts,) = tr.sample()
    p = parts[0]
    g_id = m.identify_graphs(p.window, 3, m.forward_model.stats(p.graph.nodes.dtype))
    graph = m.with_gid(p.graph, g_id)
    gn, ge, Fn, Fe = ID.out_nodes, ID.out_edges, len(nom.node_names), len(nom.edge_names)
    N = p.graph.n_node.shape[0]
    want = nom.tensors()
    assert graph.nodes.shape[1] == gn + Fn + 13 and graph.edges.shape[1] == ge + Fe + p.graph.edges.shape[1]
    assert torch.equal(graph.nodes[:, gn:gn + Fn], want["nodes"].float().repeat(N, 1))
    assert torch.equal(graph.edges[:, ge:ge + Fe], want["edges"].float().repeat(N, 1))
    assert torch.equal(graph.nodes[:, :gn], g_id.nodes)
    # G_ID's columns pass the normalizer as they are (D.3); the nominal ones are normalized
    assert m.forward_model.norm_nodes.skip == gn and m.forward_model.norm_edges.skip == ge

    summary = tr.run()
    back = load_sysid(summary["last"]).bind(jaco)
    assert back.sysid.nominal == nom
    assert sysid_rollout_error(back, jaco, "test", 3) == pytest.approx(sysid_rollout_error(m, jaco, "test", 3),
                                                                       rel=1e-6)
    assert SysIDConfig.from_dict(json.loads(json.dumps(back.sysid.to_dict()))) == back.sysid
    with pytest.raises(ValueError, match="another topology"):
        back.bind(pendulum)
    moved = {**jaco.static, "nodes": np.asarray(jaco.static["nodes"]) * 1.5}     # the same arm, other bodies
    other = data.Dataset({**jaco.meta}, moved, {k: jaco[k] for k in ("train", "valid", "test")})
    with pytest.raises(CheckpointError, match="another nominal static graph"):
        SysIDTrainer(dataclasses.replace(cfg, steps=4), sc, datasets=[other])
    varied = {**jaco.static, "n_node": np.asarray(jaco.static["n_node"]).copy()}
    varied["n_node"][-1] -= 1
    with pytest.raises(ValueError, match="differ in topology"):
        nominal_graph(data.Dataset({**jaco.meta}, varied, {k: jaco[k] for k in ("train", "valid", "test")}))
    with pytest.raises(ValueError, match="train on one"):
        SysIDTrainer(dataclasses.replace(cfg, out=str(tmp_path / "two")), sc, datasets=[jaco, jaco])
    with pytest.raises(ValueError, match="set nominal_static=True"):
        SysIDConfig(nominal=nom)
    with pytest.raises(ValueError, match="build the model with"):
        SysIDModel(sc, jaco.layout)
    good = nom.to_dict()
    assert NominalGraph.from_dict(good) == nom
    for key, bad, match in (("nodes", [r[:-1] for r in good["nodes"]], "nodes: row 0 has"),
                            ("edges", [[math.nan] * Fe] + good["edges"][1:], "edges"),
                            ("senders", good["senders"][:-1], "senders"),
                            ("receivers", [99] * len(good["receivers"]), "beyond the graph's 10 nodes"),
                            ("globals", [1.0], "globals: row 0 has 1 values")):
        with pytest.raises(ConfigError, match=match):
            NominalGraph.from_dict({**good, key: bad})


def test_sysid_flags_map_to_the_config_and_trainer_options():
    """``gnwarp.train.sysid_config.add_sysid_arguments`` / ``sysid_settings`` (shared by ``gnwarp
    train --sysid`` and the figures script): each flag reaches its ``SysIDConfig`` or
    ``SysIDTrainConfig`` field, ``sysid_flags_given`` names every flag set, and a misfit flag is
    refused by name."""
    import argparse
    from gnwarp.train.sysid_config import add_sysid_arguments, sysid_flag_values, sysid_flags_given, sysid_settings
    ap = argparse.ArgumentParser()
    add_sysid_arguments(ap)
    args = ap.parse_args(["--transitions", "--stateless", "--targets", "3", "--readout", "ridge", "--ridge-head", "8",
                          "--ridge-features", "2", "--ridge", "1e-5", "--local-params", "--gid-globals", "7",
                          "--nominal-static",
                          "--start-windows", "0.25", "--consistency", "0.5", "--param-loss", "2",
                          "--param-teacher", "0.75"])
    sysid, options = sysid_settings(args, ID, window=4)
    assert (sysid.transitions, sysid.stateless, sysid.readout, sysid.ridge_head, sysid.ridge_features, sysid.ridge,
            sysid.local_params, sysid.nominal_static, sysid.window) == (True, True, "ridge", 8, 2, 1e-5, True, True, 4)
    assert (sysid.identifier.out_globals, sysid.identifier.hidden_globals) == (7, 7)
    assert dataclasses.replace(sysid.identifier, out_globals=ID.out_globals, hidden_globals=ID.hidden_globals) == ID
    assert options == SysIDTrainConfig(targets=3, start_windows=0.25, consistency=0.5, param_loss=2.0,
                                       param_teacher=0.75)
    every = {a.option_strings[0] for a in ap._actions if a.option_strings[0] != "-h"}
    assert set(sysid_flags_given(args)) == every and len(every) == 14 and sysid_flags_given(ap.parse_args([])) == []
    assert sysid_flag_values(args)["param_loss"] == 2.0 and sysid_flag_values(ap.parse_args([]))["readout"] is None
    assert sysid_settings(ap.parse_args([])) == (SysIDConfig(), SysIDTrainConfig())
    with pytest.raises(ConfigError, match="--ridge-features: ridge_features splits"):
        sysid_settings(ap.parse_args(["--ridge-features", "2"]))
    with pytest.raises(ConfigError, match="--ridge: ridge weights the fit of readout 'ridge' or 'dynamics'"):
        sysid_settings(ap.parse_args(["--ridge", "1e-5"]))
    with pytest.raises(ConfigError, match="--param-teacher: .*needs param_loss > 0"):
        sysid_settings(ap.parse_args(["--param-teacher", "0.5"]))
    assert sysid_settings(ap.parse_args(["--readout", "dynamics", "--ridge", "1e-4"]))[0].ridge == 1e-4


def test_generated_flags_follow_the_config_fields(capsys):
    """``gnwarp.validation.add_config_flags``: one flag per field of ``SysIDTrainConfig``, its help
    the field's description and default, its values checked by the field's annotation as they
    are parsed (a bad value refused naming its flag and the allowed values)."""
    import argparse
    from gnwarp.validation import add_config_flags, config_flags_given, config_from_flags
    ap = argparse.ArgumentParser()
    flags = add_config_flags(ap, SysIDTrainConfig)
    names = [f.name for f in dataclasses.fields(SysIDTrainConfig)]
    assert flags == ["--" + n.replace("_", "-") for n in names]
    actions = {a.dest: a for a in ap._actions}
    for f in dataclasses.fields(SysIDTrainConfig):
        assert actions[f.name].default is None   # not given: the config's default
        assert f.metadata["help"] in actions[f.name].help and f"(default: {f.default!r})" in actions[f.name].help
    assert config_from_flags(SysIDTrainConfig, ap.parse_args([])) == SysIDTrainConfig()
    args = ap.parse_args(["--param-loss", "0.5", "--targets", "2"])
    assert config_flags_given(args, SysIDTrainConfig) == {"targets": 2, "param_loss": 0.5}
    assert config_from_flags(SysIDTrainConfig, args) == SysIDTrainConfig(targets=2, param_loss=0.5)
    for argv, text in ((["--targets", "0"], "argument --targets: must be an integer >= 1, got '0'"),
                       (["--start-windows", "1.5"], "argument --start-windows: must be a finite number >= 0 and <= 1"),
                       (["--consistency", "x"], "argument --consistency: must be a finite number >= 0, got 'x'")):
        with pytest.raises(SystemExit):
            ap.parse_args(argv)
        assert text in capsys.readouterr().err
    # the model's flags: a choice field lists its choices, a switch takes no value
    ap = argparse.ArgumentParser()
    add_config_flags(ap, SysIDConfig, ["readout", "transitions"])
    assert {a.dest: a.choices for a in ap._actions if a.dest == "readout"} == {
        "readout": ["last", "mean", "ridge", "dynamics"]}
    assert ap.parse_args(["--transitions"]).transitions is True and ap.parse_args([]).transitions is None
    with pytest.raises(TypeError, match="nested config"):
        add_config_flags(argparse.ArgumentParser(), SysIDConfig, ["identifier"])
    with pytest.raises(TypeError, match="no field 'readouts'"):
        add_config_flags(argparse.ArgumentParser(), SysIDConfig, ["readouts"])
    assert "(default: off)" in {a.dest: a.help for a in ap._actions}["transitions"]
