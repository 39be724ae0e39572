"""Validation of a dataset's arrays (``gnwarp.data.format``'s layout), vectorized.

On ``load``: the dtypes and shapes, the static arrays (finite features, senders and receivers
in [0, n_node) of their graph, -1 beyond n_edge, edge_ctrl in [-1, U), counts within the padded
sizes); whenever a split's arrays are read (``CheckedArray``): states, controls, qpos and qvel
finite with ``|x| <= MAX_ABS``, real bodies with unit quaternions and padded bodies zero. Each
check returns what is wrong as sentences naming the array and the first bad index (a list of
problems, or None); the readers of ``gnwarp.data.dataset`` raise ``DatasetError`` with them or
list them (``check``).
"""
from __future__ import annotations

import h5py
import numpy as np

from gnwarp.data.format import ARRAYS, AXES, FLOATS, SPLIT_SHAPES, STATIC_FLOAT, STATIC_SHAPES, nbytes
from gnwarp.state import DYN_NODE_NAMES, DYN_NODE_SIZE

__all__ = ["MAX_ABS", "STATIC_MAX_ABS", "read_problem", "rows_of", "index_map", "bad_value", "with_count",
           "check_body_structure", "summary", "check_static", "check_split_layout", "check_dataset_values"]

# Bounds of stored values: a state, control, qpos or qvel beyond MAX_ABS (1e6 m, m/s, rad/s, N...)
# is no simulation of the paper's systems but corruption or divergence (generation refuses the same);
# static features (masses, inertias, gains ...) may be larger, up to STATIC_MAX_ABS.
MAX_ABS = 1e6
STATIC_MAX_ABS = 1e12
_QUAT_TOL = 2e-3  # | |q|^2 - 1 | of a stored (float32) body orientation


def read_problem(dset, split, key, err, args=Ellipsis) -> str:
    """What a failed read of /split/key means, with the first sequence that cannot be read."""
    where = f"/{split}/{key}" if split else f"/static/{key}"
    bad = None
    if dset.ndim >= 1 and dset.shape[0]:
        rows = rows_of(args, dset.shape)
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


def rows_of(args, shape):
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


def index_map(args, shape):
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
    axes = AXES.get(key)
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


def bad_value(where: str, key: str, a: np.ndarray, to_stored=None, bound: float = MAX_ABS):
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


def with_count(msg: str, n: int, of: str = "") -> str:
    return msg if n <= 1 else f"{msg} ({n} bad entries{of})"


def check_body_structure(split, body: np.ndarray, n_node_rows: np.ndarray, rows: np.ndarray):
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


def summary(where, problems: list[str]) -> str:
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


def check_meta(meta: dict) -> list[str]:
    """Problems of the metadata values every reader relies on: the system's name, the data
    timestep ``dt`` (finite, > 0) and the steps per sequence; [] when valid."""
    import math
    p = []
    if not isinstance(meta.get("system"), str) or not meta.get("system"):
        p.append(f"metadata 'system' must be the system's name, got {meta.get('system')!r}")
    dt = meta.get("dt")
    if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not math.isfinite(dt) or dt <= 0:
        p.append(f"metadata 'dt' must be the data timestep in seconds (finite, > 0), got {dt!r}")
    steps = meta.get("num_steps")
    if steps is not None and (isinstance(steps, bool) or not isinstance(steps, int) or steps < 1):
        p.append(f"metadata 'num_steps' must be an integer >= 1, got {steps!r}")
    return p


