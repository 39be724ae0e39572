"""The forward model: quaternions, normalizers, state update, loss, rollouts (CPU)."""
import math

import numpy as np
import pytest
import torch

from gnwarp import data
from gnwarp.data.builder import GraphTemplate
from gnwarp.data.layout import LayoutMismatchError
from gnwarp.gn import RunOptions
from gnwarp.interop import vjp, warp
from gnwarp.models import ForwardModel, GNCoreConfig, MLPForwardModel, ModelConfig, Normalizer
from gnwarp.state import DYN_NODE_SIZE, apply_delta, quat_mul, quat_normalize, rotation_loss, state_delta

warp()  # initialize Warp quietly

TINY = GNCoreConfig(latent=8, edge_hidden=(16,), node_hidden=(16,), global_hidden=(16,))


@pytest.fixture(scope="module")
def pendulum():
    return data.generate("pendulum", (6, 2, 2), num_steps=12, seed=0, backend="mujoco", progress=False)


@pytest.fixture(scope="module")
def swimmer():
    return data.generate("swimmer3", (4, 1, 1), num_steps=8, seed=1, backend="mujoco", progress=False)


def tiny_model(ds, impl="torch", dtype=torch.float64, recenter=False, seed=0, warm=True, device="cpu"):
    torch.manual_seed(seed)
    m = ForwardModel(ModelConfig(gn=TINY, run=RunOptions(impl=impl), recenter=recenter), ds.layout)
    m.to(device=device, dtype=dtype).bind(ds)
    if warm:  # normalizer statistics from the data, so inputs are O(1)
        sp = ds["train"]
        S, T = sp.ctrl.shape[:2]
        body = torch.as_tensor(sp.body[:, :T]).reshape(S * T, *sp.body.shape[2:])
        nxt = torch.as_tensor(sp.body[:, 1:]).reshape(S * T, *sp.body.shape[2:])
        ctrl = torch.as_tensor(sp.ctrl).reshape(S * T, -1)
        inst = torch.as_tensor(np.repeat(sp.instance, T))
        g = m.builder(inst, body, ctrl)
        b = m.builder
        target = nxt.reshape(-1, DYN_NODE_SIZE) if b.uniform else nxt[b.node_mask[inst]]
        with torch.no_grad():  # with training noise, as in train(): no feature has a vanishing std
            m.loss(g, target.to(device, dtype), noise_std=0.01, accumulate=True,
                   generator=torch.Generator(device=device).manual_seed(0))
    return m


# -- quaternions ----------------------------------------------------------------------------------

def _axis_angle(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return torch.tensor(np.r_[math.cos(angle / 2), math.sin(angle / 2) * axis], dtype=torch.float64)


def test_hamilton_product_hand_cases():
    one, i, j, k = torch.eye(4, dtype=torch.float64)
    assert torch.equal(quat_mul(i, j), k)          # ij = k
    assert torch.equal(quat_mul(j, i), -k)         # ji = -k
    assert torch.equal(quat_mul(i, i), -one)       # i^2 = -1
    assert torch.equal(quat_mul(one, j), j)
    q = torch.tensor([1.0, 2.0, 3.0, 4.0], dtype=torch.float64)
    p = torch.tensor([5.0, 6.0, 7.0, 8.0], dtype=torch.float64)
    # (1 + 2i + 3j + 4k)(5 + 6i + 7j + 8k), worked out by hand
    assert torch.equal(quat_mul(q, p), torch.tensor([-60.0, 12.0, 30.0, 24.0], dtype=torch.float64))
    # two quarter turns about z make a half turn
    qz = _axis_angle([0, 0, 1], math.pi / 2)
    torch.testing.assert_close(quat_mul(qz, qz), _axis_angle([0, 0, 1], math.pi))


def _state(q, pos=(0.0, 0.0, 0.0), lin=(0.0, 0.0, 0.0), ang=(0.0, 0.0, 0.0)):
    return torch.cat([torch.tensor(pos, dtype=torch.float64), q, torch.tensor(lin, dtype=torch.float64),
                      torch.tensor(ang, dtype=torch.float64)])


def test_state_delta_and_update_hand_case():
    q0 = _axis_angle([0, 0, 1], math.pi / 2)        # 90 degrees about z
    q1 = _axis_angle([0, 0, 1], math.pi)            # 180 degrees about z
    x0 = _state(q0, (1.0, 2.0, 3.0), (0.5, 0, 0), (0, 0, 1.0))
    x1 = _state(q1, (1.5, 2.0, 2.0), (0.0, 1.0, 0), (0, 0, 3.0))
    d = state_delta(x0, x1)
    torch.testing.assert_close(d[0:3], torch.tensor([0.5, 0.0, -1.0], dtype=torch.float64))
    torch.testing.assert_close(d[3:7], _axis_angle([0, 0, 1], math.pi / 2))  # the rotation in between
    torch.testing.assert_close(d[7:10], torch.tensor([-0.5, 1.0, 0.0], dtype=torch.float64))
    torch.testing.assert_close(d[10:13], torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64))
    # the update inverts the change; the rotation is forced to unit norm (scaling it changes nothing)
    torch.testing.assert_close(apply_delta(x0, d), x1)
    d2 = d.clone()
    d2[3:7] *= 3.7
    torch.testing.assert_close(apply_delta(x0, d2), x1)
    # a delta written with -dq is the same rotation
    d3 = d.clone()
    d3[3:7] *= -1
    x1b = apply_delta(x0, d3)
    torch.testing.assert_close(torch.abs(x1b[3:7]), torch.abs(x1[3:7]))
    # the rotation is applied in the world frame: dq (x) q
    qa, qb = _axis_angle([1, 0, 0], 0.3), _axis_angle([0, 1, 0], 0.4)
    x = _state(qa)
    dd = torch.cat([torch.zeros(3, dtype=torch.float64), qb, torch.zeros(6, dtype=torch.float64)])
    torch.testing.assert_close(apply_delta(x, dd)[3:7], quat_mul(qb, qa))


