"""The agents' updates through ``Updater``: the same draws and numbers as the eager ``update``
on batches sampled the usual way (CPU), hard target copies counted, a stale recording after
``load_state_dict`` dropped; on CUDA, updates replayed from a CUDA graph against eager ones."""
import copy

import pytest
import torch
from torch import nn

from gnwarp.rl.agents import make_agent
from gnwarp.rl.graphed import Updater
from gnwarp.rl.replay import ReplayBuffer
from gnwarp.rl.settings import AgentSettings

D, U, E = 4, 2, 3
CUDA = torch.cuda.is_available()


class Model(nn.Module):
    def __init__(self):
        super().__init__()
        self.lin = nn.Linear(D + U, D)

    def forward(self, x, a):
        return x + 0.1 * self.lin(torch.cat([x, a], -1))


def reward(x, a, x2):
    return -(x2 ** 2).sum(-1) - 0.1 * (a ** 2).sum(-1)


def _setup(agent, device="cpu", **kw):
    torch.manual_seed(0)
    s = AgentSettings(agent=agent, hidden=(16, 16), batch_size=8, seed=3, **kw)
    model = Model() if agent not in ("ddpg", "svg0") else None
    ag = make_agent(s, D, [-1] * U, [1] * U, model=model.to(device) if model else None,
                    reward=reward if model else None, device=device)
    buf = ReplayBuffer(60, D, U, num_envs=E, device=device)
    g = torch.Generator().manual_seed(1)
    for t in range(12):
        x = torch.randn(E, D, generator=g)
        a = torch.rand(E, U, generator=g) * 2 - 1
        done = torch.tensor([t % 5 == 4] * E)
        buf.add(x, a, -(x ** 2).sum(-1), x + 0.1 * a.sum(-1, keepdim=True), torch.zeros(E, dtype=torch.bool), done)
    return ag, buf


def _params(ag):
    nets = [ag.policy, ag.q, ag.policy_target, ag.q_target] + ([ag.model] if getattr(ag, "model", None) else [])
    return [p.detach().cpu().clone() for n in nets for p in n.parameters()]


def _assert_runs_agree(runs, rtol, atol):
    """Two runs' (parameters, per-call metrics) equal up to ``rtol`` / ``atol``."""
    (p0, m0), (p1, m1) = runs
    for a, b in zip(p0, p1):
        torch.testing.assert_close(a, b, rtol=rtol, atol=atol)
    for a, b in zip(m0, m1):
        assert a.keys() == b.keys() and all(abs(a[k] - b[k]) <= rtol * (1 + abs(a[k])) for k in a)


@pytest.mark.parametrize("agent,seq", [("ddpg", None), ("svg0", None), ("svg1", None), ("svg2", 2)])
def test_updater_draws_and_computes_as_eager_updates(agent, seq):
    ag, buf = _setup(agent)
    ref, ref_buf = copy.deepcopy(ag), copy.deepcopy(buf)
    g, g_ref = torch.Generator().manual_seed(7), torch.Generator().manual_seed(7)
    up = Updater(ag, buf, g, model_sequence=seq)
    assert not up.capture and not up.captured
    m = up.run(5)
    for _ in range(5):          # the same draws in the same order: indices, sequences, then noise
        batch = ref_buf.sample(8, g_ref)
        mb = ref_buf.sample_sequences(8, seq, g_ref) if seq else None
        shape = ref.update_noise_shape(8)
        noise = None if shape is None else torch.randn(shape, generator=ref.generator)
        m_ref = ref.update(batch, mb, noise)
    assert ag.updates == ref.updates == 5
    assert all(torch.equal(a, b) for a, b in zip(_params(ag), _params(ref)))
    assert m.keys() == m_ref.keys() and all(torch.equal(m[k], m_ref[k]) for k in m)
    assert ("model_loss" in m) == (agent in ("svg1", "svg2"))
    assert up.run(0) == {}


@pytest.mark.parametrize("agent,seq,kw", [("ddpg", None, {"squash_penalty": 1e-2}), ("svg0", None, {}),
                                          ("svg1", None, {"squash_penalty": 1e-2, "model_noise": "inferred"}),
                                          ("svg2", 2, {})])
