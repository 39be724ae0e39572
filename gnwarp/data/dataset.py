"""The dataset format: simulated sequences (paper, section C.2) stored as HDF5.

``gnwarp.data.generate`` simulates sequences under random spline controls and returns a
``Dataset``; ``Dataset.save(path)`` writes it (to a temporary file, renamed into place when
complete) and ``load(path)`` reads it back, lazily: split arrays stay on disk until sliced.

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
one has one per sequence. Features, states and controls are float32 (float64 is accepted), the
index arrays and ``instance`` integers.

Every array is written with HDF5's Fletcher-32 checksum filter, so bytes changed after writing are
detected when they are read (files written before had none: they load with a ``DatasetWarning``).
What is read is also validated, vectorized: on ``load``, the dtypes and shapes above, the static
arrays (finite features, senders and receivers in [0, n_node) of their graph, -1 beyond n_edge,
edge_ctrl in [-1, U), counts within the padded sizes); and whenever a split's arrays are read
(``Split`` arrays of a lazily loaded file are ``CheckedArray``\\ s): states, controls, qpos and
qvel finite with ``|x| <= MAX_ABS``, real bodies with unit quaternions and padded bodies zero.
Anything else raises ``DatasetError`` naming the file, the array and the first bad index.
``check(path)`` (``gnwarp check FILE``) reads and validates everything and lists every problem.
"""
from __future__ import annotations

import glob
import json
import os
import shutil
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from gnwarp.data.builder import GraphBuilder
from gnwarp.data.layout import FeatureLayout
from gnwarp.files import pid_alive
from gnwarp.graphs import GraphsTuple
from gnwarp.state import DYN_NODE_NAMES, DYN_NODE_SIZE

__all__ = ["FORMAT", "VERSION", "SPLITS", "MAX_ABS", "STATIC_MAX_ABS", "DatasetError", "DatasetWarning", "Split",
           "Dataset", "CheckedArray", "load", "check"]

FORMAT, VERSION = "gnwarp-dataset", 1
SPLITS = ("train", "valid", "test")

# Bounds of stored values: a state, control, qpos or qvel beyond MAX_ABS (1e6 m, m/s, rad/s, N...)
# is no simulation of the paper's systems but corruption or divergence (generation refuses the same);
# static features (masses, inertias, gains ...) may be larger, up to STATIC_MAX_ABS.
MAX_ABS = 1e6
STATIC_MAX_ABS = 1e12
_QUAT_TOL = 2e-3  # | |q|^2 - 1 | of a stored (float32) body orientation

_FLOATS = (np.dtype(np.float32), np.dtype(np.float64))
_STATIC_FLOAT = ("globals", "nodes", "edges", "params")
_STATIC_SHAPES = {"globals": "[I, F_g]", "nodes": "[I, B, F_v]", "edges": "[I, E, F_e]", "senders": "[I, E]",
                  "receivers": "[I, E]", "n_node": "[I]", "n_edge": "[I]", "edge_ctrl": "[I, E, K]",
                  "params": "[I, P]"}
_ARRAYS = ("body", "ctrl", "qpos", "qvel", "instance")
_SPLIT_SHAPES = {"body": "[S, T+1, B, 13]", "ctrl": "[S, T, U]", "qpos": "[S, T+1, nq]", "qvel": "[S, T+1, nv]",
                 "instance": "[S]"}
_AXES = {"body": ("sequence", "step", "body", None), "ctrl": ("sequence", "step", "actuator"),
         "qpos": ("sequence", "step", "coordinate"), "qvel": ("sequence", "step", "dof"),
         "instance": ("sequence",), "globals": ("instance", "feature"),
         "nodes": ("instance", "body", "feature"), "edges": ("instance", "edge", "feature"),
         "params": ("instance", "parameter")}


class DatasetError(ValueError):
    """A dataset file is missing, corrupt, truncated or of another layout, or holds invalid values."""


class DatasetWarning(UserWarning):
    """A dataset loads but cannot be fully verified (written without checksums)."""


def remove_stale_temporaries(path: Path) -> None:
    """Remove ``<name>.<pid>.tmp`` files beside ``path`` that saves killed before their rename
    left (those of processes no longer running)."""
    parent = path.parent if str(path.parent) else Path(".")
    prefix = path.name + "."
    for p in parent.glob(glob.escape(prefix) + "*.tmp"):
        pid = p.name[len(prefix):-len(".tmp")]
        if not pid.isdigit() or pid_alive(int(pid)):  # a running writer's (or cannot tell): leave it
            continue
        try:
            p.unlink()  # a dead writer's: debris
        except OSError:
            pass


