"""Animations of true vs predicted motion (GIF): MuJoCo's renderer where it works
(``gnwarp.eval.render``), else bodies drawn with matplotlib from their poses and the system's
geoms (no OpenGL needed)."""
from __future__ import annotations

import types
from pathlib import Path

import mujoco
import numpy as np

from gnwarp.eval.render import RenderUnavailable, render_rollouts
from gnwarp.eval.video import check_video_path, write_video
from gnwarp.sim.systems import make
from gnwarp.state import POS, body_points, quat_rotate

__all__ = ["animate", "animate_system"]


def _geom_segments(system) -> list[tuple[int, np.ndarray, np.ndarray, float]]:
    """(body, local end a, local end b, radius) per drawable geom of a MuJoCo model's moving bodies:
    capsules and cylinders along their axis, boxes and ellipsoids along their longest axis, spheres
    as points."""
    m = system.model
    T = mujoco.mjtGeom
    segs = []
    for g in range(m.ngeom):
        b = int(m.geom_bodyid[g])
        if b == 0:
            continue
        t, size = int(m.geom_type[g]), np.asarray(m.geom_size[g], dtype=np.float64)
        pos, quat = np.asarray(m.geom_pos[g], dtype=np.float64), np.asarray(m.geom_quat[g], dtype=np.float64)
        if t in (T.mjGEOM_CAPSULE, T.mjGEOM_CYLINDER):
            axis, r = np.array([0.0, 0.0, size[1]]), size[0]
        elif t in (T.mjGEOM_BOX, T.mjGEOM_ELLIPSOID):
            k = int(np.argmax(size))
            axis = np.zeros(3)
            axis[k] = size[k]
            r = float(np.sort(size)[1])
        elif t == T.mjGEOM_SPHERE:
            axis, r = np.zeros(3), size[0]
        else:
            continue
        a = quat_rotate(quat, axis)
        segs.append((b, pos - a, pos + a, float(r)))
    return segs


def _system_spec(dataset, instance: int) -> dict:
    """{"name", "params"} of a dataset's system instance (rebuilt with ``systems.make``)."""
    params = None
    if dataset.meta.get("parameterized"):
        names = dataset.meta.get("param_names", [])
        vals = np.asarray(dataset.static["params"])[instance]
        params = {n: float(v) for n, v in zip(names, vals) if np.isfinite(v)}
    return {"name": dataset.meta["system"], "params": params}


def _system_of(dataset, instance: int):
    return make(**_system_spec(dataset, instance))


def _world_segments(body: np.ndarray, segs, edges) -> np.ndarray:
    """[T, n_seg, 2, 3] world end points (and radius handled by caller) from states [T, B, 13]."""
    if segs:
        ids = np.array([s[0] for s in segs])
        a = np.stack([s[1] for s in segs])
        b = np.stack([s[2] for s in segs])
        return np.stack([body_points(body, ids, a), body_points(body, ids, b)], 2)
    snd, rcv = edges  # fallback: a stick figure along the graph's edges
    return np.stack([body[:, snd, POS], body[:, rcv, POS]], 2)