def test_state_delta_round_trip_random():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(50, 13, generator=g, dtype=torch.float64)
    y = torch.randn(50, 13, generator=g, dtype=torch.float64)
    x[:, 3:7] = quat_normalize(x[:, 3:7])
    y[:, 3:7] = quat_normalize(y[:, 3:7])
    d = state_delta(x, y)
    assert (d[:, 3] >= 0).all()  # canonical sign
    z = apply_delta(x, d)
    torch.testing.assert_close(z[:, [0, 1, 2, 7, 8, 9, 10, 11, 12]], y[:, [0, 1, 2, 7, 8, 9, 10, 11, 12]])
    s = torch.sign((z[:, 3:7] * y[:, 3:7]).sum(-1, keepdim=True))
    torch.testing.assert_close(z[:, 3:7] * s, y[:, 3:7])


def test_rotation_loss_hand_cases():
    q = _axis_angle([0.3, -1.0, 0.2], 0.7)
    assert float(rotation_loss(q, q)) == pytest.approx(0.0, abs=1e-15)
    assert float(rotation_loss(q, -q)) == pytest.approx(0.0, abs=1e-15)   # q and -q: same rotation
    # rotations 90 degrees apart: q_e . q_p = cos(45 deg), loss = 1 - 1/2
    a, b = _axis_angle([0, 0, 1], 0.0), _axis_angle([0, 0, 1], math.pi / 2)
    assert float(rotation_loss(a, b)) == pytest.approx(0.5, abs=1e-12)
    # 180 degrees apart: orthogonal quaternions, the largest loss
    assert float(rotation_loss(a, _axis_angle([1, 0, 0], math.pi))) == pytest.approx(1.0, abs=1e-12)
    # small angles: sin^2(theta / 2)
    th = 1e-2
    assert float(rotation_loss(a, _axis_angle([0, 1, 0], th))) == pytest.approx(math.sin(th / 2) ** 2, rel=1e-6)


# -- normalizer --------------------------------------------------------------------------------------

