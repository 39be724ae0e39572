"""The fused model step (``gnwarp.models.fused_step``) against the torch step it replaces: encode,
decode, one step and its vector-Jacobian product, rollout engines and a planner (CPU, float64)."""
import copy

import numpy as np
import pytest
import torch

from gnwarp import data
from gnwarp.control import GradientMPC, GradientMPCConfig
from gnwarp.data.convert import static_arrays
from gnwarp.gn import RunOptions, blas_block
from gnwarp.gn.rules import TUNABLES, choose_fused
from gnwarp.models import ForwardModel, GNCoreConfig, MLPForwardModel, ModelConfig
from gnwarp.models import fused_step
from gnwarp.models.fused_step import BatchCore, FusedStep
from gnwarp.models.normalizer import normalize_graph
from gnwarp.sim.systems import make
from gnwarp.state import DYN_NODE_SIZE, apply_delta

TINY = GNCoreConfig(latent=8, edge_hidden=(16,), node_hidden=(16,), global_hidden=(16,))
F64 = torch.float64


@pytest.fixture(scope="module")
def pendulum():
    return data.generate("pendulum", (6, 1, 2), num_steps=8, seed=0, backend="mujoco", progress=False)


@pytest.fixture(scope="module")
def cheetah():
    return data.generate("cheetah", (3, 1, 2), num_steps=6, seed=0, backend="mujoco", progress=False)


def warm(m, ds):
    """Normalizer statistics from ``ds`` (inputs O(1), no vanishing std), as training sets them,
    on the model's device (the loss launches Warp kernels there)."""
    sp = ds["train"]
    S, T = sp.ctrl.shape[:2]
    dev = m.builder.s_nodes.device
    body = torch.as_tensor(sp.body[:, :T]).reshape(S * T, *sp.body.shape[2:])
    nxt = torch.as_tensor(sp.body[:, 1:]).reshape(S * T, -1, DYN_NODE_SIZE)
    g = m.builder(torch.as_tensor(np.repeat(sp.instance, T)), body, torch.as_tensor(sp.ctrl).reshape(S * T, -1))
    with torch.no_grad():
        m.loss(g, nxt.reshape(-1, DYN_NODE_SIZE).to(dev, m.dtype), noise_std=0.01, accumulate=True,
               generator=torch.Generator(device=dev).manual_seed(0))
    return m


def tiny_model(ds, recenter=True, impl="torch", dtype=F64, seed=0, device="cpu"):
    """A small model bound to ``ds`` on ``device``, its normalizers set there (a CUDA model never
    launches a CPU Warp kernel: the GPU machine has no CPU compiler)."""
    torch.manual_seed(seed)
    m = ForwardModel(ModelConfig(gn=TINY, run=RunOptions(impl=impl), recenter=recenter), ds.layout)
    m.to(device=device, dtype=dtype).bind(ds)
    return warm(m, ds)


def case(ds, N=3, dtype=F64, **kw):
    m = tiny_model(ds, dtype=dtype, **kw)
    sp = ds["test"]
    tm = m.template(torch.as_tensor(sp.instance[:N]))
    x = torch.as_tensor(sp.body[:N, 0], dtype=dtype)
    x[:, 1:, :2] += torch.tensor([0.5, -0.3], dtype=dtype)  # moved in x, y: the re-centring has work to do
    u = torch.as_tensor(sp.ctrl[:N, 0], dtype=dtype) * 1.3   # a little outside the data's controls
    return m, tm, x, u


def torch_step(m, tm, x, u):
    return tm.to_body(m.next_nodes(tm.graph(x, u)), x)


@pytest.mark.parametrize("system", ["pendulum", "cheetah"])
@pytest.mark.parametrize("recenter", [False, True])
def test_encode_and_decode_equal_the_torch_step(system, recenter, request):
    """encode = the normalized input graph of ``next_nodes`` (re-centred dynamic part, control
    slots, statistics); decode = its de-normalization, quaternion update and world body."""
    m, tm, x, u = case(request.getfixturevalue(system), recenter=recenter)
    fs = FusedStep(m, tm)
    assert isinstance(fs.core, BatchCore)
    stats = fs.stats()
    nodes, edges, glob = fs.encode(x[:, None], 0, u[:, None], 0, stats)
    g = tm.graph(x, u)
    ctx = m.context(g)
    dyn_c, off = m._recenter(g.nodes[:, -DYN_NODE_SIZE:], ctx)
    assert (off is not None) == recenter and (not recenter or off.abs().max() > 0)
    ref = normalize_graph(m._with_dynamic(g, dyn_c), ctx.stats)
    torch.testing.assert_close(nodes, ref.nodes, rtol=0, atol=1e-13)
    torch.testing.assert_close(edges, ref.edges, rtol=0, atol=1e-13)
    torch.testing.assert_close(glob, ref.globals, rtol=0, atol=1e-13)
    # decode of an arbitrary normalized change (rotations included) as next_nodes post-processes it
    delta_n = torch.randn(tm.N * tm.B, DYN_NODE_SIZE, dtype=F64, generator=torch.Generator().manual_seed(1))
    mean, std = ctx.stats["delta"]
    nxt = apply_delta(dyn_c, delta_n * std + mean) + (off if off is not None else 0)
    want = tm.to_body(torch.where(ctx.movable[:, None], nxt, g.nodes[:, -DYN_NODE_SIZE:]), x)
    got = torch.empty_like(x)
    fs.decode(delta_n, x[:, None], 0, stats, got[:, None], 0)
    torch.testing.assert_close(got, want, rtol=1e-13, atol=1e-13)
    assert torch.equal(got[:, 0], x[:, 0]) and not torch.allclose(got[:, 1:], x[:, 1:])


