"""A forward model's step in a handful of launches, for rollouts of graphs of one size.

``ForwardModel.next_nodes`` on ``GraphTemplate.graph`` costs some hundred small torch kernels
around the GN core (input graph, re-centring, normalization, de-normalization, quaternion update,
world body kept), and as many again in its autograd backward. ``FusedStep`` runs the same step
as::

    encode   body [N, B, 13], ctrl [N, U] -> normalized nodes, edges, globals     (one launch)
    core     normalized graph -> normalized change [N*B, 13]                      (the model's core)
    decode   normalized change, body -> next body [N, B, 13]                       (one launch)

and its vector-Jacobian product as encode, the core's forward and backward, and two hand-written
backward launches (``kernels/models/fused_step.py``): no torch glue, no weight gradients.
``RolloutEngine(fused=...)`` runs its loops on it (``forward_loop`` / ``backward_loop``: the
backward walks the steps in reverse on the states the forward kept). In the loops each decode
also writes the next step's input graph, and each step's last backward launch the previous
step's: per step, the forward is the core and one launch, the backward the core's forward and
backward and two launches. Given a ``scope`` (the engine's ``ActivationStore``), the forward
records each step's GN blocks and the backward's core forward replays them (no block GEMM).

The core is ``BatchCore``: the model's own GN core (its Warp blocks) on the batch's graph, built
once. Only templates whose graphs all have the same size and edges (``builder.uniform``)
are fused; ``FusedStep.unsupported`` says why another is not.
"""
from __future__ import annotations

import contextlib

import torch

from gnwarp.gn.rules import choose_fused
from gnwarp.graphs import GraphsTuple
from gnwarp.interop import WP_DTYPE, Launcher, vjp
from gnwarp.kernels.models import fused_step as K
from gnwarp.models.cores import GNCore
from gnwarp.state import DYN_NODE_SIZE

__all__ = ["FusedStep", "BatchCore", "fused_step_for", "frozen_parameters"]


@contextlib.contextmanager
def frozen_parameters(module):
    """``module``'s parameters with ``requires_grad`` off inside the block, restored after: a
    backward that wants only input gradients then skips every weight gradient (the GN blocks'
    backward computes those only for parameters that require them)."""
    params = [p for p in getattr(module, "parameters", lambda: ())() if p.requires_grad]
    for p in params:
        p.requires_grad_(False)
    try:
        yield
    finally:
        for p in params:
            p.requires_grad_(True)


class BatchCore:
    """A model's core on N graphs of ``n_node`` nodes with the edges ``senders`` / ``receivers``
    [E] (local to one graph): ``__call__(nodes [N*n_node, Fv], edges [N*E, Fe], globals [N, Fg])
    -> [N*n_node, 13]``, differentiable through the core's own backward. The batch's topology and
    its graph index are made once."""

    def __init__(self, core, senders, receivers, n_node: int, n_graphs: int):
        dev = senders.device
        off = torch.arange(n_graphs, device=dev)[:, None] * n_node
        E = int(senders.shape[0])
        self.core = core
        self.topology = GraphsTuple(nodes=None, edges=None, globals=None,
                                    senders=(senders.long()[None] + off).reshape(-1),
                                    receivers=(receivers.long()[None] + off).reshape(-1),
                                    n_node=torch.full((n_graphs,), n_node, device=dev, dtype=torch.int64),
                                    n_edge=torch.full((n_graphs,), E, device=dev, dtype=torch.int64))
        self.index = core.graph_index(self.topology)   # validated once (one host sync), here

    def __call__(self, nodes, edges, globals_):
        return self.core(self.topology._replace(nodes=nodes, edges=edges, globals=globals_), self.index)


class _FusedStepFn(torch.autograd.Function):
    """(step, body [N, B, 13], ctrl [N, U]) -> next body; input gradients only."""

    @staticmethod
    def forward(ctx, fs, body, ctrl):
        body, ctrl = body.detach(), ctrl.detach()   # Warp views of leaves that want no .grad of their own
        stats = fs.stats()
        b4, c3 = body[:, None], ctrl[:, None]
        graph = fs.encode(b4, 0, c3, 0, stats)
        with torch.no_grad():
            delta = fs.core(*graph)
        nxt = torch.empty_like(body)
        fs.decode(delta, b4, 0, stats, nxt[:, None], 0)
        ctx.fs, ctx.stats = fs, stats
        ctx.save_for_backward(body, ctrl, *graph)
        return nxt

    @staticmethod
    def backward(ctx, g_next):
        body, ctrl, *graph = ctx.saved_tensors
        g_body, g_ctrl = ctx.fs.vjp(body, ctrl, g_next, stats=ctx.stats, graph=tuple(graph))
        return None, g_body, g_ctrl


