"""The backward's side CUDA streams: weight-gradient GEMMs off the critical path."""
from __future__ import annotations

import contextlib

import torch

from gnwarp.gn.rules import TUNABLES

__all__ = ["SideStreams"]

_SIDE_POOL: dict[int, list] = {}


class SideStreams:
    """The backward's weight-gradient GEMMs on side CUDA streams, off the critical path (the
    chain of input-gradient GEMMs, ReLU masks and scatters that each layer waits on): at batch
    200 each GEMM fills a fraction of the GPU, so the chains overlap. ``with side(*reads):``
    enqueues the body on the next side stream (round robin over ``TUNABLES.side_streams``) after
    everything the current stream has enqueued; ``reads`` (the tensors the body reads) stay
    referenced until ``join``, so the caching allocator cannot hand their memory to later
    current-stream work while a side stream may still read it. ``after(fn)`` runs ``fn`` on the
    current stream at ``join``, which makes the current stream wait for the side streams (also
    inside a CUDA graph capture: forks and joins). Off CUDA (or with ``side_streams`` = 0) the
    bodies run in place."""

    def __init__(self, like: torch.Tensor):
        n = TUNABLES.side_streams if like.device.type == "cuda" else 0
        self.streams, self.used, self.k = [], [], 0
        self.keep, self.pending = [], []
        if n > 0:
            self.main = torch.cuda.current_stream(like.device)
            pool = _SIDE_POOL.setdefault(self.main.cuda_stream, [])
            while len(pool) < n:
                pool.append(torch.cuda.Stream(like.device))
            self.streams = pool[:n]

    @contextlib.contextmanager
    def __call__(self, *reads):
        if not self.streams:
            yield
            return
        stream = self.streams[self.k % len(self.streams)]
        self.k += 1
        stream.wait_stream(self.main)
        self.keep.extend(r for r in reads if r is not None)
        if stream not in self.used:
            self.used.append(stream)
        with torch.cuda.stream(stream):
            yield

    def after(self, fn):
        self.pending.append(fn)

    def join(self):
        for stream in self.used:
            self.main.wait_stream(stream)
        self.used.clear()
        self.keep.clear()
        for fn in self.pending:
            fn()
        self.pending.clear()