def test_normalizer_statistics_match_numpy():
    rng = np.random.default_rng(0)
    chunks = [rng.normal([1.0, -2.0, 5.0, 3.0], [0.5, 2.0, 1e-7, 1.0], (n, 4)) for n in (7, 30, 1)]
    for c in chunks:
        c[:, 3] = 3.0                          # a constant column
    weights = [None, (rng.random(30) > 0.5).astype(float), None]
    n = Normalizer(4, std_floor=1e-3)
    m0, s0 = n.mean_std(torch.float64)         # identity before any data
    assert torch.equal(m0, torch.zeros(4, dtype=torch.float64)) and torch.equal(s0, torch.ones(4, dtype=torch.float64))
    for c, w in zip(chunks, weights):
        n.accumulate(torch.as_tensor(c, dtype=torch.float32 if w is None else torch.float64),
                     None if w is None else torch.as_tensor(w))
    rows = np.concatenate([chunks[0].astype(np.float32).astype(np.float64), chunks[1][weights[1] > 0],
                           chunks[2].astype(np.float32).astype(np.float64)])
    m, s = n.mean_std(torch.float64)
    assert float(n.count) == rows.shape[0]
    np.testing.assert_allclose(m.numpy(), rows.mean(0), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(s.numpy()[:2], rows.std(0)[:2], rtol=1e-8)
    assert s[2] == pytest.approx(1e-3) and s[3] == pytest.approx(1e-3)   # floored
    # accumulators stay float64 when the module is cast, and travel in the state dict
    n.to(torch.float32)
    assert n.sum.dtype == torch.float64 and n.count.dtype == torch.float64
    n2 = Normalizer(4, std_floor=1e-3)
    n2.load_state_dict(n.state_dict())
    torch.testing.assert_close(n2.mean_std(torch.float64)[0], m)
    assert set(n.state_dict()) == {"count", "sum", "sumsq"}


# -- the model ----------------------------------------------------------------------------------------

def test_loss_hand_case(pendulum):
    m = tiny_model(pendulum)
    sp = pendulum["train"]
    body = torch.as_tensor(sp.body[:3, 4], dtype=torch.float64)
    nxt = torch.as_tensor(sp.body[:3, 5], dtype=torch.float64)
    g = m.builder(torch.zeros(3, dtype=torch.long), body, torch.as_tensor(sp.ctrl[:3, 4]))
    target = nxt.reshape(-1, 13)
    delta = state_delta(body.reshape(-1, 13), target)
    mean, std = m.norm_delta.mean_std(torch.float64)

    class Oracle(torch.nn.Module):  # a core predicting exactly the normalized true change
        def __init__(self, out):
            super().__init__()
            self.out = out
            self.w = torch.nn.Parameter(torch.zeros((), dtype=torch.float64))

        def graph_index(self, graph):
            return None

        def forward(self, graph, index=None):
            return self.out + self.w

    def loss(*a, **k):
        return {n: v.detach() for n, v in m.loss(*a, **k).items()}

    m.core = Oracle((delta - mean) / std)
    terms = loss(g, target)
    for k in ("pos", "quat", "linvel", "angvel", "loss"):
        assert float(terms[k]) == pytest.approx(0.0, abs=1e-12), k
    # the oracle's one-step prediction is the true next state, world body included
    torch.testing.assert_close(m.next_nodes(g), target)
    # off by 1 in the normalized x-velocity of each pendulum body (not the world): L2 term = 1
    out = (delta - mean) / std
    out[1::2, 7] += 1.0
    m.core = Oracle(out)
    terms = loss(g, target)
    assert float(terms["linvel"]) == pytest.approx(1.0, rel=1e-9)
    assert float(terms["pos"]) == pytest.approx(0.0, abs=1e-12)
    # rotation term: the paper's 1 - (q_e . q_p)^2, optionally over the rotation's variance
    q = out.clone()
    q[1::2, 3:7] = (torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64) - mean[3:7]) / std[3:7]
    m.core = Oracle(q)
    expect = rotation_loss(delta[1::2, 3:7], torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)).mean()
    assert float(loss(g, target, rotation_scale="paper")["quat"]) == pytest.approx(float(expect), rel=1e-9)
    norm = float(expect / (std[4:7] ** 2).sum())
    assert float(loss(g, target)["quat"]) == pytest.approx(norm, rel=1e-9)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_fused_loss_matches_torch_reference(dtype):
    """The loss's Warp kernels against its torch formulas: terms and the gradient w.r.t. the
    prediction, both rotation scales, some nodes not moving; finite differences in float64."""
    from gnwarp.models.forward import _FusedLoss, loss_terms
    g = torch.Generator().manual_seed(3)
    n = 29
    pred = torch.randn(n, 13, generator=g, dtype=dtype, requires_grad=True)
    delta = torch.randn(n, 13, generator=g, dtype=dtype)
    delta[:, 3:7] = torch.nn.functional.normalize(delta[:, 3:7], dim=1)
    m, s = 0.1 * torch.randn(13, generator=g, dtype=dtype), torch.rand(13, generator=g, dtype=dtype) + 0.5
    movable = (torch.rand(n, generator=g) > 0.3).to(torch.int32)
    tol = dict(rtol=1e-12, atol=1e-12) if dtype == torch.float64 else dict(rtol=1e-5, atol=1e-6)
    for scale in ("normalized", "paper"):
        got = _FusedLoss.apply(pred, delta, m, s, movable, scale == "normalized")
        ref = loss_terms(pred, delta, m, s, movable.to(dtype), scale)
        torch.testing.assert_close(got, ref, **tol)
        w = torch.randn(5, generator=g, dtype=dtype)
        torch.testing.assert_close(torch.autograd.grad(got, pred, w)[0], torch.autograd.grad(ref, pred, w)[0], **tol)
    if dtype == torch.float64:
        assert torch.autograd.gradcheck(lambda p: _FusedLoss.apply(p, delta, m, s, movable, True), (pred,))
    # no moving node: every term is 0 and so is the gradient (the count is clamped to 1)
    none = torch.zeros(n, dtype=torch.int32)
    got = _FusedLoss.apply(pred, delta, m, s, none, True)
    assert torch.all(got == 0) and torch.all(torch.autograd.grad(got.sum(), pred)[0] == 0)


def test_noise_makes_target_from_noisy_input(pendulum):
    m = tiny_model(pendulum)
    sp = pendulum["train"]
    body = torch.as_tensor(sp.body[:4, 2], dtype=torch.float64)
    g = m.builder(torch.zeros(4, dtype=torch.long), body, torch.as_tensor(sp.ctrl[:4, 2]))
    target = torch.as_tensor(sp.body[:4, 3], dtype=torch.float64).reshape(-1, 13)
    seen = {}
    orig = m.norm_delta.accumulate_stats

    def spy(x, w=None):
        seen["delta"], seen["w"] = x.clone(), w.clone()
        return orig(x, w)
    m.norm_delta.accumulate_stats = spy
    gen = torch.Generator().manual_seed(3)
    m.loss(g, target, noise_std=0.1, accumulate=True, generator=gen)
    clean = state_delta(body.reshape(-1, 13), target)
    d = seen["delta"]
    assert torch.equal(d[0::2], clean[0::2])                       # world: no noise, no change
    assert (d[1::2, 0:3] - clean[1::2, 0:3]).abs().max() > 0.01    # bodies: the target absorbs the noise
    assert torch.equal(seen["w"], torch.tensor([0.0, 1.0] * 4, dtype=torch.float64))


