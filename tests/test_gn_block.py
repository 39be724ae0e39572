"""The Warp GN block against the pure-torch reference (CPU).

Sizes are small and few distinct ones are used, so the number of kernels Warp compiles stays
modest (each configuration compiles once; ~0.1 s per SIMT kernel, ~5 s per fused tile kernel).
"""
import itertools

import pytest
import torch
import warp as wp

wp.config.quiet = True

from torch.func import functional_call  # noqa: E402

from gnwarp import GNBlockConfig, GraphNetwork, GraphsTuple  # noqa: E402
from gnwarp.gn import (TUNABLES, EdgeBlockConfig, GlobalBlockConfig, NodeBlockConfig, RunOptions,  # noqa: E402
                       TorchGraphNetwork, fp16x3, graph_index, graph_ops, rules, tile_block)
from gnwarp.gn.config import pad  # noqa: E402
from gnwarp.graphs import batch  # noqa: E402
from gnwarp.interop import WP_DTYPE, Launcher  # noqa: E402

FV, FE, FU = 3, 2, 4
SMALL = dict(node_size=FV, edge_size=FE, global_size=FU, node_out=5, edge_out=6, global_out=7,
             edge_hidden=(16, 16), node_hidden=(16,), global_hidden=(16,))
# the tiny block of the gradcheck and tile-path tests
TINY = dict(node_size=2, edge_size=2, global_size=2, node_out=3, edge_out=3, global_out=2,
            edge_hidden=(4,), node_hidden=(4,), global_hidden=(4,))


# -- graphs -------------------------------------------------------------------------------------
def one_graph(gen, n_node, n_edge, fv=FV, fe=FE, fu=FU, dtype=torch.float64, active=None, scale=1.0):
    """A random graph; edges only touch the first ``active`` nodes (the rest are isolated)."""
    active = n_node if active is None else active
    s = torch.randint(0, max(active, 1), (n_edge,), generator=gen)
    r = torch.randint(0, max(active, 1), (n_edge,), generator=gen)

    def feats(rows, f):
        return None if f == 0 else scale * torch.randn(rows, f, generator=gen, dtype=dtype)
    return GraphsTuple(nodes=feats(n_node, fv), edges=feats(n_edge, fe), globals=feats(1, fu), senders=s,
                       receivers=r, n_node=torch.tensor([n_node]), n_edge=torch.tensor([n_edge]))


def make_batch(kind, dtype=torch.float64, seed=0, scale=1.0, fv=FV, fe=FE, fu=FU):
    gen = torch.Generator().manual_seed(seed)
    specs = {
        # several graphs of different sizes, one without edges, one with isolated nodes
        "mixed": [(4, 7, None), (3, 0, None), (6, 11, 3), (1, 1, None), (5, 9, None)],
        "one_graph": [(7, 12, None)],
        "no_edges": [(3, 0, None), (2, 0, None)],
        "chain": [(5, 8, None), (8, 16, 6), (3, 4, None)],
        "gradcheck": [(3, 4, None), (2, 0, None), (3, 3, 2)],
    }[kind]
    return batch([one_graph(gen, n, e, fv, fe, fu, dtype, a, scale) for n, e, a in specs])


def with_grad(g):
    f = (lambda x: None if x is None else x.detach().clone().requires_grad_())
    return g._replace(nodes=f(g.nodes), edges=f(g.edges), globals=f(g.globals))


def cast(g, dtype):
    f = (lambda x: None if x is None else x.to(dtype))
    return g._replace(nodes=f(g.nodes), edges=f(g.edges), globals=f(g.globals))


def rel_err(a, b):
    """max |a - b| / max |b| (error relative to the tensor's scale)."""
    b = b.double()
    return ((a.double() - b).abs().max() / b.abs().max().clamp_min(1e-30)).item()


def loss_of(out):
    # weights that differ per output so every gradient entry is exercised
    terms = []
    for k, x in enumerate((out.nodes, out.edges, out.globals)):
        if x is not None and x.numel():
            w = torch.linspace(-1.0, 1.5, x.numel(), dtype=x.dtype, device=x.device).reshape(x.shape)
            terms.append((torch.sin(x + k) * w).sum())
    return sum(terms)


def pair(cfg_kwargs, dtype=torch.float32, seed=0, **gn_kwargs):
    """A Warp GraphNetwork and a float64 torch reference with the same weights."""
    torch.manual_seed(seed)
    gn = GraphNetwork(**cfg_kwargs, **gn_kwargs).to(dtype)
    ref = TorchGraphNetwork(**cfg_kwargs).double()
    ref.load_state_dict({k: v.double() for k, v in gn.state_dict().items()})
    return gn, ref


def compare(gn, ref, g, fwd_tol, grad_tol):
    """Forward outputs and gradients of every input and parameter, Warp vs float64 reference."""
    gw = with_grad(cast(g, gn.edge_mlp.layers[0].weight.dtype))
    gr = with_grad(cast(g, torch.float64))
    out, expect = gn(gw), ref(gr)
    for name in ("nodes", "edges", "globals"):
        a, b = getattr(out, name), getattr(expect, name)
        if a is None and b is None:
            continue
        assert a.shape == b.shape, name
        if b.numel():
            assert torch.isfinite(a).all(), name
            assert rel_err(a, b) <= fwd_tol, (name, rel_err(a, b))
    loss_of(out).backward()
    loss_of(expect).backward()
    for name in ("nodes", "edges", "globals"):
        a, b = getattr(gw, name), getattr(gr, name)
        if a is None or a.numel() == 0:
            continue
        if b.grad is None:  # input not read by this block
            assert a.grad is None or not a.grad.abs().any(), name
            continue
        assert a.grad is not None, f"no gradient for input {name}"
        assert rel_err(a.grad, b.grad) <= grad_tol, (name, rel_err(a.grad, b.grad))
    for (name, p), (_, q) in zip(gn.named_parameters(), ref.named_parameters()):
        assert p.grad is not None, f"no gradient for {name}"
        assert rel_err(p.grad, q.grad) <= grad_tol, (name, rel_err(p.grad, q.grad))


# -- forward and gradients vs the reference -----------------------------------------------------
@pytest.mark.parametrize("kind", ["mixed", "one_graph", "no_edges"])
@pytest.mark.parametrize("deterministic", [False, True])
def test_float32_matches_float64_reference(kind, deterministic):
    gn, ref = pair(SMALL, deterministic=deterministic)
    compare(gn, ref, make_batch(kind), fwd_tol=1e-5, grad_tol=1e-5)