@dataclass
class Split:
    """One split; arrays are numpy arrays, or ``CheckedArray`` (h5py datasets) for a lazily loaded file."""
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
        """This split with every array read into memory (and validated, for a file's arrays)."""
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
        """Write to ``path`` (HDF5), every array with a Fletcher-32 checksum. Refuses an existing
        path unless ``overwrite``, and a folder without the space for the arrays; writes a
        temporary file beside it and renames it into place, so a failure leaves nothing behind."""
        path = Path(path)
        if path.exists() and not overwrite:
            raise FileExistsError(f"dataset path already exists: {path} (pass overwrite=True to replace it)")
        parent = path.parent if str(path.parent) else Path(".")
        if not parent.exists():
            raise FileNotFoundError(f"folder of the dataset path does not exist: {parent}")
        if not os.access(parent, os.W_OK):
            raise PermissionError(f"cannot write into folder {parent}")
        need = sum(_nbytes(a) for a in self.static.values())
        need += sum(_nbytes(getattr(sp, k)) for sp in self.splits.values() for k in _ARRAYS)
        free = shutil.disk_usage(parent).free
        if compression is None and need > free:
            raise OSError(f"not enough disk space for {path}: the dataset needs {_gib(need)} GiB, "
                          f"{parent} has {_gib(free)} GiB free")
        remove_stale_temporaries(path)  # of saves to this path killed before their rename
        tmp = str(parent / f"{path.name}.{os.getpid()}.tmp")
        os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600))
        try:
            with h5py.File(tmp, "w") as f:
                f.attrs["format"] = FORMAT
                f.attrs["version"] = VERSION
                f.attrs["meta"] = json.dumps(self.meta)
                g = f.create_group("static")
                for k, v in self.static.items():
                    _write(g, k, np.asarray(v[...]), None, None)
                for name, sp in self.splits.items():
                    g = f.create_group(name)
                    for k in _ARRAYS:
                        a = np.asarray(getattr(sp, k)[...])
                        chunks = (1,) + a.shape[1:] if a.ndim > 1 and a.shape[0] > 0 else None
                        _write(g, k, a, chunks, compression)
                f.attrs["complete"] = True
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(tmp, 0o666 & ~umask)  # private while written; give it a normal file's mode
            os.replace(tmp, path)
        except BaseException:
            if os.path.exists(tmp):
                os.unlink(tmp)
            raise
        return path

    # -- graphs --------------------------------------------------------------------------------
    def graphs(self, split: str, seq, t, device=None, dtype=None) -> GraphsTuple:
        """Input graphs (static concatenated with dynamic) for sequences ``seq`` at steps ``t``.

        ``seq``, ``t``: int arrays [N], seq in [0, S), t in [0, T]. Returns a torch GraphsTuple of
        N graphs (see ``GraphBuilder``). Reads only the rows asked for (validated as they are read).
        """
        sp = self[split]
        seq, t = (np.asarray(x) if np.size(x) else np.zeros(0, np.int64) for x in (seq, t))
        S, T = len(sp), sp.num_steps
        if seq.dtype.kind not in "iu" or t.dtype.kind not in "iu" or seq.ndim != 1 or seq.shape != t.shape:
            raise ValueError(f"graphs(): seq and t must be integer arrays of one length, got {seq.dtype} "
                             f"{seq.shape} and {t.dtype} {t.shape}")
        if seq.size and (seq.min() < 0 or seq.max() >= S):
            raise IndexError(f"graphs(): sequence index {int(seq.min() if seq.min() < 0 else seq.max())} "
                             f"outside split '{split}' of {S} sequences")
        if t.size and (t.min() < 0 or t.max() > T):
            raise IndexError(f"graphs(): step {int(t.min() if t.min() < 0 else t.max())} outside [0, {T}] "
                             f"of split '{split}'")
        order = np.argsort(seq, kind="stable")  # h5py wants increasing indices
        inv = np.empty_like(order)
        inv[order] = np.arange(order.size)
        s_sorted, t_sorted = seq[order], t[order]
        uniq, first = np.unique(s_sorted, return_inverse=True)
        body = np.asarray(sp.body[uniq])  # numpy or h5py: one read of the rows asked for
        ctrl = np.asarray(sp.ctrl[uniq])
        inst = np.asarray(sp.instance[...])[uniq]
        b = body[first, t_sorted][inv]
        c = ctrl[first, np.minimum(t_sorted, ctrl.shape[1] - 1)][inv]
        import torch
        key = (str(device), dtype)
        if key not in self._builders:  # static tensors built once per device and dtype
            if not self._builders:  # a Dataset made in memory was never checked: its indices now
                U = int(sp.ctrl.shape[2]) if len(sp.ctrl.shape) == 3 else None
                problems = _check_static(self.static, self.meta, U)
                if problems:
                    raise DatasetError(_summary(f"dataset of '{self.meta.get('system')}'", problems))
            self._builders[key] = GraphBuilder(self.static, device=device, dtype=dtype)
        builder = self._builders[key]
        return builder(torch.as_tensor(inst[first][inv]), torch.as_tensor(b), torch.as_tensor(c))


