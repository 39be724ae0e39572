"""Datasets of simulated sequences: the ``Dataset`` (its static graphs and splits), ``load`` and
``check`` of its files (layout: ``gnwarp.data.format``; validation: ``gnwarp.data.checks``).

``gnwarp.data.generate`` simulates sequences under random spline controls and returns a
``Dataset``; ``Dataset.save(path)`` writes it (to a temporary file, renamed into place when
complete) and ``load(path)`` reads it back, lazily: split arrays stay on disk until sliced.
What is read is validated (``gnwarp.data.checks``): on ``load`` the dtypes, shapes and static
arrays, and whenever a split's arrays are read (``Split`` arrays of a lazily loaded file are
``CheckedArray``\\ s) their values. Anything else raises ``DatasetError`` naming the file, the
array and the first bad index. ``check(path)`` (``gnwarp check FILE``) reads and validates
everything and lists every problem.
"""
from __future__ import annotations

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
from gnwarp.data.checks import (bad_value, check_body_structure, check_dataset_values, check_split_layout,
                                check_meta, check_static, index_map, read_problem, rows_of, summary, with_count)
from gnwarp.data.format import (ARRAYS, FORMAT, SPLITS, VERSION, DatasetError, DatasetWarning, gib, nbytes, open_file,
                                meta_digest, write_file)
from gnwarp.data.layout import FeatureLayout
from gnwarp.files import atomic_write, remove_stale_temporaries
from gnwarp.graphs import GraphsTuple

__all__ = ["Split", "Dataset", "CheckedArray", "load", "check"]


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
        need = sum(nbytes(a) for a in self.static.values())
        need += sum(nbytes(getattr(sp, k)) for sp in self.splits.values() for k in ARRAYS)
        free = shutil.disk_usage(parent).free
        if compression is None and need > free:
            raise OSError(f"not enough disk space for {path}: the dataset needs {gib(need)} GiB, "
                          f"{parent} has {gib(free)} GiB free")
        remove_stale_temporaries(path)  # of saves to this path killed before their rename
        with atomic_write(path) as tmp:
            os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600))
            write_file(tmp, self.meta, self.static, self.splits, compression)
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(tmp, 0o666 & ~umask)  # private while written; give it a normal file's mode
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
        if not seq.size:
            raise ValueError("graphs(): no sequences asked for (seq and t are empty): a batch needs at least one graph")
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
            if not self._builders:  # a Dataset made in memory skipped load's checks: check its indices here
                U = int(sp.ctrl.shape[2]) if len(sp.ctrl.shape) == 3 else None
                problems = check_static(self.static, self.meta, U)
                if problems:
                    raise DatasetError(summary(f"dataset of '{self.meta.get('system')}'", problems))
            self._builders[key] = GraphBuilder(self.static, device=device, dtype=dtype)
        builder = self._builders[key]
        return builder(torch.as_tensor(inst[first][inv]), torch.as_tensor(b), torch.as_tensor(c))



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
            raise DatasetError(f"{self._gn_path}: {read_problem(self, self._gn_split, self._gn_key, e, args)}") \
                from None
        if isinstance(out, np.ndarray) and out.dtype.kind == "f":
            bad = bad_value(f"/{self._gn_split}/{self._gn_key}", self._gn_key, out, index_map(args, self.shape))
            problem = with_count(*bad, " in the part read") if bad else None
            rows = rows_of(args, self.shape) if problem is None and self._gn_key == "body" else None
            if rows is not None and self._gn_n_node is not None and out.ndim == 4 and out.shape[1:] == self.shape[1:]:
                problem = check_body_structure(self._gn_split, out, self._gn_n_node[rows], rows)
            if problem is not None:
                raise DatasetError(f"{self._gn_path}: {problem}")
        return out

    def __array__(self, dtype=None, copy=None):
        out = self[...] if self.size else np.zeros(self.shape, self.dtype)
        return out if dtype is None else out.astype(dtype, copy=False)



def _inspect(path: Path, f) -> tuple[dict, dict, list[str], list[str]]:
    """(meta, static, problems, arrays without checksums) of an open file; raises DatasetError for
    what makes the file unusable at all (other format, incomplete, missing groups)."""
    if f.attrs.get("format") != FORMAT:
        raise DatasetError(f"{path} is not a gnwarp dataset (format attribute: {f.attrs.get('format')!r})")
    if int(f.attrs.get("version", -1)) > VERSION:
        raise DatasetError(f"{path} has dataset version {f.attrs.get('version')}, newer than this gnwarp ({VERSION})")
    if not f.attrs.get("complete", False):
        raise DatasetError(f"{path} was not completely written")
    text = f.attrs["meta"]
    text = text.decode("utf-8", "replace") if isinstance(text, bytes) else str(text)
    digest = f.attrs.get("meta_sha256")   # written since the metadata had one (older files: none)
    if digest is not None and (digest.decode() if isinstance(digest, bytes) else str(digest)) != meta_digest(text):
        raise DatasetError(f"{path}: its metadata was changed or damaged (its SHA-256 checksum does not match)")
    try:
        meta = json.loads(text)
    except ValueError as e:
        raise DatasetError(f"{path}: its metadata is not JSON ({e})") from None
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
            raise DatasetError(f"{path}: {read_problem(d, '', k, e)}") from None
    for name in SPLITS:
        if name not in f:
            raise DatasetError(f"{path} lacks the split '{name}'")
        for k in ARRAYS:
            if k not in f[name] or not isinstance(f[name][k], h5py.Dataset):
                raise DatasetError(f"{path}: split '{name}' lacks the array '{k}'")
            if not f[name][k].fletcher32:
                unchecked.append(f"/{name}/{k}")
    ctrl = f["train"]["ctrl"]
    problems = check_meta(meta) + check_static(static, meta, int(ctrl.shape[2]) if ctrl.ndim == 3 else None)
    for name in SPLITS:
        problems += check_split_layout(name, {k: f[name][k] for k in ARRAYS}, static, meta)
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
    f = open_file(path)
    try:
        meta, static, problems, unchecked = _inspect(path, f)
        if problems:
            raise DatasetError(summary(str(path), problems))
        n_node = static["n_node"].astype(np.int64)
        splits = {}
        for name in SPLITS:
            g = f[name]
            nn = n_node[np.asarray(g["instance"][...], dtype=np.int64)]
            splits[name] = Split(*(CheckedArray(g[k], path, name, k, nn if k == "body" else None) for k in ARRAYS))
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
        f = open_file(path)
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
        n_read = sum(a.nbytes for a in static.values())
        for name in SPLITS:
            g = f[name]
            inst = np.asarray(g["instance"][...], dtype=np.int64) if structure_ok else None
            for k in ARRAYS:
                d = g[k]
                n_read += nbytes(d)
                lines += [f"error: {path}: {q}" for q in check_dataset_values(name, k, d, block_bytes,
                          n_node[inst] if structure_ok and k == "body" else None)]
    finally:
        f.close()
    if not any(x.startswith("error:") for x in lines):
        sizes = ", ".join(f"{k} {meta['splits'][k]}" for k in SPLITS) if isinstance(meta.get("splits"), dict) else ""
        lines.append(f"ok: {path}: gnwarp dataset of '{meta.get('system')}' ({sizes} sequences x "
                     f"{meta.get('num_steps')} steps, {static['nodes'].shape[1]} bodies, {static['nodes'].shape[0]} "
                     f"instance(s)); {n_read / 2**20:.3g} MiB read and validated"
                     f"{', every Fletcher-32 checksum verified' if not unchecked else ' (no checksums to verify)'}")
    return lines