def test_float64_matches_reference_to_rounding():
    gn, ref = pair(SMALL, dtype=torch.float64)
    compare(gn, ref, make_batch("mixed"), fwd_tol=1e-12, grad_tol=1e-12)


def _switch_cases():
    cases = []
    names = ("use_edges", "use_sender_nodes", "use_receiver_nodes", "use_globals")
    for bits in itertools.product([True, False], repeat=4):
        if any(bits):
            cases.append(("edge", dict(edge_block=EdgeBlockConfig(**dict(zip(names, bits))))))
    names = ("use_received_edges", "use_nodes", "use_globals")
    for bits in itertools.product([True, False], repeat=3):
        if any(bits):
            cases.append(("node", dict(node_block=NodeBlockConfig(**dict(zip(names, bits))))))
    names = ("use_edges", "use_nodes", "use_globals")
    for bits in itertools.product([True, False], repeat=3):
        if any(bits):
            cases.append(("global", dict(global_block=GlobalBlockConfig(**dict(zip(names, bits))))))
    cases.append(("no_global_update", dict(update_globals=False)))
    return cases


@pytest.mark.parametrize("case", _switch_cases(), ids=lambda c: f"{c[0]}-" + "-".join(
    f"{k}:{''.join('1' if getattr(v, f) else '0' for f in v.__dataclass_fields__)}" if hasattr(v, "__dataclass_fields__")
    else f"{k}:{v}" for k, v in c[1].items()))
def test_block_switches(case):
    """Every combination of the use_* switches of each update (float64: exact to rounding)."""
    _, switches = case
    gn, ref = pair({**SMALL, **switches}, dtype=torch.float64)
    compare(gn, ref, make_batch("mixed"), fwd_tol=1e-12, grad_tol=1e-12)
    c = gn.config
    assert gn.edge_mlp.layers[0].in_features == sum(w for _, w in c.edge_layout)
    if not c.update_globals:
        g = make_batch("mixed", dtype=torch.float32)
        out = GraphNetwork(**{**SMALL, **switches})(g)
        assert out.globals is g.globals  # passed through, no global MLP ran
        assert gn.global_mlp is None


_EDGE_CASES = [c for c in _switch_cases() if c[0] == "edge"]


@pytest.mark.parametrize("case", _EDGE_CASES, ids=lambda c: "edge:" + "".join(
    "1" if getattr(c[1]["edge_block"], f) else "0" for f in c[1]["edge_block"].__dataclass_fields__))
def test_project_edge_first_layer_switches(case, monkeypatch):
    """Edge blocks with wide gathered inputs compute their first layer from projections (node /
    global projections gathered per edge, ``project`` kernel) instead of concatenating the inputs:
    every edge switch combination in that mode (float64: exact to rounding)."""
    monkeypatch.setattr(TUNABLES, "edge_concat_max_k", -1)
    gn, ref = pair({**SMALL, **case[1]}, dtype=torch.float64)
    compare(gn, ref, make_batch("mixed"), fwd_tol=1e-12, grad_tol=1e-12)


@pytest.mark.parametrize("deterministic", [False, True])
def test_project_edge_first_layer(deterministic, monkeypatch):
    """The projected edge first layer in float32 (both aggregation modes) and under gradcheck."""
    monkeypatch.setattr(TUNABLES, "edge_concat_max_k", -1)
    gn, ref = pair(SMALL, deterministic=deterministic)
    compare(gn, ref, make_batch("mixed"), fwd_tol=1e-5, grad_tol=1e-5)
    g = make_batch("gradcheck", fv=2, fe=2, fu=2)
    torch.manual_seed(1)
    _gradcheck(GraphNetwork(**TINY, deterministic=deterministic, check_inputs=False).double(), g)


@pytest.mark.parametrize("mode", ["concat", "project"])
@pytest.mark.parametrize("deterministic", [False, True])
def test_edge_first_layer_forced(mode, deterministic):
    """``edge_first_layer`` forces either first-layer mode; both match the float64 reference,
    forward and every gradient."""
    gn, ref = pair(SMALL, deterministic=deterministic, edge_first_layer=mode)
    compare(gn, ref, make_batch("mixed"), fwd_tol=1e-5, grad_tol=1e-5)
    with pytest.raises(ValueError, match="edge_first_layer"):
        GraphNetwork(**SMALL, edge_first_layer="fused")


def _run(dtype=torch.float32, **options):
    return RunOptions(**options).resolve(dtype)


def test_edge_first_layer_mode_rule():
    """Narrow gathered edge inputs concatenate, wide ones project (the paper core's two blocks)."""
    narrow, wide = GNBlockConfig(31, 64, 32), GNBlockConfig(31 + 128, 64 + 128, 32 + 128)
    assert rules.edge_concat(narrow, _run(), 1000)
    assert not rules.edge_concat(wide, _run(), 1000)
    assert not rules.edge_concat(wide, _run(torch.float64, precision="fp64"), 1000)
    for precision in ("tf32", "fp16", "bf16"):  # tensor cores: concat measured faster everywhere
        assert rules.edge_concat(wide, _run(precision=precision), 1000)
    # fp16x3: concat where it emulates, fp32's rule below its rows and on float64 parameters
    assert rules.edge_concat(wide, _run(precision="fp16x3"), TUNABLES.emulate_min_rows)
    assert not rules.edge_concat(wide, _run(precision="fp16x3"), TUNABLES.emulate_min_rows - 1)
    assert not rules.edge_concat(wide, _run(torch.float64, precision="fp16x3"), 10 ** 6)
    assert rules.edge_concat(wide, _run(edge_first_layer="concat"), 1000)
    assert not rules.edge_concat(narrow, _run(edge_first_layer="project"), 1000)