def test_compiled_updates_compute_as_eager_ones(agent, seq, kw):
    """The update's losses traced by torch.compile ("aot_eager": the traced graphs run by eager
    kernels, no compiler needed) give the eager update's numbers."""
    runs = []
    for backend in (None, "aot_eager"):
        ag, buf = _setup(agent, **kw)
        if backend:
            ag.compile_update(backend)
            assert ag.compiled == backend and hasattr(ag.q_loss.compiled, "_torchdynamo_orig_callable")
            torch._dynamo.reset()
        from torch._dynamo.utils import counters
        counters.clear()
        up = Updater(ag, buf, torch.Generator().manual_seed(7), model_sequence=seq)
        ms = [{k: float(v) for k, v in up.run(1).items()}]
        assert counters["stats"]["unique_graphs"] == 0       # the first update: eager, compiled or not
        ms += [{k: float(v) for k, v in up.run(4).items()} for _ in range(2)]
        runs.append((_params(ag), ms))
        if backend:   # then the losses were traced: graphs compiled, not run as plain Python
            assert counters["stats"]["unique_graphs"] >= 2 and ag.q_loss.calls == 9
    _assert_runs_agree(runs, 1e-5, 1e-6)
    ag, _ = _setup(agent)
    with pytest.raises(Exception, match="inductor or aot_eager"):
        ag.compile_update("tensorrt")


def test_inferred_model_noise_reaches_the_update():
    """An update with model_noise "inferred" scores the policy from the replayed transitions: other
    policy steps than with the model's own predictions; the model's steps, which read replayed
    transitions only, the same."""
    out = {}
    for mode in ("none", "inferred"):
        ag, buf = _setup("svg1", model_noise=mode)
        Updater(ag, buf, torch.Generator().manual_seed(7)).run(3)
        out[mode] = ag
    a, b = out["none"], out["inferred"]
    assert not all(torch.equal(p, q) for p, q in zip(a.policy.parameters(), b.policy.parameters()))
    # the model learns from replayed transitions only: the same steps either way
    assert all(torch.equal(p, q) for p, q in zip(a.model.parameters(), b.model.parameters()))


def test_hard_target_copies_counted_and_loads_noticed():
    ag, buf = _setup("ddpg", preset="paper", target_period=3)
    up = Updater(ag, buf, torch.Generator().manual_seed(0))
    up.run(2)
    assert not all(torch.equal(p, t) for p, t in zip(ag.q.parameters(), ag.q_target.parameters()))
    up.run(1)                   # the third update copies the networks into the targets
    assert all(torch.equal(p, t) for p, t in zip(ag.q.parameters(), ag.q_target.parameters()))
    saved = ag.state_dict()
    ag.load_state_dict(saved)
    up.run(1)                   # a load is noticed (on CUDA: the graph is recorded again)
    assert up._loads == ag.loads == 1 and ag.updates == 4


def test_updater_refuses_capture_off_cuda():
    ag, buf = _setup("ddpg")      # on the CPU
    with pytest.raises(ValueError, match="needs the agent on CUDA"):
        Updater(ag, buf, torch.Generator(), capture=True)


@pytest.mark.skipif(not CUDA, reason="needs CUDA")
@pytest.mark.parametrize("agent,seq,kw", [("ddpg", None, {}), ("svg0", None, {}), ("svg1", None, {}), ("svg2", 2, {}),
                                          ("svg1", None, {"model_noise": "inferred"})])
def test_captured_updates_equal_eager_ones_cuda(agent, seq, kw):
    runs = []
    for capture in (False, True):
        ag, buf = _setup(agent, device="cuda", **kw)
        up = Updater(ag, buf, torch.Generator("cuda").manual_seed(7), model_sequence=seq, capture=capture)
        ms = [{k: float(v) for k, v in up.run(4).items()} for _ in range(5)]
        assert up.captured == capture and up.recordings == int(capture)
        runs.append((_params(ag), ms))
    _assert_runs_agree(runs, 1e-5, 1e-6)


@pytest.mark.skipif(not CUDA, reason="needs CUDA")
@pytest.mark.parametrize("agent,seq,kw", [("svg0", None, {}), ("svg1", None, {}), ("svg1", None, {"model_noise": "inferred"})])
def test_compiled_captured_updates_equal_eager_ones_cuda(agent, seq, kw):
    """Inductor's kernels recorded in the Updater's CUDA graph: the eager update's numbers up to
    rounding."""
    runs = []
    for backend in (None, "inductor"):
        ag, buf = _setup(agent, device="cuda", **kw)
        if backend:
            ag.compile_update(backend)
        up = Updater(ag, buf, torch.Generator("cuda").manual_seed(7), model_sequence=seq, capture=True)
        ms = [{k: float(v) for k, v in up.run(4).items()} for _ in range(5)]
        assert up.captured and up.failure is None
        runs.append((_params(ag), ms))
    _assert_runs_agree(runs, 1e-4, 1e-5)


