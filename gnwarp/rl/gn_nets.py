"""Graph-network policies, Q-functions and observation models on observation graphs
(``gnwarp.rl.obs_graph``), with the call signatures of the agents' MLP networks so that either
can be used:

- ``GNGaussianPolicy``: ``policy(obs [N, D]) -> (mean [N, U], log_std [N, U])``, each joint's
  action read from its forward edge's two outputs (``ObservationGraph.edge_actions``);
  ``log_std`` squashed smoothly into [``log_std_min``, ``log_std_max``], starting at
  ``log(init_std)``;
- ``GNDeterministicPolicy``: ``policy(obs) -> u [N, U]`` (one output per forward edge);
- ``GNQFunction``: ``q(obs [N, D], action [N, U]) -> [N]``, the last block's global output, the
  actions on the edges as joint forces;
- ``GNObservationModel``: ``model(obs, action) -> next_obs [N, D]``, the observation plus a
  change predicted in the graph's places (node, forward edge and global outputs gathered back).

Each is a stack of ``blocks`` full GN blocks (``gnwarp.gn.GraphNetwork``, edge -> node ->
global updates): the first reads the observation graph, the middle ones map ``latent`` widths to
``latent`` widths, the last gives the outputs; every MLP has ``hidden`` layers. Run options
(``impl="warp"`` kernels or the ``"torch"`` reference, ``path``, ``precision``) go to every
block; ``net.gn.impl = "torch"`` or ``net.gn.set_options(...)`` changes them all. ``make_networks("gn" | "mlp", ...)`` builds the
policy and Q-function of either kind (``"mlp"``: MLPs on the flat observation).

    >>> og = ObservationGraph("swimmer6")
    >>> policy, q = make_networks("gn", og, gaussian=True, latent=64, hidden=(64,))
    >>> mean, log_std = policy(obs)          # obs [N, 25] -> [N, 5], [N, 5]
    >>> value = q(obs, action)               # [N]
"""
from __future__ import annotations

import math

import torch
from torch import nn

from gnwarp.gn.config import GNBlockConfig
from gnwarp.gn.module import GraphNetwork
from gnwarp.gn.options import RunOptions
from gnwarp.rl.networks import NormalizedModel
from gnwarp.gn.reference import MLP
from gnwarp.rl.obs_graph import ObservationGraph

__all__ = ["GNStack", "GNGaussianPolicy", "GNDeterministicPolicy", "GNQFunction", "GNObservationModel",
           "MLPGaussianPolicy", "MLPDeterministicPolicy", "MLPQFunction", "make_networks", "NETWORKS"]

NETWORKS = ("gn", "mlp")
_INDEX_CACHE = 4   # graph indices kept per stack (one per batch size and device in use)


class GNStack(nn.Module):
    """``blocks`` GN blocks from input widths (``node_size``, ``edge_size``, ``global_size``) to
    outputs (``node_out``, ``edge_out``, ``global_out``; ``global_out=0``: the last block keeps
    no global update). ``stack(graph) -> GraphsTuple``; run options as ``GraphNetwork``'s, with
    ``check_inputs`` off unless given (the topology is validated once per batch size)."""

    def __init__(self, node_size: int, edge_size: int, global_size: int, node_out: int, edge_out: int,
                 global_out: int, latent: int = 64, hidden: tuple[int, ...] = (64,), blocks: int = 2,
                 options: RunOptions | None = None, **run):
        super().__init__()
        if int(blocks) < 1:
            raise ValueError(f"blocks must be at least 1, got {blocks}")
        # the observation graph's topology is fixed and validated once per batch size (the index
        # cache below) and its features come from checked observations: per-call input checks
        # would only sync with the host (which a CUDA-graph capture of an update cannot take)
        options = options if options is not None else RunOptions(**{"check_inputs": False, **run})
        hidden = tuple(int(h) for h in hidden)
        sizes = (node_size, edge_size, global_size)
        layers = []
        for k in range(int(blocks)):
            last = k == int(blocks) - 1
            outs = (node_out, edge_out, global_out) if last else (latent, latent, latent)
            cfg = GNBlockConfig(node_size=sizes[0], edge_size=sizes[1], global_size=sizes[2],
                                node_out=max(outs[0], 1), edge_out=outs[1], global_out=max(outs[2], 1),
                                edge_hidden=hidden, node_hidden=hidden, global_hidden=hidden,
                                update_globals=not (last and global_out == 0))
            layers.append(GraphNetwork(cfg, options=options))
            sizes = outs
        self.blocks = nn.ModuleList(layers)
        self._index: dict = {}

    @property
    def impl(self) -> str:
        return self.blocks[0].impl

    @impl.setter
    def impl(self, value: str) -> None:
        for b in self.blocks:
            b.impl = value

    def set_options(self, **kw) -> None:
        """Change run options (``RunOptions`` fields: ``impl``, ``path``, ``precision``,
        ``deterministic``, ...) of every block."""
        for b in self.blocks:
            b.options = b.options.replace(**kw)

    def forward(self, graph):
        index = None
        if self.blocks[0].impl == "warp":
            key = (int(graph.n_node.shape[0]), str(graph.senders.device), self.blocks[0].deterministic)
            index = self._index.get(key)
            if index is None:   # one validation (a host sync) per batch size: the topology is fixed
                index = self.blocks[0].graph_index(graph)
                if len(self._index) >= _INDEX_CACHE:
                    self._index.pop(next(iter(self._index)))
                self._index[key] = index
        for b in self.blocks:
            graph = b(graph, index)
        return graph