@pytest.mark.parametrize("widths,gathered,vec_", [
    ((5, 3, 3, 4), (False, True, True, True), 4),   # the edge rows: three gathered pieces
    ((5, 0, 7, 0), (False, False, True, False), 4),  # absent pieces in the middle and at the end
    ((0, 9, 0, 1), (False, True, False, False), 2),
    ((13, 17, 2, 6), (True, False, True, False), 8),  # vec_ wider than some pieces
    ((300, 7, 0, 40), (True, False, False, True), 4),  # a piece over several warps, one row per warp
])
def test_concat_kernel(widths, gathered, vec_):
    """``concat_kernel`` writes each piece's (gathered) rows side by side, cast to the output
    dtype, and zeros in the padding columns; nothing outside its rows (11 rows: the last block
    of rows sharing warps is partial)."""
    from gnwarp.kernels.gn import graph_ops as K
    gen = torch.Generator().manual_seed(sum(widths))
    rows, src_rows, K_ = 11, 4, pad(sum(widths)) + 8
    dtypes = (torch.float32, torch.float64, torch.float32, torch.float16)
    srcs = [torch.randn(src_rows if g else rows, max(w, 1), generator=gen).to(dt)[:, :w].contiguous()
            for w, g, dt in zip(widths, gathered, dtypes)]
    idx = [torch.randint(0, src_rows, (rows,), generator=gen, dtype=torch.int32) for _ in widths]
    out = torch.full((rows + 1, K_), float("nan"), dtype=torch.float32)  # one row past the end
    kern = K.concat_kernel(widths, gathered, tuple(WP_DTYPE[t.dtype] for t in srcs), wp.float32, K_, max_vec=vec_)
    wp.launch(kern, dim=K.concat_threads(rows, widths, K_, vec_), device="cpu",
              inputs=[wp.from_torch(t.view(-1)) for t in srcs] + [wp.from_torch(i) for i in idx] + [rows],
              outputs=[wp.from_torch(out.view(-1))])
    expect = torch.cat([(t[i.long()] if g else t).float() for t, i, g in zip(srcs, idx, gathered)]
                       + [torch.zeros(rows, K_ - sum(widths))], 1)
    assert torch.equal(out[:rows], expect)
    assert out[rows].isnan().all()


@pytest.mark.parametrize("deterministic_order", [False, True])
def test_route_kernel(deterministic_order):
    """``route_kernel`` (the adjoint of ``concat_kernel``): a stored piece lands in its own rows in
    the output dtype, added pieces are summed into their (indexed) rows on top of what the
    output held, padding columns and unrouted pieces are never read, and nothing past the rows
    is touched."""
    from gnwarp.kernels.gn import graph_ops as K
    gen = torch.Generator().manual_seed(7)
    rows, n_dst = 13, 4
    g = torch.randn(rows, 24, generator=gen)
    g[:, 21:] = float("nan")  # padding columns: must not be read
    g[:, 3:6] = float("nan")  # an unrouted piece
    idx = torch.randint(0, n_dst, (rows,), generator=gen, dtype=torch.int32)
    if deterministic_order:  # every row to one destination: the most contention
        idx.zero_()
    store = torch.full((rows + 1, 3), float("nan"), dtype=torch.float64)
    acc = torch.randn(n_dst + 1, 5, generator=gen)
    acc0 = acc.clone()
    own = torch.randn(rows, 7, generator=gen)
    own0 = own.clone()
    pieces = ((0, 3, K.ROUTE_STORE, False, wp.float64), (6, 5, K.ROUTE_ADD, True, wp.float32),
              (11, 5, K.ROUTE_ADD, True, wp.float32), (16, 5, K.ROUTE_ADD, False, wp.float32))
    # pieces 1 and 2 add into one output (sender and receiver columns into the nodes' gradient)
    kern = K.route_kernel(pieces, wp.float32)
    wp.launch(kern, dim=rows * 18, device="cpu",
              inputs=[wp.from_torch(g)] + [wp.from_torch(idx)] * 4,
              outputs=[wp.from_torch(store), wp.from_torch(acc), wp.from_torch(acc), wp.from_torch(own[:, :5])])
    assert torch.equal(store[:rows], g[:, :3].double()) and store[rows].isnan().all()
    expect = acc0.clone()
    expect.index_add_(0, idx.long(), g[:, 6:11])
    expect.index_add_(0, idx.long(), g[:, 11:16])
    assert torch.allclose(acc, expect, atol=1e-5) and torch.equal(acc[n_dst], acc0[n_dst])
    assert torch.allclose(own[:, :5], own0[:, :5] + g[:, 16:21]) and torch.equal(own[:, 5:], own0[:, 5:])


@pytest.mark.parametrize("deterministic", [False, True])
def test_strided_and_broadcast_output_gradients(deterministic):
    """The backward reads the gradients autograd hands over as they are: column slices of a
    concatenation (strided) and a sum's broadcast gradient (stride 0) give the reference's
    input and parameter gradients."""
    gn, ref = pair(SMALL, deterministic=deterministic)
    g = make_batch("mixed")
    gw, gr = with_grad(cast(g, torch.float32)), with_grad(g)
    losses = []
    for net, x in ((gn, gw), (ref, gr)):
        out = net(x)
        cat = torch.cat([out.nodes, out.nodes[:, :2] * 2], 1)  # backward: strided column slices
        losses.append((torch.sin(cat) * torch.linspace(-1, 1, cat.shape[1], dtype=cat.dtype)).sum()
                      + out.edges.sum() + out.globals.sum())  # sums: broadcast gradients
    losses[0].backward()
    losses[1].backward()
    for name in ("nodes", "edges", "globals"):
        assert rel_err(getattr(gw, name).grad, getattr(gr, name).grad) <= 1e-5, name
    for (name, p), (_, q) in zip(gn.named_parameters(), ref.named_parameters()):
        assert rel_err(p.grad, q.grad) <= 1e-5, name


def test_graph_without_globals():
    """A block that reads no globals runs on a GraphsTuple with globals=None."""
    kw = dict(SMALL, global_size=0, update_globals=False, edge_block=EdgeBlockConfig(use_globals=False),
              node_block=NodeBlockConfig(use_globals=False))
    gn, ref = pair(kw, dtype=torch.float64)
    g = make_batch("mixed", fu=0)
    assert g.globals is None
    compare(gn, ref, g, fwd_tol=1e-12, grad_tol=1e-12)


def test_single_layer_mlps():
    kw = dict(SMALL, edge_hidden=(), node_hidden=(), global_hidden=())
    gn, ref = pair(kw, dtype=torch.float64)
    compare(gn, ref, make_batch("mixed"), fwd_tol=1e-12, grad_tol=1e-12)


@pytest.mark.parametrize("deterministic", [False, True])
def test_gradcheck_float64(deterministic):
    g = make_batch("gradcheck", fv=2, fe=2, fu=2)
    torch.manual_seed(1)
    gn = GraphNetwork(**TINY, deterministic=deterministic, check_inputs=False).double()
    _gradcheck(gn, g)


