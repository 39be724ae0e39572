"""Dataset generation over several ranks (``torchrun``): each rank simulates its share of the
sequences on its own GPU and writes a checksummed shard; the shards read as one dataset.

    torchrun --nproc_per_node 4 -m gnwarp.cli generate cheetah -n 12000 -o cheetah.h5

Every rank draws the same random initial states, controls and parameters (the seed is the
dataset's, each sequence's draws are its own), simulates the sequences ``rank, rank + ranks, ...``
(``gnwarp.data.generation.generate(shard=...)``) and writes them to
``<out>.shard-<rank>-of-<ranks>.h5`` (atomically, with Fletcher-32 checksums like any dataset
file). Rank 0 then reads the shards (``merge``: each shard validated, every sequence put back in
its place) and writes ``<out>``, array for array the dataset one process generates, whatever the
number of ranks; the shards are removed once ``<out>`` is in place (``keep_shards`` keeps them,
and ``load_shards`` reads a set of shards as one dataset without merging them on disk).
"""
from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from gnwarp.data.dataset import Dataset, Split, load
from gnwarp.data.format import ARRAYS, SPLITS, DatasetError

__all__ = ["shard_path", "shard_paths", "merge", "load_shards", "generate"]


def shard_path(out: str | os.PathLike, rank: int, ranks: int) -> Path:
    """Where rank ``rank`` of ``ranks`` writes its shard of the dataset ``out``."""
    out = Path(out)
    return out.with_name(f"{out.name}.shard-{rank}-of-{ranks}.h5")


def shard_paths(out: str | os.PathLike, ranks: int) -> list[Path]:
    return [shard_path(out, r, ranks) for r in range(ranks)]


def merge(shards: list[Dataset]) -> Dataset:
    """One dataset of the shards of one generation (each from ``generate(shard=(r, ranks))``, in
    any order): every sequence back in its place, the arrays in memory. Refuses shards of different
    generations (system, seed, sizes, steps), a missing or repeated rank, and a shard whose
    sequence counts are not its share."""
    if not shards:
        raise DatasetError("no shards to merge")
    info = [d.meta.get("shard") for d in shards]
    if any(not isinstance(i, dict) for i in info):
        raise DatasetError("a dataset given to merge is not a shard (its meta has no 'shard')")
    ranks = {int(i["ranks"]) for i in info}
    if len(ranks) != 1:
        raise DatasetError(f"the shards come from runs of different numbers of ranks: {sorted(ranks)}")
    ranks = ranks.pop()
    by_rank = {int(i["rank"]): d for i, d in zip(info, shards)}
    if sorted(by_rank) != list(range(ranks)) or len(shards) != ranks:
        raise DatasetError(f"shards of ranks {sorted(int(i['rank']) for i in info)} given; a generation over "
                           f"{ranks} ranks needs each of 0..{ranks - 1} once")
    same = ("system", "seed", "num_steps", "parameterized", "dt", "layout", "nq", "nv", "nu", "max_bodies")
    first = by_rank[0].meta
    for r, d in by_rank.items():
        diff = [k for k in same if d.meta.get(k) != first.get(k)]
        diff += ["splits"] * (d.meta["shard"].get("splits") != first["shard"].get("splits"))
        if diff:
            raise DatasetError(f"shard {r} is of another generation than shard 0 (differs in {', '.join(diff)})")
        for k in sorted(by_rank[0].static):
            if not np.array_equal(np.asarray(d.static[k][...]), np.asarray(by_rank[0].static[k][...])):
                raise DatasetError(f"shard {r}'s static '{k}' differs from shard 0's: not one generation")
    sizes = first["shard"]["splits"]
    splits, start = {}, 0
    for k in SPLITS:
        n = int(sizes.get(k, 0))
        parts = {}
        for r, d in by_rank.items():
            pos = np.arange(start, start + n)
            mine = np.flatnonzero(pos % ranks == r)          # positions in the split of rank r's sequences
            sp = d[k] if k in d.splits else None
            got = 0 if sp is None else len(sp)
            if got != len(mine):
                raise DatasetError(f"shard {r} holds {got} '{k}' sequences, its share is {len(mine)}")
            parts[r] = (mine, sp)
        arrays = {}
        for name in ARRAYS:
            template = np.asarray(getattr(by_rank[0][k], name)[...])   # dtype and trailing shape
            full = np.zeros((n,) + template.shape[1:], dtype=template.dtype)
            for mine, sp in parts.values():
                if sp is not None and len(mine):
                    full[mine] = np.asarray(getattr(sp, name)[...])
            arrays[name] = full
        splits[k] = Split(**arrays)
        start += n
    meta = {k: v for k, v in first.items() if k != "shard"}
    meta["splits"] = dict(sizes)
    meta["generation_seconds"] = max(float(d.meta.get("generation_seconds", 0.0)) for d in shards)
    meta["simulation_seconds"] = max(float(d.meta.get("simulation_seconds", 0.0)) for d in shards)
    meta["ranks"] = ranks
    return Dataset(meta, dict(by_rank[0].static), splits)


