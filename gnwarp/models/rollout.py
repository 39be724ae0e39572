"""Rollouts of a learned model: gradients with memory proportional to the states, and rollouts
replayed from CUDA graphs.

A rollout of T steps keeps, under plain autograd, every step's MLP activations until the
backward: for the paper core at 4096 cheetah graphs that is ~1 GB a step, so 100 steps do not fit
a GPU. ``rollout_with_adjoint`` runs the forward loop without autograd, keeps only the states
(and the controls), and in the backward walks the steps in reverse, recomputing one step at a
time with autograd on and taking its vector-Jacobian product: the adjoint loop. Peak memory is
the states plus one step's activations; the price is one more forward per step.

``RolloutEngine`` holds one batch shape (system instances, horizon) and, on CUDA, replays the
whole forward loop from one CUDA graph and the whole adjoint loop from another: a rollout is one
launch instead of thousands from Python. Its steps may run fused (``gnwarp/models/fused_step.py``:
a few launches a step, and a backward of vector-Jacobian products on the kept states).
"""
from __future__ import annotations

import contextlib
import math
import weakref
from typing import Callable

import numpy as np
import torch

from gnwarp.gn.replay import ActivationStore
from gnwarp.interop import Graphed, vjp
from gnwarp.models.fused_step import frozen_parameters, fused_step_for
from gnwarp.state import DYN_NODE_SIZE, QUAT_MIN

__all__ = ["adjoint_loop", "rollout_with_adjoint", "RolloutEngine", "CTRL_POLICIES", "RolloutInputError",
           "check_instance", "RolloutInputs"]

# What a rollout does with controls outside an actuator's range: "clamp" them to it (as MuJoCo
# does for ctrllimited actuators), "error" (refuse them), or "none" (use them as they are). The
# range is ``gnwarp.sim.actuators.Actuators``' low / high (+-inf where unlimited): the bound
# Systems' own record, or for a dataset the static edge features it stores the record's values in.
CTRL_POLICIES = ("clamp", "error", "none")


class RolloutInputError(ValueError):
    """Rollout inputs refused before any launch: a shape, an instance, a non-finite value or a
    control outside its actuator's range; the message names the argument."""


def _as_tensor(x, name: str) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x
    try:
        return torch.as_tensor(x)
    except Exception as e:
        raise RolloutInputError(f"{name} must be a tensor (or array), got {type(x).__name__}: {e}") from None


def float_tensor(x, name: str) -> torch.Tensor:
    x = _as_tensor(x, name)
    if x.dtype == torch.bool or x.is_complex():
        raise RolloutInputError(f"{name} must hold real numbers, got dtype {x.dtype}")
    return x


def check_instance(instance, n_instances: int, N: int | None = None) -> torch.Tensor:
    """``instance`` as an int64 tensor [N] of system instances in [0, n_instances), or
    ``RolloutInputError`` naming what is wrong (float or bool values, shape, range)."""
    t = _as_tensor(instance, "instance")
    if t.dtype == torch.bool or t.is_floating_point() or t.is_complex():
        raise RolloutInputError(f"instance must hold integers (system instance numbers), got dtype {t.dtype}")
    if t.ndim != 1:
        raise RolloutInputError(f"instance must be 1-D [N], got shape {tuple(t.shape)}")
    if N is not None and t.shape[0] != N:
        raise RolloutInputError(f"instance has {t.shape[0]} entries but initial_body {N} sequences")
    if t.numel():
        lo, hi = (int(v) for v in torch.stack([t.min(), t.max()]).tolist())  # on the host: one sync at most
        if lo < 0 or hi >= n_instances:
            bad = lo if lo < 0 else hi
            raise RolloutInputError(f"instance {bad} is out of range: the bound source has {n_instances} system "
                                    f"instance(s), 0..{n_instances - 1}")
    return t.long()