def _gradcheck(gn, g):
    names = [n for n, _ in gn.named_parameters()]

    def f(v, e, u, *ps):
        out = functional_call(gn, dict(zip(names, ps)), (g._replace(nodes=v, edges=e, globals=u),))
        return out.nodes, out.edges, out.globals

    inputs = (g.nodes, g.edges, g.globals, *[p.detach() for p in gn.parameters()])
    inputs = tuple(x.clone().requires_grad_() for x in inputs)
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-7, rtol=1e-6)


def test_state_dict_interchangeable():
    g = make_batch("mixed", dtype=torch.float32)
    torch.manual_seed(3)
    warp_gn = GraphNetwork(**SMALL)
    torch_gn = TorchGraphNetwork(**SMALL)
    torch_gn.load_state_dict(warp_gn.state_dict())
    a, b = warp_gn(g), torch_gn(g)
    assert rel_err(a.nodes, b.nodes) < 1e-5 and rel_err(a.globals, b.globals) < 1e-5
    warp_gn.impl = "torch"
    assert torch.equal(warp_gn(g).nodes, b.nodes)


def test_inference_keeps_no_activations_and_matches():
    g = make_batch("mixed", dtype=torch.float32)
    gn = GraphNetwork(**SMALL)
    with torch.no_grad():
        a = gn(g)
    assert not a.nodes.requires_grad
    b = gn(g)
    assert b.nodes.requires_grad
    assert torch.equal(a.nodes, b.nodes) and torch.equal(a.edges, b.edges) and torch.equal(a.globals, b.globals)


def test_second_backward_with_retain_graph():
    g = with_grad(make_batch("mixed", dtype=torch.float32))
    gn = GraphNetwork(**SMALL)
    loss = loss_of(gn(g))
    loss.backward(retain_graph=True)
    first = [p.grad.clone() for p in gn.parameters()]
    loss.backward()
    for p, f in zip(gn.parameters(), first):
        assert torch.allclose(p.grad, 2 * f, rtol=1e-6, atol=1e-7)


def test_shared_index_and_unchecked_inputs():
    """A GraphIndex built once serves several blocks; check_inputs=False skips validation."""
    g = make_batch("mixed", dtype=torch.float32)
    gn1 = GraphNetwork(**SMALL, check_inputs=False)
    gn2 = GraphNetwork(**dict(SMALL, node_size=5, edge_size=6, global_size=7), check_inputs=False)
    idx = gn1.graph_index(g)
    out = gn2(gn1(g, idx), idx)
    gn1.impl = gn2.impl = "torch"
    expect = gn2(gn1(g))
    assert rel_err(out.nodes, expect.nodes) < 1e-5
    assert rel_err(out.edges, expect.edges) < 1e-5


# -- aggregation order and determinism ----------------------------------------------------------
def test_csr_index_groups_edges_by_receiver():
    g = make_batch("mixed")
    gi = graph_index(g, deterministic=True)
    rcv, snd = g.receivers, g.senders
    for perm, offs, idx in ((gi.recv_perm, gi.recv_offsets, rcv), (gi.send_perm, gi.send_offsets, snd)):
        assert offs[0] == 0 and offs[-1] == g.total_edges
        for i in range(g.total_nodes):
            seg = perm[offs[i]:offs[i + 1]].long()
            assert (idx[seg] == i).all()
            assert (seg[1:] > seg[:-1]).all()  # stable: edge order kept within a segment
    assert sorted(gi.recv_perm.tolist()) == list(range(g.total_edges))


def test_segment_sum_is_sequential_in_edge_order():
    """Deterministic aggregation sums each segment left to right in float32, starting from 0."""
    gen = torch.Generator().manual_seed(5)
    g = make_batch("mixed")
    gi = graph_index(g, deterministic=True)
    # magnitudes spread over many binades make any other summation order round differently
    src = (torch.randn(g.total_edges, 6, generator=gen) * 10.0 ** torch.randint(-4, 5, (g.total_edges, 6),
                                                                             generator=gen)).float()
    out = torch.zeros(g.total_nodes, 6)
    graph_ops.segment(Launcher(src), _run(deterministic=True), src, gi.recv_perm, gi.recv_offsets, out)
    expect = torch.zeros(g.total_nodes, 6)
    for k in range(g.total_edges):  # edges in id order: the order of the stable sort
        i = int(g.receivers[k])
        expect[i] = (expect[i] + src[k]).float()
    assert torch.equal(out, expect)


def test_deterministic_mode_is_bitwise_reproducible():
    g = make_batch("chain", dtype=torch.float32)
    gn = GraphNetwork(**SMALL, deterministic=True)
    results = []
    for _ in range(3):
        gn.zero_grad()
        gw = with_grad(g)
        out = gn(gw)
        loss_of(out).backward()
        results.append([out.nodes, out.edges, out.globals, gw.nodes.grad, gw.edges.grad, gw.globals.grad]
                       + [p.grad.clone() for p in gn.parameters()])
    for other in results[1:]:
        for a, b in zip(results[0], other):
            assert torch.equal(a, b)


# -- precisions ---------------------------------------------------------------------------------
@pytest.mark.parametrize("mode", ["concat", "project"])
@pytest.mark.parametrize("precision,tol", [("tf32", 1e-5), ("fp16", 5e-3), ("bf16", 4e-2)])
def test_reduced_precision_close_to_reference(precision, tol, mode):
    """tf32 is plain fp32 on the CPU; fp16/bf16 round GEMM inputs and activations (float32
    inputs: the concat kernels cast them to the compute dtype as they read them)."""
    gn, ref = pair(SMALL, precision=precision, edge_first_layer=mode)
    g = make_batch("mixed")
    out = gn(cast(g, torch.float32))
    expect = ref(g)
    for name in ("nodes", "edges", "globals"):
        a = getattr(out, name)
        assert a.dtype == torch.float32
        assert rel_err(a, getattr(expect, name)) < tol, (name, rel_err(a, getattr(expect, name)))
    gw = with_grad(cast(g, torch.float32))
    loss_of(gn(gw)).backward()
    assert all(torch.isfinite(p.grad).all() for p in gn.parameters())
    assert torch.isfinite(gw.nodes.grad).all()


