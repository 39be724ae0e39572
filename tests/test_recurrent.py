"""The recurrent GN core against an unrolled reference (plain torch GRU equations on the same
parameters), Warp against torch, and its gradients against finite differences."""
import pytest
import torch

from gnwarp.gn import RunOptions
from gnwarp.graphs import GraphsTuple
from gnwarp.interop import warp
from gnwarp.models.recurrent import KINDS, RecurrentGNConfig, RecurrentGNCore

warp()

SIZES = {"nodes": 5, "edges": 2, "globals": 0}
CFG = RecurrentGNConfig(latent=6, hidden_edges=3, hidden_nodes=4, hidden_globals=2, edge_mlp=(8,), node_mlp=(8,),
                        global_mlp=(8,), out_edges=0, out_nodes=3, out_globals=2)


def graphs(T, dtype=torch.float64, seed=0):
    """T graphs of one topology: two graphs of 3 and 2 nodes, 4 and 2 edges."""
    g = torch.Generator().manual_seed(seed)
    snd = torch.tensor([0, 1, 1, 2, 3, 4])
    rcv = torch.tensor([1, 0, 2, 1, 4, 3])
    out = []
    for _ in range(T):
        out.append(GraphsTuple(nodes=torch.randn(5, SIZES["nodes"], generator=g, dtype=dtype),
                               edges=torch.randn(6, SIZES["edges"], generator=g, dtype=dtype),
                               receivers=rcv, senders=snd, globals=torch.zeros(2, 0, dtype=dtype),
                               n_node=torch.tensor([3, 2]), n_edge=torch.tensor([4, 2])))
    return out


def core(impl="torch", dtype=torch.float64, seed=0):
    torch.manual_seed(seed)
    return RecurrentGNCore(CFG, SIZES, RunOptions(impl=impl)).to(dtype)


def gru_reference(cell: torch.nn.GRUCell, x, h):
    """The GRU equations written out (r, z, n gates in torch's weight order)."""
    gi = x @ cell.weight_ih.T + cell.bias_ih
    gh = h @ cell.weight_hh.T + cell.bias_hh
    i_r, i_z, i_n = gi.chunk(3, -1)
    h_r, h_z, h_n = gh.chunk(3, -1)
    r, z = torch.sigmoid(i_r + h_r), torch.sigmoid(i_z + h_z)
    n = torch.tanh(i_n + r * h_n)
    return (1 - z) * n + z * h


def unrolled(m: RecurrentGNCore, seq):
    h = {k: torch.zeros(getattr(seq[0], k).shape[0] if k != "edges" else seq[0].senders.shape[0],
                        m.config.hidden(k), dtype=torch.float64) for k in KINDS}
    h["globals"] = torch.zeros(2, m.config.hidden_globals, dtype=torch.float64)
    outs = []
    for g in seq:
        x = g._replace(nodes=torch.cat([g.nodes, h["nodes"]], -1), edges=torch.cat([g.edges, h["edges"]], -1),
                       globals=h["globals"])
        z = m.gn.reference_forward(x)
        h = {k: gru_reference(m.gru[k], getattr(z, k), h[k]) for k in KINDS}
        outs.append({k: torch.cat([getattr(z, k), h[k]], -1) @ m.out[k].weight.T + m.out[k].bias
                     for k in KINDS if m.config.out(k)})
    return outs, h


def test_sequence_matches_unrolled_reference():
    m, seq = core(), graphs(4)
    outs, h = m.sequence(seq)
    ref_outs, ref_h = unrolled(m, seq)
    assert len(outs) == 4
    for o, r in zip(outs, ref_outs):
        assert o.edges is None
        for k, v in r.items():
            torch.testing.assert_close(getattr(o, k), v, rtol=1e-12, atol=1e-12)
    for k in KINDS:
        torch.testing.assert_close(getattr(h, k), ref_h[k], rtol=1e-12, atol=1e-12)
    # a callable and an explicit hidden state give the same
    outs2, h2 = m.sequence(lambda t: seq[t], hidden=m.initial_hidden(seq[0]), steps=4)
    torch.testing.assert_close(outs2[-1].nodes, outs[-1].nodes)
    # last_only: the last output alone, the same numbers
    outs3, h3 = m.sequence(seq, last_only=True)
    assert len(outs3) == 1
    torch.testing.assert_close(outs3[0].nodes, outs[-1].nodes, rtol=0, atol=0)
    torch.testing.assert_close(h3.nodes, h.nodes, rtol=0, atol=0)
    # continuing from a hidden state is the same as one longer sequence
    _, h_a = m.sequence(seq[:2])
    _, h_b = m.sequence(seq[2:], hidden=h_a)
    torch.testing.assert_close(h_b.nodes, h.nodes)


def test_warp_and_torch_agree():
    a, b = core("torch", torch.float32), core("warp", torch.float32)
    b.load_state_dict(a.state_dict())
    seq = graphs(3, torch.float32)
    oa, ha = a.sequence(seq)
    ob, hb = b.sequence(seq)
    for k in ("nodes", "globals"):
        torch.testing.assert_close(getattr(oa[-1], k), getattr(ob[-1], k), rtol=1e-5, atol=1e-5)
    for k in KINDS:
        torch.testing.assert_close(getattr(ha, k), getattr(hb, k), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("impl", ["torch", "warp"])
def test_gradients_through_the_window_match_finite_differences(impl):
    m, seq = core(impl), graphs(3)
    nodes = [g.nodes.clone().requires_grad_() for g in seq]
    edges = seq[1].edges.clone().requires_grad_()

    def f(n0, n1, n2, e1):
        gs = [seq[0]._replace(nodes=n0), seq[1]._replace(nodes=n1, edges=e1), seq[2]._replace(nodes=n2)]
        outs, h = m.sequence(gs)
        return outs[-1].nodes.sum(-1), outs[-1].globals, h.edges
    assert torch.autograd.gradcheck(f, (*nodes, edges), eps=1e-6, atol=1e-6, rtol=1e-5)


def test_shape_errors():
    m, seq = core(), graphs(2)
    h = m.initial_hidden(seq[0])
    with pytest.raises(ValueError, match="hidden graph nodes"):
        m.step(seq[0], h._replace(nodes=h.nodes[:3]))
    with pytest.raises(ValueError, match="input graph edges"):
        m.step(seq[0]._replace(edges=seq[0].edges[:, :1]), h)
    with pytest.raises(ValueError, match="steps="):
        m.sequence(lambda t: seq[t])
