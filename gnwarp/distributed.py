"""Several processes, one per GPU (or several on CPUs), through ``torch.distributed``, launched
by ``torchrun``: the ranks, their devices, and the few collectives gnwarp's stages use.

    torchrun --nproc_per_node 2 -m gnwarp.cli train --data cheetah.h5 -o runs/cheetah

Nothing in a config says how many processes run: a process started by ``torchrun`` (its
``WORLD_SIZE``, ``RANK`` and ``LOCAL_RANK`` variables) joins the process group the first time a
stage asks for ``ranks()``; any other process is rank 0 of 1 and no group is made. On CUDA each
rank takes the GPU of its local rank (torch's current device and Warp's default device agree)
and talks over NCCL; on CPUs over gloo.

Failures: every collective has the group's timeout (``GNWARP_DIST_TIMEOUT`` seconds, default
1800). On gloo a collective that fails because another rank died or timed out raises
``DistributedError`` naming this rank and what it was doing; on NCCL the watchdog aborts the
rank; ``torchrun`` stops the other workers of a job when one exits with an error. Only rank 0
writes checkpoints and results, each atomically
(``gnwarp.files.atomic_write``), so a rank that dies leaves no file half written.
"""
from __future__ import annotations

import contextlib
import datetime
import os
from dataclasses import dataclass

import torch

__all__ = ["Ranks", "Pending", "DistributedError", "ranks", "launched", "shard", "unshard", "timeout_seconds", "collective"]

ENV_TIMEOUT = "GNWARP_DIST_TIMEOUT"


class DistributedError(RuntimeError):
    """A collective between the ranks failed: another rank died, timed out or disagreed."""


def launched() -> bool:
    """Whether this process was started by ``torchrun`` (or another launcher setting its variables)
    as one of several."""
    return int(os.environ.get("WORLD_SIZE", "1") or 1) > 1


def timeout_seconds() -> float:
    """The process group's timeout: ``GNWARP_DIST_TIMEOUT`` seconds (default 1800: rank 0's merges
    and fits run while the other ranks wait in a collective)."""
    text = os.environ.get(ENV_TIMEOUT, "1800")
    try:
        t = float(text)
    except ValueError:
        t = -1.0
    if not t > 0:
        raise ValueError(f"{ENV_TIMEOUT} must be a number of seconds > 0, got {text!r}")
    return t