def check_static(static: dict, meta: dict, n_ctrl: int | None) -> list[str]:
    """Problems of the static arrays (dtypes, shapes, values, index ranges, counts): [] when valid.
    ``n_ctrl``: the controls per sequence (U), or None when unknown."""
    p: list[str] = []
    missing = [k for k in STATIC_SHAPES if k not in static]
    if missing:
        return [f"/static lacks the array{'s' if len(missing) > 1 else ''} {', '.join(missing)}"]
    st = {k: static[k] for k in STATIC_SHAPES}
    for k, a in st.items():
        nd = STATIC_SHAPES[k].count(",") + 1
        if a.ndim != nd:
            p.append(f"/static/{k} has shape {tuple(a.shape)}, expected {STATIC_SHAPES[k]}")
        if k in STATIC_FLOAT and a.dtype not in FLOATS:
            p.append(f"/static/{k} has dtype {a.dtype}, expected float32 (float64 accepted)")
        elif k not in STATIC_FLOAT and a.dtype.kind not in "iu":
            p.append(f"/static/{k} has dtype {a.dtype}, expected int64 (an integer type)")
    if p:
        return p
    I, B, E, K = st["nodes"].shape[0], st["nodes"].shape[1], st["edges"].shape[1], st["edge_ctrl"].shape[2]
    want = {"globals": (I, None), "nodes": (I, B, None), "edges": (I, E, None), "senders": (I, E),
            "receivers": (I, E), "n_node": (I,), "n_edge": (I,), "edge_ctrl": (I, E, K),
            "params": (I, len(meta.get("param_names", [])) if "param_names" in meta else None)}
    for k, shape in want.items():
        if any(w is not None and w != s for w, s in zip(shape, st[k].shape)):
            p.append(f"/static/{k} has shape {tuple(st[k].shape)}, expected {STATIC_SHAPES[k]} = "
                     f"{tuple('*' if w is None else w for w in shape)}")
    if "edge_ctrl_gain" in static:   # optional: the control weights of actuators on tendons
        gain = static["edge_ctrl_gain"]
        if gain.dtype not in FLOATS or tuple(gain.shape) != (I, E, K):
            p.append(f"/static/edge_ctrl_gain has shape {tuple(gain.shape)} and dtype {gain.dtype}, expected "
                     f"[I, E, K] = {(I, E, K)} float32 (the shape of /static/edge_ctrl)")
        elif not np.all(np.abs(gain) <= STATIC_MAX_ABS):
            i, e, s = _first(~(np.abs(gain) <= STATIC_MAX_ABS))
            p.append(f"/static/edge_ctrl_gain: instance {i}, edge {e}, slot {s} holds {float(gain[i, e, s])!r}, not a "
                     f"finite control weight")
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
        bad = bad_value(f"/static/{k}", k, st[k], None, STATIC_MAX_ABS)
        if bad:
            p.append(with_count(*bad))
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


def check_split_layout(name: str, arrays: dict, static: dict, meta: dict) -> list[str]:
    """Problems of one split's dtypes and shapes, and of its instance indices (read here)."""
    p: list[str] = []
    for k in ARRAYS:
        a = arrays[k]
        nd = SPLIT_SHAPES[k].count(",") + 1
        if k == "instance" and a.dtype.kind not in "iu":
            p.append(f"/{name}/{k} has dtype {a.dtype}, expected int64 (an integer type)")
        elif k != "instance" and a.dtype not in FLOATS:
            p.append(f"/{name}/{k} has dtype {a.dtype}, expected float32 (float64 accepted)")
        if len(a.shape) != nd:
            p.append(f"/{name}/{k} has shape {tuple(a.shape)}, expected {SPLIT_SHAPES[k]}")
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
            p.append(f"/{name}/{k} has shape {got}, expected {SPLIT_SHAPES[k]} = "
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



def check_dataset_values(split: str, key: str, d, block_bytes: int, n_node_of_seq) -> list[str]:
    """Read /split/key in blocks of sequences: its read errors, first bad value and (``body``) first
    state that does not fit its instance's bodies."""
    if d.ndim == 0 or d.shape[0] == 0:
        return []
    step = max(1, block_bytes // max(1, nbytes(d) // d.shape[0]))
    out, first, n_bad, structure = [], None, 0, None
    for s0 in range(0, d.shape[0], step):
        s1 = min(d.shape[0], s0 + step)
        try:
            a = h5py.Dataset.__getitem__(d, slice(s0, s1))
        except OSError as e:
            out.append(read_problem(d, split, key, e, slice(s0, s1)))
            continue
        if a.dtype.kind != "f":
            continue
        bad = bad_value(f"/{split}/{key}", key, a, lambda pos, s0=s0: (pos[0] + s0,) + pos[1:])
        if bad:
            first = first or bad[0]
            n_bad += bad[1]
        elif key == "body" and n_node_of_seq is not None and structure is None:
            rows = np.arange(s0, s1)
            structure = check_body_structure(split, a, n_node_of_seq[rows], rows)
    if first:
        out.append(with_count(first, n_bad))
    if structure:
        out.append(structure)
    return out