def animate(true: np.ndarray, preds: dict[str, np.ndarray], dataset, instances, path, dt: float | None = None,
            fps_max: float = 25.0, title: str = "", renderer: str = "matplotlib", marks=None) -> Path:
    """GIF of true vs predicted motion for a few rollouts.

    ``true`` [K, H+1, B, 13], ``preds`` {name: [K, H+1, B, 13]}, ``instances`` [K] system instance
    of each rollout. ``marks`` [K, 3] (or None): a fixed world point per rollout, such as a task's
    target, drawn as a red circle; only "matplotlib" draws them, so "auto" picks it where marks
    are given. ``renderer``:

    - "mujoco": MuJoCo's offscreen renderer (EGL/OSMesa, see ``gnwarp.eval.render``): one row per
      rollout, columns true, then each prediction in order; raises ``RenderUnavailable`` without GL.
    - "matplotlib": bodies drawn from their poses with the system's capsules, boxes and spheres
      (a stick figure along the graph's edges when the system cannot be rebuilt), true in grey
      under the predictions, projected on the two world axes along which the motion spreads most.
    - "auto": "mujoco" where it works, else "matplotlib".
    """
    if renderer not in ("auto", "mujoco", "matplotlib"):
        raise ValueError(f"renderer must be 'auto', 'mujoco' or 'matplotlib', got {renderer!r}")
    path = check_video_path(path)   # a format it can write, a writable place: before drawing anything
    if marks is not None:
        marks = np.asarray(marks, dtype=np.float64)
        if marks.shape != (true.shape[0], 3):
            raise ValueError(f"marks must be [K, 3] = [{true.shape[0]}, 3] world points, got {list(marks.shape)}")
        if not np.isfinite(marks).all():
            raise ValueError("marks must be finite world points (a NaN or Inf is in them)")
        if renderer == "mujoco":
            raise ValueError("marks are drawn by renderer 'matplotlib' only")
        renderer = "matplotlib"
    if renderer in ("auto", "mujoco"):
        try:
            specs = [_system_spec(dataset, int(i)) for i in instances]
            return render_rollouts(true, preds, specs, path, dt or float(dataset.meta.get("dt", 0.02)), fps_max)
        except (RenderUnavailable, ValueError):
            if renderer == "mujoco":
                raise
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    K, H1 = true.shape[:2]
    dt = dt or float(dataset.meta.get("dt", 0.02))
    panels = []
    for k in range(K):
        inst = int(instances[k])
        n_node = int(np.asarray(dataset.static["n_node"])[inst])
        try:
            sys_ = _system_of(dataset, inst)
            segs = _geom_segments(sys_)
            radius = np.array([s[3] for s in segs])
            edges = None
        except Exception:  # noqa: BLE001 - a user MJCF we cannot rebuild: draw the graph instead
            segs, radius = [], None
            ne = int(np.asarray(dataset.static["n_edge"])[inst])
            st = dataset.static
            edges = (np.asarray(st["senders"])[inst, :ne], np.asarray(st["receivers"])[inst, :ne])
        tw = _world_segments(true[k, :, :n_node], segs, edges)
        pw = {n: _world_segments(p[k, :, :n_node], segs, edges) for n, p in preds.items()}
        panels.append((tw, pw, radius))

    # the two axes along which the true motion spreads most (in x, y, z order)
    allpts = np.concatenate([tw.reshape(-1, 3) for tw, _, _ in panels])
    axes = np.sort(np.argsort(allpts.std(0))[-2:])
    labels = "xyz"

    # one scale for all panels, each centred on its own motion
    spans = []
    for k, (tw, pw, _) in enumerate(panels):
        extra = [marks[k:k + 1]] if marks is not None else []
        pts = np.concatenate([tw.reshape(-1, 3)] + [v.reshape(-1, 3) for v in pw.values()] + extra)[:, axes]
        pts = pts[np.isfinite(pts).all(1)]
        lo, hi = np.percentile(pts, 1, 0), np.percentile(pts, 99, 0)
        if extra:   # the mark in view, whatever the percentiles leave out
            lo, hi = np.minimum(lo, extra[0][0, axes]), np.maximum(hi, extra[0][0, axes])
        spans.append(((lo + hi) / 2, (hi - lo).max() / 2))
    half = max(max(h for _, h in spans) * 1.15, 0.3)

    fig, axs = plt.subplots(1, K, figsize=(3.2 * K, 3.7), squeeze=False)
    colors = ["tab:red", "tab:blue", "tab:green"]
    dashes = ["-", "--", ":"]
    artists = []
    for k, (tw, pw, radius) in enumerate(panels):
        ax = axs[0, k]
        c = spans[k][0]
        ax.set_xlim(c[0] - half, c[0] + half)
        ax.set_ylim(c[1] - half, c[1] + half)
        ax.set_aspect("equal")
        ax.set_xlabel(labels[axes[0]])
        ax.set_ylabel(labels[axes[1]])
        pts_per_unit = 3.2 * 72 * 0.7 / (2 * half)
        n_seg = tw.shape[1]
        lw = (2 * radius * pts_per_unit).clip(2.0, 14) if radius is not None else np.full(n_seg, 3.0)
        lines = {"true": [ax.plot([], [], color="0.55", lw=lw[s], solid_capstyle="round")[0]
                          for s in range(n_seg)]}
        for j, name in enumerate(pw):
            lines[name] = [ax.plot([], [], color=colors[j % 3], lw=1.6, ls=dashes[j % 3])[0] for s in range(n_seg)]
        if marks is not None:
            ax.plot(marks[k, axes[0]], marks[k, axes[1]], "o", ms=9, mfc="none", mec="tab:red", mew=2)
        txt = ax.set_title("", fontsize=9)
        artists.append((lines, txt))
    handles = [plt.Line2D([], [], color="0.55", lw=5, label="true")]
    if marks is not None:
        handles.append(plt.Line2D([], [], ls="", marker="o", mfc="none", mec="tab:red", mew=2, label="target"))
    handles += [plt.Line2D([], [], color=colors[j % 3], lw=1.6, ls=dashes[j % 3], label=n)
                for j, n in enumerate(preds)]
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8, frameon=False)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0.09, 1, 0.95))

    stride = max(1, int(round(1.0 / (fps_max * dt))))
    frames = []
    for t in range(0, H1, stride):
        for (tw, pw, _), (lines, txt) in zip(panels, artists):
            for name, segs_w in [("true", tw)] + list(pw.items()):
                for s, ln in enumerate(lines[name]):
                    ln.set_data(segs_w[t, s, :, axes[0]], segs_w[t, s, :, axes[1]])
            txt.set_text(f"t = {t * dt:.2f} s (step {t})")
        fig.canvas.draw()
        frames.append(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())
    plt.close(fig)
    return write_video(path, np.stack(frames), int(round(1000 * stride * dt)))


def animate_system(states: np.ndarray, system, path, title: str = "", renderer: str = "auto",
                   fps_max: float = 25.0, marks=None) -> Path:
    """``animate`` for episodes of one built-in system (``gnwarp.sim.systems.System``, unparameterized):
    ``states`` [K, T+1, B, 13] body states (the true motion, no prediction) at ``system.dt``;
    ``marks`` [K, 3]: a world point per episode (its target), as ``animate`` draws them."""
    states = np.asarray(states)
    if states.ndim != 4 or states.shape[2:] != (system.nbody, 13):
        raise ValueError(f"states must be [K, T+1, {system.nbody}, 13] for {system.name}, got {states.shape}")
    k = states.shape[0]
    shim = types.SimpleNamespace(meta={"system": system.name, "parameterized": False, "dt": system.dt},
                                 static={"n_node": np.full(k, system.nbody)})
    return animate(states, {}, shim, np.zeros(k, dtype=np.int64), path, dt=system.dt, fps_max=fps_max,
                   title=title, renderer=renderer, marks=marks)