def _nbytes(a) -> int:
    shape, dtype = getattr(a, "shape", None), getattr(a, "dtype", None)
    if shape is None or dtype is None:
        return np.asarray(a).nbytes
    return int(np.prod(shape, dtype=np.float64)) * np.dtype(dtype).itemsize


def _gib(n: float) -> str:
    return f"{n / 2**30:.3g}"


def _write(group, name: str, a: np.ndarray, chunks, compression):
    """One array with a Fletcher-32 checksum (chunked: per sequence for split arrays)."""
    if a.ndim == 0:  # scalars cannot be chunked, so carry no checksum (the format has none)
        return group.create_dataset(name, data=a)
    if chunks is not None and np.prod(chunks, dtype=np.float64) * a.dtype.itemsize > 2**30:
        chunks = True  # HDF5 chunks stay under 4 GiB: let h5py choose
    return group.create_dataset(name, data=a, chunks=chunks if chunks is not None else True,
                                compression=compression, fletcher32=True)


# -- reading with checks ------------------------------------------------------------------------

class CheckedArray(h5py.Dataset):
    """An array of a split in a dataset file that validates what is read from it.

    An ``h5py.Dataset`` (lazy, sliced like one): every read turns an HDF5 read error (a failed
    Fletcher-32 checksum: bytes changed after writing) into a ``DatasetError`` naming the file,
    the array and the sequence, and checks the values read (finite, ``|x| <= MAX_ABS``; for
    ``body`` read by whole sequences also unit quaternions of real bodies and zero padded bodies).
    ``np.asarray(a)`` reads and checks the whole array.
    """

    def __init__(self, dset: h5py.Dataset, path, split: str, key: str, n_node_of_seq=None):
        super().__init__(dset.id)
        self._gn_path, self._gn_split, self._gn_key = str(path), split, key
        self._gn_n_node = n_node_of_seq  # [S] bodies of each sequence's instance (for ``body``)

    def __getitem__(self, args, new_dtype=None):
        try:
            out = super().__getitem__(args, new_dtype)
        except OSError as e:
            raise DatasetError(f"{self._gn_path}: {_read_problem(self, self._gn_split, self._gn_key, e, args)}") \
                from None
        if isinstance(out, np.ndarray) and out.dtype.kind == "f":
            bad = _bad_value(f"/{self._gn_split}/{self._gn_key}", self._gn_key, out, _index_map(args, self.shape))
            problem = _with_count(*bad, " in the part read") if bad else None
            rows = _rows_of(args, self.shape) if problem is None and self._gn_key == "body" else None
            if rows is not None and self._gn_n_node is not None and out.ndim == 4 and out.shape[1:] == self.shape[1:]:
                problem = _check_body_structure(self._gn_split, out, self._gn_n_node[rows], rows)
            if problem is not None:
                raise DatasetError(f"{self._gn_path}: {problem}")
        return out

    def __array__(self, dtype=None, copy=None):
        out = self[...] if self.size else np.zeros(self.shape, self.dtype)
        return out if dtype is None else out.astype(dtype, copy=False)


def _read_problem(dset, split, key, err, args=Ellipsis) -> str:
    """What a failed read of /split/key means, with the first sequence that cannot be read."""
    where = f"/{split}/{key}" if split else f"/static/{key}"
    bad = None
    if dset.ndim >= 1 and dset.shape[0]:
        rows = _rows_of(args, dset.shape)
        rows = np.arange(dset.shape[0]) if rows is None else np.atleast_1d(rows)
        for r in rows[:100000]:
            try:
                h5py.Dataset.__getitem__(dset, int(r))
            except OSError:
                bad = int(r)
                break
    at = f" (sequence {bad})" if split and bad is not None else (f" (row {bad})" if bad is not None else "")
    if dset.fletcher32:
        return (f"{where}{at} fails its Fletcher-32 checksum: the stored bytes changed after writing "
                f"(HDF5: {err})")
    return f"{where}{at} cannot be read (corrupt or truncated; HDF5: {err})"


def _rows_of(args, shape):
    """Sequence indices [n] read by ``args`` when it reads whole sequences, else None."""
    if not isinstance(args, tuple):
        args = (args,)
    if len(args) == 0 or (len(args) == 1 and args[0] is Ellipsis):
        return np.arange(shape[0])
    first, rest = args[0], args[1:]
    if any(not (r is Ellipsis or (isinstance(r, slice) and r == slice(None))) for r in rest):
        return None
    if isinstance(first, slice):
        return np.arange(shape[0])[first]
    if isinstance(first, (list, np.ndarray)) and np.asarray(first).dtype.kind in "iu":
        return np.asarray(first).reshape(-1)
    return None