@pytest.mark.parametrize("impl", ["torch", "warp"])
def test_rollout_keeps_world_fixed_and_matches_steps(pendulum, impl):
    m = tiny_model(pendulum, impl=impl, dtype=torch.float32)
    sp = pendulum["test"]
    x0 = torch.as_tensor(sp.body[:, 0])
    u = torch.as_tensor(sp.ctrl[:, :5])
    r = m.rollout(x0, u)
    assert r.shape == (2, 6, 2, 13) and torch.isfinite(r).all()
    assert torch.equal(r[:, :, 0], x0[:, None, 0].expand(-1, 6, -1))   # world body unchanged
    torch.testing.assert_close(r[:, 0], x0)
    # a rollout is the composition of one-step predictions
    x = x0
    for t in range(5):
        x = m.predict(x, u[:, t])
    torch.testing.assert_close(r[:, -1], x, rtol=1e-5, atol=1e-5)
    norms = r[:, :, 1, 3:7].norm(dim=-1)
    torch.testing.assert_close(norms, torch.ones_like(norms))


def test_warp_and_torch_implementations_agree(pendulum):
    a = tiny_model(pendulum, impl="torch", dtype=torch.float32)
    b = tiny_model(pendulum, impl="warp", dtype=torch.float32)
    b.load_state_dict(a.state_dict())
    sp = pendulum["test"]
    x0, u = torch.as_tensor(sp.body[:, 0]), torch.as_tensor(sp.ctrl[:, :8])
    torch.testing.assert_close(a.rollout(x0, u), b.rollout(x0, u), rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("impl", ["torch", "warp"])
def test_rollout_gradients_match_finite_differences(pendulum, impl):
    m = tiny_model(pendulum, impl=impl, dtype=torch.float64)
    sp = pendulum["test"]
    x0 = torch.as_tensor(sp.body[:2, 0], dtype=torch.float64)
    u = torch.as_tensor(sp.ctrl[:2, :3], dtype=torch.float64)

    def f(x1, ctrl):  # the moving body's initial state and the actions
        x = torch.cat([x0[:, :1], x1[:, None]], 1)
        return m.rollout(x, ctrl)[:, 1:, 1].sum(-1)

    assert torch.autograd.gradcheck(f, (x0[:, 1].clone().requires_grad_(), u.clone().requires_grad_()),
                                    eps=1e-6, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("impl", ["torch", "warp"])
def test_adjoint_rollout_gradients_equal_plain_autograd(pendulum, impl):
    """The adjoint loop (states kept, each step recomputed in the backward) gives plain autograd's
    gradients for the initial states, the controls and every parameter, through ``backward`` and
    ``torch.autograd.grad`` alike, and the same forward bit for bit."""
    m = tiny_model(pendulum, impl=impl, dtype=torch.float64)
    sp = pendulum["test"]
    x0 = torch.as_tensor(sp.body[:2, 0], dtype=torch.float64).requires_grad_()
    u = torch.as_tensor(sp.ctrl[:2, :6], dtype=torch.float64).requires_grad_()
    w = torch.linspace(-1, 2, 2 * 7 * x0.shape[1] * 13, dtype=torch.float64).reshape(2, 7, -1, 13)

    def grads(adjoint):
        m.zero_grad()
        for x in (x0, u):
            x.grad = None
        traj = m.rollout(x0, u, adjoint=adjoint)
        (torch.sin(traj) * w).sum().backward()
        return traj.detach(), [x0.grad.clone(), u.grad.clone()] + [p.grad.clone() for p in m.parameters()]
    ta, ga = grads(True)
    tb, gb = grads(False)
    assert torch.equal(ta, tb)
    assert len(ga) == len(gb) and all(b.abs().max() > 0 for b in gb[:2])
    for a, b in zip(ga, gb):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)
    # torch.autograd.grad, controls only (frozen parameters and initial state)
    for p in m.parameters():
        p.requires_grad_(False)
    traj = m.rollout(x0.detach(), u)
    (gu,) = torch.autograd.grad((torch.sin(traj) * w).sum(), u)
    torch.testing.assert_close(gu, gb[1], rtol=1e-10, atol=1e-12)


def test_adjoint_rollout_keeps_no_activations(pendulum, monkeypatch):
    """Memory: with the adjoint loop no GN block keeps activations in the forward of a
    differentiable rollout; the backward recomputes each step once (two blocks a step). Plain
    autograd keeps every step's."""
    from gnwarp.gn import blas_block
    m = tiny_model(pendulum, impl="warp", dtype=torch.float32)
    kept = []
    real = blas_block.BlasBlock.forward

    def spy(ctx, plan, keep, *args):
        kept.append(keep)
        return real(ctx, plan, keep, *args)
    monkeypatch.setattr(blas_block.BlasBlock, "forward", staticmethod(spy))
    sp = pendulum["test"]
    u = torch.as_tensor(sp.ctrl[:2, :5]).requires_grad_()
    traj = m.rollout(torch.as_tensor(sp.body[:2, 0]), u)
    assert sum(kept) == 0 and len(kept) == 2 * 5  # two blocks a step, 5 steps
    traj.sum().backward()
    assert sum(kept) == 2 * 5 and u.grad is not None
    kept.clear()
    m.rollout(torch.as_tensor(sp.body[:2, 0]), u, adjoint=False)
    assert sum(kept) == 2 * 5


def _engine_case(ds, device="cpu", dtype=torch.float64, impl="warp", T=5, N=2):
    m = tiny_model(ds, impl=impl, dtype=dtype, device=device)
    for p in m.parameters():
        p.requires_grad_(False)
    sp = ds["test"]
    x0 = torch.as_tensor(sp.body[:N, 0], dtype=dtype, device=device)
    u = torch.as_tensor(sp.ctrl[:N, :T], dtype=dtype, device=device)
    return m, m.rollout_engine(np.asarray(sp.instance[:N]), T, fused=False), x0, u   # the unfused step and its store


def _engine_agrees(m, engine, x0, u, calls=3, tol=1e-12):
    """The engine's rollouts and their gradients w.r.t. x0 and controls equal model.rollout's, on
    every call (on CUDA: eager, recorded, replayed), for new inputs each time."""
    w = torch.linspace(-1, 2, x0.shape[0] * (u.shape[1] + 1) * x0.shape[1] * 13, dtype=x0.dtype,
                       device=x0.device).reshape(x0.shape[0], u.shape[1] + 1, x0.shape[1], 13)
    for k in range(calls):
        xa, ua = (x0 * (1 + 0.01 * k)).requires_grad_(), (u * (1 - 0.1 * k)).requires_grad_()
        xb, ub = xa.detach().clone().requires_grad_(), ua.detach().clone().requires_grad_()
        a, b = engine.rollout(xa, ua), m.rollout(xb, ub)
        torch.testing.assert_close(a, b, rtol=tol, atol=tol)
        (torch.sin(a) * w).sum().backward()
        (torch.sin(b) * w).sum().backward()
        torch.testing.assert_close(xa.grad, xb.grad, rtol=tol, atol=tol)
        torch.testing.assert_close(ua.grad, ub.grad, rtol=tol, atol=tol)
        assert ua.grad.abs().max() > 0


def test_rollout_engine_matches_model_rollout(pendulum):
    """``RolloutEngine`` (replayed CUDA graphs on CUDA; the same loops run eagerly on the CPU):
    rollouts and gradients equal ``model.rollout``'s; another batch shape is refused."""
    m, engine, x0, u = _engine_case(pendulum)
    _engine_agrees(m, engine, x0, u)
    # the engine's backward computes no weight gradients, and leaves the parameters as they were
    for i, p in enumerate(m.parameters()):
        p.requires_grad_(i % 3 != 1)
    flags = [p.requires_grad for p in m.parameters()]
    xe, ue = x0.clone().requires_grad_(True), u.clone().requires_grad_(True)
    engine.rollout(xe, ue).sum().backward()
    assert ue.grad.abs().max() > 0 and all(p.grad is None for p in m.parameters())
    assert [p.requires_grad for p in m.parameters()] == flags and any(flags)
    with pytest.raises(ValueError, match="rolls out 5 steps"):
        m.rollout_engine([0, 0], 5).rollout(x0, u[:, :4])
    with pytest.raises(ValueError, match="holds x0"):
        engine.rollout(x0[:1], u[:1])
    with torch.no_grad():
        assert torch.equal(engine.rollout(x0, u), m.rollout(x0, u))


def _store_case(ds, device="cpu", dtype=torch.float64, T=5, N=2, **kw):
    torch.manual_seed(1)
    gn = GNCoreConfig(latent=8, edge_hidden=(16, 40), node_hidden=(16,), global_hidden=(16,))
    m = ForwardModel(ModelConfig(gn=gn, run=RunOptions(impl="warp")), ds.layout).to(device=device, dtype=dtype)
    m.bind(ds)
    for p in m.parameters():
        p.requires_grad_(False)
    sp = ds["test"]
    x0 = torch.as_tensor(sp.body[:N, 0], dtype=dtype, device=device)
    u = torch.as_tensor(sp.ctrl[:N, :T], dtype=dtype, device=device)
    inst = np.asarray(sp.instance[:N])
    return m, inst, x0, u


def _grads(engine, x0, u, k=0):
    xa, ua = (x0 * (1 + 0.01 * k)).requires_grad_(), (u * (1 - 0.1 * k)).requires_grad_()
    traj = engine.rollout(xa, ua)
    return traj, (xa, ua)


def _backward(traj, leaves):
    (torch.sin(traj) * torch.linspace(-1, 2, traj.numel(), dtype=traj.dtype, device=traj.device)
     .reshape(traj.shape)).sum().backward()
    return [x.grad for x in leaves]


def test_rollout_engine_store_replays_exactly(pendulum):
    """An engine that records its forward's GN blocks (packed ReLU masks, GN2's nodes) and replays
    them in the backward gives the same rollouts and gradients, bit for bit, as one that
    recomputes the blocks; a backward after another forward, a store over budget and a no-grad
    forward fall back to recomputing (still exact); a replay with parameters that want gradients
    is refused."""
    m, inst, x0, u = _store_case(pendulum)
    plain = m.rollout_engine(inst, 5, store=False)
    stored = m.rollout_engine(inst, 5, store=True)
    assert plain.store is None and stored.store is not None
    for k in range(2):
        ta, la = _grads(plain, x0, u, k)
        tb, lb = _grads(stored, x0, u, k)
        assert torch.equal(ta, tb)
        st = stored.store
        assert st.valid and st.generation == k + 1 and all(len(row) == 2 for row in st.slots)
        assert not st.slots[0][0].outputs and set(st.slots[0][1].outputs) == {"nodes"}
        assert [x.width for x in st.slots[0][0].masks["edge"]] == [16, 40]
        for a, b in zip(_backward(ta, la), _backward(tb, lb)):
            assert torch.equal(a, b) and a.abs().max() > 0
    # two forwards, then the first's backward: the store holds the second's, so it recomputes
    t1, l1 = _grads(stored, x0, u, 3)
    t2, l2 = _grads(stored, x0, u, 4)
    tp, lp = _grads(plain, x0, u, 3)
    for a, b in zip(_backward(t1, l1), _backward(tp, lp)):
        assert torch.equal(a, b)
    # no backward can follow a no-grad forward: nothing is recorded
    gen = stored.store.generation
    with torch.no_grad():
        assert torch.equal(stored.rollout(x0, u), plain.rollout(x0, u))
    assert stored.store.generation == gen
    # over budget: the store is dropped at the first recording, and the engine recomputes
    tight = m.rollout_engine(inst, 5, store="auto", store_bytes=0)
    tt, lt = _grads(tight, x0, u, 0)
    assert tight.store is None
    ta, la = _grads(plain, x0, u, 0)
    for a, b in zip(_backward(tt, lt), _backward(ta, la)):
        assert torch.equal(a, b)
    # a replayed block computes no weight gradients
    step_ctx = m.context(stored.template.graph(x0, u[:, 0]))
    _grads(stored, x0, u, 0)
    p = next(m.parameters())
    p.requires_grad_(True)
    try:
        with pytest.raises(RuntimeError, match="must not require grad"), stored.store.replaying(0):
            stored._step(step_ctx)(x0, u[:, 0])
    finally:
        p.requires_grad_(False)
    with pytest.raises(ValueError, match="store must be"):
        m.rollout_engine(inst, 5, store="yes")
    with pytest.raises(ValueError, match="store_bytes"):
        m.rollout_engine(inst, 5, store_bytes=-1)


def test_rollout_engine_one_step_sizes_the_store(pendulum):
    """``one_step`` makes an eager one-step engine like the engine (same store policy and
    budget); after its forward and backward, ``size_store`` decides the engine's store from that
    step's bytes before the engine records anything: kept within the budget (and the engine's
    rollouts and gradients unchanged), dropped over it, untouched before the one step recorded."""
    m, inst, x0, u = _store_case(pendulum)
    plain = m.rollout_engine(inst, 5, store=False)
    eng = m.rollout_engine(inst, 5, store="auto")
    one = eng.one_step()
    assert one.horizon == 1 and not one.cuda and one.store_policy == "auto" and one.fused == eng.fused
    eng.size_store(one)                       # nothing recorded yet: nothing decided
    assert eng.store is not None and not eng.store.sized
    t1, l1 = _grads(one, x0, u[:, :1], 0)
    _backward(t1, l1)
    need = one.store.step_bytes(0)
    assert need > 0
    eng.size_store(one)
    assert eng.store is not None and eng.store.sized and eng.store.enabled and eng.store.generation == 0
    ta, la = _grads(plain, x0, u, 0)
    tb, lb = _grads(eng, x0, u, 0)
    assert torch.equal(ta, tb) and eng.store.valid
    for a, b in zip(_backward(ta, la), _backward(tb, lb)):
        assert torch.equal(a, b)
    # a budget for four steps of five: dropped before any recording; the engine recomputes
    tight = m.rollout_engine(inst, 5, store="auto", store_bytes=4 * need)
    one = tight.one_step()
    assert one.store_bytes == 4 * need
    _backward(*_grads(one, x0, u[:, :1], 0))
    assert one.store is not None              # one step fits
    tight.size_store(one)
    assert tight.store is None
    tt, lt = _grads(tight, x0, u, 0)
    for a, b in zip(_backward(tt, lt), _backward(*_grads(plain, x0, u, 0))):
        assert torch.equal(a, b)
    # one step over the budget: so is every step
    none = m.rollout_engine(inst, 5, store="auto", store_bytes=need - 1)
    one = none.one_step()
    _backward(*_grads(one, x0, u[:, :1], 0))
    assert one.store is None
    none.size_store(one)
    assert none.store is None
    # decided once: a later one-step engine changes nothing; an engine unlike this one is refused
    assert eng.store.sized and eng.size_store(eng.one_step()) is None and eng.store is not None
    with pytest.raises(ValueError, match="store policy and budget"):
        eng.size_store(m.rollout_engine(inst, 1, store=False))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-10), (torch.float32, 2e-4)])
