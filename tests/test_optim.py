"""FlatAdam (Warp kernels over one flat buffer) against torch.optim.Adam + clip_grad_norm_, and
the Warp GN implementation's gradients added into ``main_grad`` against autograd's ``p.grad`` (CPU)."""
import copy

import pytest
import torch
import warp as wp

wp.config.quiet = True

from gnwarp import GraphNetwork  # noqa: E402
from gnwarp.gn.flat import flat_span, has_main_grad  # noqa: E402
from gnwarp.train import FlatAdam  # noqa: E402
from test_gn_block import SMALL, cast, loss_of, make_batch  # noqa: E402


def _mlp(dtype):
    torch.manual_seed(0)
    return torch.nn.Sequential(torch.nn.Linear(5, 33), torch.nn.Tanh(), torch.nn.Linear(33, 3)).to(dtype)


def _train(model, opt, xs, clip=None):
    for x in xs:
        opt.zero_grad()
        model(x).pow(2).sum().backward()
        if clip is not None:
            torch.nn.utils.clip_grad_norm_(model.parameters(), clip)
        opt.step()


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 2e-5)])
@pytest.mark.parametrize("opts", [dict(), dict(max_grad_norm=0.05), dict(weight_decay=0.1),
                                  dict(weight_decay=0.1, decoupled_weight_decay=True)])
def test_matches_torch_adam(dtype, tol, opts):
    """Same parameters as torch's Adam / AdamW (+ clip_grad_norm_) after 5 steps; the clipping
    threshold is small enough that every step clips."""
    a, b = _mlp(dtype), _mlp(dtype)
    xs = [torch.randn(16, 5, dtype=dtype, generator=torch.Generator().manual_seed(k)) for k in range(5)]
    wd = opts.get("weight_decay", 0.0)
    ref_cls = torch.optim.AdamW if opts.get("decoupled_weight_decay") else torch.optim.Adam
    ref = ref_cls(a.parameters(), lr=3e-2, betas=(0.8, 0.99), eps=1e-6, weight_decay=wd)
    opt = FlatAdam(b.parameters(), lr=3e-2, betas=(0.8, 0.99), eps=1e-6, **opts)
    _train(a, ref, xs, opts.get("max_grad_norm"))
    _train(b, opt, xs)
    assert opt.step_count == 5
    for p, q in zip(a.parameters(), b.parameters()):
        assert torch.allclose(p, q, rtol=tol, atol=tol), (p - q).abs().max()
    moved = max((p - q).abs().max().item() for p, q in zip(_mlp(dtype).parameters(), b.parameters()))
    assert moved > 1e-3  # the comparison is not vacuous: the parameters did change


def test_grad_norm_is_the_unclipped_norm():
    m = _mlp(torch.float64)
    opt = FlatAdam(m.parameters(), lr=1e-3, max_grad_norm=1e-3)
    opt.zero_grad()
    m(torch.randn(8, 5, dtype=torch.float64)).sum().backward()
    grads = [p.grad.clone() for p in m.parameters()]
    opt.step()
    expect = torch.linalg.vector_norm(torch.cat([g.reshape(-1) for g in grads]))
    assert abs(opt.grad_norm.item() - expect.item()) <= 1e-12 * expect.item()


def test_parameters_become_views_and_modules_still_work():
    m = _mlp(torch.float32)
    x = torch.randn(4, 5)
    before = m(x).detach()
    opt = FlatAdam(m.parameters())
    assert torch.equal(m(x), before)
    for p, o in zip(m.parameters(), opt.offsets):
        assert p.data_ptr() == opt.flat[o:].data_ptr()
        assert p.main_grad.shape == p.shape
    assert has_main_grad(list(m.parameters()))
    m.load_state_dict({k: v + 1 for k, v in m.state_dict().items()})  # in place: still the flat buffer
    assert torch.equal(opt.flat[opt.offsets[1]], m[0].bias[0])


def test_state_dict_round_trip_continues_identically(tmp_path):
    a = _mlp(torch.float32)
    opt = FlatAdam(a.parameters(), lr=1e-2, max_grad_norm=1.0)
    xs = [torch.randn(8, 5, generator=torch.Generator().manual_seed(k)) for k in range(4)]
    _train(a, opt, xs[:2])
    torch.save({"model": a.state_dict(), "opt": opt.state_dict()}, tmp_path / "ck.pt")
    _train(a, opt, xs[2:])
    b = _mlp(torch.float32)
    ck = torch.load(tmp_path / "ck.pt")
    b.load_state_dict(ck["model"])
    opt_b = FlatAdam(b.parameters(), lr=0.5)
    opt_b.load_state_dict(ck["opt"])
    assert opt_b.param_groups[0]["lr"] == 1e-2 and opt_b.step_count == 2
    _train(b, opt_b, xs[2:])
    for p, q in zip(a.parameters(), b.parameters()):
        assert torch.equal(p, q)