def _index_map(args, shape):
    """A function from an index into the array read by ``args`` to the index in the stored array
    (or None where the selection is not a plain one)."""
    if not isinstance(args, tuple):
        args = (args,)
    ell = [i for i, a in enumerate(args) if a is Ellipsis]
    if ell:
        k = ell[0]
        fill = len(shape) - (len(args) - 1)
        args = args[:k] + (slice(None),) * fill + args[k + 1:]
    args = args + (slice(None),) * (len(shape) - len(args))
    if sum(isinstance(a, (list, np.ndarray)) for a in args) > 1:
        return None

    def to_stored(pos):
        out, j = [], 0
        for ax, a in enumerate(args):
            if isinstance(a, (int, np.integer)):
                out.append(int(a) % shape[ax])
            elif isinstance(a, slice):
                out.append(range(shape[ax])[a][pos[j]])
                j += 1
            elif isinstance(a, (list, np.ndarray)) and np.asarray(a).dtype.kind in "iu":
                out.append(int(np.asarray(a).reshape(-1)[pos[j]]))
                j += 1
            else:
                return None
        return tuple(out)
    return to_stored


def _locate(key: str, idx) -> str:
    axes = _AXES.get(key)
    if idx is None:
        return "in the part read"
    parts = []
    for ax, i in enumerate(idx):
        name = axes[ax] if axes and ax < len(axes) else None
        if name is None:
            parts.append(DYN_NODE_NAMES[i] if key == "body" and i < len(DYN_NODE_NAMES) else f"component {i}")
        else:
            parts.append(f"{name} {i}")
    return "at " + ", ".join(parts)


def _describe(v) -> str:
    v = float(v)
    if np.isnan(v):
        return "NaN"
    if np.isinf(v):
        return "Inf" if v > 0 else "-Inf"
    return f"{v:.4g}"


_BLOCK = 1 << 22  # elements per vectorized pass of a check: bounds its temporaries on large reads


def _bad_value(where: str, key: str, a: np.ndarray, to_stored=None, bound: float = MAX_ABS):
    """(message, count) of the values of array ``where`` that are not finite or beyond ``bound``
    (the first one located in the stored array through ``to_stored``), or None when all are good."""
    if a.size == 0:
        return None
    flat = a.reshape(-1)
    first, n_bad = None, 0
    for i in range(0, flat.size, _BLOCK):
        ok = np.abs(flat[i:i + _BLOCK]) <= bound  # False for NaN and Inf too
        if not ok.all():
            n_bad += int(ok.size - np.count_nonzero(ok))
            if first is None:
                first = i + int(np.argmin(ok))
    if first is None:
        return None
    pos = tuple(int(i) for i in np.unravel_index(first, a.shape))
    idx = to_stored(pos) if to_stored is not None else pos
    v = a[pos]
    what = "a non-finite value" if not np.isfinite(v) else f"an absurd value (|x| > {bound:g})"
    return f"{where} holds {what}, {_describe(v)}, {_locate(key, idx)}", n_bad


def _with_count(msg: str, n: int, of: str = "") -> str:
    return msg if n <= 1 else f"{msg} ({n} bad entries{of})"


