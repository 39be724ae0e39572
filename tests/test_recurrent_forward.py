"""The partly observed JACO (gnwarp.data.proprio) and the recurrent one-step model (D.7.3)."""
import json
import math

import mujoco
import numpy as np
import pytest
import torch

from gnwarp.data import proprio
from gnwarp.files import sha256_file
from gnwarp.models.normalizer import normalize_graph
from gnwarp.models.recurrent import RecurrentGNConfig
from gnwarp.models.recurrent_forward import (RecurrentForwardConfig, RecurrentForwardModel, apply_observation_delta,
                                             observation_delta)
from gnwarp.sim.systems import make
from gnwarp.train import CheckpointError, TrainConfig
from gnwarp.train.recurrent import TeacherForcingTrainer, load_recurrent

TINY = RecurrentGNConfig(latent=16, hidden_edges=8, hidden_nodes=8, hidden_globals=8, edge_mlp=(32,), node_mlp=(32,),
                         global_mlp=(32,))


@pytest.fixture(scope="module")
def data():
    return proprio.ProprioData.simulate(proprio.proprio_jaco(), (8, 2, 2), num_steps=24, seed=3, backend="mujoco")


def model(data, recurrent=True, impl="torch", seed=0):
    torch.manual_seed(seed)
    cfg = RecurrentForwardConfig(core=TINY, recurrent=recurrent)
    cfg.run = cfg.run.replace(impl=impl)
    return RecurrentForwardModel(cfg, data.sizes, data.graphs, data.movable)


def train_config(out, steps, **changes):
    """A short CPU run that steps as a plain Adam loop does (no clipping, no decay, no warm-up
    batches), logging every step."""
    kw = dict(out=str(out), steps=steps, batch_size=8, lr=3e-3, seed=0, grad_clip=None, lr_decay=1.0,
              normalizer_warmup=0, log_every=1, device="cpu", progress=False)
    return TrainConfig(**{**kw, **changes})


def fit(cfg, data, m, **kw):
    """(trainer, loss of every step) of a run of ``TeacherForcingTrainer``."""
    rows = []
    t = TeacherForcingTrainer(cfg, data, m, callbacks=[lambda tr, ev, info: rows.append(info["row"]) if ev == "log"
                                                         else None], **kw)
    t.run()
    return t, [r["loss"] for r in rows if r.get("loss", "") != ""]


def test_variant_hides_a_lagged_command():
    s = proprio.proprio_jaco(lag=0.2, servo_scale=0.1)
    base = make("jaco")
    assert (s.dt, s.substeps, s.timestep) == (0.04, 4, 0.01)
    assert s.model.na == s.model.nu == 9
    assert all(int(t) == mujoco.mjtDyn.mjDYN_FILTER for t in s.model.actuator_dyntype)
    np.testing.assert_allclose(s.model.actuator_dynprm[:, 0], 0.2)
    np.testing.assert_allclose(s.model.actuator_gainprm[:, 0], 0.1 * base.model.actuator_gainprm[:, 0])
    assert proprio.proprio_jaco(lag=0.0).model.na == 0
    with pytest.raises(ValueError, match="multiple"):
        proprio.proprio_jaco(dt=0.035)


def test_observe_one_body_by_hand():
    m = proprio.proprio_jaco().model
    qpos = np.linspace(-1.0, 2.0, m.nq)
    qvel = np.linspace(0.5, -0.7, m.nv)
    obs = proprio.observe(qpos, qvel, m)
    assert obs.shape == (m.nbody, 3)
    b = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "forearm")
    j = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "joint_3")
    q, v = qpos[m.jnt_qposadr[j]], qvel[m.jnt_dofadr[j]]
    np.testing.assert_allclose(obs[b].numpy(), [math.cos(q), math.sin(q), v], rtol=1e-6)
    np.testing.assert_array_equal(obs[0].numpy(), [1.0, 0.0, 0.0])       # the world: no joint
    with pytest.raises(ValueError, match="one hinge per body"):
        proprio.joint_of_body(make("cheetah").model)                       # a root with three joints


