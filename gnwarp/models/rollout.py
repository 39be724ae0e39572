"""Gradients through rollouts with memory proportional to the states, not to the activations.

A rollout of T steps through a learned model keeps, under plain autograd, every step's MLP
activations until the backward: for the paper core at 4096 cheetah graphs that is ~1 GB a step,
so 100 steps do not fit a GPU. ``rollout_with_adjoint`` runs the forward loop without autograd,
keeps only the states (and the controls), and in the backward walks the steps in reverse,
recomputing one step at a time with autograd on and taking its vector-Jacobian product: the
adjoint loop. Peak memory is the states plus one step's activations; the price is one more
forward per step.
"""
from __future__ import annotations

from typing import Callable

import torch

__all__ = ["rollout_with_adjoint"]


class _AdjointRollout(torch.autograd.Function):
    """Inputs: (step, n_params, x0 [N, B, 13], ctrl [N, T, U], *params); output: states
    [N, T+1, B, 13]. ``step(body, ctrl_t) -> next body`` is the model's one step."""

    @staticmethod
    def forward(ctx, step: Callable, n_params: int, x0, ctrl, *params):
        states = [x0]
        with torch.no_grad():  # no activations kept: the backward recomputes each step
            for t in range(ctrl.shape[1]):
                states.append(step(states[-1], ctrl[:, t]))
        traj = torch.stack(states, 1)
        ctx.step = step
        ctx.save_for_backward(traj, ctrl, *params)
        return traj

    @staticmethod
    def backward(ctx, g_traj):
        traj, ctrl, *params = ctx.saved_tensors
        need_x, need_u = ctx.needs_input_grad[2], ctx.needs_input_grad[3]
        want = [p for p, need in zip(params, ctx.needs_input_grad[4:]) if need]
        g_params = [torch.zeros_like(p) for p in want]
        g_ctrl = torch.zeros_like(ctrl) if need_u else None
        g = g_traj[:, -1]  # dL/d(state T)
        for t in range(ctrl.shape[1] - 1, -1, -1):
            with torch.enable_grad():
                body = traj[:, t].detach().requires_grad_(need_x or t > 0)
                c = ctrl[:, t].detach().requires_grad_(need_u)
                nxt = ctx.step(body, c)
                inputs = [x for x in (body, c) if x.requires_grad] + want
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
        g_params = iter(g_params)
        return (None, None, g if need_x else None, g_ctrl,
                *(next(g_params) if need else None for need in ctx.needs_input_grad[4:]))


def rollout_with_adjoint(step: Callable, x0: torch.Tensor, ctrl: torch.Tensor, params) -> torch.Tensor:
    """States [N, T+1, B, 13] of ``step`` applied T times from ``x0`` [N, B, 13] under ``ctrl``
    [N, T, U], differentiable with respect to ``x0``, ``ctrl`` and ``params`` (the tensors the step
    reads that may need gradients) by the adjoint loop: only the states are kept for the backward.
    Supports ``backward()`` and ``torch.autograd.grad``; not double backward."""
    params = list(params)
    return _AdjointRollout.apply(step, len(params), x0, ctrl, *params)