def test_lr_change_is_used():
    a, b = _mlp(torch.float64), _mlp(torch.float64)
    ra = torch.optim.Adam(a.parameters(), lr=1e-2)
    ob = FlatAdam(b.parameters(), lr=1e-2)
    sa, sb = (torch.optim.lr_scheduler.StepLR(o, 1, gamma=0.5) for o in (ra, ob))
    for k in range(3):
        x = torch.randn(4, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(k))
        _train(a, ra, [x])
        _train(b, ob, [x])
        sa.step()
        sb.step()
    for p, q in zip(a.parameters(), b.parameters()):
        assert torch.allclose(p, q, rtol=1e-12, atol=1e-12)


def test_bad_arguments_and_states():
    m = _mlp(torch.float32)
    with pytest.raises(ValueError, match="lr"):
        FlatAdam(m.parameters(), lr=-1.0)
    with pytest.raises(ValueError, match="betas"):
        FlatAdam(m.parameters(), betas=(0.9, 1.0))
    with pytest.raises(ValueError, match="max_grad_norm"):
        FlatAdam(m.parameters(), max_grad_norm=0.0)
    with pytest.raises(ValueError, match="one dtype"):
        FlatAdam([torch.nn.Parameter(torch.zeros(2)), torch.nn.Parameter(torch.zeros(2, dtype=torch.float64))])
    with pytest.raises(TypeError, match="float32 or float64"):
        FlatAdam([torch.nn.Parameter(torch.zeros(2, dtype=torch.float16))])
    with pytest.raises(ValueError, match="empty parameter list"):
        FlatAdam([])
    opt = FlatAdam(m.parameters())
    with pytest.raises(ValueError, match="not a FlatAdam state"):
        opt.load_state_dict(torch.optim.Adam(_mlp(torch.float32).parameters()).state_dict())
    other = FlatAdam(torch.nn.Linear(2, 2).parameters()).state_dict()
    with pytest.raises(ValueError, match="sizes"):
        opt.load_state_dict(other)
    bad = opt.state_dict()
    bad["exp_avg"][0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        opt.load_state_dict(bad)


def test_check_finite_refuses_nan_gradients_and_leaves_parameters():
    m = _mlp(torch.float32)
    opt = FlatAdam(m.parameters(), check_finite=True)
    before = [p.detach().clone() for p in m.parameters()]
    opt.zero_grad()
    m(torch.full((2, 5), float("nan"))).sum().backward()
    with pytest.raises(FloatingPointError, match="NaN or Inf"):
        opt.step()
    assert opt.step_count == 0
    assert all(torch.equal(p, q) for p, q in zip(m.parameters(), before))


# -- the Warp GN implementation writes main_grad--------------------------------------------------------
@pytest.mark.parametrize("precision", ["fp32", "fp16"])
@pytest.mark.parametrize("deterministic", [False, True])
def test_warp_block_accumulates_into_main_grad(precision, deterministic):
    """Gradients the Warp backward adds into main_grad (one launch per weights / biases) equal
    the p.grad it returns without FlatAdam; two backward passes accumulate."""
    torch.manual_seed(1)
    a = GraphNetwork(**SMALL, precision=precision, deterministic=deterministic)
    b = copy.deepcopy(a)
    g = cast(make_batch("mixed"), torch.float32)
    loss_of(a(g)).backward()
    opt = FlatAdam(b.parameters())
    opt.zero_grad()
    for _ in range(2):
        loss_of(b(g)).backward()
    for (name, p), q in zip(a.named_parameters(), b.parameters()):
        assert q.grad is None, name  # the Warp block returned None: the gradient went to main_grad
        assert torch.allclose(q.main_grad, 2 * p.grad, rtol=1e-6, atol=1e-6), name
    opt.zero_grad()
    assert not opt.grad_flat.any()


def test_warp_block_main_grad_with_a_frozen_parameter():
    """A parameter frozen after FlatAdam was made (requires_grad off) gets nothing added into its
    main_grad; the others get the gradients autograd gives without FlatAdam."""
    torch.manual_seed(5)
    a = GraphNetwork(**SMALL)
    b = copy.deepcopy(a)
    g = cast(make_batch("mixed"), torch.float32)
    opt = FlatAdam(b.parameters())
    opt.zero_grad()
    a.node_mlp.layers[0].bias.requires_grad_(False)
    b.node_mlp.layers[0].bias.requires_grad_(False)
    loss_of(a(g)).backward()
    loss_of(b(g)).backward()
    for (name, p), q in zip(a.named_parameters(), b.parameters()):
        if not p.requires_grad:
            assert not q.main_grad.any(), name
        else:
            assert torch.allclose(q.main_grad, p.grad, rtol=1e-6, atol=1e-6), name


def test_gn_training_with_flat_adam_matches_torch_adam():
    """Three training steps of two chained Warp blocks: FlatAdam (gradients through main_grad)
    against torch's Adam + clip_grad_norm_ (gradients through p.grad)."""
    torch.manual_seed(2)
    net = torch.nn.ModuleList([GraphNetwork(**SMALL), GraphNetwork(**{**SMALL, "node_size": 5, "edge_size": 6,
                                                                       "global_size": 7})])
    ref_net = copy.deepcopy(net)
    g = cast(make_batch("mixed"), torch.float32)

    def loss(n):
        return loss_of(n[1](n[0](g)))
    ref = torch.optim.Adam(ref_net.parameters(), lr=1e-2)
    opt = FlatAdam(net.parameters(), lr=1e-2, max_grad_norm=0.5)
    for _ in range(3):
        ref.zero_grad()
        loss(ref_net).backward()
        torch.nn.utils.clip_grad_norm_(ref_net.parameters(), 0.5)
        ref.step()
        opt.zero_grad()
        loss(net).backward()
        opt.step()
    for p, q in zip(ref_net.parameters(), net.parameters()):
        assert torch.allclose(p, q, rtol=1e-4, atol=1e-5), (p - q).abs().max()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("precision", ["fp32", "fp16"])
def test_cuda_captured_training_step_matches_eager_torch_adam(precision):
    """A whole training step (two Warp blocks, FlatAdam with clipping) captured as one CUDA
    graph and replayed 4 times, against eager steps with torch's Adam + clip_grad_norm_: bias
    corrections advance on the device, so the replays match."""
    from gnwarp.interop import cuda_graph
    from test_gn_block import _on
    torch.manual_seed(3)
    net = torch.nn.ModuleList([GraphNetwork(**SMALL, precision=precision, check_inputs=False),
                               GraphNetwork(**{**SMALL, "node_size": 5, "edge_size": 6, "global_size": 7},
                                            precision=precision, check_inputs=False)]).cuda()
    ref_net = copy.deepcopy(net)
    g = _on(cast(make_batch("mixed"), torch.float32), "cuda")
    ref = torch.optim.Adam(ref_net.parameters(), lr=1e-2)
    opt = FlatAdam(net.parameters(), lr=1e-2, max_grad_norm=0.5)

    def step(n, o, flat):
        o.zero_grad()
        loss_of(n[1](n[0](g))).backward()
        if not flat:
            torch.nn.utils.clip_grad_norm_(n.parameters(), 0.5)
        o.step()
    s = torch.cuda.Stream()
    s.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(s):
        step(net, opt, True)  # warm-up: compiles kernels, makes the segment tables
    torch.cuda.current_stream().wait_stream(s)
    graph = torch.cuda.CUDAGraph()
    with cuda_graph(graph, s):
        step(net, opt, True)  # recorded, not run
    step(ref_net, ref, False)
    for _ in range(4):
        graph.replay()
        step(ref_net, ref, False)
    torch.cuda.synchronize()
    assert opt.step_count == 5
    tol = 1e-4 if precision == "fp32" else 2e-3
    for p, q in zip(ref_net.parameters(), net.parameters()):
        assert torch.allclose(p, q, rtol=tol, atol=tol), (p - q).abs().max()


# first-layer input widths that are multiples of 8 (node 8 + 8 + 8, global 8 + 8 + 8): those
# weights are read in place (from the cast copy), not as padded blocks
ALIGNED = dict(SMALL, node_size=8, edge_size=8, global_size=8, node_out=8, edge_out=8, global_out=8)


@pytest.mark.parametrize("mode,sizes", [("concat", "small"), ("project", "small"), ("concat", "aligned")])
def test_flatten_parameters_keeps_outputs_and_casts_one_span(mode, sizes):
    """fp16 block on flattened parameters: the same outputs bit for bit, and the block sees
    one span (one cast launch, no cat) for either edge first layer, with padded first-layer
    blocks or weights read in place."""
    from gnwarp import flatten_parameters
    torch.manual_seed(4)
    kw = SMALL if sizes == "small" else ALIGNED
    a = GraphNetwork(**kw, precision="fp16", edge_first_layer=mode)
    b = copy.deepcopy(a)
    g = cast(make_batch("mixed", fv=kw["node_size"], fe=kw["edge_size"], fu=kw["global_size"]), torch.float32)
    assert flat_span(b.flat_parameters()) is None
    flat, offsets = flatten_parameters(b.parameters())
    assert flat_span(b.flat_parameters()) is not None and flat.numel() >= sum(p.numel() for p in b.parameters())
    ref = copy.deepcopy(a)
    ref.precision = "fp32"
    for x, y, z in zip(a(g), b(g), ref(g)):
        assert (x is None and y is None) or torch.equal(x, y)
        if z is not None:  # and both right: fp16 GEMMs against fp32 ones
            assert (y - z).abs().max() <= 1e-2 * z.abs().max(), (y - z).abs().max()
    with pytest.raises(ValueError, match="twice"):
        flatten_parameters([a.edge_mlp.layers[0].weight] * 2)
    with pytest.raises(ValueError, match="no parameters"):
        flatten_parameters([])


# -- WeightAverage ------------------------------------------------------------------------------
def test_weight_average_follows_its_formula_and_swaps_back():
    """After each update the average is a reference loop's (d_t = min(decay, (1+t)/(10+t)));
    applied() puts it in the tensors' place and the weights back; a state taken inside applied()
    resumes another average exactly."""
    from gnwarp.train import WeightAverage
    g = torch.Generator().manual_seed(0)
    w = [torch.randn(4, 3, dtype=torch.float64, generator=g), torch.randn(5, dtype=torch.float64, generator=g)]
    avg = WeightAverage(w, 0.6)
    ref = [x.clone() for x in w]
    for t in range(1, 16):
        for x in w:
            x.add_(torch.randn(x.shape, dtype=x.dtype, generator=g))
        avg.update()
        d = min(0.6, (1 + t) / (10 + t))
        ref = [d * r + (1 - d) * x for r, x in zip(ref, w)]
        for a, r in zip(avg.average, ref):
            torch.testing.assert_close(a, r, rtol=1e-12, atol=1e-12)
    assert d == 0.6   # the cap was reached, not only the warm-up
    live = [x.clone() for x in w]
    with avg.applied():
        for x, r in zip(w, ref):
            torch.testing.assert_close(x, r, rtol=1e-12, atol=1e-12)
        state = avg.state_dict()
        saved = [x.clone() for x in w]            # what a checkpoint's model.pt holds
        with pytest.raises(RuntimeError, match="inside applied"):
            avg.update()
    for x, y in zip(w, live):
        assert torch.equal(x, y)
    with pytest.raises(RuntimeError, match="outside applied"):
        avg.state_dict()
    # resume: tensors holding the averages + the state -> the live weights and the same averages
    w2 = [x.clone() for x in saved]
    avg2 = WeightAverage(w2, 0.6)
    avg2.load_state_dict(state)
    assert all(torch.equal(x, y) for x, y in zip(w2, live))
    assert all(torch.equal(a, b) for a, b in zip(avg2.average, avg.average)) and int(avg2.count) == 15
    for x in w:
        x.mul_(1.5)
    for x in w2:
        x.mul_(1.5)
    avg.update()
    avg2.update()
    assert all(torch.equal(a, b) for a, b in zip(avg2.average, avg.average))


def test_weight_average_refuses_bad_decays_and_states():
    from gnwarp.train import WeightAverage
    w = [torch.zeros(3)]
    for bad in (0.0, 1.0, -0.5, True, float("nan"), "0.9"):
        with pytest.raises(ValueError, match="decay must be a number in"):
            WeightAverage(w, bad)
    avg = WeightAverage(w, 0.9)
    good = {"format": WeightAverage.FORMAT, "count": 3, "weights": [torch.ones(3)]}
    for state, match in [({"format": "x"}, "not a WeightAverage state"),
                         ({**good, "count": -1}, "count must be an integer"),
                         ({**good, "count": 2.5}, "count must be an integer"),
                         ({**good, "weights": []}, "holds 0 weight tensors, this model 1"),
                         ({**good, "weights": [torch.ones(4)]}, r"weights\[0\] should have shape \(3,\)"),
                         ({**good, "weights": [torch.tensor([1.0, float("nan"), 0.0])]}, "NaN or Inf")]:
        with pytest.raises(ValueError, match=match):
            avg.load_state_dict(state)
    assert torch.equal(w[0], torch.zeros(3))   # a refused state changed nothing
    avg.load_state_dict(good)
    assert torch.equal(w[0], torch.ones(3)) and int(avg.count) == 3