def test_dataset_view(data):
    tr, ds = data.split("train"), data.dataset["train"]
    assert tr.obs.shape == (8, 25, 10, 3) and tr.ctrl.shape == (8, 24, 9)
    s, t = 5, 17
    ref = proprio.observe(np.asarray(ds.qpos[s, t], np.float64), np.asarray(ds.qvel[s, t], np.float64),
                          data.system.model)
    torch.testing.assert_close(tr.obs[s, t], ref)
    g = data.graphs(tr.instance[:2], tr.obs[:2, 0], tr.ctrl[:2, 0])
    assert g.nodes.shape == (20, data.sizes["nodes"]) and g.edges.shape[1] == data.sizes["edges"]
    torch.testing.assert_close(g.nodes[:10, -3:], tr.obs[0, 0])


def test_delta_round_trip():
    a = torch.rand(50) * 6 - 3
    b = torch.rand(50) * 6 - 3
    o0 = torch.stack([a.cos(), a.sin(), torch.randn(50)], -1)
    o1 = torch.stack([b.cos(), b.sin(), torch.randn(50)], -1)
    d = observation_delta(o0, o1)
    assert d.abs()[:, 0].max() <= math.pi
    torch.testing.assert_close(apply_observation_delta(o0, d), o1, atol=1e-5, rtol=1e-5)


def test_loss_and_rollout_shapes(data):
    tr = data.split("train")
    m = model(data)
    obs, ctrl, inst = tr.windows(4, 21, torch.Generator().manual_seed(0))
    assert obs.shape == (4, 21, 10, 3) and ctrl.shape == (4, 20, 9)
    loss = m.loss(inst, obs, ctrl, accumulate=True)
    assert loss.ndim == 0 and torch.isfinite(loss)
    with torch.no_grad():
        r = m.rollout(tr.instance[:3], tr.obs[:3], tr.ctrl[:3], warmup=20)
    assert r.shape == (3, 25, 10, 3)
    torch.testing.assert_close(r[:, :21], tr.obs[:3, :21])                 # the warm-up is given
    torch.testing.assert_close(r[:, :, 0], tr.obs[:3, :, 0])               # the world does not move
    torch.testing.assert_close(r[..., 0] ** 2 + r[..., 1] ** 2, torch.ones(3, 25, 10))
    with pytest.raises(ValueError, match="warmup"):
        m.rollout(tr.instance[:3], tr.obs[:3], tr.ctrl[:3], warmup=24)


def test_training_lowers_the_loss(data, tmp_path):
    tr = data.split("train")
    m = model(data)
    fixed = tr.windows(8, 21, torch.Generator().manual_seed(1))
    _, losses = fit(train_config(tmp_path, 30), data, m)
    assert len(losses) == 30
    with torch.no_grad():
        after = float(m.loss(fixed[2], fixed[0], fixed[1]))
    assert np.mean(losses[-5:]) < 0.8 * np.mean(losses[:3]) and after < losses[0]


@pytest.mark.parametrize("normalizer_steps", [None, 2])
def test_trainer_steps_as_a_plain_adam_loop(data, tmp_path, normalizer_steps):
    """Without clipping, decay or warm-up batches, the trainer's steps are Adam on the loss of
    windows drawn from a generator seeded with ``seed``: the same losses and weights."""
    tr = data.split("train")
    ref = model(data)
    gen, opt, want = torch.Generator().manual_seed(0), torch.optim.Adam(ref.parameters(), lr=3e-3), []
    for k in range(4):
        obs, ctrl, inst = tr.windows(8, 21, gen)
        loss = ref.loss(inst, obs, ctrl, accumulate=normalizer_steps is None or k < normalizer_steps)
        opt.zero_grad()
        loss.backward()
        opt.step()
        want.append(float(loss.detach()))
    t, got = fit(train_config(tmp_path, 4), data, model(data), normalizer_steps=normalizer_steps)
    np.testing.assert_allclose(got, want, rtol=1e-6)
    for (name, p), q in zip(t.model.state_dict().items(), ref.state_dict().values()):
        torch.testing.assert_close(p, q, msg=name)
    assert len(set(got)) == 4   # the steps trained


