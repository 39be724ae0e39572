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
one has one per sequence.
"""
from __future__ import annotations

import json
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gnwarp.data.builder import GraphBuilder
from gnwarp.data.layout import FeatureLayout
from gnwarp.graphs import GraphsTuple
from gnwarp.state import DYN_NODE_SIZE

__all__ = ["FORMAT", "VERSION", "SPLITS", "DatasetError", "Split", "Dataset", "load"]

FORMAT, VERSION = "gnwarp-dataset", 1
SPLITS = ("train", "valid", "test")


class DatasetError(ValueError):
    """A dataset file is missing, corrupt, truncated or of another layout."""


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
            self._builders[key] = GraphBuilder(self.static, device=device, dtype=dtype)
        builder = self._builders[key]
        return builder(torch.as_tensor(inst[first][inv]), torch.as_tensor(b), torch.as_tensor(c))


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