@pytest.mark.skipif(not CUDA, reason="needs CUDA")
def test_captured_update_records_again_after_load_cuda():
    ag, buf = _setup("svg1", device="cuda")
    early = copy.deepcopy(ag.state_dict())      # before any update: a stale graph would go on from later
    up = Updater(ag, buf, torch.Generator("cuda").manual_seed(0))
    up.run(3)
    assert up.captured and up.recordings == 1
    ag.load_state_dict(early)
    ref, _ = _setup("svg1", device="cuda")
    ref.load_state_dict(early)
    ref_up = Updater(ref, buf, torch.Generator("cuda"), capture=False)
    ref_up.generator.set_state(up.generator.get_state())
    up.run(3)                   # one eager update, then a new recording on the loaded tensors
    ref_up.run(3)
    assert up.recordings == 2 and up.captured
    for a, b in zip(_params(ag), _params(ref)):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


@pytest.mark.skipif(not CUDA, reason="needs CUDA")
@pytest.mark.parametrize("agent", ["ddpg", "svg1"])
def test_captured_gn_networks_equal_eager_ones_cuda(agent):
    pytest.importorskip("dm_control")
    from gnwarp.rl.gn_nets import GNObservationModel, make_networks
    from gnwarp.rl.obs_graph import ObservationGraph
    from gnwarp.rl.obs_reward import ObservationReward
    og = ObservationGraph("swimmer6")
    reward_fn = ObservationReward("swimmer6")
    runs = []
    for capture in (False, True):
        torch.manual_seed(0)
        s = AgentSettings(agent=agent, batch_size=16, seed=3)
        policy, q = make_networks("gn", og, gaussian=agent != "ddpg", latent=32)
        model = GNObservationModel(og, 32, (32,), 2).cuda() if agent == "svg1" else None
        ag = make_agent(s, og.obs_size, [-1] * og.nu, [1] * og.nu, model=model,
                        reward=(lambda x, a, x2: reward_fn(x, a, x2).to(x.dtype)) if model else None,
                        policy=policy, q=q, device="cuda")
        buf = ReplayBuffer(200, og.obs_size, og.nu, num_envs=2, device="cuda")
        g = torch.Generator("cuda").manual_seed(1)
        for _ in range(20):
            x = torch.randn(2, og.obs_size, device="cuda", generator=g)
            a = torch.rand(2, og.nu, device="cuda", generator=g) * 2 - 1
            buf.add(x, a, torch.randn(2, device="cuda", generator=g), x + 0.05 * torch.randn_like(x),
                    torch.zeros(2, dtype=torch.bool), torch.zeros(2, dtype=torch.bool))
        up = Updater(ag, buf, torch.Generator("cuda").manual_seed(7), capture=capture)
        ms = [{k: float(v) for k, v in up.run(3).items()} for _ in range(4)]
        assert up.captured == capture
        runs.append((_params(ag), ms))
    (p0, m0), (p1, m1) = runs
    for a, b in zip(p0, p1):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)
    for a, b in zip(m0, m1):
        assert all(abs(a[k] - b[k]) <= 1e-4 * (1 + abs(a[k])) for k in a)


def test_failed_recording_warns_and_updates_eagerly(monkeypatch):
    import gnwarp.interop

    class FailingGraphed:        # gnwarp.interop.Graphed whose recording fails (here on the CPU)
        def __init__(self, fn, warmup=1):
            self.fn, self.warmup, self.graph = fn, warmup, None

        def __call__(self):
            if self.warmup > 0:
                self.warmup -= 1
                return self.fn()
            raise RuntimeError("operation not permitted when stream is capturing\nmore")
    monkeypatch.setattr(gnwarp.interop, "Graphed", FailingGraphed)
    ag, buf = _setup("svg1")
    ref, ref_buf = copy.deepcopy(ag), copy.deepcopy(buf)
    up = Updater(ag, buf, torch.Generator().manual_seed(7))
    up.capture = True                       # as on CUDA
    with pytest.warns(RuntimeWarning, match="could not be recorded.*not permitted when stream is capturing"):
        up.run(4)
    assert not up.capture and not up.captured and up.failure.startswith("RuntimeError: operation not permitted")
    assert up.recordings == 0 and not any(g["capturable"] for o in ag.optimizers() for g in o.param_groups)
    Updater(ref, ref_buf, torch.Generator().manual_seed(7)).run(4)   # the same draws, all eager
    assert ag.updates == 4 and all(torch.equal(a, b) for a, b in zip(_params(ag), _params(ref)))


def test_backward_compiled_now_is_a_no_op_on_a_torch_without_the_setting(monkeypatch):
    """A torch without ``force_non_lazy_backward_lowering``: the compiling call's context enters
    and exits without error (patch() raises only on entry, so the check must come first)."""
    import torch._functorch.config as functorch_config

    from gnwarp.rl.agents import _backward_compiled_now
    with _backward_compiled_now():
        assert functorch_config.force_non_lazy_backward_lowering is True
    monkeypatch.delattr(functorch_config, "force_non_lazy_backward_lowering")
    with _backward_compiled_now():
        pass