def _check_body_structure(split, body: np.ndarray, n_node_rows: np.ndarray, rows: np.ndarray):
    """Body states of whole sequences: real bodies have unit quaternions, padded ones are zero."""
    if body.size == 0:
        return None
    B = body.shape[2]
    n_node_rows = np.asarray(n_node_rows)
    step = max(1, _BLOCK // max(1, int(np.prod(body.shape[1:]))))
    for s0 in range(0, body.shape[0], step):  # blocks of sequences: bounded temporaries
        blk = body[s0:s0 + step]
        nn = n_node_rows[s0:s0 + step]
        real = np.arange(B)[None, :] < nn[:, None]                                 # [n, B]
        pad_bad = (~real)[:, None, :] & np.any(blk != 0, axis=-1) if not real.all() else real[:0]  # [n, T+1, B]
        if pad_bad.any():
            i, t, b = (int(x) for x in np.argwhere(pad_bad)[0])
            return (f"/{split}/body: sequence {int(rows[s0 + i])} has non-zero states for body {b} at step {t}, "
                    f"beyond the {int(nn[i])} bodies (n_node) of its system instance: n_node does not match the "
                    f"stored states")
        q = blk[..., 3:7]
        qn = np.einsum("...i,...i->...", q, q)  # in the stored precision: float32 is plenty for _QUAT_TOL
        q_bad = real[:, None, :] & ~(np.abs(qn - 1.0) <= _QUAT_TOL)
        if q_bad.any():
            i, t, b = (int(x) for x in np.argwhere(q_bad)[0])
            n = int(q_bad.sum())
            return (f"/{split}/body: sequence {int(rows[s0 + i])}, step {t}, body {b} has an orientation quaternion "
                    f"of norm {np.sqrt(qn[i, t, b]):.4g}, not 1: not a body state, or n_node ({int(nn[i])}) of its "
                    f"system instance is wrong{f' ({n} such states in its block)' if n > 1 else ''}")
    return None


def _summary(where, problems: list[str]) -> str:
    more = (f" (and {len(problems) - 1} more problem{'s' if len(problems) > 2 else ''}; "
            f"`gnwarp check` lists them)") if len(problems) > 1 else ""
    return f"{where}: {problems[0]}{more}"


# -- static and layout checks ---------------------------------------------------------------------

def _first(mask):
    return tuple(int(i) for i in np.argwhere(mask)[0])


def _check_places(meta: dict, B: int, nu) -> list[str]:
    """Problems of the metadata's ``param_places`` (optional; ``gnwarp.sim.param_places``): one
    [kind, id] per parameter, a body id below B (not the world), an actuator id below nu, or
    ["globals", 0]."""
    if "param_places" not in meta:
        return []
    places, names = meta["param_places"], meta.get("param_names", [])
    if not isinstance(places, list) or len(places) != len(names):
        return [f"metadata's param_places must list one [kind, id] per parameter ({len(names)}), got {places!r:.80}"]
    hi = {"nodes": B, "edges": nu if isinstance(nu, int) else 0, "globals": 1}
    for name, pl in zip(names, places):
        ok = (isinstance(pl, list) and len(pl) == 2 and pl[0] in hi and isinstance(pl[1], int)
              and not isinstance(pl[1], bool) and int(pl[0] == "nodes") <= pl[1] < hi[pl[0]])
        if not ok:
            return [f"metadata's param_places: parameter {name!r} is placed at {pl!r:.60}; expected [\"nodes\", a body "
                    f"1..{B - 1}], [\"edges\", an actuator 0..{hi['edges'] - 1}] or [\"globals\", 0]"]
    return []


def _check_static(static: dict, meta: dict, n_ctrl: int | None) -> list[str]:
    """Problems of the static arrays (dtypes, shapes, values, index ranges, counts): [] when valid.
    ``n_ctrl``: the controls per sequence (U), or None when unknown."""
    p: list[str] = []
    missing = [k for k in _STATIC_SHAPES if k not in static]
    if missing:
        return [f"/static lacks the array{'s' if len(missing) > 1 else ''} {', '.join(missing)}"]
    st = {k: static[k] for k in _STATIC_SHAPES}
    for k, a in st.items():
        nd = _STATIC_SHAPES[k].count(",") + 1
        if a.ndim != nd:
            p.append(f"/static/{k} has shape {tuple(a.shape)}, expected {_STATIC_SHAPES[k]}")
        if k in _STATIC_FLOAT and a.dtype not in _FLOATS:
            p.append(f"/static/{k} has dtype {a.dtype}, expected float32 (float64 accepted)")
        elif k not in _STATIC_FLOAT and a.dtype.kind not in "iu":
            p.append(f"/static/{k} has dtype {a.dtype}, expected int64 (an integer type)")
    if p:
        return p
    I, B, E, K = st["nodes"].shape[0], st["nodes"].shape[1], st["edges"].shape[1], st["edge_ctrl"].shape[2]
    want = {"globals": (I, None), "nodes": (I, B, None), "edges": (I, E, None), "senders": (I, E),
            "receivers": (I, E), "n_node": (I,), "n_edge": (I,), "edge_ctrl": (I, E, K),
            "params": (I, len(meta.get("param_names", [])) if "param_names" in meta else None)}
    for k, shape in want.items():
        if any(w is not None and w != s for w, s in zip(shape, st[k].shape)):
            p.append(f"/static/{k} has shape {tuple(st[k].shape)}, expected {_STATIC_SHAPES[k]} = "
                     f"{tuple('*' if w is None else w for w in shape)}")
    if I < 1:
        p.append("/static holds no system instance (I = 0)")
    lay = meta.get("layout")
    if not isinstance(lay, dict):
        p.append("metadata has no feature layout")
    else:
        try:
            for k, names in (("globals", "global_names"), ("nodes", "node_names"), ("edges", "edge_names")):
                if st[k].shape[-1] != len(lay[names]):
                    p.append(f"/static/{k} has {st[k].shape[-1]} feature columns, the layout in the metadata names "
                             f"{len(lay[names])}")
        except (KeyError, TypeError):
            p.append("metadata's feature layout is malformed")
        if isinstance(lay.get("n_ctrl_slots"), int) and lay["n_ctrl_slots"] != K:
            p.append(f"/static/edge_ctrl has {K} control slots per edge, the layout {lay['n_ctrl_slots']}")
    for k, size in (("max_bodies", B), ("max_edges", E)):
        if k in meta and meta[k] != size:
            p.append(f"metadata says {k} = {meta[k]}, the static arrays hold {size}")
    if p:
        return p
    for k in ("globals", "nodes", "edges"):
        bad = _bad_value(f"/static/{k}", k, st[k], None, STATIC_MAX_ABS)
        if bad:
            p.append(_with_count(*bad))
    par = st["params"]
    if par.size and not np.all(np.isnan(par) | (np.abs(par) <= STATIC_MAX_ABS)):
        p.append(f"/static/params holds {_describe(par[_first(~(np.isnan(par) | (np.abs(par) <= STATIC_MAX_ABS)))])} "
                 f"at instance {_first(~(np.isnan(par) | (np.abs(par) <= STATIC_MAX_ABS)))[0]} (NaN marks a missing "
                 f"parameter; infinite or absurd values are not parameters)")
    p += _check_places(meta, B, meta.get("nu"))
    n_node, n_edge = st["n_node"].astype(np.int64), st["n_edge"].astype(np.int64)
    for k, a, lo, hi in (("n_node", n_node, 1, B), ("n_edge", n_edge, 0, E)):
        bad = (a < lo) | (a > hi)
        if bad.any():
            i = int(np.argmax(bad))
            p.append(f"/static/{k} of instance {i} is {int(a[i])}, outside [{lo}, {hi}] (the padded size of the "
                     f"stored arrays)")
    if p:
        return p
    real_e = np.arange(E)[None, :] < n_edge[:, None]         # [I, E]
    nn = n_node[:, None]
    for k in ("senders", "receivers"):
        a = st[k].astype(np.int64)
        bad = real_e & ((a < 0) | (a >= nn))
        if bad.any():
            i, e = _first(bad)
            n = int(bad.sum())
            p.append(f"/static/{k}: instance {i}, edge {e} holds body index {int(a[i, e])}, outside [0, {int(n_node[i])}) "
                     f"(n_node of that graph){f'; {n} such indices' if n > 1 else ''}")
        pad = ~real_e & (a != -1)
        if pad.any():
            i, e = _first(pad)
            p.append(f"/static/{k}: instance {i}, edge {e} holds {int(a[i, e])} beyond n_edge = {int(n_edge[i])}, where "
                     f"the format has -1 (padding): n_edge does not match the stored edges")
    ec = st["edge_ctrl"].astype(np.int64)
    hi = n_ctrl if n_ctrl is not None else meta.get("nu")
    bad = real_e[..., None] & ((ec < -1) | ((ec >= hi) if isinstance(hi, int) else False))
    if bad.any():
        i, e, s = _first(bad)
        p.append(f"/static/edge_ctrl: instance {i}, edge {e}, slot {s} holds control index {int(ec[i, e, s])}, outside "
                 f"[-1, {hi}) (-1 = no actuator; {hi} controls)")
    pad = ~real_e[..., None] & (ec != -1)
    if pad.any():
        i, e, s = _first(pad)
        p.append(f"/static/edge_ctrl: instance {i}, edge {e} holds {int(ec[i, e, s])} beyond n_edge = {int(n_edge[i])}, "
                 f"where the format has -1 (padding)")
    real_v = np.arange(B)[None, :] < nn                         # [I, B]
    for k, mask, count in (("nodes", real_v, "n_node"), ("edges", real_e, "n_edge")):
        a = st[k]
        if a.shape[-1]:
            pad = ~mask & np.any(a != 0, axis=-1)
            if pad.any():
                i, j = _first(pad)
                p.append(f"/static/{k}: instance {i} has features for {k[:-1]} {j}, beyond {count} = "
                         f"{int((n_node if k == 'nodes' else n_edge)[i])}, where the format pads with zeros: {count} "
                         f"does not match the stored graph")
    return p


def _check_split_layout(name: str, arrays: dict, static: dict, meta: dict) -> list[str]:
    """Problems of one split's dtypes and shapes, and of its instance indices (read here)."""
    p: list[str] = []
    for k in _ARRAYS:
        a = arrays[k]
        nd = _SPLIT_SHAPES[k].count(",") + 1
        if k == "instance" and a.dtype.kind not in "iu":
            p.append(f"/{name}/{k} has dtype {a.dtype}, expected int64 (an integer type)")
        elif k != "instance" and a.dtype not in _FLOATS:
            p.append(f"/{name}/{k} has dtype {a.dtype}, expected float32 (float64 accepted)")
        if len(a.shape) != nd:
            p.append(f"/{name}/{k} has shape {tuple(a.shape)}, expected {_SPLIT_SHAPES[k]}")
    if p:
        return p
    body, ctrl = arrays["body"], arrays["ctrl"]
    S, T = body.shape[0], ctrl.shape[1]
    B = static["nodes"].shape[1] if getattr(static.get("nodes"), "ndim", 0) == 3 else None
    want = {"body": (S, T + 1, B, DYN_NODE_SIZE), "ctrl": (S, T, meta.get("nu")), "qpos": (S, T + 1, meta.get("nq")),
            "qvel": (S, T + 1, meta.get("nv")), "instance": (S,)}
    for k, shape in want.items():
        got = tuple(arrays[k].shape)
        if any(w is not None and w != s for w, s in zip(shape, got)):
            p.append(f"/{name}/{k} has shape {got}, expected {_SPLIT_SHAPES[k]} = "
                     f"{tuple('*' if w is None else w for w in shape)}")
    if isinstance(meta.get("num_steps"), int) and meta["num_steps"] != T:
        p.append(f"/{name}/ctrl holds {T} steps, the metadata says num_steps = {meta['num_steps']}")
    n_meta = meta.get("splits", {}).get(name) if isinstance(meta.get("splits"), dict) else None
    if isinstance(n_meta, int) and n_meta != S:
        p.append(f"/{name} holds {S} sequences, the metadata says {n_meta}")
    if p or not S:
        return p
    inst = np.asarray(arrays["instance"][...])
    I = static["nodes"].shape[0]
    bad = (inst < 0) | (inst >= I)
    if bad.any():
        i = int(np.argmax(bad))
        p.append(f"/{name}/instance of sequence {i} is {int(inst[i])}, outside [0, {I}) (the system instances in /static)")
    return p


# -- loading ------------------------------------------------------------------------------------

def _open(path: Path):
    if not path.exists():
        raise FileNotFoundError(f"no dataset at {path}")
    if path.is_dir():
        raise DatasetError(f"{path} is a folder, not a dataset file")
    try:
        return h5py.File(path, "r")
    except OSError as e:
        raise DatasetError(f"{path} is not a readable HDF5 dataset (corrupt or truncated?): {e}") from None


def _inspect(path: Path, f) -> tuple[dict, dict, list[str], list[str]]:
    """(meta, static, problems, arrays without checksums) of an open file; raises DatasetError for
    what makes the file unusable at all (other format, incomplete, missing groups)."""
    if f.attrs.get("format") != FORMAT:
        raise DatasetError(f"{path} is not a gnwarp dataset (format attribute: {f.attrs.get('format')!r})")
    if int(f.attrs.get("version", -1)) > VERSION:
        raise DatasetError(f"{path} has dataset version {f.attrs.get('version')}, newer than this gnwarp ({VERSION})")
    if not f.attrs.get("complete", False):
        raise DatasetError(f"{path} was not completely written")
    meta = json.loads(f.attrs["meta"])
    if not isinstance(meta, dict):
        raise DatasetError(f"{path}: its metadata is not a JSON object")
    if "static" not in f:
        raise DatasetError(f"{path} lacks the group /static")
    unchecked = []
    static = {}
    for k in f["static"]:
        d = f["static"][k]
        if not isinstance(d, h5py.Dataset):
            raise DatasetError(f"{path}: /static/{k} is not an array")
        if not d.fletcher32 and d.ndim:
            unchecked.append(f"/static/{k}")
        try:
            static[k] = d[...]
        except OSError as e:
            raise DatasetError(f"{path}: {_read_problem(d, '', k, e)}") from None
    for name in SPLITS:
        if name not in f:
            raise DatasetError(f"{path} lacks the split '{name}'")
        for k in _ARRAYS:
            if k not in f[name] or not isinstance(f[name][k], h5py.Dataset):
                raise DatasetError(f"{path}: split '{name}' lacks the array '{k}'")
            if not f[name][k].fletcher32:
                unchecked.append(f"/{name}/{k}")
    ctrl = f["train"]["ctrl"]
    problems = _check_static(static, meta, int(ctrl.shape[2]) if ctrl.ndim == 3 else None)
    for name in SPLITS:
        problems += _check_split_layout(name, {k: f[name][k] for k in _ARRAYS}, static, meta)
    return meta, static, problems, unchecked


def _warn_unchecked(path, unchecked, stacklevel=3):
    warnings.warn(f"{path} was written without per-array checksums (by an older gnwarp; {len(unchecked)} arrays, "
                  f"e.g. {unchecked[0]}): bytes changed in it cannot be detected, only invalid values. Saving it "
                  f"again adds checksums", DatasetWarning, stacklevel=stacklevel)


def load(path: str | os.PathLike, lazy: bool = True) -> Dataset:
    """Open a dataset written by ``Dataset.save``. ``lazy``: keep split arrays on disk
    (``CheckedArray``: h5py datasets validated as they are read); otherwise read and validate
    everything now. Raises ``DatasetError`` for a corrupt, truncated, foreign or invalid file,
    naming the array and the first bad index; warns (``DatasetWarning``) for a file without
    checksums."""
    path = Path(path)
    f = _open(path)
    try:
        meta, static, problems, unchecked = _inspect(path, f)
        if problems:
            raise DatasetError(_summary(str(path), problems))
        n_node = static["n_node"].astype(np.int64)
        splits = {}
        for name in SPLITS:
            g = f[name]
            nn = n_node[np.asarray(g["instance"][...], dtype=np.int64)]
            splits[name] = Split(*(CheckedArray(g[k], path, name, k, nn if k == "body" else None) for k in _ARRAYS))
        if unchecked:
            _warn_unchecked(path, unchecked)
        if not lazy:
            splits = {name: sp.load() for name, sp in splits.items()}
            f.close()
            f = None
        return Dataset(meta, static, splits, _file=f)
    except DatasetError:
        if f is not None:
            f.close()
        raise
    except (KeyError, OSError, ValueError, json.JSONDecodeError) as e:
        f.close()
        raise DatasetError(f"{path} is corrupt or truncated: {type(e).__name__}: {e}") from None


def check(path: str | os.PathLike, block_bytes: int = 64 << 20) -> list[str]:
    """The full validation of a dataset file (``gnwarp check FILE``): reads every array (so
    every checksum is verified) in blocks of about ``block_bytes``, and runs every check of
    ``load`` and of reading. Returns lines: "error: ..." for each problem, "warning: ..." for what
    cannot be verified, and one "ok: ..." summary when there is no error."""
    path = Path(path)
    try:
        f = _open(path)
    except (DatasetError, FileNotFoundError) as e:
        return [f"error: {e}"]
    lines: list[str] = []
    try:
        try:
            meta, static, problems, unchecked = _inspect(path, f)
        except DatasetError as e:
            return [f"error: {e}"]
        except (KeyError, OSError, ValueError, json.JSONDecodeError) as e:
            return [f"error: {path} is corrupt or truncated: {type(e).__name__}: {e}"]
        lines += [f"error: {path}: {q}" for q in problems]
        if unchecked:
            lines.append(f"warning: {path} was written without per-array checksums ({len(unchecked)} arrays, e.g. "
                         f"{unchecked[0]}): changed bytes cannot be detected, only invalid values")
        structure_ok = not problems
        n_node = static["n_node"].astype(np.int64) if structure_ok else None
        nbytes = sum(a.nbytes for a in static.values())
        for name in SPLITS:
            g = f[name]
            inst = np.asarray(g["instance"][...], dtype=np.int64) if structure_ok else None
            for k in _ARRAYS:
                d = g[k]
                nbytes += _nbytes(d)
                lines += [f"error: {path}: {q}" for q in _check_dataset_values(name, k, d, block_bytes,
                          n_node[inst] if structure_ok and k == "body" else None)]
    finally:
        f.close()
    if not any(x.startswith("error:") for x in lines):
        sizes = ", ".join(f"{k} {meta['splits'][k]}" for k in SPLITS) if isinstance(meta.get("splits"), dict) else ""
        lines.append(f"ok: {path}: gnwarp dataset of '{meta.get('system')}' ({sizes} sequences x "
                     f"{meta.get('num_steps')} steps, {static['nodes'].shape[1]} bodies, {static['nodes'].shape[0]} "
                     f"instance(s)); {nbytes / 2**20:.3g} MiB read and validated"
                     f"{', every Fletcher-32 checksum verified' if not unchecked else ' (no checksums to verify)'}")
    return lines


def _check_dataset_values(split: str, key: str, d, block_bytes: int, n_node_of_seq) -> list[str]:
    """Read /split/key in blocks of sequences: its read errors, first bad value and (``body``) first
    state that does not fit its instance's bodies."""
    if d.ndim == 0 or d.shape[0] == 0:
        return []
    step = max(1, block_bytes // max(1, _nbytes(d) // d.shape[0]))
    out, first, n_bad, structure = [], None, 0, None
    for s0 in range(0, d.shape[0], step):
        s1 = min(d.shape[0], s0 + step)
        try:
            a = h5py.Dataset.__getitem__(d, slice(s0, s1))
        except OSError as e:
            out.append(_read_problem(d, split, key, e, slice(s0, s1)))
            continue
        if a.dtype.kind != "f":
            continue
        bad = _bad_value(f"/{split}/{key}", key, a, lambda pos, s0=s0: (pos[0] + s0,) + pos[1:])
        if bad:
            first = first or bad[0]
            n_bad += bad[1]
        elif key == "body" and n_node_of_seq is not None and structure is None:
            rows = np.arange(s0, s1)
            structure = _check_body_structure(split, a, n_node_of_seq[rows], rows)
    if first:
        out.append(_with_count(first, n_bad))
    if structure:
        out.append(structure)
    return out