def test_cuda_rollout_engine_replays(pendulum, dtype, tol):
    """On CUDA the engine's forward and backward replay CUDA graphs and agree with the eager
    model.rollout, call after call."""
    m, engine, x0, u = _engine_case(pendulum, "cuda", dtype)
    _engine_agrees(m, engine, x0, u, calls=4, tol=tol)
    assert engine._fwd_rec.graph is not None and engine._bwd_rep.graph is not None
    assert engine.store.valid and engine.store.generation == 4


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_rollout_engine_store_replays_exactly(pendulum):
    """On CUDA, recording and replaying (both captured) give the gradients of recomputing."""
    m, inst, x0, u = _store_case(pendulum, "cuda", torch.float32, T=6, N=3)
    plain = m.rollout_engine(inst, 6, store=False, fused=False)
    stored = m.rollout_engine(inst, 6, store=True, fused=False)
    for k in range(4):
        ta, la = _grads(plain, x0, u, k)
        tb, lb = _grads(stored, x0, u, k)
        torch.testing.assert_close(ta, tb, rtol=1e-5, atol=1e-6)
        for a, b in zip(_backward(ta, la), _backward(tb, lb)):
            torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)
    assert stored._fwd_rec.graph is not None and stored._bwd_rep.graph is not None and stored._bwd is None


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_adjoint_rollout_memory_is_the_states():
    """Peak memory of a differentiable rollout: with the adjoint loop it grows with the states,
    not with every step's activations (plain autograd)."""
    ds = data.generate("cheetah", (8, 1, 4), num_steps=60, seed=0, backend="mujoco", progress=False)
    m = ForwardModel(ModelConfig(gn=GNCoreConfig(latent=64, edge_hidden=(256, 256), node_hidden=(128,),
                                                 global_hidden=(128,))), ds.layout).cuda().bind(ds)
    sp = ds["train"]
    idx = np.arange(256) % len(sp)
    x0 = torch.as_tensor(sp.body[idx, 0], device="cuda")
    u = torch.as_tensor(sp.ctrl[idx, :60], device="cuda").requires_grad_()
    peaks = {}
    for adjoint in (True, False):
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
        base = torch.cuda.memory_allocated()
        m.rollout(x0, u, adjoint=adjoint).pow(2).sum().backward()
        torch.cuda.synchronize()
        peaks[adjoint] = torch.cuda.max_memory_allocated() - base
        u.grad = None
    assert peaks[True] < 0.25 * peaks[False], peaks


