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
launch instead of thousands from Python.
"""
from __future__ import annotations

from typing import Callable

import torch

from gnwarp.interop import Graphed

__all__ = ["adjoint_loop", "rollout_with_adjoint", "RolloutEngine"]


def adjoint_loop(step: Callable, traj, ctrl, g_traj, need_x: bool, need_u: bool, params=()):
    """The backward of T steps ``traj[:, t+1] = step(traj[:, t], ctrl[:, t])``, one step at a time
    in reverse, each recomputed with autograd on: (dL/dx0 or None, dL/dctrl or None, [dL/dp for p
    in params]) for dL/dtraj ``g_traj`` [N, T+1, B, 13]."""
    g_params = [torch.zeros_like(p) for p in params]
    g_ctrl = torch.zeros_like(ctrl) if need_u else None
    g = g_traj[:, -1]  # dL/d(state T)
    for t in range(ctrl.shape[1] - 1, -1, -1):
        with torch.enable_grad():
            body = traj[:, t].detach().requires_grad_(need_x or t > 0)
            c = ctrl[:, t].detach().requires_grad_(need_u)
            nxt = step(body, c)
            inputs = [x for x in (body, c) if x.requires_grad] + list(params)
            grads = torch.autograd.grad(nxt, inputs, g, allow_unused=True) if inputs else ()
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
        traj = engine._forward(x0, ctrl)
        ctx.engine = engine
        ctx.save_for_backward(traj, ctrl)
        return traj

    @staticmethod
    def backward(ctx, g_traj):
        traj, ctrl = ctx.saved_tensors
        g_x, g_u = ctx.engine._backward(traj, ctrl, g_traj)
        return None, g_x, g_u


class RolloutEngine:
    """Rollouts of one batch shape: ``instance`` [N] system instances of a bound model, ``horizon``
    T steps. ``rollout(x0 [N, B, 13], ctrl [N, T, U]) -> [N, T+1, B, 13]`` is ``model.rollout``,
    differentiable with respect to ``x0`` and ``ctrl`` by the adjoint loop; on CUDA its forward
    and its backward each replay one CUDA graph (recorded on the second call of each, after an
    eager warm-up). Gradients with respect to the model's parameters are not computed (use
    ``model.rollout``). The model's weights and normalizer statistics are read at every replay;
    change them in place, not by replacing tensors. Results are fresh tensors (copies)."""

    def __init__(self, model, instance, horizon: int, builder=None):
        self.model = model
        self.template = model.template(torch.as_tensor(instance), builder)
        self.horizon = int(horizon)
        self.cuda = self.template.static_nodes.is_cuda
        self._bufs = None
        self._fwd = self._bwd = None

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

    def _forward_fn(self):
        b = self._bufs
        with torch.no_grad():
            ctx = self.model.context(self.template.graph(b["x0"], b["ctrl"][:, 0]))
            step, traj = self._step(ctx), b["traj"]
            traj[:, 0] = b["x0"]
            for t in range(self.horizon):
                traj[:, t + 1] = step(traj[:, t], b["ctrl"][:, t])

    def _backward_fn(self):
        b = self._bufs
        with torch.no_grad():
            ctx = self.model.context(self.template.graph(b["x0"], b["ctrl"][:, 0]))
        g_x, g_u, _ = adjoint_loop(self._step(ctx), b["traj"], b["ctrl"], b["g_traj"], True, True)
        b["g_x0"].copy_(g_x)
        b["g_ctrl"].copy_(g_u)

    def _forward(self, x0, ctrl):
        b = self._buffers(x0, ctrl)
        b["x0"].copy_(x0)
        b["ctrl"].copy_(ctrl)
        if not self.cuda:
            self._forward_fn()
        else:
            if self._fwd is None:
                self._fwd = Graphed(self._forward_fn)
            self._fwd()
        return b["traj"].clone()

    def _backward(self, traj, ctrl, g_traj):
        b = self._bufs
        b["traj"].copy_(traj)
        b["ctrl"].copy_(ctrl)
        b["x0"].copy_(traj[:, 0])
        b["g_traj"].copy_(g_traj)
        if not self.cuda:
            self._backward_fn()
        else:
            if self._bwd is None:
                self._bwd = Graphed(self._backward_fn)
            self._bwd()
        return b["g_x0"].clone(), b["g_ctrl"].clone()

    def rollout(self, x0: torch.Tensor, ctrl: torch.Tensor) -> torch.Tensor:
        """States [N, T+1, B, 13] from ``x0`` [N, B, 13] under ``ctrl`` [N, T, U]."""
        dev, dt = self.template.static_nodes.device, self.template.dtype
        return _EngineRollout.apply(self, x0.to(dev, dt), ctrl.to(dev, dt))