@pytest.mark.parametrize("system,impl", [("pendulum", "torch"), ("cheetah", "torch"), ("pendulum", "warp")])
@pytest.mark.parametrize("recenter", [False, True])
def test_step_and_vjp_equal_torch_autograd(system, impl, recenter, request):
    """``FusedStep.step`` equals the torch step, and its backward and ``vjp`` equal torch
    autograd of the torch step, in float64; the parameters get no gradient."""
    m, tm, x, u = case(request.getfixturevalue(system), recenter=recenter, impl=impl)
    fs = FusedStep(m, tm)
    ref = torch_step(m, tm, x, u)
    torch.testing.assert_close(fs.step(x, u), ref, rtol=1e-12, atol=1e-12)
    w = torch.randn(x.shape, dtype=F64, generator=torch.Generator().manual_seed(2))
    xa, ua = x.clone().requires_grad_(), u.clone().requires_grad_()
    gx, gu = torch.autograd.grad((torch_step(m, tm, xa, ua) * w).sum(), (xa, ua))
    assert gu.abs().max() > 0 and gx[:, 1:].abs().max() > 0
    fx, fu = fs.vjp(x, u, w)
    torch.testing.assert_close(fx, gx, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(fu, gu, rtol=1e-10, atol=1e-12)
    xb, ub = x.clone().requires_grad_(), u.clone().requires_grad_()
    (fs.step(xb, ub) * w).sum().backward()
    torch.testing.assert_close(xb.grad, gx, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(ub.grad, gu, rtol=1e-10, atol=1e-12)
    assert all(p.grad is None for p in m.parameters())


def test_float32_step_is_close_to_float64(cheetah):
    """In float32 the fused step stays within float32 rounding of the float64 torch step."""
    m64, tm64, x, u = case(cheetah)
    m32 = copy.deepcopy(m64).float().bind(cheetah)
    tm32 = m32.template(tm64.instance)
    got = FusedStep(m32, tm32).step(x.float(), u.float())
    assert got.dtype == torch.float32
    torch.testing.assert_close(got.double(), torch_step(m64, tm64, x, u), rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("system,recenter", [("pendulum", True), ("cheetah", True), ("cheetah", False)])
def test_fused_engine_equals_the_unfused_engine(system, recenter, request):
    """A fused ``RolloutEngine``'s rollouts and gradients w.r.t. x0 and controls equal the unfused
    engine's (float64, horizon 5), call after call."""
    ds = request.getfixturevalue(system)
    m = tiny_model(ds, recenter=recenter)
    sp, N, T = ds["test"], 2, 5
    inst = np.asarray(sp.instance[:N])
    plain, fused = m.rollout_engine(inst, T, fused=False), m.rollout_engine(inst, T, fused=True)
    assert not plain.fused and fused.fused and fused.store is not None
    assert plain.fused_step is None and isinstance(fused.fused_step, FusedStep)
    assert not m.rollout_engine(inst, T).fused          # automatic: the CPU keeps the unfused step
    x0 = torch.as_tensor(sp.body[:N, 0], dtype=F64)
    u = torch.as_tensor(sp.ctrl[:N, :T], dtype=F64)
    for k in range(2):
        out = []
        for e in (plain, fused):
            xa, ua = (x0 * (1 + 0.01 * k)).requires_grad_(), (u * (1 - 0.2 * k)).requires_grad_()
            traj = e.rollout(xa, ua)
            w = torch.linspace(-1, 2, traj.numel(), dtype=F64).reshape(traj.shape)
            (torch.sin(traj) * w).sum().backward()
            out.append((traj, xa.grad, ua.grad))
        for a, b in zip(*out):
            torch.testing.assert_close(b, a, rtol=1e-10, atol=1e-12)
        assert out[1][2].abs().max() > 0
    with torch.no_grad():
        torch.testing.assert_close(fused.rollout(x0, u), plain.rollout(x0, u), rtol=1e-12, atol=1e-12)


def _fwd_bwd(engine, x0, u, k):
    """(states, dL/dx0, dL/du) of one rollout of ``engine`` and a fixed loss on all states."""
    xa, ua = (x0 * (1 + 0.01 * k)).requires_grad_(), (u * (1 - 0.2 * k)).requires_grad_()
    traj = engine.rollout(xa, ua)
    w = torch.linspace(-1, 2, traj.numel(), dtype=traj.dtype).reshape(traj.shape)
    (torch.sin(traj) * w).sum().backward()
    return traj, xa.grad, ua.grad


@pytest.mark.parametrize("system", ["pendulum", "cheetah"])
def test_fused_engine_replays_its_forward_recording(system, request, monkeypatch):
    """A fused engine with an activation store records its forward's GN blocks and its backward
    replays them (no block forward reruns): rollouts and gradients equal the fused engine's
    without a store bit for bit and the unfused engine's to rounding (float64, Warp blocks). A
    backward after another forward recomputes: it replays no stale recording."""
    ds = request.getfixturevalue(system)
    m = tiny_model(ds, impl="warp")
    sp, N, T = ds["test"], 2, 4
    inst = np.asarray(sp.instance[:N])
    plain = m.rollout_engine(inst, T, fused=False, store=True)
    bare, stored = (m.rollout_engine(inst, T, fused=True, store=s) for s in (False, True))
    assert bare.store is None and stored.store is not None and stored.fused
    replays = []
    real = blas_block._replay
    monkeypatch.setattr(blas_block, "_replay", lambda *a: replays.append(1) or real(*a))
    x0 = torch.as_tensor(sp.body[:N, 0], dtype=F64)
    u = torch.as_tensor(sp.ctrl[:N, :T], dtype=F64)
    for k in range(2):
        ref, want = _fwd_bwd(plain, x0, u, k), _fwd_bwd(bare, x0, u, k)
        replays.clear()
        got = _fwd_bwd(stored, x0, u, k)
        assert len(replays) == 2 * T and stored.store.generation == k + 1   # both blocks of every step
        for a, b, c in zip(ref, want, got):
            assert torch.equal(c, b) and c.abs().max() > 0
            torch.testing.assert_close(c, a, rtol=1e-10, atol=1e-12)
    # two forwards, then the first's backward: the store holds the second's, so it recomputes
    xa, ua = x0.clone().requires_grad_(), (u * 0.5).requires_grad_()
    first = stored.rollout(xa, ua)
    second = stored.rollout(x0 * 1.1, u.clone().requires_grad_())
    replays.clear()
    first.square().sum().backward()
    assert not replays
    xb, ub = x0.clone().requires_grad_(), (u * 0.5).requires_grad_()
    bare.rollout(xb, ub).square().sum().backward()
    assert torch.equal(xa.grad, xb.grad) and torch.equal(ua.grad, ub.grad) and ua.grad.abs().max() > 0
    second.sum().backward()   # its own recording: replayed
    assert len(replays) == 2 * T
    # over budget: dropped at the first recording, and the engine recomputes
    tight = m.rollout_engine(inst, T, fused=True, store_bytes=0)
    replays.clear()
    for a, b in zip(_fwd_bwd(tight, x0, u, 0), _fwd_bwd(bare, x0, u, 0)):
        assert torch.equal(a, b)
    assert tight.store is None and not replays


def test_unsupported_cases_fall_back_or_raise(pendulum, monkeypatch):
    """An MLP core and graphs of several sizes are not fused: ``fused=None`` falls back quietly,
    ``fused=True`` raises naming the reason; the automatic rule fuses small CUDA batches only."""
    sp = pendulum["test"]
    mlp = MLPForwardModel(pendulum.layout, n_node=2, n_edge=int(pendulum.static["n_edge"][0])).double().bind(pendulum)
    assert "MLPCore" in FusedStep.unsupported(mlp, mlp.template(torch.zeros(2, dtype=torch.int64)))
    assert "not a ForwardModel" in FusedStep.unsupported(object(), mlp.template(torch.zeros(2, dtype=torch.int64)))
    assert not mlp.rollout_engine([0, 0], 3).fused and not mlp.rollout_engine([0, 0], 3, fused=None).fused
    with pytest.raises(ValueError, match="fused=True.*MLPCore"):
        mlp.rollout_engine([0, 0], 3, fused=True)
    # swimmers of 3 and 4 links bound together: padded graphs of two sizes
    swimmers = [make("swimmer3"), make("swimmer4")]
    _, layout, _ = static_arrays(swimmers)
    m = ForwardModel(ModelConfig(gn=TINY), layout).double().bind(swimmers)
    assert "differ in size" in FusedStep.unsupported(m, m.template(torch.tensor([0, 1])))
    assert not m.rollout_engine([0, 1], 3).fused
    with pytest.raises(ValueError, match="differ in size"):
        m.rollout_engine([0, 1], 3, fused=True)
    with pytest.raises(ValueError, match="fused must be"):
        tiny_model(pendulum).rollout_engine([0], 3, fused="yes")
    # where the rule picks the fused step (a small CUDA batch), what cannot run it falls back quietly
    monkeypatch.setattr(fused_step, "choose_fused", lambda n, device: True)
    assert not mlp.rollout_engine([0, 0], 3).fused and not m.rollout_engine([0, 1], 3).fused
    assert tiny_model(pendulum).rollout_engine([0, 0], 3).fused
    monkeypatch.undo()
    assert not choose_fused(1, "cpu") and choose_fused(1, "cuda")
    assert not choose_fused(TUNABLES.fused_step_max_graphs + 1, torch.device("cuda"))
    with pytest.raises(ValueError, match="body must be"):
        FusedStep(tiny_model(pendulum), tiny_model(pendulum).template(torch.zeros(2, dtype=torch.int64))).step(
            torch.as_tensor(sp.body[:2, 0, :1]), torch.as_tensor(sp.ctrl[:2, 0]))


def test_gradient_mpc_plans_the_same_fused(pendulum):
    """GradientMPC with ``fused=True`` plans what it plans with ``fused=False`` (float64)."""
    m = tiny_model(pendulum)
    x = torch.as_tensor(pendulum["test"].body[:2, 0], dtype=F64)
    plans = []
    for fused in (False, True):
        cfg = GradientMPCConfig(horizon=6, iterations=2, warmup=3, lr=0.05, fused=fused)
        p = GradientMPC(m, "pendulum-balance", "pendulum", n=2, config=cfg)
        assert p.engine.fused == fused
        p.step(x)
        p.step(x)
        plans.append(p.plan)
    assert not torch.equal(plans[0], torch.zeros_like(plans[0]))
    torch.testing.assert_close(plans[1], plans[0], rtol=1e-9, atol=1e-10)


@pytest.fixture
def no_cpu_warp(monkeypatch):
    """Fails a test at its first Warp launch on the CPU (a CUDA test launches none: Warp on the
    GPU machine has no CPU compiler)."""
    import warp as wp

    def guard(launch):
        def guarded(kernel, *args, **kw):
            if wp.get_device(kw.get("device")).is_cpu:
                raise AssertionError(f"a CUDA test launched Warp kernel {kernel.key} on the CPU")
            return launch(kernel, *args, **kw)
        return guarded
    monkeypatch.setattr(wp, "launch", guard(wp.launch))
    monkeypatch.setattr(wp, "launch_tiled", guard(wp.launch_tiled))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-10), (torch.float32, 2e-4)])
