"""GraphsTuple batching/unbatching/validation, numpy and torch alike."""
import numpy as np
import pytest
import torch

from gnwarp.graphs import GraphsTuple, batch, tile, unbatch, validate


def _graph(rng, nv, ne, fv=4, fe=3, fg=2):
    return GraphsTuple(nodes=rng.normal(size=(nv, fv)), edges=rng.normal(size=(ne, fe)),
                       globals=rng.normal(size=(1, fg)), senders=rng.integers(0, nv, ne),
                       receivers=rng.integers(0, nv, ne), n_node=np.array([nv]), n_edge=np.array([ne]))


@pytest.mark.parametrize("to_torch", [False, True])
def test_batch_unbatch_roundtrip_varied_sizes(to_torch):
    rng = np.random.default_rng(0)
    gs = [_graph(rng, 3, 4), _graph(rng, 1, 0), _graph(rng, 7, 12), _graph(rng, 2, 1)]
    if to_torch:
        gs = [g.to_torch() for g in gs]
    b = batch(gs)
    validate(b)
    assert b.total_nodes == 13 and b.total_edges == 17 and b.n_graph == 4
    # third graph's indices are offset by the nodes before it
    s = np.asarray(b.senders[4:16]) if not to_torch else b.senders[4:16].numpy()
    np.testing.assert_array_equal(s, np.asarray(gs[2].senders) + 4)
    for g, u in zip(gs, unbatch(b)):
        for a, c in zip(g, u):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(c))
    ng = np.asarray(b.node_graph_index())
    np.testing.assert_array_equal(ng, np.repeat(np.arange(4), [3, 1, 7, 2]))


def test_tile_matches_batch():
    rng = np.random.default_rng(1)
    g = _graph(rng, 5, 6)
    nodes = rng.normal(size=(3, 5, 4))
    t = tile(g, 3, nodes=nodes)
    b = batch([g._replace(nodes=nodes[k], edges=None, globals=None) for k in range(3)])
    np.testing.assert_array_equal(t.senders, b.senders)
    np.testing.assert_array_equal(t.receivers, b.receivers)
    np.testing.assert_allclose(t.nodes, b.nodes)
    tt = tile(g.to_torch(), 3, nodes=torch.as_tensor(nodes))
    np.testing.assert_array_equal(tt.senders.numpy(), b.senders)


@pytest.mark.parametrize("change,msg", [
    (dict(senders=np.array([0, 1, 1, 9])), "out of range"),
    (dict(n_edge=np.array([3])), "n_edge sums"),
    (dict(nodes=np.zeros((2, 4))), "n_node sums"),
    (dict(globals=np.zeros((2, 2))), "globals has"),
    (dict(senders=np.array([0.0, 1, 1, 2])), "integer"),
])
def test_validate_names_the_problem(change, msg):
    g = GraphsTuple(nodes=np.zeros((3, 4)), edges=np.zeros((4, 2)), globals=np.zeros((1, 2)),
                    senders=np.array([0, 1, 1, 2]), receivers=np.array([1, 0, 2, 1]), n_node=np.array([3]),
                    n_edge=np.array([4]))
    validate(g)
    with pytest.raises(ValueError, match=msg):
        validate(g._replace(**change))


def test_validate_rejects_edges_across_graphs():
    rng = np.random.default_rng(2)
    b = batch([_graph(rng, 2, 2), _graph(rng, 2, 2)])
    bad = b._replace(receivers=np.array([2, 1, 2, 3]))
    with pytest.raises(ValueError, match="different graph"):
        validate(bad)
