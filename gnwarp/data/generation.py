"""Dataset generation (paper, section C): random initial states, random spline controls (C.1),
batched simulation, and the split sizes of C.2.

``generate`` simulates every sequence of a system (or of sampled instances of its parameterized
variant), checks that the simulation did not diverge, and returns a ``Dataset``
(``gnwarp.data.dataset``) with the static graphs of its instances (``gnwarp.data.convert``).
"""
from __future__ import annotations

import numbers
import time

import numpy as np

from gnwarp.data.convert import check_actuators, static_arrays
from gnwarp.data.checks import MAX_ABS
from gnwarp.data.dataset import Dataset, Split
from gnwarp.data.format import SPLITS
from gnwarp.sim.common import resolve_backend, topology_signature
from gnwarp.sim.excitation import control_range, random_spline_controls
from gnwarp.sim.families import family_of
from gnwarp.sim.backends import simulate
from gnwarp.sim.systems import System, check_model, make, param_places
from gnwarp.state import DYN_NODE_NAMES, DYN_NODE_SIZE
from gnwarp.version import __version__
from gnwarp.validation import available_memory

__all__ = ["PAPER_SIZES", "initial_states", "split_sizes", "generate", "memory_estimate"]

# Paper, C.2: sequences per split.
PAPER_SIZES = {False: {"train": 10000, "valid": 1000, "test": 1000},
               True: {"train": 20000, "valid": 5000, "test": 5000}}


# -- initial states ------------------------------------------------------------------------------