@dataclass(frozen=True)
class Ranks:
    """This process's place among the ranks: ``rank`` of ``world``, ``local_rank`` on its host,
    ``device`` (its GPU, or the CPU) and the group's ``backend`` ("nccl", "gloo", or None for a
    single process)."""
    rank: int = 0
    world: int = 1
    local_rank: int = 0
    device: torch.device = torch.device("cpu")
    backend: str | None = None

    @property
    def main(self) -> bool:
        """Rank 0: the one that writes checkpoints, logs and results."""
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world > 1

    def shard(self, n: int) -> range:
        """This rank's items of ``n`` (every ``world``-th, from ``rank``): see ``shard``."""
        return shard(n, self.rank, self.world)

    # -- collectives (no-ops for a single process) -----------------------------------------------
    def all_reduce_(self, t: torch.Tensor, mean: bool = False, async_op: bool = False):
        """Sum (or average) ``t`` over the ranks, in place; returns ``t``, or with ``async_op`` a
        ``Pending`` whose ``wait()`` returns it (the reduction runs on the group's stream while this
        one goes on; the current stream waits for it at ``wait``). NCCL averages in the reduction;
        gloo sums and divides. Captured CUDA graphs may hold either (NCCL)."""
        if not self.distributed:
            return Pending(self, None, t, False) if async_op else t
        import torch.distributed as dist
        avg = mean and self.backend == "nccl"
        with collective(self, "all_reduce"):
            work = dist.all_reduce(t, op=dist.ReduceOp.AVG if avg else dist.ReduceOp.SUM, async_op=async_op)
        pending = Pending(self, work, t, mean and not avg)
        return pending if async_op else pending.wait()

    def broadcast_(self, t: torch.Tensor, src: int = 0) -> torch.Tensor:
        """``t`` of rank ``src`` on every rank, in place."""
        if self.distributed:
            import torch.distributed as dist
            with collective(self, "broadcast"):
                dist.broadcast(t, src)
        return t

    def broadcast_object(self, obj, src: int = 0):
        """A picklable value of rank ``src`` on every rank (small values: decisions, errors)."""
        if not self.distributed:
            return obj
        import torch.distributed as dist
        box = [obj]
        group, device = _objects_group(self)
        with collective(self, "broadcast_object_list"):
            dist.broadcast_object_list(box, src, group=group, device=device)
        return box[0]

    def gather_objects(self, obj) -> list | None:
        """Each rank's ``obj`` in rank order, on rank 0 (None elsewhere). Values are pickled between
        the ranks of one job; nothing read from a file goes through here."""
        if not self.distributed:
            return [obj]
        import torch.distributed as dist
        out = [None] * self.world if self.main else None
        group, _ = _objects_group(self)
        with collective(self, "gather_object"):
            if group is None and self.backend == "nccl":  # NCCL has no gather of objects: all-gather them
                full = [None] * self.world
                dist.all_gather_object(full, obj)
                return full if self.main else None
            dist.gather_object(obj, out, dst=0, group=group)
        return out

    def on_main(self, what: str, fn):
        """``fn()`` on rank 0 alone (what writes, validates or decides), its value (small,
        picklable) on every rank once it is done: the others wait for it, so they read only what
        rank 0 has finished. An error on rank 0 is raised there and, as ``DistributedError``
        naming ``what``, on every other rank (none waits for the group's timeout). A single
        process just calls ``fn()``."""
        if not self.distributed:
            return fn()
        answer = None
        if self.main:
            try:
                answer = ("ok", fn())
            except Exception as e:   # the others stop with rank 0's reason instead of waiting for it
                self.broadcast_object(("error", f"{type(e).__name__}: {e}"))
                raise
        kind, value = self.broadcast_object(answer)
        if kind == "error":
            raise DistributedError(f"rank {self.rank} of {self.world}: {what}: rank 0 failed ({value})")
        return value

    def map_sharded(self, items, fn, *, batched: bool = False, what: str = "map_sharded") -> list | None:
        """``fn`` over ``items`` (a sequence), each rank computing its shard (``self.shard``: items
        ``rank, rank + world, ...``); the results, in the order of ``items``, on rank 0 (None on the
        others). A single process computes every item and returns them (no collective).

        ``fn``: one item -> its result, or with ``batched`` the list of this rank's items -> one
        result per item (e.g. episodes planned together; not called for a rank with no items).
        Results are pickled to rank 0 (keep them small: returns, not every state). A rank whose
        ``fn`` raises re-raises it after telling the others, which raise ``DistributedError``
        naming that rank and its error, so no rank waits for the group's timeout."""
        items = list(items)
        mine = [items[i] for i in self.shard(len(items))]
        if not self.distributed:
            return run_items(mine, fn, batched)
        error, out = None, None
        try:
            out = run_items(mine, fn, batched)
        except Exception as e:   # every rank learns of it below, instead of waiting at the gather
            error = e
        parts = self.gather_objects((None if error is None else f"{type(error).__name__}: {error}", out))
        failed = None
        if self.main:
            failed = next(((k, msg) for k, (msg, _) in enumerate(parts) if msg is not None), None)
        failed = self.broadcast_object(failed)
        if error is not None:
            raise error
        if failed is not None:
            raise DistributedError(f"rank {self.rank} of {self.world}: {what}: rank {failed[0]} failed "
                                   f"({failed[1]})")
        return unshard([p[1] for p in parts]) if self.main else None

    def barrier(self, what: str = "barrier") -> None:
        """Wait for every rank (gloo: ``monitored_barrier``, which names a rank that did not come)."""
        if not self.distributed:
            return
        import torch.distributed as dist
        with collective(self, what):
            if self.backend == "gloo":
                dist.monitored_barrier(timeout=datetime.timedelta(seconds=timeout_seconds()))
            else:
                dist.barrier(device_ids=[self.device.index])


