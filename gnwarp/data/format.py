"""The dataset file format: simulated sequences (paper, section C.2) stored as HDF5, and writing it.

``gnwarp.data.dataset`` holds the ``Dataset`` (``Dataset.save`` writes it through ``write_file``)
and reads files back (``load``, ``check``); ``gnwarp.data.checks`` validates their arrays.

File layout (HDF5, ``format = "gnwarp-dataset"``, ``version = 1``)::

    /                      attrs: format, version, meta (JSON: system, timesteps, seeds, layout, ...)
    /static/globals        [I, F_g]        kept static global features of each system instance
    /static/nodes          [I, B, F_v]     kept static node features (padded to B bodies)
    /static/edges          [I, E, F_e]     kept static edge features (padded to E edges)
    /static/senders        [I, E]          body index of each edge's sender (-1 = padding)
    /static/receivers      [I, E]
    /static/n_node, n_edge [I]
    /static/edge_ctrl      [I, E, K]       ctrl index driving each edge (-1 = none)
    /static/edge_ctrl_gain [I, E, K]       optional, only where an actuator drives a fixed tendon:
                                           each slot's control weight (the tendon's coefficient on
                                           the edge's joint, 1 for a joint actuator, 0 for none)
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
"""
from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np

__all__ = ["FORMAT", "VERSION", "SPLITS", "ARRAYS", "FLOATS", "STATIC_FLOAT", "STATIC_SHAPES", "SPLIT_SHAPES", "AXES",
           "DatasetError", "DatasetWarning", "nbytes", "gib", "write_array", "write_file", "open_file"]

FORMAT, VERSION = "gnwarp-dataset", 1
SPLITS = ("train", "valid", "test")

# what the arrays may hold: dtypes, static float arrays, shapes and the names of their axes
FLOATS = (np.dtype(np.float32), np.dtype(np.float64))
STATIC_FLOAT = ("globals", "nodes", "edges", "params")
STATIC_SHAPES = {"globals": "[I, F_g]", "nodes": "[I, B, F_v]", "edges": "[I, E, F_e]", "senders": "[I, E]",
                 "receivers": "[I, E]", "n_node": "[I]", "n_edge": "[I]", "edge_ctrl": "[I, E, K]",
                 "params": "[I, P]"}
ARRAYS = ("body", "ctrl", "qpos", "qvel", "instance")
SPLIT_SHAPES = {"body": "[S, T+1, B, 13]", "ctrl": "[S, T, U]", "qpos": "[S, T+1, nq]", "qvel": "[S, T+1, nv]",
                "instance": "[S]"}
AXES = {"body": ("sequence", "step", "body", None), "ctrl": ("sequence", "step", "actuator"),
        "qpos": ("sequence", "step", "coordinate"), "qvel": ("sequence", "step", "dof"),
        "instance": ("sequence",), "globals": ("instance", "feature"),
        "nodes": ("instance", "body", "feature"), "edges": ("instance", "edge", "feature"),
        "params": ("instance", "parameter")}


class DatasetError(ValueError):
    """A dataset file is missing, corrupt, truncated or of another layout, or holds invalid values."""


class DatasetWarning(UserWarning):
    """A dataset loads but cannot be fully verified (written without checksums)."""



def nbytes(a) -> int:
    shape, dtype = getattr(a, "shape", None), getattr(a, "dtype", None)
    if shape is None or dtype is None:
        return np.asarray(a).nbytes
    return int(np.prod(shape, dtype=np.float64)) * np.dtype(dtype).itemsize


def gib(n: float) -> str:
    return f"{n / 2**30:.3g}"


def write_array(group, name: str, a: np.ndarray, chunks, compression):
    """One array with a Fletcher-32 checksum (chunked: per sequence for split arrays)."""
    if a.ndim == 0:  # scalars cannot be chunked, so carry no checksum (the format has none)
        return group.create_dataset(name, data=a)
    if chunks is not None and np.prod(chunks, dtype=np.float64) * a.dtype.itemsize > 2**30:
        chunks = True  # HDF5 chunks stay under 4 GiB: let h5py choose
    return group.create_dataset(name, data=a, chunks=chunks if chunks is not None else True,
                                compression=compression, fletcher32=True)


def meta_digest(text: str) -> str:
    """The SHA-256 of a dataset's metadata text (the ``meta_sha256`` attribute beside it)."""
    import hashlib
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def write_file(path, meta: dict, static: dict, splits: dict, compression: str | None = None) -> None:
    """Write a dataset to the HDF5 file ``path`` in the layout above: ``meta`` (JSON), the
    ``static`` arrays, each split's ``ARRAYS`` (attributes of ``splits[name]``), every array with
    a Fletcher-32 checksum, split arrays chunked per sequence; ``complete`` set last."""
    with h5py.File(path, "w") as f:
        f.attrs["format"] = FORMAT
        f.attrs["version"] = VERSION
        text = json.dumps(meta)
        f.attrs["meta"] = text
        f.attrs["meta_sha256"] = meta_digest(text)   # the arrays have Fletcher-32; the metadata this
        g = f.create_group("static")
        for k, v in static.items():
            write_array(g, k, np.asarray(v[...]), None, None)
        for name, sp in splits.items():
            g = f.create_group(name)
            for k in ARRAYS:
                a = np.asarray(getattr(sp, k)[...])
                chunks = (1,) + a.shape[1:] if a.ndim > 1 and a.shape[0] > 0 else None
                write_array(g, k, a, chunks, compression)
        f.attrs["complete"] = True


def open_file(path: Path):
    if not path.exists():
        raise FileNotFoundError(f"no dataset at {path}")
    if path.is_dir():
        raise DatasetError(f"{path} is a folder, not a dataset file")
    try:
        return h5py.File(path, "r")
    except OSError as e:
        raise DatasetError(f"{path} is not a readable HDF5 dataset (corrupt or truncated?): {e}") from None