# -- bad inputs: clear errors before any launch -------------------------------------------------
def _bad_cases():
    g = make_batch("mixed", dtype=torch.float32)
    nan_edges = g.edges.clone()
    nan_edges[3, 1] = float("nan")
    inf_globals = g.globals.clone()
    inf_globals[0, 0] = float("inf")
    snd = g.senders.clone()
    snd[2] = g.total_nodes + 3
    return [
        ("node feature size", g._replace(nodes=torch.randn(g.total_nodes, FV + 1)), ValueError, "nodes has shape"),
        ("edge feature size", g._replace(edges=torch.randn(g.total_edges, 1)), ValueError, "edges has shape"),
        ("sender out of range", g._replace(senders=snd), ValueError, "senders index out of range"),
        ("negative receiver", g._replace(receivers=g.receivers - 100), ValueError, "receivers index out of range"),
        ("n_node sum", g._replace(n_node=g.n_node + 1), ValueError, "n_node sums to"),
        ("n_edge sum", g._replace(n_edge=g.n_edge * 2), ValueError, "n_edge sums to"),
        ("dtype", g._replace(nodes=g.nodes.double()), TypeError, "dtype torch.float64"),
        ("index dtype", g._replace(senders=g.senders.float()), TypeError, "senders must be int32 or int64"),
        ("device", g._replace(globals=g.globals.to("meta")), ValueError, "globals is on meta"),
        ("nan", g._replace(edges=nan_edges), ValueError, "edges contains NaN or Inf"),
        ("inf", g._replace(globals=inf_globals), ValueError, "globals contains NaN or Inf"),
        ("missing globals", g._replace(globals=None), ValueError, "globals is None"),
        ("numpy", g.to_numpy(), TypeError, "must be a torch.Tensor"),
        ("cross-graph edge", g._replace(senders=torch.where(torch.arange(g.total_edges) == 0,
                                                            torch.tensor(g.total_nodes - 1), g.senders)),
         ValueError, "different graph"),
    ]


@pytest.mark.parametrize("case", _bad_cases(), ids=lambda c: c[0])
def test_bad_input_raises_before_launch(case, monkeypatch):
    _, g, exc, msg = case
    gn = GraphNetwork(**SMALL)

    def no_launch(*a, **k):
        raise AssertionError("a kernel was launched before the input was checked")
    monkeypatch.setattr(wp, "launch", no_launch)
    monkeypatch.setattr(wp, "launch_tiled", no_launch)
    with pytest.raises(exc, match=msg):
        gn(g)


def test_bad_config_raises():
    with pytest.raises(ValueError, match="global_size=0"):
        GNBlockConfig(**dict(SMALL, global_size=0))
    with pytest.raises(ValueError, match="uses no input"):
        GNBlockConfig(**SMALL, edge_block=EdgeBlockConfig(False, False, False, False))
    with pytest.raises(ValueError, match="precision"):
        GraphNetwork(**SMALL, precision="fp8")
    with pytest.raises(ValueError, match="deterministic"):
        GraphNetwork(**SMALL, path="tile", deterministic=True)(make_batch("mixed", dtype=torch.float32))


# -- run options ----------------------------------------------------------------------------------
def test_run_options_resolve_once_per_dtype():
    """Each precision resolves to its compute / accumulation dtypes, TF32 switch and fp16x3 rule."""
    r = _run(precision="fp16")
    assert (r.compute_dtype, r.acc_dtype, r.autocast, r.tf32, r.emulate) == (
        torch.float16, torch.float32, torch.float16, False, None)
    r = _run(torch.float64, precision="tf32")
    assert (r.compute_dtype, r.acc_dtype, r.tf32) == (torch.float64, torch.float64, True)
    assert _run(precision="fp16x3").emulate == (TUNABLES.emulate_min_rows, TUNABLES.emulate_min_width)
    assert _run(precision="fp16x3", emulate_min=(3, 4)).emulate == (3, 4)
    assert _run(torch.float64, precision="fp16x3").emulate is None  # float64 parameters never emulate
    assert RunOptions(precision="fp64").param_dtype == torch.float64 and RunOptions().param_dtype == torch.float32


def test_tf32_off_cuda_is_fp32(monkeypatch):
    """TF32 exists only on CUDA: elsewhere precision "tf32" resolves to fp32 (no tensor-core
    rules either) and gives fp32's outputs bit for bit; models default to it."""
    from gnwarp.models import ModelConfig
    cpu = torch.device("cpu")
    r = RunOptions(precision="tf32").resolve(torch.float32, cpu)
    assert not r.tf32 and not r.tensor_cores and r.ieee and r.precision == "tf32"
    assert RunOptions(precision="tf32").resolve(torch.float32, torch.device("cuda")).tf32
    monkeypatch.setattr(TUNABLES, "edge_concat_max_k", -1)  # fp32's rule: project; tensor cores': concat
    gn = GraphNetwork(**SMALL, precision="tf32")
    g = make_batch("mixed", dtype=torch.float32)
    a = gn(g)
    gn.precision = "fp32"
    assert all(torch.equal(getattr(a, n), getattr(gn(g), n)) for n in ("nodes", "edges", "globals"))
    assert ModelConfig().run.precision == "tf32"


class _Matmul:
    """torch.backends.cuda.matmul's settings as one torch version has them: older torch has only
    ``allow_tf32`` and raises AttributeError for ``fp32_precision``."""
    def __init__(self, new_api: bool):
        self.__dict__["values"] = {"allow_tf32": False, **({"fp32_precision": "ieee"} if new_api else {})}

    def __getattr__(self, name):
        if name not in self.values:
            raise AttributeError("Unknown attribute " + name)
        return self.values[name]

    def __setattr__(self, name, value):
        if name not in self.values:
            raise AttributeError("Unknown attribute " + name)
        self.values[name] = value


@pytest.mark.parametrize("new_api", [True, False])
def test_tf32_matmul_on_either_torch_api(monkeypatch, new_api):
    """TF32 is scoped through ``fp32_precision`` where torch has it, else through the legacy
    ``allow_tf32`` flag (torch < 2.9), and restored afterwards; the other setting is untouched."""
    from gnwarp.gn import tf32_matmul
    m = _Matmul(new_api)
    monkeypatch.setattr(torch.backends.cuda, "matmul", m)
    before = dict(m.values)
    with tf32_matmul(True):
        inside = dict(m.values)
    assert m.values == before
    if new_api:
        assert inside == {"allow_tf32": False, "fp32_precision": "tf32"}
    else:
        assert inside == {"allow_tf32": True}
    with tf32_matmul(False):
        assert m.values == before