def test_recentering_makes_rollouts_translation_equivariant(swimmer):
    m = tiny_model(swimmer, recenter=True)
    sp = swimmer["test"]
    x0 = torch.as_tensor(sp.body[:, 0], dtype=torch.float64)
    u = torch.as_tensor(sp.ctrl[:, :4], dtype=torch.float64)
    shift = torch.zeros(13, dtype=torch.float64)
    shift[:2] = torch.tensor([3.0, -1.5])
    xs = x0.clone()
    xs[:, 1:] += shift                         # move every body but the world
    a, b = m.rollout(x0, u), m.rollout(xs, u)
    b[:, :, 1:] -= shift
    torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9)
    # without re-centring the prediction depends on where the swimmer is
    m.config.recenter = False
    a, b = m.rollout(x0, u), m.rollout(xs, u)
    b[:, :, 1:] -= shift
    assert (a - b).abs().max() > 1e-6


def test_mixed_graph_sizes_roll_out_like_single_graphs():
    ds = data.generate("swimmer", (3, 1, 1), num_steps=4, seed=2, parameterized=True, backend="mujoco",
                       progress=False)
    n_node = ds.static["n_node"][ds["train"].instance]
    assert len(set(n_node.tolist())) > 1, "want swimmers of different lengths"
    m = tiny_model(ds)
    sp = ds["train"]
    x0 = torch.as_tensor(sp.body[:, 0], dtype=torch.float64)
    x0[:, n_node.max():] = 0
    pad = torch.full_like(x0, 7.0)
    for s in range(3):   # padding rows come back untouched
        pad[s, :n_node[s]] = x0[s, :n_node[s]]
    u = torch.as_tensor(sp.ctrl[:, :3], dtype=torch.float64)
    inst = torch.as_tensor(sp.instance)
    r = m.rollout(pad, u, inst)
    for s in range(3):
        one = m.rollout(pad[s:s + 1], u[s:s + 1], inst[s:s + 1])
        torch.testing.assert_close(r[s:s + 1], one)
        assert (r[s, :, n_node[s]:] == 7.0).all()
    tmpl = GraphTemplate(m.builder, inst)
    assert tmpl.rows is not None and tmpl.n_nodes == int(n_node.sum())