def _graph(graph) -> ObservationGraph:
    return graph if isinstance(graph, ObservationGraph) else ObservationGraph(graph)


def _log_std_head(init_std: float, lo: float, hi: float) -> float:
    """The raw output that puts ``lo + (hi - lo)(tanh(raw) + 1) / 2`` at log(init_std)."""
    if not lo < math.log(init_std) < hi:
        raise ValueError(f"init_std {init_std} lies outside exp([{lo}, {hi}])")
    return math.atanh(2 * (math.log(init_std) - lo) / (hi - lo) - 1)


class GNGaussianPolicy(nn.Module):
    """``obs [N, D] -> (mean [N, U], log_std [N, U])`` on the observation graph (module docstring).
    ``graph``: an ``ObservationGraph`` or a name it takes."""

    def __init__(self, graph, latent: int = 64, hidden: tuple[int, ...] = (64,), blocks: int = 2,
                 init_std: float = 0.5, log_std_min: float = -5.0, log_std_max: float = 1.0, **run):
        super().__init__()
        self.graph = _graph(graph)
        g = self.graph
        self.lo, self.hi = float(log_std_min), float(log_std_max)
        raw0 = _log_std_head(init_std, self.lo, self.hi)
        self.gn = GNStack(g.node_size, g.edge_size(False), g.global_size, 1, 2, 0, latent, hidden, blocks, **run)
        with torch.no_grad():
            self.gn.blocks[-1].edge_mlp.layers[-1].bias[1] = raw0

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = self.graph.edge_actions(self.gn(self.graph(obs)).edges)     # [N, U, 2]
        mean, raw = out[..., 0], out[..., 1]
        return mean, self.lo + 0.5 * (self.hi - self.lo) * (torch.tanh(raw) + 1)


class GNDeterministicPolicy(nn.Module):
    """``obs [N, D] -> u [N, U]`` (unbounded; the agent squashes it) on the observation graph."""

    def __init__(self, graph, latent: int = 64, hidden: tuple[int, ...] = (64,), blocks: int = 2, **run):
        super().__init__()
        self.graph = _graph(graph)
        g = self.graph
        self.gn = GNStack(g.node_size, g.edge_size(False), g.global_size, 1, 1, 0, latent, hidden, blocks, **run)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.graph.edge_actions(self.gn(self.graph(obs)).edges)[..., 0]


class GNQFunction(nn.Module):
    """``(obs [N, D], action [N, U]) -> [N]``: the last block's global output."""

    def __init__(self, graph, latent: int = 64, hidden: tuple[int, ...] = (64,), blocks: int = 2, **run):
        super().__init__()
        self.graph = _graph(graph)
        g = self.graph
        self.gn = GNStack(g.node_size, g.edge_size(True), g.global_size, 1, 1, 1, latent, hidden, blocks, **run)

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.gn(self.graph(obs, action)).globals[:, 0]