def test_killed_run_resumes_to_the_same_weights(data, tmp_path):
    """A run killed after its step-2 checkpoint and resumed into the same folder (from a new,
    differently initialized model) ends with the weights, normalizers and log of an uninterrupted
    run; ``load_recurrent`` reads the checkpoint back to the same model."""
    clip = dict(grad_clip=0.5, checkpoint_every=2, valid_every=2)   # clipping on, as by default
    whole, _ = fit(train_config(tmp_path / "whole", 4, **clip), data, model(data))

    class Killed(Exception):
        pass

    def kill(trainer, event, info):
        if event == "checkpoint" and info["name"] == "last":
            raise Killed
    with pytest.raises(Killed):
        TeacherForcingTrainer(train_config(tmp_path / "cut", 4, **clip), data, model(data), callbacks=[kill]).run()
    killed_at = torch.load(tmp_path / "cut" / "last" / "training.pt", weights_only=True)["state"]["step"]
    assert killed_at == 2
    resumed, _ = fit(train_config(tmp_path / "cut", 4, **clip), data, model(data, seed=5))
    assert resumed.state["step"] == 4
    for (name, p), q in zip(whole.model.state_dict().items(), resumed.model.state_dict().values()):
        torch.testing.assert_close(p, q, msg=name, rtol=0, atol=0)
    logs = [(tmp_path / d / "log.csv").read_text().splitlines() for d in ("whole", "cut")]
    assert [r.split(",")[0] for r in logs[0]] == [r.split(",")[0] for r in logs[1]] == ["step", "1", "2", "3", "4"]
    back = load_recurrent(tmp_path / "cut" / "last", data)
    assert back.config.to_dict() == resumed.model.config.to_dict()
    for (name, p), q in zip(resumed.model.state_dict().items(), back.state_dict().values()):
        torch.testing.assert_close(p, q, msg=name, rtol=0, atol=0)
    tr = data.split("valid")
    with torch.no_grad():
        torch.testing.assert_close(back.rollout(tr.instance, tr.obs, tr.ctrl, warmup=20),
                                   resumed.model.rollout(tr.instance, tr.obs, tr.ctrl, warmup=20))


def test_trainer_refuses_what_it_cannot_train(data, tmp_path):
    fit(train_config(tmp_path, 1), data, model(data))
    other = RecurrentForwardModel(RecurrentForwardConfig(core=TINY.__class__(**{**TINY.to_dict(), "latent": 24})),
                                  data.sizes, data.graphs, data.movable)
    with pytest.raises(CheckpointError, match="model.core.latent: 16 -> 24"):
        TeacherForcingTrainer(train_config(tmp_path, 2), data, other)
    with pytest.raises(ValueError, match="window must be 2..25"):
        TeacherForcingTrainer(train_config(tmp_path / "w", 2), data, model(data), window=26)
    with pytest.raises(TypeError, match="ProprioData"):
        TeacherForcingTrainer(train_config(tmp_path / "d", 2), data.dataset, model(data))
    with pytest.raises(CheckpointError, match="not a recurrent one-step model"):
        cfg = json.loads((tmp_path / "last" / "config.json").read_text())
        cfg.pop("kind")
        (tmp_path / "last" / "config.json").write_text(json.dumps(cfg))
        manifest = json.loads((tmp_path / "last" / "manifest.json").read_text())
        manifest["config.json"] = sha256_file(tmp_path / "last" / "config.json")
        (tmp_path / "last" / "manifest.json").write_text(json.dumps(manifest))
        load_recurrent(tmp_path / "last", data)


@pytest.mark.parametrize("recurrent", [True, False])
def test_rollout_matches_the_step_loop_by_hand(data, recurrent):
    tr = data.split("train")
    m = model(data, recurrent, impl="warp")
    m.loss(tr.instance[:4], tr.obs[:4, :21], tr.ctrl[:4, :20], accumulate=True)  # non-trivial statistics
    inst, obs, ctrl = tr.instance[:2], tr.obs[:2], tr.ctrl[:2]
    with torch.no_grad():
        r = m.rollout(inst, obs, ctrl, warmup=20)
        hidden, x, preds = None, None, []
        for t in range(24):
            graph = data.graphs(inst, obs[:, t] if t <= 20 else x, ctrl[:, t])
            stats = m.stats(torch.float32)
            if hidden is None or not recurrent:
                hidden = m.core.initial_hidden(graph)
            out, hidden = m.core.step(normalize_graph(graph, stats), hidden)
            mean, std = stats["delta"]
            d = (out.nodes * std + mean).reshape(2, 10, 2)
            nxt = apply_observation_delta(obs[:, t] if t <= 20 else x, d)
            x = torch.where(data.movable[:, None], nxt, obs[:, t] if t <= 20 else x)
            preds.append(x)
    torch.testing.assert_close(r[:, 21:], torch.stack(preds[20:], 1), atol=1e-5, rtol=1e-5)