def test_mlp_baseline(pendulum):
    torch.manual_seed(0)
    m = MLPForwardModel(pendulum.layout, n_node=2, n_edge=2, size="3x128").bind(pendulum)
    assert [l.out_features for l in m.core.mlp.layers] == [128, 128, 128, 26]
    sp = pendulum["test"]
    r = m.rollout(torch.as_tensor(sp.body[:, 0]), torch.as_tensor(sp.ctrl[:, :3]))
    assert r.shape == (2, 4, 2, 13) and torch.equal(r[:, :, 0], r[:, :1, 0].expand(-1, 4, -1))
    with pytest.raises(ValueError, match="unknown MLP size"):
        MLPForwardModel(pendulum.layout, 2, 2, size="4x100")


def test_data_with_another_layout_is_refused(pendulum):
    m = tiny_model(pendulum, warm=False)
    cart = data.generate("cartpole", (2, 1, 1), num_steps=3, seed=0, backend="mujoco", progress=False)
    with pytest.raises(LayoutMismatchError, match="timestep"):
        m.bind(cart)   # a pendulum model has never seen a 10 ms timestep
    # a column the model reads that the data does not have at all
    lay = pendulum.layout
    bad = data.Dataset(dict(pendulum.meta), pendulum.static, pendulum.splits)
    d = lay.to_dict()
    d["node_names"] = [n for n in d["node_names"] if n != "body_mass"]
    d["dropped"] = {k: {n: v for n, v in c.items() if n != "body_mass"} for k, c in d["dropped"].items()}
    bad.meta["layout"] = d
    bad.static = {**pendulum.static, "nodes": np.asarray(pendulum.static["nodes"])[..., 1:]}
    with pytest.raises(LayoutMismatchError, match="body_mass"):
        m.bind(bad)
    # a system object binds directly (planning without a dataset)
    from gnwarp.sim import systems
    m.bind(systems.make("pendulum"))
    assert m.rollout(torch.as_tensor(pendulum["test"].body[:1, 0], dtype=torch.float64),
                     torch.zeros(1, 2, 1, dtype=torch.float64)).shape == (1, 3, 2, 13)