def initial_states(system, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Random initial (qpos [n, nq], qvel [n, nv]) for a system.

    Hinge and slide joints: uniform inside their range (shrunk to its middle half) when limited;
    unlimited hinges over the full circle for the families whose record says so (``Family.full_circle``:
    pendulum, cartpole and acrobot), and +-0.1 rad otherwise (so floating bases such as cheetah's
    torso start upright). Velocities ~ N(0, 0.1).
    """
    import mujoco
    m = system.model
    qpos = np.tile(np.asarray(m.qpos0, dtype=np.float64), (n, 1))
    fam = family_of(system.name)
    full_circle = fam is not None and fam.full_circle
    for j in range(m.njnt):
        t = int(m.jnt_type[j])
        if t not in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
            continue
        a = int(m.jnt_qposadr[j])
        if m.jnt_limited[j]:
            lo, hi = m.jnt_range[j]
            mid, half = 0.5 * (lo + hi), 0.25 * (hi - lo)
            qpos[:, a] = rng.uniform(mid - half, mid + half, n)
        elif t == mujoco.mjtJoint.mjJNT_HINGE and full_circle:
            qpos[:, a] = rng.uniform(-np.pi, np.pi, n)
        else:
            qpos[:, a] += rng.uniform(-0.1, 0.1, n)
    qvel = rng.normal(0.0, 0.1, (n, m.nv))
    return qpos, qvel


# -- generation ---------------------------------------------------------------------------------

def split_sizes(num_sequences, parameterized: bool) -> dict[str, int]:
    """Sequences per split: None -> the paper's; an int -> split in the paper's proportions;
    a dict or (train, valid, test) tuple -> as given."""
    paper = PAPER_SIZES[bool(parameterized)]
    if num_sequences is None:
        return dict(paper)

    def count(x, what: str) -> int:   # a whole number: 2.5 sequences is a mistake, not 2
        if isinstance(x, bool) or not isinstance(x, (int, np.integer)):
            raise ValueError(f"{what} must be a whole number of sequences, got {x!r}")
        return int(x)
    if isinstance(num_sequences, dict):
        unknown = sorted(set(num_sequences) - set(SPLITS))
        if unknown:
            raise ValueError(f"num_sequences names unknown splits {unknown}: the splits are {', '.join(SPLITS)}")
        sizes = {k: count(num_sequences.get(k, 0), f"num_sequences[{k!r}]") for k in SPLITS}
    elif isinstance(num_sequences, (tuple, list)):
        if len(num_sequences) != 3:
            raise ValueError(f"num_sequences as a sequence must be (train, valid, test), got {num_sequences}")
        sizes = {k: count(x, f"num_sequences' {k}") for k, x in zip(SPLITS, num_sequences)}
    else:
        n = count(num_sequences, "num_sequences")
        if n < 1:
            raise ValueError(f"num_sequences must be >= 1, got {n}")
        tot = sum(paper.values())
        sizes = {k: int(round(n * paper[k] / tot)) for k in ("valid", "test")}
        sizes["train"] = n - sizes["valid"] - sizes["test"]
        sizes = {k: sizes[k] for k in SPLITS}
    if any(v < 0 for v in sizes.values()) or sum(sizes.values()) < 1:
        raise ValueError(f"split sizes must be non-negative and not all zero, got {sizes}")
    return sizes


def memory_estimate(total: int, num_steps: int, bodies: int, nq: int, nv: int, nu: int, substeps: int = 1,
                    backend: str = "mujoco") -> dict[str, int]:
    """Bytes a dataset of ``total`` sequences of ``num_steps`` steps needs: "dataset" (its float32
    arrays: body [S, T+1, B, 13], ctrl [S, T, U], qpos [S, T+1, nq], qvel [S, T+1, nv]) and "peak"
    (about what generating it holds at once: the dataset, the simulator's copy of one topology's
    trajectories, float64 controls and the backend's per-chunk buffers)."""
    S, T = int(total), int(num_steps)
    states = S * (T + 1) * (bodies * 13 + nq + nv) * 4
    data = states + S * T * nu * 4
    ctrl64 = S * T * nu * 8
    if backend == "mujoco":  # mujoco.rollout: states and sensors of every physics step of a chunk
        chunk = min(S, 512) * (T * substeps + 1) * (1 + 2 * (nq + nv + nu) + 13 * bodies + nu) * 8
    else:  # MuJoCo-Warp: outputs of a chunk of worlds copied back to the host
        chunk = min(S, 32768) * (T + 1) * (bodies * 13 + nq + nv) * 4
    return {"dataset": data, "peak": data + states + ctrl64 + chunk}


def _check_memory(name, total, num_steps, dims, substeps, backend):
    """Refuse, before allocating, a dataset that would not fit in memory; ``dims``: (B, nq, nv, nu)."""
    est = memory_estimate(total, num_steps, *dims, substeps, backend)
    avail = available_memory()
    if avail is not None and est["peak"] > avail:
        gib = lambda n: f"{n / 2**30:.3g} GiB"  # noqa: E731
        raise ValueError(f"dataset of '{name}' too large: {total} sequences x {num_steps} steps x {dims[0]} bodies "
                         f"is {gib(est['dataset'])} of float32 states and controls, and generating it needs about "
                         f"{gib(est['peak'])} of memory; this machine has {gib(avail)} available. Use fewer sequences "
                         f"or steps")
    if backend == "mujoco_warp":  # one chunk of worlds' outputs lives on the GPU
        B, nq, nv, nu = dims
        gpu = min(total, 32768) * ((num_steps + 1) * (B * 13 + nq + nv) + num_steps * nu) * 4
        try:
            import torch
            free = torch.cuda.mem_get_info()[0]
        except Exception:  # no CUDA context to ask: MuJoCo-Warp reports it when it allocates
            free = None
        if free is not None and gpu > free:
            raise ValueError(f"dataset of '{name}' too large for the GPU: a chunk of {min(total, 32768)} worlds x "
                             f"{num_steps} steps needs {gpu / 2**30:.3g} GiB of GPU memory, {free / 2**30:.3g} GiB "
                             f"are free. Use fewer steps")


def _progress(total: int, desc: str, enabled: bool):
    from tqdm.auto import tqdm
    return tqdm(total=total, desc=desc, unit="seq", disable=not enabled, dynamic_ncols=True)


def generate(system, num_sequences=None, num_steps: int = 100, seed: int = 0, parameterized: bool = False,
             backend: str = "auto", progress: bool = True, shard: tuple[int, int] | None = None) -> Dataset:
    """Simulate sequences under random spline controls (C.1) and return a ``Dataset``.

    ``system``: a built-in name (``gnwarp.sim.systems.names()``, e.g. "cheetah", "swimmer6") or a
    ``System``. ``parameterized``: draw each sequence's system instance from the system's
    parameter ranges (built-in systems only). ``num_sequences``: see ``split_sizes``.
    ``backend``: "auto", "mujoco_warp" (CUDA), "mujoco_warp_cpu" or "mujoco" (MuJoCo C).
    Raises ``gnwarp.data.convert.UnsupportedActuatorError`` (a ValueError) before simulating when
    an actuator's transmission is one the graph cannot carry (``check_actuators``).

    ``shard=(rank, ranks)``: simulate only the sequences ``rank, rank + ranks, ...`` (of all
    splits, in order) and return them as a shard (``meta["shard"]``); every rank draws the same
    random initial states, controls and parameters, so ``gnwarp.data.shards.merge`` of the ranks'
    shards is, array for array, the dataset one process generates (``gnwarp.data.shards.generate``
    runs it under ``torchrun``).
    """
    if isinstance(num_steps, bool) or not isinstance(num_steps, numbers.Integral) or num_steps < 1:
        raise ValueError(f"num_steps must be an integer >= 1, got {num_steps!r}")
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    num_steps, seed = int(num_steps), int(seed)
    backend = resolve_backend(backend)
    sizes = split_sizes(num_sequences, parameterized)
    total = sum(sizes.values())
    rank, ranks = _check_shard(shard)
    own = np.zeros(total, dtype=bool)
    own[rank::ranks] = True                 # the sequences this call simulates
    local = np.cumsum(own) - 1              # global sequence -> row of this call's arrays
    n_own = int(own.sum())
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()

    if isinstance(system, str):
        name = system
        base_sys = make(name)
    elif isinstance(system, System):
        base_sys, name = system, system.name
        if parameterized:
            raise ValueError("parameterized=True needs a built-in system name, not a System instance")
        check_model(base_sys.model, f"system '{name}'")
    else:
        raise TypeError(f"system must be a built-in system's name or a System (gnwarp.systems.make / from_mjcf), "
                        f"got {type(system).__name__} {system!r}"[:300])
    if base_sys.model.nu == 0:
        raise ValueError(f"system '{name}' has no actuators: random-control datasets need at least one")
    check_actuators(base_sys.model, f"system '{name}'")   # before simulating: train could not use the data
    m0 = base_sys.model
    _check_memory(name, n_own, num_steps, (m0.nbody, m0.nq, m0.nv, m0.nu), base_sys.substeps, backend)
    if parameterized:
        seeds = rng.integers(0, 2**31 - 1, total)
        bar = _progress(total, f"{name}: building instances", progress)
        instances = []
        for s in seeds:  # one model compile per sampled instance
            instances.append(make(name, seed=int(s)))
            bar.update(1)
        bar.close()
        seq_instance = np.arange(total)
    else:
        instances = [base_sys]
        seq_instance = np.zeros(total, dtype=np.int64)

    # group instances by topology (SwimmerN with several N): one simulation per group
    groups: dict[tuple, list[int]] = {}
    for i, inst in enumerate(instances):
        groups.setdefault(topology_signature(inst.model), []).append(i)

    B = max(s.model.nbody for s in instances)
    nq = max(s.model.nq for s in instances)
    nv = max(s.model.nv for s in instances)
    nu = max(s.model.nu for s in instances)
    if parameterized:  # sampled instances may be larger than the fixed system (swimmer links)
        _check_memory(name, n_own, num_steps, (B, nq, nv, nu), base_sys.substeps, backend)
    body = np.zeros((n_own, num_steps + 1, B, DYN_NODE_SIZE), dtype=np.float32)
    ctrl = np.zeros((n_own, num_steps, nu), dtype=np.float32)
    qpos = np.zeros((n_own, num_steps + 1, nq), dtype=np.float32)
    qvel = np.zeros((n_own, num_steps + 1, nv), dtype=np.float32)

    bar = _progress(n_own, f"{name}: simulating ({backend})", progress)
    sim_time = 0.0
    for key, inst_ids in groups.items():
        seqs = np.flatnonzero(np.isin(seq_instance, inst_ids))
        rep = instances[inst_ids[0]]
        m = rep.model
        # drawn for every sequence (the stream is the same for any shard), made for this call's
        mine = own[seqs]
        q0, v0 = initial_states(rep, len(seqs), rng)
        u = random_spline_controls(len(seqs), num_steps, control_range(m), rng, keep=None if mine.all() else mine)
        seqs, q0, v0 = seqs[mine], q0[mine], v0[mine]
        if len(seqs) == 0:
            continue
        group_systems = [instances[seq_instance[s]] for s in seqs] if parameterized else rep
        ts = time.perf_counter()
        tr = simulate(group_systems, q0, v0, u, backend=backend, progress=bar.update)
        sim_time += time.perf_counter() - ts
        bad = [k for k, a in (("body", tr.body), ("qpos", tr.qpos), ("qvel", tr.qvel)) if not _sane(a)]
        if bad:
            raise FloatingPointError(f"simulation of '{name}' produced NaN/Inf or huge (>{_MAXVAL:g}) values in "
                                     f"{', '.join(bad)}: the model is unstable at this timestep or under these controls")
        rows = local[seqs]
        body[rows, :, :m.nbody] = tr.body
        ctrl[rows, :, :m.nu] = u
        qpos[rows, :, :m.nq] = tr.qpos
        qvel[rows, :, :m.nv] = tr.qvel
    bar.close()

    static, layout, graph_meta = static_arrays(instances)
    param_names = sorted({k for s in instances for k in s.params})
    static["params"] = np.array([[float(s.params.get(k, np.nan)) for k in param_names] for s in instances],
                                dtype=np.float64).reshape(len(instances), len(param_names))
    # where each parameter lives in the graph (gnwarp.sim.param_places), from an instance that has it
    places = [list(param_places(next(s for s in instances if k in s.params), [k])[0]) for k in param_names]

    # splits: consecutive blocks of the (already random) sequences
    splits, start = {}, 0
    for k in SPLITS:
        n = sizes[k]
        g = np.flatnonzero(own[start:start + n]) + start     # this call's sequences of the split
        rows = local[g]
        sl = slice(int(rows[0]), int(rows[-1]) + 1) if len(rows) else slice(0, 0)   # consecutive rows: views
        splits[k] = Split(body[sl], ctrl[sl], qpos[sl], qvel[sl], seq_instance[g])
        start += n

    meta = {
        "system": name, "parameterized": bool(parameterized), "dt": float(base_sys.dt),
        "physics_timestep": float(base_sys.model.opt.timestep), "substeps": int(base_sys.substeps),
        "num_steps": int(num_steps), "seed": int(seed), "backend": backend, "splits": sizes,
        "param_names": param_names, "param_places": places, "translation_invariant": bool(base_sys.translation_invariant),
        "layout": layout.to_dict(), "max_bodies": int(B), "max_edges": int(static["senders"].shape[1]),
        "nq": int(nq), "nv": int(nv), "nu": int(nu), "graph": graph_meta,
        "dynamic_node_names": list(DYN_NODE_NAMES),
        "generation_seconds": time.perf_counter() - t0, "simulation_seconds": sim_time,
        "gnwarp_version": __version__,
    }
    if shard is not None:
        # the shard's own split sizes in "splits" (what its arrays hold); the whole dataset's here
        meta["shard"] = {"rank": rank, "ranks": ranks, "sequences": n_own, "splits": sizes}
        meta["splits"] = {k: len(sp) for k, sp in splits.items()}
    return Dataset(meta, static, splits)


def _check_shard(shard) -> tuple[int, int]:
    """(rank, ranks) of ``shard`` (None: the whole dataset, (0, 1))."""
    if shard is None:
        return 0, 1
    try:
        rank, ranks = (int(v) for v in shard)
    except (TypeError, ValueError):
        raise ValueError(f"shard must be (rank, ranks), two integers, got {shard!r}") from None
    if not (ranks >= 1 and 0 <= rank < ranks):
        raise ValueError(f"shard (rank, ranks) needs 0 <= rank < ranks, got {shard!r}")
    return rank, ranks


_MAXVAL = MAX_ABS  # what a dataset may hold (loading refuses more): MuJoCo's own divergence bound is 1e10


def _sane(a: np.ndarray) -> bool:
    return bool(np.all(np.abs(a) <= _MAXVAL))  # False for NaN and Inf too