def test_run_options_saved_names_and_errors():
    """Saved option dicts round-trip; earlier versions' names are read as today's; bad values and
    unknown keys are refused naming what is wrong."""
    o = RunOptions(impl="torch", path="blas", precision="fp16x3", emulate_min=(5, 6), check_inputs=False)
    assert RunOptions.from_dict(o.to_dict()) == o
    old = RunOptions.from_dict({"backend": "torch", "path": "split", "edge_first_layer": "split"})
    assert (old.impl, old.path, old.edge_first_layer) == ("torch", "blas", "project")
    with pytest.raises(ValueError, match="unknown run options"):
        RunOptions.from_dict({"precison": "fp16"})
    for bad in (dict(impl="jax"), dict(path="split"), dict(edge_first_layer="split"), dict(deterministic=1)):
        with pytest.raises(ValueError, match=next(iter(bad))):
            RunOptions(**bad)


def test_graph_network_options_attributes():
    """Options are set as a whole or one by one (validated; a refused value changes nothing), and
    "fp64" checks that the parameters are float64: there it is the fp32 path bit for bit."""
    gn = GraphNetwork(**SMALL, options=RunOptions(precision="tf32"))
    assert gn.precision == "tf32" and gn.options.precision == "tf32"
    with pytest.raises(TypeError, match="options"):
        GraphNetwork(**SMALL, options=RunOptions(), precision="fp16")
    with pytest.raises(ValueError, match="precision"):
        gn.precision = "fp8"
    assert gn.precision == "tf32"
    g = make_batch("mixed", dtype=torch.float32)
    gn.precision = "fp64"
    with pytest.raises(ValueError, match="float64 parameters"):
        gn(g)
    gn = gn.double()
    a = gn(cast(g, torch.float64))
    gn.precision = "fp32"
    assert torch.equal(a.nodes, gn(cast(g, torch.float64)).nodes)


# -- numerical stability ------------------------------------------------------------------------
CHAIN = dict(node_size=4, edge_size=4, global_size=4, node_out=4, edge_out=4, global_out=4,
             edge_hidden=(16, 16), node_hidden=(16,), global_hidden=(16,))


@pytest.mark.parametrize("deterministic", [False, True])
def test_large_inputs_and_long_chain_stay_accurate(deterministic):
    """Inputs of magnitude 1e4 through a residual chain of 6 blocks (x <- x + GN(x), float32):
    finite, and within 1e-4 of the float64 reference relative to each output's scale (float32
    eps is 6e-8; sums and GEMMs amplify it by the condition number, not by the magnitude)."""
    g = make_batch("chain", scale=1e4, fv=4, fe=4, fu=4)
    blocks, refs = [], []
    for k in range(6):
        gn, ref = pair(CHAIN, seed=10 + k, deterministic=deterministic)
        blocks.append(gn)
        refs.append(ref)
    gw = with_grad(cast(g, torch.float32))
    x, y = gw, with_grad(g)
    def residual(g, out):
        return g._replace(nodes=g.nodes + out.nodes, edges=g.edges + out.edges, globals=g.globals + out.globals)
    for gn, ref in zip(blocks, refs):
        x, y = residual(x, gn(x)), residual(y, ref(y))
    for name in ("nodes", "edges", "globals"):
        a, b = getattr(x, name), getattr(y, name)
        assert torch.isfinite(a).all(), name
        assert b.abs().max() > 1e3  # the large scale survived the chain
        assert rel_err(a, b) < 1e-4, (name, rel_err(a, b))
    (x.nodes.sum() + x.globals.sum()).backward()
    assert torch.isfinite(gw.nodes.grad).all() and torch.isfinite(gw.edges.grad).all()
    assert all(torch.isfinite(p.grad).all() for gn in blocks for p in gn.parameters())


# -- the fused tile path ------------------------------------------------------------------------
def test_tile_path_matches_reference_and_gradcheck():
    gn, ref = pair(TINY, dtype=torch.float64, path="tile")
    compare(gn, ref, make_batch("mixed", fv=2, fe=2, fu=2), fwd_tol=1e-12, grad_tol=1e-12)
    gn.check_inputs = False
    _gradcheck(gn, make_batch("gradcheck", fv=2, fe=2, fu=2))


def test_tile_path_float32():
    gn, ref = pair(TINY, path="tile")
    compare(gn, ref, make_batch("mixed", fv=2, fe=2, fu=2), fwd_tol=1e-5, grad_tol=1e-5)


def test_tile_kernel_too_large_is_refused_before_launch(monkeypatch):
    """A fused kernel over the CPU tile arena (256 KiB; Warp would abort the process) raises;
    path="auto" falls back to the blas path."""
    kw = dict(node_size=2, edge_size=2, global_size=2, node_out=2, edge_out=2, global_out=2,
              edge_hidden=(256, 256), node_hidden=(2,), global_hidden=(2,))  # a 256 KiB layer (256 x 256)
    g = make_batch("mixed", dtype=torch.float32, fv=2, fe=2, fu=2)
    gn = GraphNetwork(**kw, path="tile")
    launches = []
    real = wp.launch_tiled
    monkeypatch.setattr(wp, "launch_tiled", lambda *a, **k: launches.append(a) or real(*a, **k))
    with pytest.raises(tile_block.TileSharedMemoryError, match="shared memory"):
        gn(with_grad(g))
    assert not launches
    monkeypatch.setattr(rules, "choose_path", lambda *a, **k: "tile")
    gn.path = "auto"
    out = gn(with_grad(g))
    gn.path = "blas"
    assert torch.equal(out.nodes, gn(g).nodes)


def test_auto_path_rule():
    cfg = GNBlockConfig(**TINY)
    cuda = torch.device("cuda")
    assert rules.choose_path(cfg, _run(), torch.device("cpu"), 1000) == "blas"
    assert rules.choose_path(cfg, _run(), cuda, 1000) == "tile"
    assert rules.choose_path(cfg, _run(torch.float64, precision="fp64"), cuda, 1000) == "tile"
    assert rules.choose_path(cfg, _run(), cuda, 18) == "blas"        # batch 1: blas measured faster
    assert rules.choose_path(cfg, _run(), cuda, 10 ** 6) == "blas"   # beyond the measured range
    assert rules.choose_path(cfg, _run(deterministic=True), cuda, 1000) == "blas"
    assert rules.choose_path(GNBlockConfig(**SMALL), _run(precision="fp16"), cuda, 10) == "blas"
    assert "shared-memory" in rules.tile_feasible(GNBlockConfig(10, 10, 10), _run(), cuda)


