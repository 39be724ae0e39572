"""The gradient all-reduce over ranks overlapped with the backward pass, as DDP's buckets do.

The paper's core is GN1 then GN2; the backward runs GN2's first. With FlatAdam every parameter's
gradient is a view of one flat buffer and the Warp GN blocks add into it, GN2's parameters one
contiguous span of it (at its end). ``GradientBuckets`` starts the all-reduce of that span as
soon as GN2's backward has returned (``gnwarp.models.cores.gn2_listener``; with several calls of
the model in one step, once the last call's GN2 backward has), on the process group's stream,
while GN1's backward runs on the current one; after the backward it reduces the rest and waits
for both. Inside a captured training step both reductions are recorded in the graph. A step
whose early span is not complete when the signal comes (a GN2 gradient left in ``p.grad``)
reduces the whole buffer after the backward instead; one that arrives after the span was sent
raises, never averages a part twice.
"""
from __future__ import annotations

import contextlib

import torch

from gnwarp.distributed import Ranks
from gnwarp.models.cores import GNCore, gn2_listener

__all__ = ["GradientBuckets"]


class GradientBuckets:
    """Two buckets of FlatAdam's flat gradient over ``ranks``: the span of the ``early``
    parameters (GN2's, with the alignment padding up to the next parameter), reduced while GN1's
    backward runs, and the rest, reduced after the backward (``reduce``): two all-reduces a step.
    ``for_model`` gives None where the model has no such span (one block, the MLP baseline, the
    torch GN)."""

    def __init__(self, ranks: Ranks, optimizer, early: list[torch.nn.Parameter]):
        self.ranks, self.optimizer, self.early = ranks, optimizer, list(early)
        params = optimizer.param_groups[0]["params"]
        spans = {id(p): (o, o + p.numel()) for p, o in zip(params, optimizer.offsets)}
        ids = {id(p) for p in self.early}
        mine = [spans[id(p)] for p in self.early]
        start, end = min(a for a, _ in mine), max(b for _, b in mine)
        others = [spans[id(p)] for p in params if id(p) not in ids]
        if any(a < end and b > start for a, b in others):
            raise ValueError("GradientBuckets: the early parameters are not one span of the flat gradient")
        # the padding after the span's last parameter goes with it: no range of padding alone
        self.start = start
        self.end = min([a for a, _ in others if a >= end], default=optimizer.grad_flat.numel())
        # what is reduced after the backward: the ranges of the other parameters, padding included
        rest = [(0, self.start), (self.end, optimizer.grad_flat.numel())]
        self.rest = [(a, b) for a, b in rest if any(a <= s < b for s, _ in others)]
        self.pending = None
        self.skipped = False
        self.calls = self.signals = 0
        self.sent = 0      # steps whose early bucket went out during the backward

    @classmethod
    def for_model(cls, ranks: Ranks, optimizer, model) -> GradientBuckets | None:
        core = getattr(model, "core", None)
        if not (ranks.distributed and isinstance(core, GNCore) and core.gn2 is not None
                and core.options.impl == "warp"):
            return None
        return cls(ranks, optimizer, list(core.gn2.parameters()))

    @contextlib.contextmanager
    def armed(self):
        """Around the loss's forward: its backward starts the early bucket."""
        self._settle()
        self.skipped, self.calls, self.signals = False, 0, 0
        with gn2_listener(self):
            yield

    def gn2_forward(self) -> None:
        self.calls += 1

    def gn2_backward(self) -> None:
        self.signals += 1
        if self.signals < self.calls or self.pending is not None or self.skipped:
            return   # another call of the model still has GN2's backward to run
        if any(p.grad is not None for p in self.early):
            self.skipped = True    # a gradient outside the flat buffer: reduce after the backward
            return
        span = self.optimizer.grad_flat[self.start:self.end]
        self.pending = self.ranks.all_reduce_(span, mean=True, async_op=True)
        self.sent += 1

    def _settle(self) -> None:
        """Wait for an early reduction still under way (a step that failed after sending it)."""
        if self.pending is not None:
            pending, self.pending = self.pending, None
            pending.wait()

    def reduce(self) -> None:
        """After the backward: the rest (or, where the early bucket was not sent, everything)
        averaged over the ranks, and the early bucket waited for."""
        if self.pending is not None and any(p.grad is not None for p in self.early):
            self._settle()
            raise RuntimeError("GradientBuckets: a GN2 gradient arrived in p.grad after its bucket was reduced; "
                               "run with overlap_allreduce=False")
        flat = self.optimizer.fold_grads()
        if self.pending is None:
            self.ranks.all_reduce_(flat, mean=True)
            return
        for a, b in self.rest:
            self.ranks.all_reduce_(flat[a:b], mean=True)
        self._settle()