class FusedStep:
    """One step of ``model`` (a ``ForwardModel`` with a GN core) on ``template``'s N graphs of B
    bodies and E edges each: ``step(body [N, B, 13], ctrl [N, U]) -> next body [N, B, 13]``, as
    ``template.to_body(model.next_nodes(template.graph(body, ctrl)), body)`` to rounding,
    differentiable with respect to body and ctrl (not the model's parameters); ``vjp(body, ctrl,
    g_next) -> (g_body, g_ctrl)``. The normalizer statistics are read from the model's device
    tensors at every call (and once per loop). Raises ValueError naming the reason where
    ``unsupported(model, template)`` gives one (``check=False``: the caller has asked it). Host
    syncs here (index checks), none in a step."""

    def __init__(self, model, template, check: bool = True):
        why = self.unsupported(model, template) if check else None   # check=False: the caller asked it
        if why is not None:
            raise ValueError(f"the fused model step cannot run here: {why}")
        self.model, self.template = model, template
        N, B = template.N, template.B
        E = int(template.static_edges.shape[0]) // N
        self.N, self.B, self.E = N, B, E
        self.dtype = template.dtype
        self.recenter = bool(model.config.recenter)
        self.static_nodes = template.static_nodes.contiguous()
        self.static_edges = template.static_edges.contiguous()
        self.static_globals = template.topology.globals.to(self.dtype).contiguous()
        self.ctrl_index = template.ctrl_index.to(torch.int32).contiguous()
        ci = template.ctrl_index
        self.n_ctrl_read = int(ci.max()) + 1 if ci.numel() else 0       # the one host sync
        snd, rcv = template.topology.senders[:E], template.topology.receivers[:E]   # graph 0's: local
        self.core = BatchCore(model.core, snd, rcv, B, N)
        self._work = None

    @staticmethod
    def unsupported(model, template) -> str | None:
        """None when ``FusedStep(model, template)`` runs, else why not."""
        if not all(hasattr(model, a) for a in ("core", "config", "stats", "norm_nodes")):
            return f"{type(model).__name__} is not a ForwardModel (the fused step reads its normalizers and core)"
        if not isinstance(model.core, GNCore):
            return f"the fused step runs GN cores, not {type(model.core).__name__}"
        if template.rows is not None:
            return "the template's graphs differ in size (instances of several sizes, padded)"
        if template.dtype not in (torch.float32, torch.float64):
            return f"the states are {template.dtype}; the fused step runs float32 and float64"
        if model.dtype != template.dtype:
            return f"the model computes in {model.dtype} but the template holds {template.dtype}"
        if getattr(template, "ctrl_gain", None) is not None:
            return ("actuators on tendons weight the edges' controls by the tendons' coefficients; the fused encode "
                    "writes controls unweighted")
        N, B = template.N, template.B
        E = int(template.static_edges.shape[0]) // max(N, 1)
        topo = template.topology
        if N > 1 and E > 0:
            off = torch.arange(N, device=topo.senders.device)[:, None] * B
            local = torch.stack([topo.senders.reshape(N, E) - off, topo.receivers.reshape(N, E) - off])
            if not bool((local == local[:, :1]).all()):                   # one host sync
                return "the graphs' edges differ between instances (one topology is fused)"
        return None

    # -- the launches -------------------------------------------------------------------------
    def stats(self) -> tuple[torch.Tensor, ...]:
        """(node mean, std, edge mean, std, global mean, std, delta mean, std) of the model's
        normalizers, as of now (device tensors; no host sync)."""
        s = self.model.stats(self.dtype)
        Fg = self.static_globals.shape[1]
        glob = s.get("globals") or (torch.zeros(Fg, dtype=self.dtype, device=self.static_nodes.device),
                                    torch.ones(Fg, dtype=self.dtype, device=self.static_nodes.device))
        return tuple(x.contiguous() for x in (*s["nodes"], *s["edges"], *glob, *s["delta"]))

    def _new(self, *shape):
        return torch.empty(shape, dtype=self.dtype, device=self.static_nodes.device)

    def encode(self, body, tb: int, ctrl, tc: int, stats, out=None):
        """Normalized (nodes [N*B, Fv], edges [N*E, Fe], globals [N, Fg]) of ``body`` [N, ., B, 13]
        at step ``tb`` and ``ctrl`` [N, ., U] at step ``tc`` (written into ``out`` when given)."""
        if ctrl.shape[-1] < self.n_ctrl_read:
            raise ValueError(f"the template's edges read {self.n_ctrl_read} controls; got {ctrl.shape[-1]}")
        N, B, E = self.N, self.B, self.E
        if out is None:
            out = (self._new(N * B, stats[0].shape[0]), self._new(N * E, stats[2].shape[0]),
                   self._new(N, self.static_globals.shape[1]))
        Launcher(self.static_nodes)(K.encode_kernel(WP_DTYPE[self.dtype], self.recenter), N * (B + E + 1), body, tb,
                                    ctrl, tc, self.static_nodes, self.static_edges, self.static_globals,
                                    self.ctrl_index, *stats[:6], N, B, E, *out)
        return out

    def decode(self, delta, body, tb: int, stats, out, tn: int, ctrl=None, tc: int = 0, graph=None) -> None:
        """Next body states into ``out`` [N, ., B, 13] at step ``tn`` from the normalized change
        ``delta`` [N*B, 13] and ``body`` [N, ., B, 13] at step ``tb``; with ``ctrl`` [N, ., U] and
        ``graph`` (the buffers of an earlier ``encode`` of these statistics), also the next input
        graph at control step ``tc`` into ``graph`` (its dynamic columns; the static ones stay)."""
        run = Launcher(delta)
        enc = graph is not None
        N, B, E = self.N, self.B, self.E
        if not enc:
            ctrl, graph = run.placeholder(self.dtype, 3), (run.placeholder(self.dtype, 2),) * 2
        run(K.decode_kernel(WP_DTYPE[self.dtype], enc, self.recenter and enc), N * (B + E) if enc else N * B,
            delta.contiguous(), body, tb, stats[6], stats[7], ctrl, tc, self.ctrl_index, *stats[:4], N, B, E, tn,
            out, graph[0], graph[1])

    def _backward_step(self, body, tb: int, graph, g_next, stats, g_add, ta: int, g_body, g_ctrl, tc: int,
                       ctrl=None, prev: int | None = None, scope=None) -> None:
        """One step's vector-Jacobian product: ``g_next`` [N*B, 13] -> ``g_body`` [N*B, 13] (plus
        ``g_add`` [N, ., B, 13] at step ``ta`` when given; ``g_body`` may be ``g_next``) and the
        controls' gradient into ``g_ctrl`` [N, ., U] at step ``tc``; ``graph``: the step's
        normalized inputs. With ``prev``, the same launch then writes step ``prev``'s input graph
        (``body``, ``ctrl`` [N, ., U]) into ``graph``. ``scope``: a context the core's forward
        runs in (an ``ActivationStore`` replaying this step). Parameters should be frozen."""
        nodes, edges, glob = graph
        with torch.enable_grad():
            n, e = nodes.detach().requires_grad_(), edges.detach().requires_grad_()
            with scope if scope is not None else contextlib.nullcontext():
                delta = self.core(n, e, glob)
            g_delta, g_direct = self._new(self.N * self.B, DYN_NODE_SIZE), self._new(self.N * self.B, DYN_NODE_SIZE)
            run = Launcher(g_next)
            run(K.decode_grad_kernel(WP_DTYPE[self.dtype]), self.N * self.B, delta.detach().contiguous(), body, tb,
                g_next, stats[6], stats[7], self.B, g_delta, g_direct)
            gn, ge = vjp(delta, (n, e), g_delta)
        gn = torch.zeros_like(nodes) if gn is None else gn.contiguous()
        ge = torch.zeros_like(edges) if ge is None else ge.contiguous()
        N, B, E, U = self.N, self.B, self.E, g_ctrl.shape[-1]
        add, enc = g_add is not None, prev is not None
        pl = run.placeholder
        if not enc:
            ctrl, nodes, edges = pl(self.dtype, 3), pl(self.dtype, 2), pl(self.dtype, 2)
        run(K.encode_grad_kernel(WP_DTYPE[self.dtype], self.recenter, add, enc), N * (B + U + (E if enc else 0)),
            gn, ge, g_direct, g_add if add else pl(self.dtype, 4), ta, self.ctrl_index, stats[1], stats[3], body,
            prev if enc else 0, ctrl, prev if enc else 0, stats[0], stats[2], N, B, E, U, tc, g_body, g_ctrl, nodes,
            edges)

    # -- one step -----------------------------------------------------------------------------
    def _check(self, body, ctrl):
        body = torch.as_tensor(body).to(self.static_nodes.device, self.dtype)
        ctrl = torch.as_tensor(ctrl).to(self.static_nodes.device, self.dtype)
        if tuple(body.shape) != (self.N, self.B, DYN_NODE_SIZE):
            raise ValueError(f"body must be [N, B, 13] = [{self.N}, {self.B}, 13], got {tuple(body.shape)}")
        if ctrl.ndim != 2 or ctrl.shape[0] != self.N:
            raise ValueError(f"ctrl must be [N, U] with N = {self.N}, got {tuple(ctrl.shape)}")
        return body, ctrl

    def step(self, body: torch.Tensor, ctrl: torch.Tensor) -> torch.Tensor:
        """Next body states [N, B, 13] of ``body`` [N, B, 13] under ``ctrl`` [N, U]; differentiable
        with respect to both (the backward is ``vjp``)."""
        body, ctrl = self._check(body, ctrl)
        return _FusedStepFn.apply(self, body.contiguous(), ctrl.contiguous())

    def vjp(self, body, ctrl, g_next, stats=None, graph=None) -> tuple[torch.Tensor, torch.Tensor]:
        """(dL/dbody [N, B, 13], dL/dctrl [N, U]) of one step for dL/dnext ``g_next`` [N, B, 13]:
        encode, the core's forward and backward, and the two backward launches; no weight
        gradients. ``stats`` / ``graph``: the step's statistics and normalized inputs, when kept."""
        body, ctrl = self._check(body, ctrl)
        body, ctrl = body.detach().contiguous(), ctrl.detach().contiguous()
        stats = stats if stats is not None else self.stats()
        b4, c3 = body[:, None], ctrl[:, None]
        graph = graph if graph is not None else self.encode(b4, 0, c3, 0, stats)
        g_body, g_ctrl = torch.empty_like(body), torch.empty_like(ctrl)
        g = g_next.detach().to(self.dtype).reshape(-1, DYN_NODE_SIZE).contiguous()
        with frozen_parameters(self.model):
            self._backward_step(b4, 0, graph, g, stats, None, 0, g_body.view(-1, DYN_NODE_SIZE), g_ctrl[:, None], 0)
        return g_body, g_ctrl

    # -- rollouts -----------------------------------------------------------------------------
    def _buffers(self, stats):
        """Normalized-graph buffers the loops reuse every step (made once, outside any capture)."""
        if self._work is None:
            N, B, E = self.N, self.B, self.E
            self._work = (self._new(N * B, stats[0].shape[0]), self._new(N * E, stats[2].shape[0]),
                          self._new(N, self.static_globals.shape[1]))
        return self._work

    def forward_loop(self, traj: torch.Tensor, ctrl: torch.Tensor, scope=None) -> None:
        """Fill ``traj`` [N, T+1, B, 13] (``traj[:, 0]`` the initial states) under ``ctrl``
        [N, T, U], one step at a time, in place; no autograd, no host sync. ``scope(t)``: a
        context step t's core runs in (an ``ActivationStore`` recording step t)."""
        stats = self.stats()
        work = self._buffers(stats)
        T = ctrl.shape[1]
        with torch.no_grad():
            graph = self.encode(traj, 0, ctrl, 0, stats, out=work)
            for t in range(T):   # each decode writes the next step's input graph too
                with scope(t) if scope is not None else contextlib.nullcontext():
                    delta = self.core(*graph)
                nxt = (ctrl, t + 1, graph) if t + 1 < T else (None, 0, None)
                self.decode(delta, traj, t, stats, traj, t + 1, *nxt)

    def backward_loop(self, traj, ctrl, g_traj, g_x0, g_ctrl, scope=None) -> None:
        """The adjoint loop over ``forward_loop``'s states ``traj`` [N, T+1, B, 13]: for dL/dtraj
        ``g_traj`` [N, T+1, B, 13], writes dL/dx0 into ``g_x0`` [N, B, 13] (contiguous; the running
        gradient) and dL/dctrl into ``g_ctrl`` [N, T, U]; no weight gradients, no host sync.
        ``scope(t)``: a context step t's core forward runs in (an ``ActivationStore`` replaying
        the forward's recording of step t: its blocks then run no GEMM of their forward)."""
        stats = self.stats()
        work = self._buffers(stats)
        T = ctrl.shape[1]
        g_x0.copy_(g_traj[:, T])
        g = g_x0.view(-1, DYN_NODE_SIZE)
        with frozen_parameters(self.model):
            graph = self.encode(traj, T - 1, ctrl, T - 1, stats, out=work)
            for t in range(T - 1, -1, -1):   # each step's last launch writes the previous step's input graph
                self._backward_step(traj, t, graph, g, stats, g_traj, t, g, g_ctrl, t, ctrl,
                                    t - 1 if t > 0 else None, scope(t) if scope is not None else None)


def fused_step_for(model, template, fused: bool | None) -> FusedStep | None:
    """The ``FusedStep`` a rollout engine of ``template`` runs, or None for the unfused step:
    ``fused`` True (ValueError naming the reason when it cannot run), False, or None (where it
    runs and ``gnwarp.gn.rules.choose_fused`` picks it for the batch size and device)."""
    if fused not in (None, True, False):
        raise ValueError(f"fused must be True, False or None (automatic), got {fused!r}")
    if fused is False or (fused is None and not choose_fused(template.N, template.static_nodes.device)):
        return None
    why = FusedStep.unsupported(model, template)
    if why is not None:
        if fused:
            raise ValueError(f"fused=True, but the fused model step cannot run here: {why}")
        return None
    return FusedStep(model, template, check=False)
