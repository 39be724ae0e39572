"""System identification (paper D.2, D.3, D.6.2, Algorithms D.2 and D.4): a recurrent GN reads a
window of dynamic graphs and outputs a latent static graph G_ID that replaces the true static
graph in a forward model.

::

    G_d^t  = dynamic graph of step t (13 body states per node, controls per edge; no static features)
    G_o, G_h = GN_p(Norm_in(G_d^t), G_h)   for t over the window (``RecurrentGNCore``), G_h = 0 first
    G_ID   = G_o of the last step          (per-node, per-edge and global latents; not normalized, D.3)
    x_t+1  = ForwardModel(concat(G_ID, G_d^t))   (the forward model's static columns are G_ID)

The forward model is a plain ``ForwardModel`` on a ``FeatureLayout`` whose static columns are
G_ID's (``gid_node_<i>``, ...); its input normalizers leave those columns as they are. ``Norm_in``
of the window is the forward model's, on the dynamic columns. In rollouts G_ID is identified
once and reused every step (``identify`` then ``rollout``); ``gnwarp.models.gid`` saves and loads it,
and holds it fixed for rollout engines and planners.
"""
from __future__ import annotations

import dataclasses
import weakref

import torch
import torch.nn as nn
import torch.nn.functional as F

from gnwarp.data.builder import GraphTemplate, graph_builder
from gnwarp.data.layout import FeatureLayout
from gnwarp.gn.index import graph_index
from gnwarp.gn.options import RunOptions
from gnwarp.gn.reference import MLP
from gnwarp.graphs import GraphsTuple
from gnwarp.models.forward import ForwardModel
from gnwarp.models.gid import FixedGIDModel, GIDError
from gnwarp.models.normalizer import Normalizer
from gnwarp.models.recurrent import KINDS, RecurrentGNCore
from gnwarp.models.rollout import (RolloutInputError, RolloutInputs, check_instance, float_tensor,
                                  source_info)
from gnwarp.models.sysid_config import FIT_TARGETS, SysIDConfig
from gnwarp.models.sysid_graphs import (StackedWindow, gid_layout, instance_topologies, place_tables, source_name,
                                        source_places, source_static)
from gnwarp.state import DYN_NODE_SIZE, state_delta

__all__ = ["SysIDModel", "LatentColumnsNormalizer"]


def _ridge_solution(phi: torch.Tensor, psi: torch.Tensor, ridge: float) -> torch.Tensor:
    """Per row of the regressors ``phi`` [T, n, F] and targets ``psi`` [T, n, P] (T steps): the
    ridge solution B [F, P] of psi ~ B^T phi over the T steps, flattened to [n, F * P], in
    ``phi``'s dtype. Solved in float64, so that a small ``ridge`` stays exact: a Cholesky solve
    without error checks (no host synchronization, so it can be captured)."""
    dtype, phi, psi = phi.dtype, phi.double(), psi.double()
    features, T = phi.shape[-1], phi.shape[0]
    S = torch.einsum("tnf,tng->nfg", phi, phi) / T
    R = torch.einsum("tnf,tnp->nfp", phi, psi) / T
    eye = torch.eye(features, dtype=phi.dtype, device=phi.device)
    lam = ridge * S.diagonal(dim1=-2, dim2=-1).mean(-1)[:, None, None] + 1e-6
    L, _ = torch.linalg.cholesky_ex(S + lam * eye)
    y = torch.linalg.solve_triangular(L, R, upper=False)
    B = torch.linalg.solve_triangular(L.transpose(-1, -2), y, upper=True)
    return B.reshape(B.shape[0], -1).to(dtype)


class LatentColumnsNormalizer(Normalizer):
    """A ``Normalizer`` whose first ``skip`` columns (G_ID's latents) stay as they are (D.3)."""

    def __init__(self, size: int, skip: int, std_floor: float = 1e-4):
        super().__init__(size, std_floor)
        self.skip = int(skip)
        self.register_buffer("latent", torch.arange(self.size) < self.skip, persistent=False)

    def _masked(self, mean, std):
        m = self.latent.to(mean.device)
        return torch.where(m, torch.zeros_like(mean), mean), torch.where(m, torch.ones_like(std), std)

    def accumulate_stats(self, x, weight=None):
        return self._masked(*super().accumulate_stats(x, weight))

    def mean_std(self, dtype=None):
        return self._masked(*super().mean_std(dtype))