def test_feed_forward_has_no_memory(data):
    tr = data.split("train")
    m = model(data, recurrent=False)
    inst, obs, ctrl = tr.instance[:2], tr.obs[:2].clone(), tr.ctrl[:2]
    with torch.no_grad():
        a = m.rollout(inst, obs, ctrl, warmup=20)
        obs[:, :20] += 0.3                                                   # change the history only
        b = m.rollout(inst, obs, ctrl, warmup=20)
        mr = model(data, recurrent=True)
        c, d = mr.rollout(inst, tr.obs[:2], ctrl, warmup=20), mr.rollout(inst, obs, ctrl, warmup=20)
    torch.testing.assert_close(a[:, 20:], b[:, 20:])
    assert (c[:, 21:] - d[:, 21:]).abs().max() > 1e-6                        # the recurrent one remembers


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("normalizer_steps", [None, 4])
def test_cuda_captured_teacher_forcing_matches_eager(data, normalizer_steps, tmp_path):
    """The trainer's teacher-forcing step replayed from CUDA graphs (windows drawn on the device,
    the sequence loop, backward, the optimizer; one graph with normalizer accumulation, one
    without) trains as eager steps with the same device generator do: the same losses and
    parameters."""
    cuda = proprio.ProprioData(data.dataset, data.system, device="cuda")
    cfg = dict(device="cuda", valid_every=1000, checkpoint_every=1000)
    with pytest.raises(ValueError, match="graphs are built on cpu"):   # a model reading CPU graphs
        TeacherForcingTrainer(train_config(tmp_path / "cpu", 1, device="cuda"), cuda, model(data, impl="warp")).run()
    runs = {}
    for capture in (True, False):
        m = model(cuda, impl="warp", seed=0)
        m.core.set_options(m.core.options.replace(deterministic=True))
        t, losses = fit(train_config(tmp_path / str(capture), 10, capture=capture, **cfg), cuda, m,
                        normalizer_steps=normalizer_steps)
        assert (t.captured is not None) == capture
        runs[capture] = (t.model, losses)
    (a, la), (b, lb) = runs[True], runs[False]
    assert len(la) == len(lb) == 10 and all(math.isfinite(x) for x in la)
    np.testing.assert_allclose(la, lb, rtol=1e-4, atol=1e-6)
    assert la[-1] != la[0]    # the replays trained: the parameters moved between steps
    for p, q in zip(a.parameters(), b.parameters()):
        torch.testing.assert_close(p, q, rtol=1e-4, atol=1e-5)
    for n, q in zip(a.buffers(), b.buffers()):
        torch.testing.assert_close(n, q)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("recurrent", [True, False])
def test_cuda_captured_rollout_matches_eager(data, recurrent):
    """``rollout`` under no_grad on CUDA replays one CUDA graph per shape: the same states as the
    eager loop, for new inputs of the same shape and after the weights change in place; with
    gradients on it runs eagerly."""
    cuda = proprio.ProprioData(data.dataset, data.system, device="cuda")
    tr = cuda.split("train")
    m = model(cuda, recurrent, impl="warp").to("cuda")
    m.loss(tr.instance[:4], tr.obs[:4, :21], tr.ctrl[:4, :20], accumulate=True)  # non-trivial statistics
    inst, obs, ctrl = tr.instance[:3], tr.obs[:3], tr.ctrl[:3]
    with torch.no_grad():
        got = m.rollout(inst, obs, ctrl, warmup=20)
        ref = m.rollout(inst, obs, ctrl, warmup=20, capture=False)
        torch.testing.assert_close(got, ref, rtol=1e-5, atol=1e-6)
        inst2, obs2, ctrl2 = tr.instance[3:6], tr.obs[3:6], tr.ctrl[3:6]       # same shapes: a replay
        torch.testing.assert_close(m.rollout(inst2, obs2, ctrl2, warmup=20),
                                   m.rollout(inst2, obs2, ctrl2, warmup=20, capture=False), rtol=1e-5, atol=1e-6)
        for p in m.parameters():                                                # in place: read at replay
            p.mul_(0.9)
        torch.testing.assert_close(m.rollout(inst, obs, ctrl, warmup=20),
                                   m.rollout(inst, obs, ctrl, warmup=20, capture=False), rtol=1e-5, atol=1e-6)
    out = m.rollout(inst, obs, ctrl, warmup=20)                                 # gradients on: eager
    assert out.requires_grad
