"""Observation graphs (Figure H.3) and the GN networks on them: layout, actuator mapping, Warp
kernels against the torch reference (forward and gradients), shapes and errors."""
from __future__ import annotations

import copy
import warnings

import pytest
import torch

pytest.importorskip("dm_control")

from gnwarp.rl.gn_nets import (GNDeterministicPolicy, GNGaussianPolicy, GNObservationModel,  # noqa: E402
                               GNQFunction, make_networks)
from gnwarp.rl.obs_graph import ObservationGraph  # noqa: E402

warnings.filterwarnings("ignore", message=".*glfw.*")
DOMAINS = ("swimmer6", "cheetah", "walker")


@pytest.fixture(scope="module")
def graphs():
    return {d: ObservationGraph(d) for d in DOMAINS}


def _batch(og, n=3, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(n, og.obs_size, generator=g, dtype=dtype),
            torch.rand(n, og.nu, generator=g, dtype=dtype) * 2 - 1)


def test_swimmer6_graph_is_figure_h3(graphs):
    og = graphs["swimmer6"]
    obs, act = _batch(og, n=2)
    g = og(obs, act).validate()
    assert og.n_node == 6 and og.n_edge == 10 and og.node_size == 3 and og.global_size == 2
    assert og.edge_names(True) == ["joints", "force", "direction"]
    assert g.nodes.shape == (12, 3) and g.edges.shape == (20, 3) and g.globals.shape == (2, 2)
    # link k's velocities on node k, joint k's angle and force on edges k (k -> k+1) and 5 + k (back)
    vel = obs[:, 7:].reshape(2, 6, 3)
    assert torch.equal(g.nodes.reshape(2, 6, 3), vel)
    e = g.edges.reshape(2, 10, 3)
    assert torch.equal(e[:, :5, 0], obs[:, :5]) and torch.equal(e[:, 5:, 0], obs[:, :5])
    assert torch.equal(e[:, :5, 1], act) and torch.equal(e[:, 5:, 1], act)
    assert e[:, :5, 2].eq(1).all() and e[:, 5:, 2].eq(-1).all()
    assert og.senders.tolist() == [0, 1, 2, 3, 4, 1, 2, 3, 4, 5]
    assert torch.equal(g.globals, obs[:, 5:7])
    # graph 1's indices offset by graph 0's 6 nodes
    assert g.senders[10:].tolist() == [s + 6 for s in og.senders.tolist()]
    assert og(obs).edges.shape == (20, 2)          # a policy's graph: no force


@pytest.mark.parametrize("domain", DOMAINS)
def test_every_observation_entry_has_one_place(graphs, domain):
    og = graphs[domain]
    places = torch.cat([og.node_index.reshape(-1), og.edge_index.reshape(-1), og.global_index])
    assert sorted(places.tolist()) == list(range(og.obs_size))
    obs, act = _batch(og)
    assert torch.equal(og.flat_features(og(obs, act)), obs)


@pytest.mark.parametrize("domain", DOMAINS)
def test_edge_actions_map_back_to_the_right_actuator(graphs, domain):
    og = graphs[domain]
    m = og.observation.model
    obs, act = _batch(og, n=4, seed=1)
    g = og(obs, act)
    force = og.edge_names(True).index("force")
    assert torch.equal(og.edge_actions(g.edges[:, force:force + 1])[..., 0], act)
    for u in range(og.nu):   # actuator u's forward edge runs from its joint's parent body to the joint's body
        body = int(m.jnt_bodyid[m.actuator_trnid[u, 0]])
        k = int(og.actuator_edge[u])
        assert (int(og.senders[k]), int(og.receivers[k])) == (int(m.body_parentid[body]) - 1, body - 1)
    # a policy's per-edge output for actuator u's forward edge lands in column u
    values = torch.zeros(4 * og.n_edge, 1, dtype=torch.float64)
    values.view(4, og.n_edge)[:, int(og.actuator_edge[og.nu - 1])] = 1
    out = og.edge_actions(values)[..., 0]
    assert out[:, -1].eq(1).all() and out[:, :-1].eq(0).all()


def _nets(domain, graphs):
    og = graphs[domain]
    kw = dict(latent=8, hidden=(8,), blocks=2, impl="warp", precision="fp64")
    torch.manual_seed(0)
    return [GNGaussianPolicy(og, **kw).double(), GNDeterministicPolicy(og, **kw).double(),
            GNQFunction(og, **kw).double(), GNObservationModel(og, **kw).double()]


def _outputs(net, obs, act):
    if isinstance(net, (GNQFunction, GNObservationModel)):
        out = net(obs, act)
    else:
        out = net(obs)
    return torch.cat([o.reshape(-1) for o in (out if isinstance(out, tuple) else (out,))])