def test_cuda_fused_engine_replays(cheetah, dtype, tol, no_cpu_warp):
    """On CUDA a small batch runs fused by itself; its forward and backward replay CUDA graphs and
    agree with the unfused engine's, call after call."""
    m = tiny_model(cheetah, impl="warp", dtype=dtype, device="cuda")
    sp, N, T = cheetah["test"], 2, 6
    inst = np.asarray(sp.instance[:N])
    plain, fused = m.rollout_engine(inst, T, fused=False), m.rollout_engine(inst, T)
    assert fused.fused and not plain.fused
    x0 = torch.as_tensor(sp.body[:N, 0], dtype=dtype, device="cuda")
    u = torch.as_tensor(sp.ctrl[:N, :T], dtype=dtype, device="cuda")
    for k in range(4):
        out = []
        for e in (plain, fused):
            xa, ua = (x0 * (1 + 0.01 * k)).requires_grad_(), (u * (1 - 0.2 * k)).requires_grad_()
            traj = e.rollout(xa, ua)
            w = torch.linspace(-1, 2, traj.numel(), dtype=dtype, device="cuda").reshape(traj.shape)
            (torch.sin(traj) * w).sum().backward()
            out.append((traj, xa.grad, ua.grad))
        for a, b in zip(*out):
            torch.testing.assert_close(b, a, rtol=tol, atol=tol)
    # a backward follows each forward: the recording forward's and the replaying backward's graphs
    assert fused.store is not None
    assert fused._fwd_rec.graph is not None and fused._bwd_rep.graph is not None
    quiet = m.rollout_engine(inst, T, check=False)   # no input checks: then no host sync at all

    def run():
        ua = u.clone().requires_grad_()
        quiet.rollout(x0, ua).square().sum().backward()
        return ua.grad
    for _ in range(2):   # eager, then recorded
        run()
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        g = run()
    finally:
        torch.cuda.set_sync_debug_mode(0)
    assert quiet.fused and torch.isfinite(g).all()