def shard(n: int, rank: int, world: int) -> range:
    """The items of ``range(n)`` rank ``rank`` of ``world`` handles: ``rank, rank + world, ...``.
    Interleaved rather than in blocks, so that items of different cost (early and late sequences,
    splits) spread evenly; the union over the ranks is every item once."""
    if not (0 <= rank < world):
        raise ValueError(f"rank {rank} is not in 0..{world - 1}")
    return range(rank, int(n), world)


def unshard(parts: list) -> list:
    """The items of every rank's list (``parts[k]``: rank ``k``'s results, in its ``shard`` order)
    in the original order: item ``i`` is ``parts[i % world][i // world]``."""
    world = len(parts)
    sizes = [len(p) for p in parts]
    n = sum(sizes)
    want = [len(shard(n, k, world)) for k in range(world)]
    if sizes != want:
        raise DistributedError(f"the ranks returned {sizes} results, {n} items over {world} ranks need {want}")
    return [parts[i % world][i // world] for i in range(n)]


def run_items(mine: list, fn, batched: bool) -> list:
    """``fn`` over this rank's items (see ``Ranks.map_sharded``): one result per item."""
    if not batched:
        return [fn(x) for x in mine]
    if not mine:
        return []
    out = list(fn(mine))
    if len(out) != len(mine):
        raise ValueError(f"a batched function returned {len(out)} results for {len(mine)} items")
    return out


@contextlib.contextmanager
def collective(r: Ranks, what: str):
    """Turn a failed collective into ``DistributedError`` naming this rank and what it did."""
    try:
        yield
    except DistributedError:
        raise
    except (RuntimeError, ValueError, ConnectionError, OSError) as e:   # DistBackendError is a RuntimeError
        raise DistributedError(
            f"rank {r.rank} of {r.world}: {what} with the other ranks failed ({type(e).__name__}: "
            f"{str(e).strip().splitlines()[0] if str(e).strip() else e!r}); often another rank died or timed out "
            f"(timeout {timeout_seconds():g} s, {ENV_TIMEOUT})") from e


class Pending:
    """An all-reduce under way (``Ranks.all_reduce_(..., async_op=True)``): ``wait()`` makes the
    current stream wait for it (and averages, where the backend did not) and returns the tensor."""

    def __init__(self, ranks: Ranks, work, t: torch.Tensor, divide: bool):
        self.ranks, self.work, self.t, self.divide = ranks, work, t, divide

    def wait(self) -> torch.Tensor:
        if self.work is not None:
            with collective(self.ranks, "all_reduce"):
                self.work.wait()
            self.work = None
        if self.divide:
            self.t.div_(self.ranks.world)
            self.divide = False
        return self.t


_RANKS: Ranks | None = None
_OBJECTS = None   # a gloo group beside an NCCL one: objects gathered on the CPU, to rank 0 alone


def _objects_group(r: Ranks):
    """(group, device) that object collectives use: the gloo side group of an NCCL job (a real
    gather to rank 0 in host memory, no GPU sync), else the default group (NCCL: on the device)."""
    if r.backend == "nccl" and _OBJECTS is not None:
        return _OBJECTS, None
    return None, (r.device if r.backend == "nccl" else None)


def ranks(device: str | torch.device | None = "auto") -> Ranks:
    """This process's ``Ranks``, joining the process group on the first call under ``torchrun``.

    ``device``: what the caller would run on ("auto": CUDA when present, "cpu", "cuda"). Under
    ``torchrun`` a CUDA request becomes the GPU of this process's local rank (NCCL) and a CPU one
    stays on the CPU (gloo); a single process gets rank 0 of 1 on the device as asked. Later calls
    return the same ranks (a later device request must agree with the group's)."""
    global _RANKS
    from gnwarp.interop import resolve_device
    want = resolve_device(device)
    if not launched():
        return Ranks(device=want)
    import torch.distributed as dist
    if _RANKS is None and dist.is_initialized() and "nccl" in str(dist.get_backend()) and want.type != "cuda":
        raise ValueError(f"the process group runs on cuda (NCCL), this asks for {want.type}: one job runs every "
                         "stage on one kind of device")
    if _RANKS is not None and dist.is_initialized():
        if want.type != _RANKS.device.type:
            raise ValueError(f"the process group runs on {_RANKS.device.type}, this asks for {want.type}: one "
                             "job runs every stage on one kind of device")
        return _RANKS
    world, rank = int(os.environ["WORLD_SIZE"]), int(os.environ.get("RANK", "0"))
    local = int(os.environ.get("LOCAL_RANK", rank))
    timeout = datetime.timedelta(seconds=timeout_seconds())
    if want.type == "cuda":
        n = torch.cuda.device_count()
        if n == 1 and int(os.environ.get("LOCAL_WORLD_SIZE", "1") or 1) == 1:   # each task shown only its own GPU
            local = 0
        if local >= n:
            raise DistributedError(f"rank {rank}: local rank {local} has no GPU of its own ({n} visible); start "
                                   f"at most {n} processes per host (torchrun --nproc_per_node {n})")
        # a rank whose peer dies ends with an error instead of waiting forever (torch's default, made explicit)
        os.environ.setdefault("TORCH_NCCL_ASYNC_ERROR_HANDLING", "3")
        dev = torch.device("cuda", local)
        torch.cuda.set_device(dev)
        from gnwarp.interop import warp
        warp().set_device(f"cuda:{local}")
        backend = "nccl"
    else:
        dev, backend = torch.device("cpu"), "gloo"
    if not dist.is_initialized():
        try:
            kw = {"device_id": dev} if backend == "nccl" else {}
            dist.init_process_group(backend, timeout=timeout, **kw)
        except (RuntimeError, ValueError, OSError) as e:
            raise DistributedError(f"rank {rank} of {world}: could not join the process group ({backend}, "
                                   f"MASTER_ADDR={os.environ.get('MASTER_ADDR')}, "
                                   f"MASTER_PORT={os.environ.get('MASTER_PORT')}): {e}") from e
    _RANKS = Ranks(rank=dist.get_rank(), world=dist.get_world_size(), local_rank=local, device=dev, backend=backend)
    if backend == "nccl":
        global _OBJECTS
        try:   # every rank makes it, in the same order (a collective of the default group)
            _OBJECTS = dist.new_group(backend="gloo", timeout=timeout)
        except (RuntimeError, ValueError):   # no gloo here: objects go over NCCL (all-gathered)
            _OBJECTS = None
    return _RANKS


def close(sync: bool = False) -> None:
    """Leave the process group at the end of a job (a later ``ranks()`` joins a new one on gloo).

    ``sync``: every rank finished its work (the job's success path): on gloo the ranks meet at a
    barrier first, so that none tears its side down (rank 0: the store) while a peer still talks
    to it. The error path leaves it out: a peer that will not come would hold this rank there.

    On NCCL the default group is left to the process's exit: ``destroy_process_group`` hangs once
    NCCL collectives were captured in a CUDA graph (pytorch/pytorch#115388; two 2-GPU benchmark
    launches hung there), so only the GPU's work is waited for and the gloo side group closed. On
    gloo the group is destroyed (left to the exit, gloo can abort the process)."""
    global _RANKS, _OBJECTS
    import torch.distributed as dist
    if dist.is_available() and dist.is_initialized():
        if "nccl" in str(dist.get_backend()):   # "nccl", or a combined "cpu:gloo,cuda:nccl"
            if _RANKS is not None and _RANKS.device.type == "cuda":
                try:
                    torch.cuda.synchronize(_RANKS.device)
                except RuntimeError:   # the device already failed: that error is what the caller reports
                    pass
            if _OBJECTS is not None:
                dist.destroy_process_group(_OBJECTS)
        else:
            if sync:
                try:
                    dist.monitored_barrier(timeout=datetime.timedelta(seconds=timeout_seconds()))
                except RuntimeError:   # a peer already gone: leave all the same
                    pass
            dist.destroy_process_group()
    _RANKS = _OBJECTS = None