@pytest.mark.parametrize("domain", ("swimmer6", "cheetah"))
def test_warp_kernels_match_the_torch_reference(graphs, domain):
    og = graphs[domain]
    for net in _nets(domain, graphs):
        results = {}
        for impl in ("warp", "torch"):
            net.gn.impl = impl
            net.zero_grad()
            obs, act = _batch(og, n=3, seed=2)
            obs.requires_grad_(True)
            act.requires_grad_(True)
            out = _outputs(net, obs, act)
            w = torch.linspace(-1, 1, out.numel(), dtype=out.dtype)
            (out * w).sum().backward()
            # (a policy's last node update feeds nothing: no gradient)
            grads = [torch.zeros_like(p) if p.grad is None else p.grad.clone() for p in net.parameters()]
            results[impl] = (out.detach(), obs.grad, act.grad, grads)
        (o1, go1, ga1, gp1), (o2, go2, ga2, gp2) = results["warp"], results["torch"]
        name = type(net).__name__
        assert torch.allclose(o1, o2, atol=1e-10), name
        assert torch.allclose(go1, go2, atol=1e-10), name
        assert ga1 is None and ga2 is None or torch.allclose(ga1, ga2, atol=1e-10), name
        assert all(torch.allclose(a, b, atol=1e-10) for a, b in zip(gp1, gp2)), name
        assert go1.abs().max() > 0 and any(g.abs().max() > 0 for g in gp1), name


def test_shapes_and_the_mlp_option(graphs):
    og = graphs["walker"]
    obs, act = _batch(og, n=5, dtype=torch.float32)
    for network in ("gn", "mlp"):
        policy, q = make_networks(network, og, gaussian=True, latent=8, hidden=(8,), impl="torch") \
            if network == "gn" else make_networks(network, og, hidden=(8,))
        mean, log_std = policy(obs)
        assert mean.shape == log_std.shape == (5, og.nu) and q(obs, act).shape == (5,)
        # log_std starts near log(0.5) and stays inside its bounds
        assert (log_std > -5).all() and (log_std < 1).all()
        det, _ = make_networks(network, og, gaussian=False, hidden=(8,), **({"impl": "torch"} if network == "gn" else {}))
        assert det(obs).shape == (5, og.nu)
    torch.manual_seed(0)
    pol = GNGaussianPolicy(og, latent=8, hidden=(8,), impl="torch", init_std=0.3)
    torch.nn.init.zeros_(pol.gn.blocks[-1].edge_mlp.layers[-1].weight)
    assert torch.allclose(pol(obs)[1], torch.full((5, og.nu), torch.log(torch.tensor(0.3)).item()), atol=1e-5)
    model = GNObservationModel(og, latent=8, hidden=(8,), impl="torch")
    assert model(obs, act).shape == obs.shape


def test_observation_model_normalization(graphs):
    og = graphs["swimmer6"]
    obs, act = _batch(og, n=6, dtype=torch.float32)
    step = torch.linspace(0.01, 2.0, og.obs_size)
    model = GNObservationModel(og, latent=8, hidden=(8,), impl="torch")
    model.normalize_from(obs, obs + step * torch.randn(6, og.obs_size))
    assert torch.allclose(model.obs_mean, obs.mean(0)) and (model.delta_std > 0).all()
    last = model.gn.blocks[-1]
    with torch.no_grad():                       # every output 1: the change is delta_std in each place
        for mlp in (last.node_mlp, last.edge_mlp, last.global_mlp):
            mlp.layers[-1].weight.zero_()
            mlp.layers[-1].bias.fill_(1)
    assert torch.allclose(model(obs, act) - obs, model.delta_std.expand(6, -1), atol=1e-6)
    state = model.state_dict()
    assert {"obs_mean", "obs_std", "delta_std"} <= set(state)
    with pytest.raises(ValueError, match=r"\[B >= 2, 25\]"):
        model.normalize_from(obs[:1], obs[:1])


def test_copies_share_the_graph_and_give_the_same_outputs(graphs):
    og = graphs["swimmer6"]
    obs, act = _batch(og, dtype=torch.float32)
    q = GNQFunction(og, latent=8, hidden=(8,))
    before = q(obs, act)                       # caches a graph index
    twin = copy.deepcopy(q)                    # as agents make their target networks
    assert twin.graph is q.graph and torch.equal(twin(obs, act), before)
    q.gn.set_options(deterministic=True)       # another index for deterministic kernels
    assert all(b.deterministic for b in q.gn.blocks)
    assert torch.allclose(q(obs, act), before, atol=1e-6)


def test_errors(graphs):
    og = graphs["swimmer6"]
    with pytest.raises(ValueError, match=r"observations must be \[N, 25\]"):
        og(torch.zeros(2, 24))
    with pytest.raises(ValueError, match=r"actions must be \[N=2, 5\]"):
        og(torch.zeros(2, 25), torch.zeros(2, 4))
    with pytest.raises(ValueError, match="unknown network"):
        make_networks("transformer", og)
    with pytest.raises(ValueError, match="init_std"):
        GNGaussianPolicy(og, init_std=10.0)
    with pytest.raises(ValueError, match="blocks must be at least 1"):
        GNQFunction(og, blocks=0)
    with pytest.raises(ValueError, match="keep identity on"):
        ObservationGraph("cheetah", identity=False)