# per GraphTemplate: (number of controls, control ranges (lo, hi) [N, U] or None), made once
_TEMPLATE_INFO: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()
# per GraphBuilder: (system instances, controls its actuators take)
_BUILDER_INFO: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def source_info(builder) -> tuple[int, int]:
    """(system instances, controls U) of a bound source's ``GraphBuilder`` (one host sync, once)."""
    info = _BUILDER_INFO.get(builder)
    if info is None:
        ec = builder.edge_ctrl
        info = (int(builder.s_nodes.shape[0]), int(ec.max()) + 1 if ec.numel() else 0)
        _BUILDER_INFO[builder] = info
    return info


def _range_columns(layout):
    """{name: column index or constant} of the actuator's ctrllimited flag and range in a feature
    layout (the static edge features of the actuator on each joint edge's first slot), or None
    when the layout has no control ranges."""
    out = {}
    for name in ("act_ctrllimited", "act_ctrlrange_0", "act_ctrlrange_1"):
        if name in layout.edge_names:
            out[name] = layout.edge_names.index(name)
        elif name in layout.dropped.get("edges", {}):
            out[name] = float(layout.dropped["edges"][name])
        else:
            return None
    return out


def _record_ranges(actuators: list, n_ctrl: int, like: torch.Tensor):
    """(lo, hi) [N, U] from each instance's ``Actuators`` record: the range of limited actuators,
    +-inf for unlimited ones and for controls beyond an instance's actuators."""
    lo = np.full((len(actuators), n_ctrl), -np.inf)
    hi = np.full((len(actuators), n_ctrl), np.inf)
    for i, act in enumerate(actuators):
        u = min(act.nu, n_ctrl)
        lo[i, :u] = np.where(act.limited, act.low, -np.inf)[:u]
        hi[i, :u] = np.where(act.limited, act.high, np.inf)[:u]
    return tuple(torch.as_tensor(a, dtype=like.dtype, device=like.device) for a in (lo, hi))


def _template_info(template, layout, n_ctrl: int | None):
    """(controls U, (lo, hi) [N, U] or None) of a GraphTemplate (cached per template).

    Ranges of a template of Systems (``template.actuators``, set by ``graph_builder``) come from
    their ``Actuators`` records. A dataset's template reads the static edge features
    ``act_ctrllimited`` / ``act_ctrlrange_*`` of ``layout``: a dataset holds no System (it may
    come from a user's MJCF file that is not at hand, and rebuilding a parameterized dataset's
    instances would compile one MjModel each), and those features are the record's values as
    generation wrote them."""
    info = _TEMPLATE_INFO.get(template)
    if info is not None and (n_ctrl is None or info[0] == n_ctrl):
        return info
    ci = template.ctrl_index
    if n_ctrl is None:  # the template's own instances: their largest control index
        n_ctrl = int(ci.max()) + 1 if ci.numel() else 0                     # one host sync, once
    ranges = None
    cols = _range_columns(layout) if layout is not None else None
    records = getattr(template, "actuators", None)
    if records is not None and n_ctrl > 0:
        lo, hi = _record_ranges(records, n_ctrl, template.static_edges)
        if bool(torch.isfinite(torch.stack([lo, hi])).any()):   # else no limited actuator: nothing to do
            ranges = (lo, hi)
    elif cols is not None and n_ctrl > 0 and ci.numel():
        se = template.static_edges
        col = lambda k: se[:, cols[k]] if isinstance(cols[k], int) else torch.full_like(se[:, 0], cols[k])  # noqa: E731
        limited, lo_e, hi_e = col("act_ctrllimited") > 0.5, col("act_ctrlrange_0"), col("act_ctrlrange_1")
        c0 = ci[:, 0]
        use = (c0 >= 0) & limited & (lo_e <= hi_e)
        N, U = template.N, n_ctrl
        slot = torch.where(use, template.edge_of.long() * U + c0.clamp(min=0).long(), torch.full_like(c0, N * U))
        inf = torch.full((N * U + 1,), math.inf, dtype=se.dtype, device=se.device)
        # both edges of a joint carry the same actuator and range: duplicates write equal values
        lo = (-inf).index_put((slot,), lo_e)[:-1].reshape(N, U)
        hi = inf.index_put((slot,), hi_e)[:-1].reshape(N, U)
        if bool(torch.isfinite(torch.stack([lo, hi])).any()):   # else no limited actuator: nothing to do
            ranges = (lo, hi)
    info = (n_ctrl, ranges)
    _TEMPLATE_INFO[template] = info
    return info


