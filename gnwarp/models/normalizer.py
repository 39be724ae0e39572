"""Online input / output normalization of a forward model (paper, D.3, D.7.1)."""
from __future__ import annotations

import torch
import torch.nn as nn

from gnwarp.graphs import GraphsTuple
from gnwarp.interop import WP_DTYPE, Launcher
from gnwarp.kernels.models import normalizer as K

__all__ = ["Normalizer", "normalize_graph", "accumulate_over_ranks"]


class Normalizer(nn.Module):
    """Online mean/std per feature, shared by every row (every node, edge or graph) (D.3).

    Accumulates count, sum and squared sum (float64 buffers, so they travel in the state dict and
    keep float64 when the model is cast). ``std = max(sqrt(var), std_floor)``; before any data the
    transform is the identity. No host synchronization anywhere.
    """

    def __init__(self, size: int, std_floor: float = 1e-4):
        super().__init__()
        self.size = int(size)
        self.std_floor = float(std_floor)
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))
        self.register_buffer("sum", torch.zeros(self.size, dtype=torch.float64))
        self.register_buffer("sumsq", torch.zeros(self.size, dtype=torch.float64))
        # ``gnwarp.distributed.Ranks`` whose batches count as one (set by a distributed trainer):
        # each batch's count and sums are summed over the ranks before they are added
        self.ranks = None

    def _apply(self, fn, recurse=True):
        saved = {k: self._buffers[k] for k in ("count", "sum", "sumsq")}
        super()._apply(fn, recurse)
        for k, old in saved.items():  # keep the accumulators in float64 whatever the model's dtype
            if self._buffers[k].dtype != torch.float64:
                self._buffers[k] = old.to(self._buffers[k].device)
        return self

    @torch.no_grad()
    def accumulate(self, x: torch.Tensor, weight: torch.Tensor | None = None) -> None:
        """Add rows of x [n, size]; ``weight`` [n] (0/1) leaves rows out."""
        x = x.detach().to(torch.float64).reshape(-1, self.size)
        if self.ranks is not None and self.ranks.distributed:
            accumulate_over_ranks([(self, x, weight)], self.ranks)
            return
        if weight is None:
            self.count += x.shape[0]
            self.sum += x.sum(0)
            self.sumsq += (x * x).sum(0)
        else:
            w = weight.detach().to(torch.float64).reshape(-1, 1)
            self.count += w.sum()
            self.sum += (x * w).sum(0)
            self.sumsq += (x * x * w).sum(0)

    @torch.no_grad()
    def accumulate_stats(self, x: torch.Tensor, weight: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``accumulate(x, weight)`` and then ``mean_std(x.dtype)``, in one Warp launch (plus the
        count's update): what a training step does each batch. Same sums, same statistics (the
        column sums in a fixed order: deterministic)."""
        x = x.detach().reshape(-1, self.size)
        if self.ranks is not None and self.ranks.distributed:
            return accumulate_over_ranks([(self, x, weight)], self.ranks)[0]
        if x.dtype not in (torch.float32, torch.float64) or x.shape[0] == 0:
            self.accumulate(x, weight)
            return self.mean_std(x.dtype)
        x = x.contiguous()
        launch = Launcher(x)
        mean = torch.empty(self.size, dtype=x.dtype, device=x.device)
        std = torch.empty_like(mean)
        w = None if weight is None else weight.detach().to(x.dtype).reshape(-1).contiguous()
        bd = K.BLOCK if launch.is_cuda else 1
        kernel = K.accumulate_kernel(WP_DTYPE[x.dtype], w is not None)
        launch.tiled(kernel, self.size, bd, x, w if w is not None else launch.placeholder(x.dtype, 1), x.shape[0], bd,
                     self.count.reshape(1), self.std_floor, self.sum, self.sumsq, mean, std)
        if w is None:
            self.count += x.shape[0]
        else:
            self.count += w.sum(dtype=torch.float64)
        return mean, std

    def reset(self) -> None:
        for b in (self.count, self.sum, self.sumsq):
            b.zero_()

    def mean_std(self, dtype: torch.dtype | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(mean [size], std [size]) in ``dtype``."""
        n = self.count.clamp_min(1.0)
        mean = self.sum / n
        var = (self.sumsq / n - mean * mean).clamp_min(0.0)
        std = var.sqrt().clamp_min(self.std_floor)
        seen = self.count > 0
        mean = torch.where(seen, mean, torch.zeros_like(mean))
        std = torch.where(seen, std, torch.ones_like(std))
        dtype = dtype or torch.get_default_dtype()
        return mean.to(dtype), std.to(dtype)

    def extra_repr(self) -> str:
        return f"size={self.size}, std_floor={self.std_floor:g}"


def accumulate_over_ranks(items, ranks) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """``accumulate_stats`` of several normalizers with each batch summed over ``ranks``: rank 0
    packs every ``(normalizer, x [n, size], weight [n] or None)``'s count, column sums and squared
    sums in one float64 buffer (one concatenation; the other ranks start from zeros), each rank
    adds its batch's sums (a Warp launch per normalizer), one all-reduce makes the buffer the new
    totals on every rank, one launch writes every (mean, std) in ``x``'s dtype and one copies the
    totals back into the normalizers: four launches and the collective beside one per normalizer.
    Returns the (mean, std) of each item, in order. Every rank calls it with the same normalizers,
    each once. On CUDA, the first call of a set of normalizers must not be captured (it makes the
    launch's index table): a trainer's eager warm-up steps come first."""
    norms = [n for n, _, _ in items]
    if len({id(n) for n in norms}) != len(norms):
        raise ValueError("accumulate_over_ranks: a normalizer is listed twice (its batches would overwrite each other)")
    first = items[0][1]
    if ranks.rank == 0:
        pack = torch.cat([t.reshape(-1) for n in norms for t in (n.count, n.sum, n.sumsq)]).to(first.device)
    else:
        pack = torch.zeros(sum(1 + 2 * n.size for n in norms), dtype=torch.float64, device=first.device)
    launch = Launcher(pack)
    bd = K.BLOCK if launch.is_cuda else 1
    dtypes, wanted, off = [], [], 0
    for norm, x, weight in items:
        x = x.detach().reshape(-1, norm.size)
        wanted.append(x.dtype)   # the statistics' dtype; the sums run in float32 or float64
        if x.dtype not in (torch.float32, torch.float64):
            x = x.to(torch.float64)
        x = x.contiguous()
        F = norm.size
        w = None if weight is None else weight.detach().to(x.dtype).reshape(-1).contiguous()
        if F > 0:
            launch.tiled(K.sums_kernel(WP_DTYPE[x.dtype], w is not None), F if x.shape[0] else 0, bd, x,
                         w if w is not None else launch.placeholder(x.dtype, 1), x.shape[0], bd,
                         pack[off:off + 1], pack[off + 1:off + 1 + F], pack[off + 1 + F:off + 1 + 2 * F])
        else:   # no column to launch over: the count alone
            pack[off:off + 1].add_(x.shape[0] if w is None else w.sum(dtype=torch.float64))
        dtypes.append(x.dtype)
        off += 1 + 2 * F
    ranks.all_reduce_(pack)
    out: list = [None] * len(items)
    for dtype in dict.fromkeys(dtypes):   # one launch per dtype (a model has one)
        picked = [k for k, d in enumerate(dtypes) if d == dtype]
        where, floors = _pack_table(tuple((n.size, n.std_floor) for n in norms), tuple(picked), pack.device)
        mean = torch.empty(where.shape[0], dtype=dtype, device=pack.device)
        std = torch.empty_like(mean)
        launch(K.pack_stats_kernel(WP_DTYPE[dtype]), where.shape[0], pack, where, floors, mean, std)
        o = 0
        for k in picked:
            F = norms[k].size
            out[k] = (mean[o:o + F].to(wanted[k]), std[o:o + F].to(wanted[k]))
            o += F
    dests, srcs, off = [], [], 0
    for n in norms:
        dests += [n.count.reshape(1), n.sum, n.sumsq]
        srcs += [pack[off:off + 1], pack[off + 1:off + 1 + n.size], pack[off + 1 + n.size:off + 1 + 2 * n.size]]
        off += 1 + 2 * n.size
    torch._foreach_copy_(dests, srcs)
    return out


_PACK_TABLES: dict = {}


def _pack_table(layout: tuple, picked: tuple, device) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``pack_stats_kernel`` table of the normalizers ``picked`` of a pack laid out as ``layout``
    ((size, std floor) per normalizer): each column's (sum, squared sum, count) indices [C, 3] and
    std floors [C]; made once per layout and device (before any captured step replays it)."""
    key = (layout, picked, str(device))
    got = _PACK_TABLES.get(key)
    if got is None:
        if torch.device(device).type == "cuda" and torch.cuda.is_current_stream_capturing():
            raise RuntimeError("accumulate_over_ranks: first called for these normalizers inside a CUDA graph "
                               "capture; run it once eagerly first (its index table is copied to the GPU then)")
        starts = [0]
        for size, _ in layout:
            starts.append(starts[-1] + 1 + 2 * size)
        where, floors = [], []
        for k in picked:
            size, floor = layout[k]
            s = starts[k]
            where += [(s + 1 + j, s + 1 + size + j, s) for j in range(size)]
            floors += [floor] * size
        got = _PACK_TABLES[key] = (torch.tensor(where, dtype=torch.int32, device=device).reshape(-1, 3),
                                   torch.tensor(floors, dtype=torch.float64, device=device))
    return got


def normalize_graph(graph: GraphsTuple, stats: dict) -> GraphsTuple:
    """``graph`` with nodes, edges (and globals, when ``stats`` has them) mapped to (x - mean) / std
    by ``stats`` {"nodes"|"edges"|"globals": (mean, std)} (a model's ``stats()``)."""
    def norm(kind, x):
        m, s = stats[kind]
        return (x - m) / s
    g = norm("globals", graph.globals) if "globals" in stats else graph.globals
    return graph._replace(nodes=norm("nodes", graph.nodes), edges=norm("edges", graph.edges), globals=g)