def load_shards(paths) -> Dataset:
    """The shard files ``paths`` (every rank's of one generation) as one dataset in memory, each
    file validated as ``gnwarp.data.dataset.load`` validates a dataset."""
    shards = [load(p, lazy=False) for p in paths]
    try:
        return merge(shards)
    finally:
        for s in shards:
            s.close()


def generate(system, out: str | os.PathLike, *, overwrite: bool = False, keep_shards: bool = False,
             ranks=None, **kwargs) -> dict:
    """Generate the dataset ``out`` over the ranks of this job (``gnwarp.distributed.ranks``; a
    single process writes ``out`` directly). ``kwargs``: ``gnwarp.data.generation.generate``'s.
    Every rank returns a summary (its sequences and seconds; rank 0 also the merge's); the other
    ranks return once every shard is written, rank 0 once ``out`` is."""
    from gnwarp.data.generation import generate as generate_one
    from gnwarp.distributed import ranks as join_ranks
    from gnwarp.files import remove_stale_temporaries

    backend = kwargs.get("backend", "auto")
    r = ranks or join_ranks("cpu" if backend in ("mujoco", "mujoco_warp_cpu") else "auto")
    out = Path(out)
    t0 = time.perf_counter()
    if not r.distributed:
        ds = generate_one(system, **kwargs)
        ds.save(out, overwrite=overwrite)
        return {"rank": 0, "ranks": 1, "sequences": sum(ds.meta["splits"].values()),
                "simulation_seconds": ds.meta["simulation_seconds"], "seconds": time.perf_counter() - t0,
                "merge_seconds": 0.0, "out": str(out)}
    problem = None
    if r.main and out.exists() and not overwrite:
        problem = f"output exists: {out} (use --overwrite)"
    problem = r.broadcast_object(problem)
    if problem:
        raise FileExistsError(problem)
    mine = shard_path(out, r.rank, r.world)
    remove_stale_temporaries(mine)
    kwargs["progress"] = bool(kwargs.get("progress", True)) and r.main   # one bar: rank 0's
    ds = generate_one(system, shard=(r.rank, r.world), **kwargs)
    ds.save(mine, overwrite=True)
    summary = {"rank": r.rank, "ranks": r.world, "sequences": ds.meta["shard"]["sequences"],
               "simulation_seconds": ds.meta["simulation_seconds"], "seconds": time.perf_counter() - t0,
               "out": str(out)}
    del ds   # its arrays are on disk; rank 0's merge holds the whole dataset next
    r.barrier("generate: waiting for every rank's shard")
    if r.main:
        tm = time.perf_counter()
        remove_stale_temporaries(out)
        merged = load_shards(shard_paths(out, r.world))
        merged.save(out, overwrite=overwrite)
        if not keep_shards:
            for p in shard_paths(out, r.world):
                p.unlink(missing_ok=True)
        summary["merge_seconds"] = time.perf_counter() - tm
        summary["seconds"] = time.perf_counter() - t0
    return summary   # the other ranks are done once their shards are written (rank 0 alone merges)