class RolloutInputs:
    """Checks and clamping of a rollout's inputs for one ``GraphTemplate`` (N system instances, B
    bodies), before any launch.

    ``n_ctrl``: the controls U the source's actuators take (None: the template's own largest
    control index + 1). The actuators' control ranges: for a template of Systems, their
    ``System.actuators`` records (low / high of limited actuators; unlimited ones are not
    clamped); for a dataset's template, ``layout`` (the model's ``FeatureLayout``) names where
    they are read from: the static edge features ``act_ctrllimited`` / ``act_ctrlrange_*`` of the
    actuator on each joint (an actuator sharing a joint with another, in a later slot, has no
    range there and is not clamped). ``ctrl_policy``: one of ``CTRL_POLICIES``. ``check``: also
    refuse NaN / Inf in the initial states (of real bodies) and the controls (one host sync).
    """

    def __init__(self, template, layout=None, n_ctrl: int | None = None, ctrl_policy: str = "clamp",
                 check: bool = True):
        if ctrl_policy not in CTRL_POLICIES:
            raise ValueError(f"ctrl_policy must be one of {CTRL_POLICIES}, got {ctrl_policy!r}")
        if not isinstance(check, bool):
            raise ValueError(f"check must be True or False, got {check!r}")
        self.template, self.ctrl_policy, self.check = template, ctrl_policy, check
        self.n_ctrl, ranges = _template_info(template, layout, n_ctrl)
        self.ranges = None if ctrl_policy == "none" else ranges

    def shapes(self, body, ctrl) -> tuple[torch.Tensor, torch.Tensor]:
        """``body`` [N, B, 13] and ``ctrl`` [N, T, U] (T >= 1) as tensors, or RolloutInputError."""
        tm = self.template
        body, ctrl = float_tensor(body, "initial_body"), float_tensor(ctrl, "ctrl")
        want = f"[N, B, {DYN_NODE_SIZE}] = [{tm.N}, {tm.B}, {DYN_NODE_SIZE}] (N sequences, B bodies of the bound source)"
        if body.ndim != 3 or tuple(body.shape) != (tm.N, tm.B, DYN_NODE_SIZE):
            raise RolloutInputError(f"initial_body must be {want}, got shape {tuple(body.shape)}")
        cw, cshape = f"[N, T, U] = [{tm.N}, T >= 1, {self.n_ctrl}]", tuple(ctrl.shape)
        if ctrl.ndim != 3 or ctrl.shape[0] != tm.N or ctrl.shape[1] < 1 or ctrl.shape[2] != self.n_ctrl:
            why = ("the number of sequences differs from initial_body's" if ctrl.ndim == 3 and ctrl.shape[0] != tm.N
                   else "no steps" if ctrl.ndim == 3 and ctrl.shape[1] < 1
                   else f"the source's actuators take {self.n_ctrl} control(s)" if ctrl.ndim == 3 else "")
            raise RolloutInputError(f"ctrl must be {cw} (U: the bound source's controls), got shape {cshape}"
                                    + (f": {why}" if why else ""))
        return body, ctrl

    def values(self, body: torch.Tensor, ctrl: torch.Tensor) -> torch.Tensor:
        """Finiteness (``check``) and the control policy: the controls to roll out with. At most
        one host sync (none when ``check`` is off and the policy is not "error")."""
        flags, names = [], []
        if self.check:
            nodes = self.template.nodes(body)
            # a real body's orientation: a quaternion, not ~zero (NaN is caught first). Other norms pass
            # as given: perturbed states (gradients, sensitivities) are the model's to read
            flags += [torch.isfinite(nodes).all(), torch.isfinite(ctrl).all(),
                      (nodes[..., 3:7].square().sum(-1) > QUAT_MIN ** 2).all()]
            names += ["initial_body", "ctrl", "quaternion"]
        if self.ranges is not None and self.ctrl_policy == "error":
            lo, hi = (r.to(ctrl.device, ctrl.dtype)[:, None] for r in self.ranges)
            flags.append(((ctrl >= lo) & (ctrl <= hi) | ~torch.isfinite(ctrl)).all())
            names.append("range")
        if flags:
            ok = torch.stack(flags).tolist()
            for name, good in zip(names, ok):
                if good:
                    continue
                if name == "range":
                    lo, hi = (r.to(ctrl.device, ctrl.dtype)[:, None].expand_as(ctrl) for r in self.ranges)
                    n, t, u = (int(i) for i in ((ctrl < lo) | (ctrl > hi)).nonzero()[0])
                    raise RolloutInputError(
                        f"ctrl[{n}, {t}, {u}] = {float(ctrl[n, t, u]):g} is outside actuator {u}'s control range "
                        f"[{float(lo[n, t, u]):g}, {float(hi[n, t, u]):g}] (ctrl_policy='error'; 'clamp' clamps "
                        "it as MuJoCo does)")
                if name == "quaternion":
                    tm = self.template
                    sq = self.template.nodes(body)[..., 3:7].square().sum(-1)
                    bad = int((sq <= QUAT_MIN ** 2).nonzero()[0, 0])
                    r = bad if tm.rows is None else int(tm.rows[bad])
                    raise RolloutInputError(f"initial_body[{r // tm.B}, {r % tm.B}] has an orientation quaternion of "
                                            f"norm {float(sq[bad].sqrt()):.4g} (columns 3:7, w x y z): a body's state needs "
                                            "its orientation, a unit quaternion")
                x = self.template.nodes(body) if name == "initial_body" else ctrl
                where = tuple(int(i) for i in (~torch.isfinite(x)).nonzero()[0])
                if name == "initial_body":
                    tm = self.template
                    r = where[0] if tm.rows is None else int(tm.rows[where[0]])
                    raise RolloutInputError(f"initial_body contains NaN or Inf (at initial_body[{r // tm.B}, "
                                            f"{r % tm.B}])")
                raise RolloutInputError(f"ctrl contains NaN or Inf (at ctrl{list(where)})")
        if self.ranges is not None and self.ctrl_policy == "clamp":
            lo, hi = (r.to(ctrl.device, ctrl.dtype)[:, None] for r in self.ranges)
            ctrl = torch.minimum(torch.maximum(ctrl, lo), hi)   # as MuJoCo clamps ctrllimited actuators
        return ctrl