# -- the core's wiring (Figure H.2 ablation) ----------------------------------------------------

H2_WIRINGS = [dict(blocks=1), dict(skip=False), dict(gn1_globals=False), dict(gn1_globals=False, skip=False),
              dict(gn1_nodes=False), dict(gn1_edges=False, skip=False)]


@pytest.mark.parametrize("wiring", H2_WIRINGS, ids=lambda w: ",".join(f"{k}={v}" for k, v in w.items()))
def test_core_wirings_match_reference_and_weight_count(swimmer, wiring):
    """Each H.2 variant: the Warp implementation equals the torch reference, the parameter count is
    what ``weight_count`` predicts from the config, and the variant differs from the default core
    (its switch is used)."""
    import dataclasses

    from gnwarp.models.config import weight_count
    from gnwarp.models.forward import input_sizes
    gn = dataclasses.replace(TINY, **wiring)
    torch.manual_seed(0)
    m = ForwardModel(ModelConfig(gn=gn, run=RunOptions(impl="warp")), swimmer.layout).to(torch.float64).bind(swimmer)
    sizes = input_sizes(swimmer.layout)
    assert sum(p.numel() for p in m.core.parameters()) == weight_count(m.config, sizes)
    default = ForwardModel(ModelConfig(gn=TINY), swimmer.layout)
    assert weight_count(m.config, sizes) != sum(p.numel() for p in default.core.parameters())
    sp = swimmer["train"]
    x0, u = torch.as_tensor(sp.body[:, 0], dtype=torch.float64), torch.as_tensor(sp.ctrl[:, :3], dtype=torch.float64)
    with torch.no_grad():
        a = m.rollout(x0, u)
        b = m.set_options(impl="torch").rollout(x0, u)
    torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-10)
    assert torch.isfinite(a).all() and not torch.equal(a[:, 1], a[:, 0])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("noise", [0.0, 0.05])
def test_noisy_centred_inputs_match_the_torch_formulas(swimmer, dtype, noise):
    """The loss's input states (one Warp launch): noise on moving bodies with re-normalized
    orientations, then each graph's moving bodies re-centred in x, y, as the torch formulas."""
    from gnwarp.state import quat_normalize as qn
    m = tiny_model(swimmer, impl="warp", dtype=dtype, recenter=True, warm=False)
    sp = swimmer["train"]
    N = 3
    g = m.builder(torch.zeros(N, dtype=torch.long), torch.as_tensor(sp.body[:N, 2]), torch.as_tensor(sp.ctrl[:N, 2]))
    ctx = m.context(g)
    noisy, centred = m._noisy_centred(g.nodes, noise, ctx, torch.Generator().manual_seed(5))
    dyn = g.nodes[:, -13:]
    if noise:
        eps = torch.randn(dyn.shape, generator=torch.Generator().manual_seed(5), dtype=dtype) * noise
        ref = dyn + eps * ctx.movable[:, None]
        ref = torch.cat([ref[:, :3], qn(ref[:, 3:7]), ref[:, 7:]], -1)
    else:
        ref = dyn
    tol = dict(rtol=1e-6, atol=1e-6) if dtype == torch.float32 else dict(rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(noisy, ref, **tol)
    torch.testing.assert_close(centred, m._recenter(ref, ctx)[0], **tol)
    assert torch.equal(noisy[~ctx.movable], dyn[~ctx.movable])          # world bodies untouched
    means = centred[ctx.movable, :2].reshape(N, -1, 2).mean(1)
    assert means.abs().max() < 1e-5 and (centred[:, :2] != noisy[:, :2]).any()   # centred, and it did something


def test_vjp_matches_autograd_grad():
    g = torch.Generator().manual_seed(0)
    a, b = torch.randn(4, 3, generator=g, requires_grad=True), torch.randn(3, requires_grad=True)
    unused = torch.randn(2, requires_grad=True)
    w = torch.randn(4, 3, generator=g)
    out = torch.tanh(a * b) @ torch.eye(3)
    ref = torch.autograd.grad(out, (a, b, unused), w, allow_unused=True, retain_graph=True)
    got = vjp(out, (a, b, unused), w)
    assert torch.equal(got[0], ref[0]) and torch.equal(got[1], ref[1]) and got[2] is None
    with pytest.raises(ValueError, match="output's shape"):
        vjp(torch.tanh(a), (a,), w[:, :2])
