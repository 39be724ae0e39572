"""The gradient all-reduce over ranks overlapped with the backward pass, as DDP's buckets do.

The paper's core is GN1 then GN2; the backward runs GN2's first. With FlatAdam every parameter's
gradient is a view of one flat buffer and the Warp GN blocks add into it, GN2's parameters one
contiguous span at its end. ``GradientBuckets`` starts the all-reduce of that span as soon as
GN2's backward has returned (``gnwarp.models.cores.after_gn2_backward``), on the process group's
stream, while GN1's backward runs on the current one; after the backward it reduces the rest
and waits for both. Inside a captured training step both reductions are recorded in the graph.
A step whose early span is not complete when the signal comes (a GN2 gradient left in
``p.grad``) reduces the whole buffer after the backward instead; one that arrives after the span
was sent raises, never averages a part twice.
"""
from __future__ import annotations

import contextlib

import torch

from gnwarp.distributed import Ranks
from gnwarp.models.cores import GNCore, after_gn2_backward

__all__ = ["GradientBuckets"]


class GradientBuckets:
    """Two buckets of FlatAdam's flat gradient over ``ranks``: GN2's span, reduced while GN1's
    backward runs, and the rest, reduced after the backward (``reduce``). ``for_model`` gives
    None where the model has no such span (one block, the MLP baseline, the torch GN)."""

    def __init__(self, ranks: Ranks, optimizer, early: list[torch.nn.Parameter]):
        self.ranks, self.optimizer, self.early = ranks, optimizer, list(early)
        spans = {id(p): (o, o + p.numel()) for p, o in zip(optimizer.param_groups[0]["params"], optimizer.offsets)}
        mine = [spans[id(p)] for p in self.early]
        self.start, self.end = min(a for a, _ in mine), max(b for _, b in mine)
        ids = {id(p) for p in self.early}
        for p in optimizer.param_groups[0]["params"]:
            a, b = spans[id(p)]
            if id(p) not in ids and a < self.end and b > self.start:
                raise ValueError("GradientBuckets: the early parameters are not one span of the flat gradient")
        self.pending = None
        self.skipped = False
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
        self.pending, self.skipped = None, False
        with after_gn2_backward(self._send_early):
            yield

    def _send_early(self) -> None:
        if self.pending is not None or self.skipped:
            return   # one signal a step (a model called twice in a step: the first one)
        if any(p.grad is not None for p in self.early):
            self.skipped = True    # a gradient outside the flat buffer: reduce after the backward
            return
        span = self.optimizer.grad_flat[self.start:self.end]
        self.pending = self.ranks.all_reduce_(span, mean=True, async_op=True)
        self.sent += 1

    def reduce(self) -> None:
        """After the backward: the rest (or, where the early bucket was not sent, everything)
        averaged over the ranks, and the early bucket waited for."""
        if self.pending is not None and any(p.grad is not None for p in self.early):
            raise RuntimeError("GradientBuckets: a GN2 gradient arrived in p.grad after its bucket was reduced; "
                               "run with overlap_allreduce=False")
        flat = self.optimizer.fold_grads()
        if self.pending is None:
            self.ranks.all_reduce_(flat, mean=True)
            return
        for a, b in ((0, self.start), (self.end, flat.numel())):
            if b > a:
                self.ranks.all_reduce_(flat[a:b], mean=True)
        self.pending.wait()
        self.pending = None