def adjoint_loop(step: Callable, traj, ctrl, g_traj, need_x: bool, need_u: bool, params=(), scope=None):
    """The backward of T steps ``traj[:, t+1] = step(traj[:, t], ctrl[:, t])``, one step at a time
    in reverse, each recomputed with autograd on: (dL/dx0 or None, dL/dctrl or None, [dL/dp for p
    in params]) for dL/dtraj ``g_traj`` [N, T+1, B, 13]. ``scope(t)``: a context each step's
    recomputation runs in (an ``ActivationStore`` replaying step t)."""
    g_params = [torch.zeros_like(p) for p in params]
    g_ctrl = torch.zeros_like(ctrl) if need_u else None
    g = g_traj[:, -1]  # dL/d(state T)
    for t in range(ctrl.shape[1] - 1, -1, -1):
        with torch.enable_grad():
            body = traj[:, t].detach().requires_grad_(need_x or t > 0)
            c = ctrl[:, t].detach().requires_grad_(need_u)
            with scope(t) if scope is not None else contextlib.nullcontext():
                nxt = step(body, c)
            inputs = [x for x in (body, c) if x.requires_grad] + list(params)
            grads = vjp(nxt, inputs, g) if inputs else ()
        k = 0
        g_body = None
        if body.requires_grad:
            g_body, k = grads[0], 1
        if c.requires_grad:
            if grads[k] is not None:
                g_ctrl[:, t] = grads[k]
            k += 1
        for acc, gp in zip(g_params, grads[k:]):
            if gp is not None:
                acc += gp
        # dL/d(state t): through step t, plus the loss's own term on state t
        g = g_traj[:, t] if g_body is None else g_body + g_traj[:, t]
    return (g if need_x else None), g_ctrl, g_params