class GNObservationModel(NormalizedModel):
    """``(obs [N, D], action [N, U]) -> next_obs [N, D]``: obs plus the change the last block
    predicts in each entry's graph place (node outputs for body entries, forward edge outputs for
    joint entries, global outputs for the rest).

    The graph reads normalized observations ``(obs - obs_mean) / obs_std`` and the outputs are
    changes in units of ``delta_std`` (buffers [D], saved with the weights; 0 and 1 until
    ``normalize_from`` sets them from data: ``NormalizedModel``)."""

    def __init__(self, graph, latent: int = 64, hidden: tuple[int, ...] = (64,), blocks: int = 2, **run):
        graph = _graph(graph)
        super().__init__(graph.obs_size)
        self.graph = graph
        g = self.graph
        fv, fe, fu = g.node_index.shape[1], g.edge_index.shape[1], g.global_index.shape[0]
        self.gn = GNStack(g.node_size, g.edge_size(True), g.global_size, max(fv, 1), max(fe, 1), fu,
                          latent, hidden, blocks, **run)

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        g = self.graph
        out = self.gn(g(self.normalized(obs), action))
        if g.global_size == 0:
            out = out._replace(globals=obs.new_zeros(obs.shape[0], 0))
        return self.step(obs, g.flat_features(out))


# -- the MLP option: the same signatures on the flat observation --------------------------------

class MLPGaussianPolicy(nn.Module):
    """``obs [N, D] -> (mean [N, U], log_std [N, U])``: an MLP of ``hidden`` widths, log_std squashed
    as ``GNGaussianPolicy``'s."""

    def __init__(self, obs_dim: int, action_dim: int, hidden: tuple[int, ...] = (256, 256), init_std: float = 0.5,
                 log_std_min: float = -5.0, log_std_max: float = 1.0):
        super().__init__()
        self.lo, self.hi = float(log_std_min), float(log_std_max)
        raw0 = _log_std_head(init_std, self.lo, self.hi)
        self.net = MLP(obs_dim, hidden, 2 * action_dim)
        with torch.no_grad():
            self.net.layers[-1].bias[action_dim:] = raw0

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean, raw = self.net(obs).chunk(2, dim=-1)
        return mean, self.lo + 0.5 * (self.hi - self.lo) * (torch.tanh(raw) + 1)


class MLPDeterministicPolicy(nn.Module):
    """``obs [N, D] -> u [N, U]``: an MLP of ``hidden`` widths."""

    def __init__(self, obs_dim: int, action_dim: int, hidden: tuple[int, ...] = (256, 256)):
        super().__init__()
        self.net = MLP(obs_dim, hidden, action_dim)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.net(obs)


class MLPQFunction(nn.Module):
    """``(obs [N, D], action [N, U]) -> [N]``: an MLP of ``hidden`` widths on their concatenation."""

    def __init__(self, obs_dim: int, action_dim: int, hidden: tuple[int, ...] = (256, 256)):
        super().__init__()
        self.net = MLP(obs_dim + action_dim, hidden, 1)

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([obs, action], -1))[:, 0]


def make_networks(network: str, graph, gaussian: bool = True, hidden: tuple[int, ...] | None = None,
                  latent: int = 64, blocks: int = 2, **kw) -> tuple[nn.Module, nn.Module]:
    """(policy, q) of kind ``network`` ("gn" on the observation graph, "mlp" on the flat
    observation) for ``graph`` (an ``ObservationGraph`` or a name it takes); a Gaussian policy
    (``gaussian``, SVG) or a deterministic one (DDPG). ``hidden``: MLP widths (default (64,) for
    GN blocks, (256, 256) for MLPs); ``kw``: the Gaussian policy's ``init_std`` /
    ``log_std_min`` / ``log_std_max`` and, for "gn", run options (``impl``, ``path``, ...)."""
    if network not in NETWORKS:
        raise ValueError(f"unknown network {network!r}: one of {', '.join(NETWORKS)}")
    g = _graph(graph)
    std_kw = {k: kw.pop(k) for k in ("init_std", "log_std_min", "log_std_max") if k in kw}
    if std_kw and not gaussian:
        raise ValueError(f"{', '.join(std_kw)} apply to a Gaussian policy only")
    if network == "mlp":
        if kw:
            raise ValueError(f"an MLP takes no run options: {', '.join(kw)}")
        h = tuple(hidden) if hidden is not None else (256, 256)
        policy = (MLPGaussianPolicy(g.obs_size, g.nu, h, **std_kw) if gaussian
                  else MLPDeterministicPolicy(g.obs_size, g.nu, h))
        return policy, MLPQFunction(g.obs_size, g.nu, h)
    h = tuple(hidden) if hidden is not None else (64,)
    policy = (GNGaussianPolicy(g, latent, h, blocks, **std_kw, **kw) if gaussian
              else GNDeterministicPolicy(g, latent, h, blocks, **kw))
    return policy, GNQFunction(g, latent, h, blocks, **kw)
