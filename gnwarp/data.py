"""Datasets of simulated sequences (paper, section C.2), stored as HDF5.

``generate`` simulates sequences under random spline controls and returns a ``Dataset``;
``Dataset.save(path)`` writes it (to a temporary file, renamed into place when complete) and
``load(path)`` reads it back, lazily: split arrays stay on disk until sliced.

File layout (HDF5, ``format = "gnwarp-dataset"``, ``version = 1``)::

    /                      attrs: format, version, meta (JSON: system, timesteps, seeds, layout, ...)
    /static/globals        [I, F_g]        kept static global features of each system instance
    /static/nodes          [I, B, F_v]     kept static node features (padded to B bodies)
    /static/edges          [I, E, F_e]     kept static edge features (padded to E edges)
    /static/senders        [I, E]          body index of each edge's sender (-1 = padding)
    /static/receivers      [I, E]
    /static/n_node, n_edge [I]
    /static/edge_ctrl      [I, E, K]       ctrl index driving each edge (-1 = none)
    /static/params         [I, P]          sampled relative parameters (names in meta)
    /<split>/body          [S, T+1, B, 13] node states: pos, quat (w,x,y,z), linvel, angvel
    /<split>/ctrl          [S, T, U]       controls applied over each data step
    /<split>/qpos, qvel    [S, T+1, nq|nv] generalized state (padded)
    /<split>/instance      [S]             index into /static of each sequence's system instance

Splits are ``train``, ``valid`` and ``test``. A fixed system has one instance; a parameterized
one has one per sequence.
"""
from __future__ import annotations

import json
import os
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gnwarp.controls import control_range, random_spline_controls
from gnwarp.convert import DYN_NODE_SIZE, FeatureLayout, static_graph, varying_columns
from gnwarp.graphs import GraphsTuple

FORMAT, VERSION = "gnwarp-dataset", 1
SPLITS = ("train", "valid", "test")
# Paper, C.2: sequences per split.
PAPER_SIZES = {False: {"train": 10000, "valid": 1000, "test": 1000},
               True: {"train": 20000, "valid": 5000, "test": 5000}}


class DatasetError(ValueError):
    """A dataset file is missing, corrupt, truncated or of another layout."""


# -- initial states ------------------------------------------------------------------------------

# Per built-in system: how far from the model's reference pose initial states are drawn.
# (scale of uniform noise on hinge/slide joints, unlimited hinges drawn over the full circle)
_FULL_CIRCLE = {"pendulum", "acrobot", "cartpole"}