# -- CUDA (runs where a GPU is present: the device machine; skipped in CI) -----------------------
def _on(g, device):
    return g._replace(**{k: getattr(g, k).to(device) for k in g._fields if isinstance(getattr(g, k), torch.Tensor)})


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("mode", ["concat", "project"])
@pytest.mark.parametrize("deterministic", [False, True])
def test_cuda_matches_float64_reference(mode, deterministic):
    """The CUDA kernels (both edge first-layer modes, both aggregations) against the float64
    reference: forward and every gradient."""
    gn, ref = pair(SMALL, deterministic=deterministic, edge_first_layer=mode)
    compare(gn.cuda(), ref.cuda(), _on(make_batch("mixed"), "cuda"), fwd_tol=1e-5, grad_tol=1e-5)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("mode", ["concat", "project"])
@pytest.mark.parametrize("precision,tol", [("tf32", 5e-3), ("fp16", 5e-3), ("bf16", 4e-2)])
def test_cuda_reduced_precision(precision, tol, mode):
    gn, ref = pair(SMALL, precision=precision, edge_first_layer=mode)
    gn, ref = gn.cuda(), ref.cuda()
    g = _on(make_batch("mixed"), "cuda")
    out, expect = gn(cast(g, torch.float32)), ref(g)
    for name in ("nodes", "edges", "globals"):
        assert rel_err(getattr(out, name), getattr(expect, name)) < tol, name


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("mode", ["concat", "project"])
def test_cuda_side_stream_gradients_identical(mode):
    """The weight-gradient GEMMs on side streams (``TUNABLES.side_streams``) give the same
    gradients, bit for bit, as on the current stream (deterministic aggregation), also when two
    backward passes run back to back."""
    gn, _ = pair(SMALL, deterministic=True, edge_first_layer=mode)
    gn = gn.cuda()
    g = with_grad(cast(_on(make_batch("mixed"), "cuda"), torch.float32))
    grads = {}
    old = TUNABLES.side_streams
    try:
        for side in (0, 1, 3):
            TUNABLES.side_streams = side
            gn.zero_grad(set_to_none=True)
            for x in (g.nodes, g.edges, g.globals):
                x.grad = None
            for _ in range(2):
                loss_of(gn(g)).backward()
            torch.cuda.synchronize()
            grads[side] = [p.grad.clone() for p in gn.parameters()] + [x.grad.clone() for x in (g.nodes, g.edges, g.globals)]
    finally:
        TUNABLES.side_streams = old
    for side in (1, 3):
        assert len(grads[side]) == len(grads[0])
        for a, b in zip(grads[0], grads[side]):
            assert torch.equal(a, b)


# -- fp16x3: float32-accurate GEMMs from fp16 pieces ---------------------------------------------
EMU = dict(SMALL, edge_hidden=(16, 16, 16), node_hidden=(16, 16), global_hidden=(16, 8))


def _emu_pieces(src, epilogue=None, relu=False, write_f32=False, weights=False):
    """Run ``pieces_kernel`` on the rows of ``src`` (CPU). ``epilogue``: (row_inv, col_inv, bias)."""
    rows, w = src.shape
    pieces = torch.full((rows, 3 * w), float("nan"), dtype=torch.float16)
    inv = torch.full((rows,), float("nan"))
    fp16x3.pieces(Launcher(src), w, rows, src, epilogue=epilogue, relu=relu, dst=src if write_f32 else None,
                  out=pieces, inv=inv, weights=weights)
    return pieces, inv


@pytest.mark.parametrize("w", [37, 38, 64])  # column groups of 1, 2, 4 (``group``)
@pytest.mark.parametrize("weights", [False, True])
def test_fp16x3_pieces_kernel(weights, w):
    """Row scales put each row's largest |y| in [2^14, 2^15); hi = fp16(y * s) (torch's rounding),
    lo = fp16 of the remainder; (hi + lo) / s recovers y to ~2^-22 of the row's largest element,
    including rows far outside fp16's range (1e30, 1e-30), an all-zero row and a NaN row."""
    gen = torch.Generator().manual_seed(0)
    y = torch.randn(7, w, generator=gen)
    y[1] *= 1e30
    y[2] *= 1e-30
    y[3] = 0.0
    y[4, :5] = torch.tensor([65504.0, -1e5, 1e-8, 3.0, -0.0])
    y[5, 7] = float("nan")
    pieces, inv = _emu_pieces(y.clone(), weights=weights)
    hi, second, third = pieces[:, :w], pieces[:, w:2 * w], pieces[:, 2 * w:]
    lo = third if weights else second
    ok = torch.ones(7, dtype=torch.bool)
    ok[5] = False
    assert torch.equal((second if weights else third)[ok], hi[ok])  # [hi|hi|lo] or [hi|lo|hi]
    s = 1.0 / inv.double()
    top = (y.double().abs().max(1).values * s)[ok & (y.abs().max(1).values > 0)]
    assert ((top >= 2.0 ** 14) & (top < 2.0 ** 15)).all(), top
    assert torch.equal(hi[ok], (y.double() * s[:, None]).float().half()[ok])  # exact powers of two: same rounding
    back = (hi.double() + lo.double()) * inv.double()[:, None]
    err = (back - y.double()).abs().max(1).values / y.double().abs().max(1).values.clamp_min(1e-300)
    assert (err[ok] <= 2.0 ** -22).all(), err
    assert torch.isnan(hi[5, 7]) and torch.isfinite(hi[5, :7]).all()


def test_fp16x3_pieces_kernel_epilogue_in_place():
    """The epilogue: y = relu(src * row_inv * col_inv + bias) written back over ``src`` and split."""
    gen = torch.Generator().manual_seed(1)
    src = torch.randn(5, 20, generator=gen) * 100
    ri = torch.tensor([2.0 ** -3, 1.0, 2.0 ** 5, 0.5, 4.0])
    ci = 2.0 ** torch.randint(-4, 4, (20,), generator=gen).float()
    b = torch.randn(20, generator=gen)
    expect = torch.relu(src * ri[:, None] * ci + b)
    buf = src.clone()
    pieces, inv = _emu_pieces(buf, (ri, ci, b), relu=True, write_f32=True)
    assert torch.equal(buf, expect)
    back = (pieces[:, :20].double() + pieces[:, 20:40].double()) * inv.double()[:, None]
    assert ((back - expect.double()).abs().max(1).values <= 2.0 ** -22 * expect.abs().max(1).values).all()