# the static edge features of an actuator's range (read from the bound source for clamping)
RANGE_COLUMNS = ("act_ctrllimited", "act_ctrlrange_0", "act_ctrlrange_1")


class SysIDModel(nn.Module):
    """GN_p (``identifier``, a ``RecurrentGNCore``) + a ``ForwardModel`` (``forward_model``) on G_ID.

    ``config``: ``SysIDConfig``; ``layout``: the data's ``FeatureLayout`` (only its control slots
    are read: GN_p and the forward model see no static feature of the data).

    Main methods (N graphs, W window steps, B bodies, U controls, T steps):
        ``bind(source)``: the Dataset or System whose graphs it reads.
        ``identify(window_body [N, W, B, 13], window_ctrl [N, W, U], instance [N]) -> G_ID``.
        ``rollout(initial_body [N, B, 13], ctrl [N, T, U], g_id, instance) -> [N, T+1, B, 13]``.
    """

    def __init__(self, config: SysIDConfig, layout: FeatureLayout):
        super().__init__()
        if layout.n_global_ctrl:
            raise ValueError(f"system identification needs every actuator on joint edges; the layout has "
                             f"{layout.n_global_ctrl} on the globals (a site, body or slider-crank transmission, or a "
                             f"tendon): regenerate the data, gnwarp generate puts actuators on fixed tendons on their "
                             f"joints' edges and refuses the rest")
        self.sysid = dataclasses.replace(config)
        c = config.identifier
        self.gid_sizes = {k: config.gid_size(k) for k in KINDS}
        K = int(layout.n_ctrl_slots)
        # what the model reads of the data: its dynamic graph only
        self.layout = FeatureLayout([], [], [], n_ctrl_slots=K)
        if config.local_params and config.param_places is None:
            raise ValueError("local_params needs param_places (where each parameter lives): set "
                             "SysIDConfig.param_places, or build the model with gnwarp.models.build_sysid_model from "
                             "a parameterized dataset")
        # local_params: per node (edge) row of a graph, the parameter of each slot; buffers, so that they live on
        # the model's device (a captured step copies nothing from the host)
        tables = place_tables(config.param_places or ())
        for kind, t in tables.items():
            self.register_buffer(f"place_{kind}", t, persistent=False)
        slots = {k: t.shape[1] for k, t in tables.items()}
        if config.param_places and len(config.param_places) > self.gid_sizes["globals"]:
            raise ValueError(f"local_params places {len(config.param_places)} parameters from G_ID's first global "
                             f"columns, but G_ID has {self.gid_sizes['globals']} (widen "
                             f"SysIDConfig.identifier.out_globals)")
        if config.nominal_static and config.nominal is None:
            raise ValueError("nominal_static needs the nominal static graph (SysIDConfig.nominal): set it, or build "
                             "the model with gnwarp.models.build_sysid_model from a dataset")
        # nominal_static: the nominal graph's columns per kind (None: none), float64 buffers on the model's device
        for kind, t in (config.nominal.tensors() if config.nominal else {}).items():
            self.register_buffer(f"nominal_{kind}", t if t.shape[-1] else None, persistent=False)
        self.forward_model = ForwardModel(config.forward, gid_layout(self.gid_sizes, K, slots, config.nominal))
        fm, f = self.forward_model, config.forward.std_floor
        fm.norm_nodes = LatentColumnsNormalizer(fm.norm_nodes.size, self.gid_sizes["nodes"] + slots["nodes"], f)
        fm.norm_edges = LatentColumnsNormalizer(fm.norm_edges.size, self.gid_sizes["edges"] + slots["edges"], f)
        if fm.norm_globals is not None:
            fm.norm_globals = LatentColumnsNormalizer(fm.norm_globals.size, self.gid_sizes["globals"], f)
        sizes = {"nodes": DYN_NODE_SIZE * (2 if config.transitions else 1), "edges": K, "globals": 0}
        self.identifier = RecurrentGNCore(c, sizes, config.forward.run).to(config.forward.run.param_dtype)
        h = config.ridge_head   # the fit's coefficients -> G_ID (SysIDConfig.ridge_head)
        self.heads = nn.ModuleDict({k: MLP(config.fit_size(k), (h, h), self.gid_sizes[k], activation=F.silu)
                                    for k in KINDS if h and self.gid_sizes[k]}).to(config.forward.run.param_dtype)
        self.builder = None
        # the bound source's actuator ranges (``bind``): a builder of just those static columns
        self._range_layout = FeatureLayout([], [], list(RANGE_COLUMNS), n_ctrl_slots=K)
        self._range_builder = None

    # -- what the Trainer and users read --------------------------------------------------------
    @property
    def config(self) -> SysIDConfig:
        return dataclasses.replace(self.sysid, forward=self.forward_model.config)

    @property
    def window(self) -> int:
        return self.sysid.window

    @property
    def options(self) -> RunOptions:
        return self.forward_model.options

    @property
    def norm_nodes(self) -> Normalizer:
        return self.forward_model.norm_nodes

    @property
    def device(self) -> torch.device:
        return self.forward_model.device

    @property
    def dtype(self) -> torch.dtype:
        return self.forward_model.dtype

    def set_options(self, options: RunOptions | None = None, **changes) -> "SysIDModel":
        """Run both parts with ``options`` (or the current ones with ``changes``); returns self."""
        self.forward_model.set_options(options, **changes)
        self.identifier.set_options(self.options)
        self.identifier.to(self.options.param_dtype)
        self.heads.to(self.options.param_dtype)
        return self

    def graph_builder(self, source, strict: bool = True):
        """A ``GraphBuilder`` of ``source``'s dynamic graphs (no static columns), on the model's
        device and dtype. Data with more control slots per edge raises ``LayoutMismatchError``."""
        return graph_builder(self.layout, source, self.device, self.dtype, strict)

    def bind(self, source, strict: bool = True) -> "SysIDModel":
        """Read ``source``'s graphs (a Dataset or System) in ``identify`` and ``rollout``, and its
        actuators' control ranges (static edge features the model itself does not read) for
        clamping controls."""
        if self.sysid.local_params and source_places(source) != self.sysid.param_places:
            raise ValueError(f"this model places its parameters as {self.sysid.param_places!r:.120}, and "
                             f"{source_name(source)} holds them elsewhere (another system, or other parameters)")
        nom = self.sysid.nominal
        if nom is not None:
            want = (len(nom.nodes), nom.senders, nom.receivers)
            other = [t for t in instance_topologies(source_static(source)) if t != want]
            if other:
                raise ValueError(f"this model reads a nominal static graph of {want[0]} bodies and "
                                 f"{len(nom.senders)} edges; {source_name(source)} has instances of another "
                                 f"topology ({other[0][0]} bodies, {len(other[0][1])} edges, or other joints)")
        self.builder = self.graph_builder(source, strict)
        try:
            self._range_builder = graph_builder(self._range_layout, source, self.device, self.dtype, strict)
        except ValueError:   # data without actuator ranges (LayoutMismatchError is one): nothing to clamp to
            self._range_builder = None
        return self

    def rollout_inputs(self, instance, n_ctrl: int, ctrl_policy: str = "clamp", check: bool = True) -> RolloutInputs:
        """Input checks and control clamping of rollouts of the bound source's ``instance`` [N]:
        the actuators' ranges come from the source's static edge features (``ctrl_policy`` as
        ``ForwardModel.rollout``'s; no ranges in the source: nothing is clamped)."""
        if self.builder is None:
            raise ValueError("no graphs to read: call model.bind(dataset_or_system) first")
        rb = self._range_builder
        if rb is None:
            return RolloutInputs(GraphTemplate(self.builder, torch.as_tensor(instance)), None, n_ctrl, ctrl_policy,
                                 check)
        return RolloutInputs(GraphTemplate(rb, torch.as_tensor(instance)), self._range_layout, n_ctrl, ctrl_policy,
                             check)

    # -- Algorithm D.2 ------------------------------------------------------------------------
    def with_gid(self, graph: GraphsTuple, g_id: GraphsTuple) -> GraphsTuple:
        """The forward model's input graph: G_ID's columns (``gid_columns``) concatenated with a
        dynamic graph."""
        return self.with_columns(graph, self.gid_columns(graph, g_id))

    @staticmethod
    def with_columns(graph: GraphsTuple, columns: dict) -> GraphsTuple:
        """``graph`` with ``columns`` (``gid_columns``' of its topology) before its own features."""
        def cat(k):
            x, z = getattr(graph, k), columns[k]
            return x if z is None else torch.cat([z.to(x.dtype), x], -1)
        return graph._replace(**{k: cat(k) for k in KINDS})

    def gid_columns(self, graph: GraphsTuple, g_id: GraphsTuple) -> dict:
        """The static columns the forward model reads per kind (None: none) on ``graph``'s
        topology: G_ID's latents; with ``local_params`` the parameters in G_ID's first global
        columns also at the nodes and edges they describe (``SysIDConfig.param_places``; 0 in
        slots no parameter fills); with ``nominal_static`` the nominal static graph's columns.
        A rollout computes them once and reuses them every step. Device gathers only: no host
        synchronization."""
        gl, dev = g_id.globals, graph.nodes.device
        dt = next((x.dtype for x in (g_id.nodes, g_id.edges, gl) if x is not None), graph.nodes.dtype)
        out = {k: [] if getattr(g_id, k) is None else [getattr(g_id, k)] for k in KINDS}
        for kind, count in (("nodes", graph.n_node), ("edges", graph.n_edge)):
            table, nominal = getattr(self, f"place_{kind}"), getattr(self, f"nominal_{kind}", None)
            if table.shape[1] == 0 and nominal is None:
                continue
            rows, count = getattr(graph, kind).shape[0], count.to(dev)
            of_graph = torch.repeat_interleave(torch.arange(count.shape[0], device=dev), count, output_size=rows)
            local = (torch.arange(rows, device=dev) - (torch.cumsum(count, 0) - count)[of_graph])   # row in its graph
            if table.shape[1]:
                which = table[local.clamp(max=table.shape[0] - 1)]     # [rows, slots] parameter index or -1
                vals = gl[of_graph[:, None], which.clamp(min=0)]
                out[kind].append(torch.where(which >= 0, vals, torch.zeros_like(vals)).to(dt))
            if nominal is not None:   # bind checked that every graph has the nominal's rows
                out[kind].append(nominal[local].to(dt))
        nominal = getattr(self, "nominal_globals", None)
        if nominal is not None:
            out["globals"].append(nominal.to(dt).expand(graph.n_node.shape[0], -1))
        return {k: None if not v else v[0] if len(v) == 1 else torch.cat(v, -1) for k, v in out.items()}

    def identify_graphs(self, window, steps: int, stats: dict | None = None) -> GraphsTuple:
        """G_ID from ``steps`` dynamic graphs of one topology: ``window`` a ``StackedWindow`` (the
        steps built as one batch), a list, or a callable t -> graph. They are normalized with the
        forward model's input statistics (``stats``: as ``ForwardModel.stats``; default its
        current ones) and re-centred as it re-centres (D.4), all steps at once; with
        ``config.transitions``, the ``steps - 1`` transitions between them; with
        ``config.readout`` "mean", the mean of GN_p's output graphs over the steps, "ridge" or
        "dynamics" their fits (through ``config.ridge_head``'s MLP where it has one;
        ``SysIDConfig``). No host synchronization once the topology's index exists."""
        fm, c = self.forward_model, self.sysid
        if not isinstance(window, StackedWindow):
            get = window if callable(window) else window.__getitem__
            window = StackedWindow.of([get(t) for t in range(steps)])
        g0, W = window[0], window.steps
        ctx = fm.context(g0, stats=False)      # the topology's index, shared with the forward model
        stats = stats if stats is not None else fm.stats(g0.nodes.dtype)
        (mn, sn), (me, se) = stats["nodes"], stats["edges"]
        K = g0.edges.shape[-1]
        transitions, readout = c.transitions, c.readout
        if (transitions or readout == "dynamics") and W < 2:
            raise ValueError("identifying from transitions or state changes needs a window of at least 2 steps")
        n = W - 1 if transitions or readout == "dynamics" else W      # GN_p's steps
        x = window.graph.nodes.reshape(W, -1, DYN_NODE_SIZE)          # [W, rows, 13]: every step at once
        dyn, _ = fm._recenter(x[:n], ctx)
        nodes = (dyn - mn[-DYN_NODE_SIZE:]) / sn[-DYN_NODE_SIZE:]
        psi = None
        if n < W:   # the change to the next step, normalized as the targets
            md, sd = stats["delta"]
            delta = (state_delta(x[:-1], x[1:]) - md) / sd
            if transitions:
                nodes = torch.cat([nodes, delta], -1)
            else:   # "dynamics": its targets; bodies that cannot move have no dynamics to fit
                psi = self._observed_targets(delta[..., FIT_TARGETS] * ctx.movable.to(delta.dtype)[:, None], g0, ctx)
        inputs = window.head(n)
        inputs = inputs._replace(nodes=nodes.reshape(-1, nodes.shape[-1]),
                                 edges=(inputs.edges - me[me.shape[0] - K:]) / se[se.shape[0] - K:])
        warp = self.options.impl == "warp" and ctx.index is not None
        if c.stateless:   # every step at once: the window's n graphs as one batch
            index = graph_index(inputs, self.options.deterministic, validate=False) if warp else None  # ctx validated
            out, last = self.identifier.first_steps(inputs, index), g0   # g0: the topology of G_ID
            per_step = {k: None if v is None else v.reshape(n, v.shape[0] // n, v.shape[-1])
                        for k, v in ((k, getattr(out, k)) for k in KINDS)}
        else:
            step = StackedWindow(inputs, n, window.topology)
            outs, _ = self.identifier.sequence(step.__getitem__, steps=n, index=ctx.index if warp else None,
                                               last_only=readout == "last")
            if readout == "last":
                return outs[-1]
            last = outs[-1]
            per_step = {k: None if getattr(last, k) is None else torch.stack([getattr(o, k) for o in outs])
                        for k in KINDS}

        def pool(k, x):   # x [T, rows, width]: GN_p's outputs of kind k over the steps
            if readout == "mean":
                return x.mean(0)
            if readout == "ridge":   # regressors and targets both GN_p's
                b = _ridge_solution(x[..., :c.ridge_features], x[..., c.ridge_features:], c.ridge)
            else:    # "dynamics": observed targets
                b = _ridge_solution(x, psi[k].to(x.dtype), c.ridge)
            return self.heads[k](b.to(self.options.param_dtype)).to(b.dtype) if k in self.heads else b
        return last._replace(**{k: None if per_step[k] is None else pool(k, per_step[k]) for k in KINDS})

    @staticmethod
    def _observed_targets(node: torch.Tensor, graph: GraphsTuple, ctx) -> dict[str, torch.Tensor]:
        """The "dynamics" readout's targets [T, rows, 6] per kind from the nodes' [T, n, 6]: an
        edge's are its receiver's, a graph's the mean over its moving bodies."""
        w = ctx.movable.to(node.dtype)
        count = node.new_zeros(ctx.n_graph).index_add_(0, ctx.node_graph, w).clamp_min(1.0)
        glob = node.new_zeros(node.shape[0], ctx.n_graph, node.shape[2]).index_add_(1, ctx.node_graph, node)
        return {"nodes": node, "edges": node[:, graph.receivers.long()], "globals": glob / count[:, None]}

    def _template(self, instance, N: int) -> tuple[GraphTemplate, int]:
        if self.builder is None:
            raise ValueError("no graphs to read: call model.bind(dataset_or_system) first")
        n_inst, n_ctrl = source_info(self.builder)
        instance = torch.zeros(N, dtype=torch.int64) if instance is None else check_instance(instance, n_inst, N)
        return GraphTemplate(self.builder, instance), n_ctrl

    def identify(self, window_body, window_ctrl, instance=None, check: bool = True,
                 capture: bool | None = None) -> GraphsTuple:
        """G_ID (a GraphsTuple: nodes [n, G], edges [e, G], globals [N, G] and the topology) of N
        system instances from an identification window: ``window_body`` [N, W, B, 13] (body
        states) and ``window_ctrl`` [N, W, U] (the controls applied at those steps); a longer
        window is cut to its last W = ``config.window`` steps. ``instance`` [N]: the bound
        source's instances (their topology; default 0). Raises ``RolloutInputError`` for a
        shorter window, shapes of another system's graph layout, and (``check``) NaN or Inf.

        ``capture`` (default: on for a CUDA model while gradients are off): GN_p's loop over the
        window replays one CUDA graph, captured on the first call of each shape, instances and
        dtype and re-captured when the weights' storage moves (weights updated in place are read
        at each replay); the window is copied in and G_ID copied out. A captured G_ID carries no
        gradient: differentiate through ``capture=False``."""
        body, ctrl = float_tensor(window_body, "window_body"), float_tensor(window_ctrl, "window_ctrl")
        W = self.window
        if body.ndim != 4 or ctrl.ndim != 3:
            raise RolloutInputError(f"window_body must be [N, W, B, {DYN_NODE_SIZE}] and window_ctrl [N, W, U], got "
                                    f"shapes {tuple(body.shape)} and {tuple(ctrl.shape)}")
        if body.shape[1] < W or ctrl.shape[1] < W:
            raise RolloutInputError(f"the identification window has {min(body.shape[1], ctrl.shape[1])} steps; this "
                                    f"model identifies systems from {W} (window_body [N, {W}, B, 13], window_ctrl "
                                    f"[N, {W}, U])")
        N = body.shape[0]
        tmpl, n_ctrl = self._template(instance, N)
        if tuple(body.shape[2:]) != (tmpl.B, DYN_NODE_SIZE) or ctrl.shape[0] != N or ctrl.shape[2] != n_ctrl:
            raise RolloutInputError(
                f"the window's graphs do not fit the bound system's graph layout: window_body {tuple(body.shape)} "
                f"and window_ctrl {tuple(ctrl.shape)}, expected [N, W, {tmpl.B}, {DYN_NODE_SIZE}] and [{N}, W, "
                f"{n_ctrl}] ({tmpl.B} bodies, {n_ctrl} controls): a window from a system with another graph layout")
        dev, dt = tmpl.static_nodes.device, tmpl.dtype
        body, ctrl = body[:, -W:].to(dev, dt), ctrl[:, -W:].to(dev, dt)
        if check:
            for name, x in (("window_body", body), ("window_ctrl", ctrl)):
                bad = ~torch.isfinite(x)
                if bool(bad.any()):
                    raise RolloutInputError(f"{name} contains NaN or Inf (first at {name}"
                                            f"{[int(i) for i in bad.nonzero()[0]]} of its last {W} steps)")
        if capture is None:
            capture = body.is_cuda and not torch.is_grad_enabled()
        if capture:
            if not body.is_cuda:
                raise ValueError("capture=True needs a model on a CUDA device")
            with torch.no_grad():
                return self._captured_identify(tmpl, body, ctrl)
        return self.identify_graphs(self._window(tmpl, {}, body, ctrl), W)

    def _window(self, tmpl: GraphTemplate, made: dict, body: torch.Tensor, ctrl: torch.Tensor) -> StackedWindow:
        """The ``StackedWindow`` of ``body`` [N, W, B, 13] and ``ctrl`` [N, W, U] on one step's
        template (``tmpl``) and one of all W steps, kept in ``made`` (made on the first call:
        outside any capture, as a template syncs with the host)."""
        W = body.shape[1]
        if W not in made:
            made[W] = GraphTemplate(self.builder, tmpl.instance.repeat(W))
        b, c = body.transpose(0, 1).reshape(-1, *body.shape[2:]), ctrl.transpose(0, 1).reshape(-1, ctrl.shape[-1])
        return StackedWindow(made[W].graph(b, c), W, tmpl.topology)

    def _captured_identify(self, tmpl: GraphTemplate, body: torch.Tensor, ctrl: torch.Tensor) -> GraphsTuple:
        from gnwarp.interop import replay_cached
        storage = tuple(t.data_ptr() for t in (*self.parameters(), *self.buffers()) if t is not None)
        key = (tmpl.instance.cpu().numpy().tobytes(), tuple(body.shape), tuple(ctrl.shape), body.dtype, ctrl.dtype,
               body.device, id(self.builder), self.options, self.sysid.readout, self.sysid.transitions, storage)
        W = body.shape[1]

        made = {}

        def run(b, c):   # the templates of the first call with these instances (its warm-up), kept by the graph
            return self.identify_graphs(self._window(tmpl, made, b, c), W)
        result = replay_cached(_IDENTIFY_GRAPHS.setdefault(self, {}), key, (body, ctrl), run, keep=self.builder)
        return result._replace(**{k: None if getattr(result, k) is None else getattr(result, k).clone() for k in KINDS})

    def rollout(self, initial_body, ctrl, g_id: GraphsTuple, instance=None, check: bool = True,
                ctrl_policy: str = "clamp") -> torch.Tensor:
        """Roll the forward model out from ``initial_body`` [N, B, 13] under ``ctrl`` [N, T, U]
        with G_ID reused at every step (D.6.2) -> states [N, T+1, B, 13]. ``g_id``: from
        ``identify`` (or ``load_gid``) on the same N graphs' topology; ``instance`` as there.
        ``ctrl_policy`` as ``ForwardModel.rollout``'s: "clamp" (default) clamps controls to the
        bound source's actuator ranges, "error" refuses controls outside them, "none" uses them
        as given. Differentiable (plain autograd) in ``initial_body``, ``ctrl``, G_ID and the
        weights."""
        initial_body = float_tensor(initial_body, "initial_body")
        if initial_body.ndim != 3:
            raise RolloutInputError(f"initial_body must be [N, B, 13], got shape {tuple(initial_body.shape)}")
        tmpl, n_ctrl = self._template(instance, initial_body.shape[0])
        inputs = self.rollout_inputs(tmpl.instance, n_ctrl, ctrl_policy, check)
        body, ctrl = inputs.shapes(initial_body, ctrl)
        dev, dt = tmpl.static_nodes.device, tmpl.dtype
        body = body.to(dev, dt)
        ctrl = inputs.values(body, ctrl.to(dev, dt))
        self.check_gid(g_id, tmpl.topology)
        g_id = g_id._replace(**{k: None if getattr(g_id, k) is None else getattr(g_id, k).to(dev, dt) for k in KINDS})
        fm = self.forward_model
        first = tmpl.graph(body, ctrl[:, 0])
        columns = self.gid_columns(first, g_id)      # the same every step: G_ID and the topology are fixed
        ctx = fm.context(self.with_columns(first, columns))
        out = [body]
        for t in range(ctrl.shape[1]):
            body = tmpl.to_body(fm.next_nodes(self.with_columns(tmpl.graph(body, ctrl[:, t]), columns), ctx), body)
            out.append(body)
        return torch.stack(out, 1)

    def with_fixed_gid(self, g_id: GraphsTuple) -> "FixedGIDModel":
        """This model with ``g_id`` as every rollout's static graph, behind the interface of a
        ``ForwardModel`` that ``RolloutEngine`` and the planners read (``gnwarp.control``): plan
        through an identified system (Figure 10's system-ID variant)."""
        return FixedGIDModel(self, g_id)

    def check_gid(self, g_id: GraphsTuple, topology: GraphsTuple) -> None:
        """``GIDError`` unless ``g_id`` has this model's widths and ``topology``'s graphs."""
        if not isinstance(g_id, GraphsTuple):
            raise GIDError(f"g_id must be a GraphsTuple (from identify or load_gid), got {type(g_id).__name__}")
        for k in KINDS:
            x, want = getattr(g_id, k), self.gid_sizes[k]
            if (0 if x is None else x.shape[-1]) != want:
                raise GIDError(f"G_ID's {k} have width {0 if x is None else x.shape[-1]}, this model's {want}")
        same = (g_id.n_node.shape == topology.n_node.shape and g_id.senders.shape == topology.senders.shape
                and all(bool(torch.equal(getattr(g_id, a).cpu(), getattr(topology, a).cpu()))
                        for a in ("n_node", "n_edge", "senders", "receivers")))
        if not same:
            raise GIDError(f"G_ID was identified on graphs of another layout ({g_id.n_node.shape[0]} graphs, nodes "
                           f"{g_id.n_node.tolist()[:4]}, {g_id.senders.shape[0]} edges) than the rollout's "
                           f"({topology.n_node.shape[0]} graphs, nodes {topology.n_node.tolist()[:4]}, "
                           f"{topology.senders.shape[0]} edges)")


# captured identifications per model (``SysIDModel.identify``), dropped with the model
_IDENTIFY_GRAPHS: "weakref.WeakKeyDictionary[SysIDModel, dict]" = weakref.WeakKeyDictionary()