def initial_states(system, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Random initial (qpos [n, nq], qvel [n, nv]) for a system.

    Hinge and slide joints: uniform inside their range (shrunk to its middle half) when limited;
    unlimited hinges over the full circle for pendulum, cartpole and acrobot, and +-0.1 rad
    otherwise (so floating bases such as cheetah's torso start upright). Velocities ~ N(0, 0.1).
    """
    import mujoco
    m = system.model
    qpos = np.tile(np.asarray(m.qpos0, dtype=np.float64), (n, 1))
    base = system.name.rstrip("0123456789")
    for j in range(m.njnt):
        t = int(m.jnt_type[j])
        if t not in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
            continue
        a = int(m.jnt_qposadr[j])
        if m.jnt_limited[j]:
            lo, hi = m.jnt_range[j]
            mid, half = 0.5 * (lo + hi), 0.25 * (hi - lo)
            qpos[:, a] = rng.uniform(mid - half, mid + half, n)
        elif t == mujoco.mjtJoint.mjJNT_HINGE and base in _FULL_CIRCLE:
            qpos[:, a] = rng.uniform(-np.pi, np.pi, n)
        else:
            qpos[:, a] += rng.uniform(-0.1, 0.1, n)
    qvel = rng.normal(0.0, 0.1, (n, m.nv))
    return qpos, qvel


# -- dataset ----------------------------------------------------------------------------------

@dataclass
class Split:
    """One split; arrays are numpy arrays, or h5py datasets for a lazily loaded file."""
    body: Any
    ctrl: Any
    qpos: Any
    qvel: Any
    instance: Any

    def __len__(self) -> int:
        return int(self.body.shape[0])

    @property
    def num_steps(self) -> int:
        return int(self.ctrl.shape[1])

    def load(self) -> "Split":
        """This split with every array read into memory."""
        return Split(*(np.asarray(a[...]) for a in (self.body, self.ctrl, self.qpos, self.qvel, self.instance)))


@dataclass
class Dataset:
    meta: dict
    static: dict[str, Any]
    splits: dict[str, Split]
    _file: Any = field(default=None, repr=False)
    _builders: dict = field(default_factory=dict, repr=False)

    @property
    def layout(self) -> FeatureLayout:
        return FeatureLayout.from_dict(self.meta["layout"])

    @property
    def system(self) -> str:
        return self.meta["system"]

    @property
    def dt(self) -> float:
        return float(self.meta["dt"])

    def __getitem__(self, split: str) -> Split:
        if split not in self.splits:
            raise KeyError(f"dataset has no split '{split}' (has {sorted(self.splits)})")
        return self.splits[split]

    def close(self):
        if self._file is not None:
            self._file.close()
            self._file = None

    def save(self, path: str | os.PathLike, overwrite: bool = False, compression: str | None = None) -> Path:
        """Write to ``path`` (HDF5). Refuses an existing path unless ``overwrite``; writes a
        temporary file beside it and renames it into place, so a failure leaves nothing behind."""
        import h5py
        path = Path(path)
        if path.exists() and not overwrite:
            raise FileExistsError(f"dataset path already exists: {path} (pass overwrite=True to replace it)")
        parent = path.parent if str(path.parent) else Path(".")
        if not parent.exists():
            raise FileNotFoundError(f"folder of the dataset path does not exist: {parent}")
        if not os.access(parent, os.W_OK):
            raise PermissionError(f"cannot write into folder {parent}")
        fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=parent)
        os.close(fd)
        try:
            with h5py.File(tmp, "w") as f:
                f.attrs["format"] = FORMAT
                f.attrs["version"] = VERSION
                f.attrs["meta"] = json.dumps(self.meta)
                g = f.create_group("static")
                for k, v in self.static.items():
                    g.create_dataset(k, data=np.asarray(v))
                for name, sp in self.splits.items():
                    g = f.create_group(name)
                    for k in ("body", "ctrl", "qpos", "qvel", "instance"):
                        a = np.asarray(getattr(sp, k)[...])
                        chunks = (1,) + a.shape[1:] if a.ndim > 1 and a.shape[0] > 0 else None
                        g.create_dataset(k, data=a, chunks=chunks, compression=compression)
                f.attrs["complete"] = True
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(tmp, 0o666 & ~umask)  # mkstemp made it private; give it a normal file's mode
            os.replace(tmp, path)
        except BaseException:
            if os.path.exists(tmp):
                os.unlink(tmp)
            raise
        return path

    # -- graphs --------------------------------------------------------------------------------
    def graphs(self, split: str, seq, t, device=None, dtype=None) -> GraphsTuple:
        """Input graphs (static concatenated with dynamic) for sequences ``seq`` at steps ``t``.

        ``seq``, ``t``: int arrays [N]. Returns a torch GraphsTuple of N graphs (see
        ``GraphBuilder``). Reads only the rows asked for.
        """
        sp = self[split]
        seq = np.asarray(seq)
        order = np.argsort(seq, kind="stable")  # h5py wants increasing indices
        inv = np.empty_like(order)
        inv[order] = np.arange(order.size)
        s_sorted, t_sorted = seq[order], np.asarray(t)[order]
        uniq, first = np.unique(s_sorted, return_inverse=True)
        body = np.asarray(sp.body[uniq])  # numpy or h5py: one read of the rows asked for
        ctrl = np.asarray(sp.ctrl[uniq])
        inst = np.asarray(sp.instance[...])[uniq]
        b = body[first, t_sorted][inv]
        c = ctrl[first, np.minimum(t_sorted, ctrl.shape[1] - 1)][inv]
        import torch
        key = (str(device), dtype)
        if key not in self._builders:  # static tensors built once per device and dtype
            self._builders[key] = GraphBuilder(self, device=device, dtype=dtype)
        builder = self._builders[key]
        return builder(torch.as_tensor(inst[first][inv]), torch.as_tensor(b), torch.as_tensor(c))


class GraphBuilder:
    """Builds batched input graphs from per-instance static graphs and dynamic states.

    Vectorized over the batch (no Python loop over bodies or states); works on torch tensors on
    any device so rollouts can rebuild graphs every step without leaving the device.
    ``__call__(instance [N], body [N, B, 13], ctrl [N, U]) -> GraphsTuple`` with
    nodes = [static node features, 13 dynamic], edges = [static edge features, controls],
    globals = static global features.
    """

    def __init__(self, dataset: Dataset, device=None, dtype=None):
        import torch
        self.dtype = dtype or torch.float32
        st = dataset.static
        t = lambda k, dt=None: torch.as_tensor(np.asarray(st[k][...]), device=device, dtype=dt)  # noqa: E731
        self.s_globals = t("globals", self.dtype)
        self.s_nodes = t("nodes", self.dtype)
        self.s_edges = t("edges", self.dtype)
        self.senders = t("senders", torch.int64)
        self.receivers = t("receivers", torch.int64)
        self.n_node = t("n_node", torch.int64)
        self.n_edge = t("n_edge", torch.int64)
        self.edge_ctrl = t("edge_ctrl", torch.int64)
        B, E = self.s_nodes.shape[1], self.s_edges.shape[1]
        self.node_mask = torch.arange(B, device=device)[None] < self.n_node[:, None]   # [I, B]
        self.edge_mask = torch.arange(E, device=device)[None] < self.n_edge[:, None]   # [I, E]
        self.uniform = bool((self.n_node == B).all() and (self.n_edge == E).all())

    def __call__(self, instance, body, ctrl) -> GraphsTuple:
        import torch
        dev = self.s_nodes.device
        instance = instance.to(dev)
        body = body.to(dev, self.dtype)
        ctrl = ctrl.to(dev, self.dtype)
        N = instance.shape[0]
        ec = self.edge_ctrl[instance]                                    # [N, E, K]
        c = torch.gather(ctrl, 1, ec.clamp(min=0).reshape(N, -1)).reshape(ec.shape)
        c = torch.where(ec >= 0, c, torch.zeros((), device=dev, dtype=self.dtype))
        nodes = torch.cat([self.s_nodes[instance], body], -1)           # [N, B, Fv+13]
        edges = torch.cat([self.s_edges[instance], c], -1)              # [N, E, Fe+K]
        n_node, n_edge = self.n_node[instance], self.n_edge[instance]
        off = torch.cumsum(n_node, 0) - n_node
        snd = self.senders[instance] + off[:, None]
        rcv = self.receivers[instance] + off[:, None]
        if self.uniform:
            return GraphsTuple(nodes=nodes.reshape(-1, nodes.shape[-1]), edges=edges.reshape(-1, edges.shape[-1]),
                               receivers=rcv.reshape(-1), senders=snd.reshape(-1), globals=self.s_globals[instance],
                               n_node=n_node, n_edge=n_edge)
        nm, em = self.node_mask[instance], self.edge_mask[instance]
        return GraphsTuple(nodes=nodes[nm], edges=edges[em], receivers=rcv[em], senders=snd[em],
                           globals=self.s_globals[instance], n_node=n_node, n_edge=n_edge)


# -- generation ---------------------------------------------------------------------------------

def split_sizes(num_sequences, parameterized: bool) -> dict[str, int]:
    """Sequences per split: None -> the paper's; an int -> split in the paper's proportions;
    a dict or (train, valid, test) tuple -> as given."""
    paper = PAPER_SIZES[bool(parameterized)]
    if num_sequences is None:
        return dict(paper)
    if isinstance(num_sequences, dict):
        sizes = {k: int(num_sequences.get(k, 0)) for k in SPLITS}
    elif isinstance(num_sequences, (tuple, list)):
        if len(num_sequences) != 3:
            raise ValueError(f"num_sequences as a sequence must be (train, valid, test), got {num_sequences}")
        sizes = dict(zip(SPLITS, (int(x) for x in num_sequences)))
    else:
        n = int(num_sequences)
        if n < 1:
            raise ValueError(f"num_sequences must be >= 1, got {n}")
        tot = sum(paper.values())
        sizes = {k: int(round(n * paper[k] / tot)) for k in ("valid", "test")}
        sizes["train"] = n - sizes["valid"] - sizes["test"]
        sizes = {k: sizes[k] for k in SPLITS}
    if any(v < 0 for v in sizes.values()) or sum(sizes.values()) < 1:
        raise ValueError(f"split sizes must be non-negative and not all zero, got {sizes}")
    return sizes


def _progress(total: int, desc: str, enabled: bool):
    from tqdm.auto import tqdm
    return tqdm(total=total, desc=desc, unit="seq", disable=not enabled, dynamic_ncols=True)


def generate(system, num_sequences=None, num_steps: int = 100, seed: int = 0, parameterized: bool = False,
             backend: str = "auto", progress: bool = True) -> Dataset:
    """Simulate sequences under random spline controls (C.1) and return a ``Dataset``.

    ``system``: a built-in name (``gnwarp.systems.names()``, e.g. "cheetah", "swimmer6") or a
    ``System``. ``parameterized``: draw each sequence's system instance from the system's
    parameter ranges (built-in systems only). ``num_sequences``: see ``split_sizes``.
    ``backend``: "auto", "mujoco_warp" (CUDA), "mujoco_warp_cpu" or "mujoco" (MuJoCo C).
    """
    from gnwarp import simulate as sim
    from gnwarp import systems as sysmod

    if num_steps < 1:
        raise ValueError(f"num_steps must be >= 1, got {num_steps}")
    backend = sim.resolve_backend(backend)
    sizes = split_sizes(num_sequences, parameterized)
    total = sum(sizes.values())
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()

    if isinstance(system, str):
        name = system
        base_sys = sysmod.make(name)
    else:
        base_sys, name = system, system.name
        if parameterized:
            raise ValueError("parameterized=True needs a built-in system name, not a System instance")
    if base_sys.model.nu == 0:
        raise ValueError(f"system '{name}' has no actuators: random-control datasets need at least one")
    if parameterized:
        seeds = rng.integers(0, 2**31 - 1, total)
        bar = _progress(total, f"{name}: building instances", progress)
        instances = []
        for s in seeds:  # one model compile per sampled instance
            instances.append(sysmod.make(name, seed=int(s)))
            bar.update(1)
        bar.close()
        seq_instance = np.arange(total)
    else:
        instances = [base_sys]
        seq_instance = np.zeros(total, dtype=np.int64)

    # group instances by topology (SwimmerN with several N): one simulation per group
    groups: dict[tuple, list[int]] = {}
    for i, inst in enumerate(instances):
        groups.setdefault(sim._topology_signature(inst.model), []).append(i)

    B = max(s.model.nbody for s in instances)
    nq = max(s.model.nq for s in instances)
    nv = max(s.model.nv for s in instances)
    nu = max(s.model.nu for s in instances)
    body = np.zeros((total, num_steps + 1, B, DYN_NODE_SIZE), dtype=np.float32)
    ctrl = np.zeros((total, num_steps, nu), dtype=np.float32)
    qpos = np.zeros((total, num_steps + 1, nq), dtype=np.float32)
    qvel = np.zeros((total, num_steps + 1, nv), dtype=np.float32)

    bar = _progress(total, f"{name}: simulating ({backend})", progress)
    sim_time = 0.0
    for key, inst_ids in groups.items():
        seqs = np.flatnonzero(np.isin(seq_instance, inst_ids))
        rep = instances[inst_ids[0]]
        m = rep.model
        q0, v0 = initial_states(rep, len(seqs), rng)
        u = random_spline_controls(len(seqs), num_steps, control_range(m), rng)
        group_systems = [instances[seq_instance[s]] for s in seqs] if parameterized else rep
        ts = time.perf_counter()
        tr = sim.simulate(group_systems, q0, v0, u, backend=backend, progress=bar.update)
        sim_time += time.perf_counter() - ts
        bad = [k for k, a in (("body", tr.body), ("qpos", tr.qpos), ("qvel", tr.qvel)) if not _sane(a)]
        if bad:
            raise FloatingPointError(f"simulation of '{name}' produced NaN/Inf or huge (>{_MAXVAL:g}) values in "
                                     f"{', '.join(bad)}: the model is unstable at this timestep or under these controls")
        body[seqs, :, :m.nbody] = tr.body
        ctrl[seqs, :, :m.nu] = u
        qpos[seqs, :, :m.nq] = tr.qpos
        qvel[seqs, :, :m.nv] = tr.qvel
    bar.close()

    static, layout, graph_meta = _static_arrays(instances)
    param_names = sorted({k for s in instances for k in s.params})
    static["params"] = np.array([[float(s.params.get(k, np.nan)) for k in param_names] for s in instances],
                                dtype=np.float64).reshape(len(instances), len(param_names))

    # splits: consecutive blocks of the (already random) sequences
    splits, start = {}, 0
    for k in SPLITS:
        n = sizes[k]
        sl = slice(start, start + n)
        splits[k] = Split(body[sl], ctrl[sl], qpos[sl], qvel[sl], seq_instance[sl])
        start += n

    meta = {
        "system": name, "parameterized": bool(parameterized), "dt": float(base_sys.dt),
        "physics_timestep": float(base_sys.model.opt.timestep), "substeps": int(base_sys.substeps),
        "num_steps": int(num_steps), "seed": int(seed), "backend": backend, "splits": sizes,
        "param_names": param_names, "translation_invariant": bool(base_sys.translation_invariant),
        "layout": layout.to_dict(), "max_bodies": int(B), "max_edges": int(static["senders"].shape[1]),
        "nq": int(nq), "nv": int(nv), "nu": int(nu), "graph": graph_meta,
        "dynamic_node_names": list(__import__("gnwarp.convert", fromlist=["x"]).DYN_NODE_NAMES),
        "generation_seconds": time.perf_counter() - t0, "simulation_seconds": sim_time,
        "gnwarp_version": __import__("gnwarp").__version__,
    }
    return Dataset(meta, static, splits)


_MAXVAL = 1e9  # MuJoCo flags |values| over 1e10 as divergence; stay below that


def _sane(a: np.ndarray) -> bool:
    return bool(np.all(np.isfinite(a)) and np.all(np.abs(a) < _MAXVAL))


def _static_arrays(instances) -> tuple[dict[str, np.ndarray], FeatureLayout, dict]:
    """Pad static graphs of all instances, drop the columns constant over all of them."""
    graphs = [static_graph(s.model) for s in instances]
    g0 = graphs[0]
    I = len(graphs)
    B = max(g.nodes.shape[0] for g in graphs)
    E = max(g.edges.shape[0] for g in graphs)
    K = max(g.topology.edge_ctrl.shape[1] for g in graphs)
    G = max(g.topology.global_ctrl.shape[0] for g in graphs)
    Fg, Fv, Fe = g0.globals.shape[0], g0.nodes.shape[1], g0.edges.shape[1]
    glob = np.stack([g.globals for g in graphs])
    nodes = np.zeros((I, B, Fv))
    edges = np.zeros((I, E, Fe))
    snd = -np.ones((I, E), dtype=np.int64)
    rcv = -np.ones((I, E), dtype=np.int64)
    ectrl = -np.ones((I, E, K), dtype=np.int64)
    n_node = np.zeros(I, dtype=np.int64)
    n_edge = np.zeros(I, dtype=np.int64)
    for i, g in enumerate(graphs):  # one row per system instance, not per state
        nb, ne = g.nodes.shape[0], g.edges.shape[0]
        nodes[i, :nb], edges[i, :ne] = g.nodes, g.edges
        snd[i, :ne], rcv[i, :ne] = g.topology.senders, g.topology.receivers
        ectrl[i, :ne, :g.topology.edge_ctrl.shape[1]] = g.topology.edge_ctrl
        n_node[i], n_edge[i] = nb, ne
    node_mask = np.arange(B)[None] < n_node[:, None]
    edge_mask = np.arange(E)[None] < n_edge[:, None]
    kg = varying_columns(glob)
    kv = varying_columns(nodes, node_mask)
    ke = varying_columns(edges, edge_mask)

    def dropped(names, keep, vals, mask=None):
        flat = vals.reshape(-1, vals.shape[-1])
        row = flat[mask.reshape(-1)][0] if mask is not None else flat[0]
        return {n: float(row[k]) for k, n in enumerate(names) if not keep[k]}

    layout = FeatureLayout(
        global_names=[n for n, k in zip(g0.global_names, kg) if k],
        node_names=[n for n, k in zip(g0.node_names, kv) if k],
        edge_names=[n for n, k in zip(g0.edge_names, ke) if k],
        dropped={"globals": dropped(g0.global_names, kg, glob),
                 "nodes": dropped(g0.node_names, kv, nodes, node_mask),
                 "edges": dropped(g0.edge_names, ke, edges, edge_mask)},
        n_ctrl_slots=K, n_global_ctrl=G)
    static = {"globals": glob[:, kg].astype(np.float32), "nodes": nodes[..., kv].astype(np.float32),
              "edges": edges[..., ke].astype(np.float32), "senders": snd, "receivers": rcv,
              "n_node": n_node, "n_edge": n_edge, "edge_ctrl": ectrl}
    meta = {"n_global_ctrl": G, "full_sizes": {"globals": Fg, "nodes": Fv, "edges": Fe}}
    return static, layout, meta


# -- loading ------------------------------------------------------------------------------------

def load(path: str | os.PathLike, lazy: bool = True) -> Dataset:
    """Open a dataset written by ``Dataset.save``. ``lazy``: keep split arrays on disk (h5py
    datasets, read when sliced); otherwise read everything into memory."""
    import h5py
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no dataset at {path}")
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise DatasetError(f"{path} is not a readable HDF5 dataset (corrupt or truncated?): {e}") from None
    try:
        if f.attrs.get("format") != FORMAT:
            raise DatasetError(f"{path} is not a gnwarp dataset (format attribute: {f.attrs.get('format')!r})")
        if int(f.attrs.get("version", -1)) > VERSION:
            raise DatasetError(f"{path} has dataset version {f.attrs.get('version')}, newer than this gnwarp ({VERSION})")
        if not f.attrs.get("complete", False):
            raise DatasetError(f"{path} was not completely written")
        meta = json.loads(f.attrs["meta"])
        static = {k: f["static"][k][...] for k in f["static"]}
        splits = {}
        for name in SPLITS:
            if name not in f:
                raise DatasetError(f"{path} lacks the split '{name}'")
            g = f[name]
            arrays = []
            for k in ("body", "ctrl", "qpos", "qvel", "instance"):
                if k not in g:
                    raise DatasetError(f"{path}: split '{name}' lacks the array '{k}'")
                arrays.append(g[k] if lazy else g[k][...])
            splits[name] = Split(*arrays)
        _check_consistency(path, meta, static, splits)
        if not lazy:
            f.close()
            f = None
        return Dataset(meta, static, splits, _file=f)
    except DatasetError:
        f.close()
        raise
    except (KeyError, OSError, ValueError, json.JSONDecodeError) as e:
        f.close()
        raise DatasetError(f"{path} is corrupt or truncated: {type(e).__name__}: {e}") from None


def _check_consistency(path, meta, static, splits):
    lay = meta.get("layout")
    if lay is None:
        raise DatasetError(f"{path}: metadata has no feature layout")
    I = static["nodes"].shape[0]
    if static["nodes"].shape[-1] != len(lay["node_names"]) or static["edges"].shape[-1] != len(lay["edge_names"]) \
            or static["globals"].shape[-1] != len(lay["global_names"]):
        raise DatasetError(f"{path}: static feature arrays do not match the layout in the metadata")
    for name, sp in splits.items():
        S = sp.body.shape[0]
        if sp.ctrl.shape[0] != S or sp.instance.shape[0] != S or sp.body.shape[-1] != DYN_NODE_SIZE:
            raise DatasetError(f"{path}: split '{name}' arrays disagree in size")
        if sp.body.shape[1] != sp.ctrl.shape[1] + 1:
            raise DatasetError(f"{path}: split '{name}' has {sp.body.shape[1]} states for {sp.ctrl.shape[1]} controls")
        if S:
            inst = np.asarray(sp.instance[...])
            if inst.min() < 0 or inst.max() >= I:
                raise DatasetError(f"{path}: split '{name}' refers to system instances outside [0, {I})")