def _fp16x3_pair(scale=1.0, mode="auto"):
    gn, ref = pair(EMU, precision="fp16x3", edge_first_layer=mode)
    gn.emulate_min = (0, 0)  # every MLP's layers 1..L emulate, whatever the batch
    return gn, ref, make_batch("mixed", scale=scale)


def _assert_fp16x3_within_4x_of_fp32(gn, ref, g):
    """fp16x3's forward error against float64 within 4x of IEEE fp32's (or under 1e-6)."""
    x = cast(g, torch.float32)
    with torch.no_grad():
        out, expect = gn(x), ref(g)
        gn.precision = "fp32"
        o32 = gn(x)
        gn.precision = "fp16x3"
    for name in ("nodes", "edges", "globals"):
        e16x3 = rel_err(getattr(out, name), getattr(expect, name))
        e32 = rel_err(getattr(o32, name), getattr(expect, name))
        assert e16x3 <= max(4 * e32, 1e-6), (name, e16x3, e32)


@pytest.mark.parametrize("mode", ["auto", "project"])
def test_fp16x3_matches_float64_reference(mode):
    """fp16x3 forward and every gradient against float64 at float32's tolerance (the backward's
    GEMMs are IEEE fp32 on the float32 activations the emulated forward also writes). "auto" is
    concat for fp16x3: the edge MLP's first layer emulates too; "project": from its second layer."""
    gn, ref, g = _fp16x3_pair(mode=mode)
    compare(gn, ref, g, fwd_tol=1e-5, grad_tol=1e-5)


@pytest.mark.parametrize("scale", [1e4, 1e6])
def test_fp16x3_outside_fp16_range(scale):
    """Inputs and activations beyond fp16's range (65504): the row scales keep the pieces finite;
    the error stays within 4x of IEEE fp32's (plain fp16 overflows at 1e6)."""
    _assert_fp16x3_within_4x_of_fp32(*_fp16x3_pair(scale))


def test_fp16x3_rule_falls_back_to_fp32():
    """Below the rule's rows / width (small batches, narrow MLPs) fp16x3 runs the IEEE fp32 path:
    bitwise the same outputs; and it does emulate once allowed (different rounding)."""
    gn, _, g = _fp16x3_pair()
    x = cast(g, torch.float32)
    gn.emulate_min = (TUNABLES.emulate_min_rows, TUNABLES.emulate_min_width)
    a = gn(x)
    gn.precision = "fp32"
    b = gn(x)
    assert all(torch.equal(getattr(a, n), getattr(b, n)) for n in ("nodes", "edges", "globals"))
    gn.precision, gn.emulate_min = "fp16x3", (0, 0)
    c = gn(x)
    assert not torch.equal(c.edges, b.edges)
    # float64 parameters: no fp16 pieces, the float64 path bitwise (whatever emulate_min says)
    gn = gn.double()
    x64 = cast(g, torch.float64)
    d = gn(x64)
    gn.precision = "fp32"
    e = gn(x64)
    assert all(torch.equal(getattr(d, n), getattr(e, n)) for n in ("nodes", "edges", "globals"))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_fp16x3():
    """fp16x3 on CUDA (fp16 GEMMs with float32 output) against float64: float32's tolerance
    for the forward and every gradient, and within 4x of IEEE fp32's forward error."""
    gn, ref, g = _fp16x3_pair()
    gn, ref = gn.cuda(), ref.cuda()
    g = _on(g, "cuda")
    compare(gn, ref, g, fwd_tol=1e-5, grad_tol=1e-5)
    _assert_fp16x3_within_4x_of_fp32(gn, ref, g)


@pytest.mark.parametrize("bad", [(1,), (1, -2), (1.5, 3), "16384,512"])
def test_emulate_min_checked(bad):
    with pytest.raises(ValueError, match="emulate_min"):
        GraphNetwork(**EMU, precision="fp16x3", emulate_min=bad)


@pytest.mark.parametrize("width", [16, 40, 64, 70])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_packed_relu_mask_backward_equals_the_activation_one(width, dtype):
    """The ReLU backward from a packed 1-bit mask (the rollout's activation store) equals the one
    from the activation, for widths that fill whole 32-bit words and widths that do not; exact
    zeros in the activation are masked as ReLU's are."""
    from gnwarp.gn.mlp import PackedMask, pack_mask, relu_grad
    from gnwarp.gn.options import RunOptions as RO
    torch.manual_seed(width)
    rows = 37
    act = torch.relu(torch.randn(rows, width, dtype=dtype))
    act[3, :5] = 0.0
    g = torch.randn(rows, width, dtype=dtype)
    run = RO().resolve(dtype, torch.device("cpu"))
    launch = Launcher(act)
    mask = pack_mask(launch, act)
    assert mask.bits.shape == (rows, (width + 31) // 32) and mask.bits.dtype == torch.int32
    a, b = g.clone(), g.clone()
    relu_grad(launch, run, act, a, None)
    relu_grad(launch, run, mask, b, None)
    assert torch.equal(a, b) and torch.equal(a, torch.where(act > 0, g, torch.zeros_like(g)))
    # the bit count is the number of positive activations
    n_set = sum(bin(int(w) & 0xFFFFFFFF).count("1") for w in mask.bits.flatten().tolist())
    assert n_set == int((act > 0).sum())
    # into an existing buffer; a wrong buffer or a bias gradient is refused
    again = pack_mask(launch, act, out=torch.zeros_like(mask.bits))
    assert torch.equal(again.bits, mask.bits)
    with pytest.raises(ValueError, match="int32"):
        pack_mask(launch, act, out=torch.zeros(rows, 1, dtype=torch.int64))
    with pytest.raises(ValueError, match="bias gradient"):
        relu_grad(launch, run, mask, g.clone(), torch.zeros(width, dtype=dtype))
    with pytest.raises(ValueError, match="packed mask"):
        relu_grad(launch, run, PackedMask(mask.bits, width + 1), g.clone(), None)