def forward_loop(step: Callable, x0, ctrl):
    """States [N, T+1, B, 13] of ``step`` applied T times from ``x0`` under ``ctrl`` [N, T, U]."""
    states = [x0]
    for t in range(ctrl.shape[1]):
        states.append(step(states[-1], ctrl[:, t]))
    return torch.stack(states, 1)


class _AdjointRollout(torch.autograd.Function):
    """Inputs: (step, x0 [N, B, 13], ctrl [N, T, U], *params); output: states [N, T+1, B, 13].
    ``step(body, ctrl_t) -> next body`` is the model's one step."""

    @staticmethod
    def forward(ctx, step: Callable, x0, ctrl, *params):
        with torch.no_grad():  # no activations kept: the backward recomputes each step
            traj = forward_loop(step, x0, ctrl)
        ctx.step = step
        ctx.save_for_backward(traj, ctrl, *params)
        return traj

    @staticmethod
    def backward(ctx, g_traj):
        traj, ctrl, *params = ctx.saved_tensors
        need = ctx.needs_input_grad
        want = [p for p, n in zip(params, need[3:]) if n]
        g_x, g_u, g_p = adjoint_loop(ctx.step, traj, ctrl, g_traj, need[1], need[2], want)
        g_p = iter(g_p)
        return (None, g_x, g_u, *(next(g_p) if n else None for n in need[3:]))


def rollout_with_adjoint(step: Callable, x0: torch.Tensor, ctrl: torch.Tensor, params) -> torch.Tensor:
    """States [N, T+1, B, 13] of ``step`` applied T times from ``x0`` [N, B, 13] under ``ctrl``
    [N, T, U], differentiable with respect to ``x0``, ``ctrl`` and ``params`` (the tensors the step
    reads that may need gradients) by the adjoint loop: only the states are kept for the backward.
    Supports ``backward()`` and ``torch.autograd.grad``; not double backward."""
    return _AdjointRollout.apply(step, x0, ctrl, *params)


class _EngineRollout(torch.autograd.Function):
    """A RolloutEngine's rollout: forward and backward replayed from its graphs."""

    @staticmethod
    def forward(ctx, engine, x0, ctrl):
        # a backward may follow: record the blocks for it (when the engine keeps a store)
        traj, ctx.generation = engine._forward(x0, ctrl, record=any(ctx.needs_input_grad[1:3]))
        ctx.engine = engine
        ctx.save_for_backward(traj, ctrl)
        return traj

    @staticmethod
    def backward(ctx, g_traj):
        traj, ctrl = ctx.saved_tensors
        g_x, g_u = ctx.engine._backward(traj, ctrl, g_traj, ctx.generation)
        return None, g_x, g_u


class RolloutEngine:
    """Rollouts of one batch shape: ``instance`` [N] system instances of a bound model (a
    ``gnwarp.dynamics.Dynamics``: ``ForwardModel``, ``FixedGIDModel``), ``horizon`` T steps. ``rollout(x0 [N, B, 13], ctrl [N, T, U]) -> [N, T+1, B, 13]`` is ``model.rollout``,
    differentiable with respect to ``x0`` and ``ctrl`` by the adjoint loop; on CUDA its forward
    and its backward each replay one CUDA graph (recorded on the second call of each, after an
    eager warm-up). Gradients with respect to the model's parameters are not computed (use
    ``model.rollout``). The model's weights and normalizer statistics are read at every replay;
    change them in place, not by replacing tensors. Results are fresh tensors (copies).
    ``instance`` is checked against the bound source; every call's inputs are checked before any
    launch and the controls clamped to the actuators' ranges (``ctrl_policy``, ``check``: see
    ``ForwardModel.rollout``).

    ``store``: a forward that a backward may follow records each step's GN blocks (their packed
    ReLU masks and the outputs the model reads: ``gnwarp/gn/replay.py``), so that the backward
    replays them instead of recomputing the blocks' GEMMs. "auto" (default): when the recording
    fits ``store_bytes`` (default: half the free CUDA memory at the first recording; 1 GiB on the
    CPU), else recompute; True: always record; False: always recompute. A backward replays only
    the recording of its own forward (after another forward, it recomputes).

    ``fused``: run each step as a ``FusedStep`` (``gnwarp/models/fused_step.py``: encode, core,
    decode in a few launches; the backward walks the steps in reverse with its vector-Jacobian
    product on the states the forward kept) instead of ``model.next_nodes`` with autograd
    recomputation. None (default): where it can run (a ``ForwardModel`` with a GN core, graphs of
    one size and topology, float32 / float64) and ``gnwarp.gn.rules.choose_fused`` picks it (CUDA,
    any batch); True: always (ValueError naming why it cannot run); False: never. A fused
    engine keeps a store as the unfused one does: the backward's core forward replays the
    recording. ``engine.fused`` says which runs."""

    def __init__(self, model, instance, horizon: int, builder=None, ctrl_policy: str = "clamp", check: bool = True,
                 graphs: bool = True, store: bool | str = "auto", store_bytes: int | None = None,
                 fused: bool | None = None):
        try:
            ok = not isinstance(horizon, bool) and int(horizon) == horizon and horizon >= 1
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise RolloutInputError(f"horizon must be an integer >= 1, got {horizon!r}")
        self.model = model
        # what ``one_step`` needs to make a one-step engine like this one
        self._args = dict(instance=instance, builder=builder, ctrl_policy=ctrl_policy, check=check)
        source = builder if builder is not None else model.builder
        if source is not None:
            n_inst, n_ctrl = source_info(source)
            instance = check_instance(instance, n_inst)
        else:
            n_ctrl = None   # model.template says what is missing
        self.template = model.template(torch.as_tensor(instance), builder)
        # the model knows where its actuators' ranges are (system ID: the bound source only)
        self.inputs = model.rollout_inputs(self.template, n_ctrl, ctrl_policy, check, builder)
        self.horizon = int(horizon)
        # graphs=False: run the loops eagerly on CUDA too (for a caller that captures a larger
        # step around the rollout, e.g. a whole planning iteration: graphs do not nest)
        self.cuda = self.template.static_nodes.is_cuda and bool(graphs)
        if store not in (True, False, "auto"):
            raise ValueError(f"store must be True, False or 'auto', got {store!r}")
        if store_bytes is not None and (isinstance(store_bytes, bool) or not isinstance(store_bytes, int)
                                        or store_bytes < 0):
            raise ValueError(f"store_bytes must be a non-negative integer (bytes), got {store_bytes!r}")
        self.store_policy, self.store_bytes = store, store_bytes
        self._fused = fused_step_for(model, self.template, fused)
        self.fused = self._fused is not None
        self._store = None
        if store is not False:
            core = getattr(model, "core", None)
            keep = core.replay_outputs() if hasattr(core, "replay_outputs") else None
            self._store = ActivationStore(self.horizon, keep)
        self._bufs = None
        self._fwd = self._bwd = None
        self._fwd_rec = self._bwd_rep = None

    @property
    def fused_step(self):
        """The ``FusedStep`` the loops run (None when the engine runs the unfused step)."""
        return self._fused

    @property
    def store(self) -> ActivationStore | None:
        """The activation store (None when the engine recomputes)."""
        return self._store

    def _step(self, ctx):
        tmpl, model = self.template, self.model
        return lambda b, c: tmpl.to_body(model.next_nodes(tmpl.graph(b, c), ctx), b)

    def _buffers(self, x0, ctrl):
        if self._bufs is None:
            if ctrl.shape[1] != self.horizon:
                raise ValueError(f"this RolloutEngine rolls out {self.horizon} steps, got controls for {ctrl.shape[1]}")
            z = lambda shape: torch.zeros(shape, dtype=self.template.dtype, device=x0.device)  # noqa: E731
            N, T = x0.shape[0], self.horizon
            self._bufs = dict(x0=z(x0.shape), ctrl=z(ctrl.shape), traj=z((N, T + 1) + tuple(x0.shape[1:])),
                              g_traj=z((N, T + 1) + tuple(x0.shape[1:])), g_x0=z(x0.shape), g_ctrl=z(ctrl.shape))
        b = self._bufs
        if x0.shape != b["x0"].shape or ctrl.shape != b["ctrl"].shape:
            raise ValueError(f"this RolloutEngine holds x0 {tuple(b['x0'].shape)} and controls "
                             f"{tuple(b['ctrl'].shape)}, got {tuple(x0.shape)} and {tuple(ctrl.shape)}")
        return b

    def one_step(self) -> "RolloutEngine":
        """A new engine like this one (model, instances, control policy, store policy and
        budget, step path) that rolls out one step, eagerly: what a caller runs before it
        records a larger step around this engine in a CUDA graph without an eager warm-up
        (Warp's modules load, torch's lazy state is made), then ``size_store`` with it."""
        a = self._args
        return RolloutEngine(self.model, a["instance"], 1, a["builder"], ctrl_policy=a["ctrl_policy"],
                             check=a["check"], graphs=False, store=self.store_policy,
                             store_bytes=self.store_bytes, fused=self.fused)

    def size_store(self, one: "RolloutEngine") -> None:
        """Decide this engine's store from the first recording of ``one`` (``one_step``: the
        same blocks, so the same bytes a step): kept when every step's would fit the budget,
        else dropped. A caller that records this engine's first forward inside a CUDA graph
        does this first, so that no budget query runs in the capture. Nothing changes where
        the store is already decided or ``one`` has recorded nothing yet. ``one`` must keep a
        store as this engine does (``one_step`` makes such an engine): ValueError otherwise."""
        if one.store_policy != self.store_policy or one.store_bytes != self.store_bytes:
            raise ValueError(f"size_store needs a one-step engine with this engine's store policy and budget "
                             f"(store={self.store_policy!r}, store_bytes={self.store_bytes!r}; one_step makes "
                             f"one), got store={one.store_policy!r}, store_bytes={one.store_bytes!r}")
        store = self._store
        if store is None or store.sized:
            return
        if one.store is None:                 # one step over the budget: its store was dropped
            self._store = None
        elif one.store.sized:
            store.sized = True
            if not self._store_fits(one.store.step_bytes(0) * self.horizon):
                self._store = None            # recompute, as a store dropped at its first recording

    @contextlib.contextmanager
    def _recording(self, t: int):
        """Context of step ``t`` of a recording forward; after the first step's first recording
        (eager: before any capture; or decided earlier by ``size_store``), drops the store when
        every step's would not fit."""
        store = self._store
        with store.recording(t):
            yield
        if t == 0 and not store.sized:
            store.sized = True
            if not self._store_fits(store.step_bytes(0) * self.horizon):
                store.drop()   # the remaining steps run without recording

    def _forward_fn(self, record: bool = False):
        b = self._bufs
        if self.fused:
            with torch.no_grad():
                b["traj"][:, 0] = b["x0"]
                self._fused.forward_loop(b["traj"], b["ctrl"], self._recording if record else None)
            return
        with torch.no_grad():
            ctx = self.model.context(self.template.graph(b["x0"], b["ctrl"][:, 0]))
            step, traj = self._step(ctx), b["traj"]
            traj[:, 0] = b["x0"]
            for t in range(self.horizon):
                with self._recording(t) if record else contextlib.nullcontext():
                    traj[:, t + 1] = step(traj[:, t], b["ctrl"][:, t])

    def _store_fits(self, need: int) -> bool:
        """Whether a recording of ``need`` bytes (every step's) fits the budget."""
        if self.store_policy is True:
            return True
        budget = self.store_bytes
        if budget is None:
            dev = self.template.static_nodes.device
            budget = torch.cuda.mem_get_info(dev)[0] // 2 if dev.type == "cuda" else 1 << 30
        return need <= budget

    def _backward_fn(self, replay: bool = False):
        b, store = self._bufs, self._store
        if self.fused:
            self._fused.backward_loop(b["traj"], b["ctrl"], b["g_traj"], b["g_x0"], b["g_ctrl"],
                                      store.replaying if replay else None)
            return
        with torch.no_grad():
            ctx = self.model.context(self.template.graph(b["x0"], b["ctrl"][:, 0]))
        with frozen_parameters(self.model):   # no weight gradients: the GN's backward skips their GEMMs
            g_x, g_u, _ = adjoint_loop(self._step(ctx), b["traj"], b["ctrl"], b["g_traj"], True, True,
                                       scope=store.replaying if replay else None)
        b["g_x0"].copy_(g_x)
        b["g_ctrl"].copy_(g_u)

    def _forward(self, x0, ctrl, record: bool = False):
        """(states, the recording's generation or None)."""
        b = self._buffers(x0, ctrl)
        b["x0"].copy_(x0)
        b["ctrl"].copy_(ctrl)
        store = self._store
        record = record and store is not None and store.enabled
        if record:
            store.valid = False   # until this recording completes
        if not self.cuda:
            self._forward_fn(record)
        else:   # the first call of each graph runs eagerly: the first recording allocates the store
            attr = "_fwd_rec" if record else "_fwd"
            if getattr(self, attr) is None:
                setattr(self, attr, Graphed(lambda: self._forward_fn(record)))
            getattr(self, attr)()
        gen = None
        if record and store.enabled:
            store.generation += 1
            store.valid = True
            gen = store.generation
        elif record:
            self._store = None   # over budget: recompute from now on
        return b["traj"].clone(), gen

    def _backward(self, traj, ctrl, g_traj, generation=None):
        b = self._bufs
        b["traj"].copy_(traj)
        b["ctrl"].copy_(ctrl)
        b["x0"].copy_(traj[:, 0])
        b["g_traj"].copy_(g_traj)
        store = self._store
        replay = (generation is not None and store is not None and store.valid and store.generation == generation)
        if not self.cuda:
            self._backward_fn(replay)
        else:
            attr = "_bwd_rep" if replay else "_bwd"
            if getattr(self, attr) is None:
                setattr(self, attr, Graphed(lambda: self._backward_fn(replay)))
            getattr(self, attr)()
        return b["g_x0"].clone(), b["g_ctrl"].clone()

    def rollout(self, x0: torch.Tensor, ctrl: torch.Tensor) -> torch.Tensor:
        """States [N, T+1, B, 13] from ``x0`` [N, B, 13] under ``ctrl`` [N, T, U]. The inputs are
        checked before any launch (shapes; with ``check``, finiteness: one host sync) and the
        controls clamped to the actuators' ranges (``ctrl_policy``, see ``RolloutInputs``)."""
        tm = self.template
        x0, ctrl = float_tensor(x0, "x0"), float_tensor(ctrl, "ctrl")
        if ctrl.ndim == 3 and ctrl.shape[1] != self.horizon:
            raise RolloutInputError(f"this RolloutEngine rolls out {self.horizon} steps, got controls for "
                                    f"{ctrl.shape[1]}")
        want_x, want_u = (tm.N, tm.B, DYN_NODE_SIZE), (tm.N, self.horizon, self.inputs.n_ctrl)
        if tuple(x0.shape) != want_x or tuple(ctrl.shape) != want_u:
            raise RolloutInputError(f"this RolloutEngine holds x0 {want_x} and controls {want_u} ([N, B, 13] and "
                                    f"[N, T, U]), got {tuple(x0.shape)} and {tuple(ctrl.shape)}")
        dev, dt = tm.static_nodes.device, tm.dtype
        x0, ctrl = x0.to(dev, dt), ctrl.to(dev, dt)
        ctrl = self.inputs.values(x0, ctrl)
        return _EngineRollout.apply(self, x0, ctrl)
