"""Evaluation of forward models the way the paper measures them (section 4, Figs. 4-5, H.1).

Errors are squared differences of the body states, computed separately for position,
orientation (sign-invariant: min over q and -q), linear and angular velocity (each summed over
its features, averaged over movable bodies, steps and sequences), each divided by the error of the
constant-prediction baseline (the input state predicted unchanged), then averaged over the four
groups. Groups the constant baseline predicts exactly (e.g. a Pendulum body's position: its frame
sits on the hinge) have no such ratio and are left out of the average.

- one-step: predictions from the true state at every step of the test sequences;
- rollout at H steps: rollouts from the first state of each test sequence under its true
  controls, errors averaged over the H predicted steps (the baseline repeats the first state).

Outputs: ``evaluate`` (numbers), ``markdown_table``, ``plot_errors`` (bars, like Figs. 4-5),
``plot_state_traces`` (13 state variables of one body, like Fig. H.1), ``animate`` (GIF of true vs
predicted motion drawn with matplotlib from the body poses and the system's geoms; no OpenGL).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from gnwarp.convert import ANGVEL, DYN_NODE_NAMES, LINVEL, POS, QUAT

__all__ = ["GROUPS", "squared_errors", "rollout_predictions", "one_step_predictions", "normalized_errors",
           "rollout_error", "evaluate", "markdown_table", "plot_errors", "plot_state_traces", "animate"]

GROUPS = {"pos": POS, "quat": QUAT, "linvel": LINVEL, "angvel": ANGVEL}


def movable_mask(dataset, instance: np.ndarray) -> np.ndarray:
    """[S, B] bool: bodies that exist (not padding) and are not the world body."""
    n_node = np.asarray(dataset.static["n_node"])[np.asarray(instance)]
    B = np.asarray(dataset.static["nodes"]).shape[1]
    b = np.arange(B)[None]
    return (b >= 1) & (b < n_node[:, None])


def squared_errors(pred: np.ndarray, true: np.ndarray) -> dict[str, np.ndarray]:
    """{group: [...] squared error summed over the group's features} for states [..., 13]."""
    out = {}
    for g, sl in GROUPS.items():
        if g == "quat":
            a = ((pred[..., sl] - true[..., sl]) ** 2).sum(-1)
            b = ((pred[..., sl] + true[..., sl]) ** 2).sum(-1)
            out[g] = np.minimum(a, b)
        else:
            out[g] = ((pred[..., sl] - true[..., sl]) ** 2).sum(-1)
    return out


def _split_arrays(dataset, split: str, sequences: int | None):
    sp = dataset[split]
    n = len(sp) if sequences is None else min(int(sequences), len(sp))
    if n == 0:
        raise ValueError(f"the {split} split of {dataset.system!r} is empty")
    body = np.asarray(sp.body[:n], dtype=np.float32)
    ctrl = np.asarray(sp.ctrl[:n], dtype=np.float32)
    inst = np.asarray(sp.instance[:n])
    return body, ctrl, inst


@torch.no_grad()
def rollout_predictions(model, dataset, split: str = "test", horizon: int = 100, sequences: int | None = None,
                        batch_size: int = 1024) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(predicted [S, H+1, B, 13], true [S, H+1, B, 13], instance [S]) of H-step rollouts from the
    first state of the first ``sequences`` sequences of ``split`` under their true controls."""
    body, ctrl, inst = _split_arrays(dataset, split, sequences)
    H = min(int(horizon), ctrl.shape[1])
    builder = model.graph_builder(dataset)
    preds = []
    for a in range(0, body.shape[0], batch_size):
        b = slice(a, a + batch_size)
        r = model.rollout(torch.as_tensor(body[b, 0]), torch.as_tensor(ctrl[b, :H]), torch.as_tensor(inst[b]),
                          builder=builder)
        preds.append(r.float().cpu().numpy())
    return np.concatenate(preds), body[:, :H + 1], inst


@torch.no_grad()
def one_step_predictions(model, dataset, split: str = "test", sequences: int | None = None,
                         batch_size: int = 4096) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(predicted [S, T, B, 13] of x_{t+1} from the true x_t, true [S, T+1, B, 13], instance [S])."""
    body, ctrl, inst = _split_arrays(dataset, split, sequences)
    S, T = ctrl.shape[:2]
    x = body[:, :T].reshape(S * T, *body.shape[2:])
    u = ctrl.reshape(S * T, 1, -1)
    i = np.repeat(inst, T)
    builder = model.graph_builder(dataset)
    preds = []
    for a in range(0, S * T, batch_size):
        b = slice(a, a + batch_size)
        r = model.rollout(torch.as_tensor(x[b]), torch.as_tensor(u[b]), torch.as_tensor(i[b]), builder=builder)
        preds.append(r[:, 1].float().cpu().numpy())
    return np.concatenate(preds).reshape(S, T, *body.shape[2:]), body, inst


def normalized_errors(pred: np.ndarray, true: np.ndarray, const: np.ndarray, mask: np.ndarray) -> dict:
    """Errors of ``pred`` and of the constant prediction ``const`` against ``true`` (all [S, H, B, 13],
    ``mask`` [S, B]): {"pos"/"quat"/"linvel"/"angvel": ratio, "mean": mean ratio, "model": {group:
    mean squared error}, "constant": {...}}."""
    w = np.broadcast_to(mask[:, None], pred.shape[:3]).astype(np.float64)
    em, ec = squared_errors(pred, true), squared_errors(const, true)
    out = {"model": {}, "constant": {}}
    for g in GROUPS:
        out["model"][g] = float((em[g] * w).sum() / max(w.sum(), 1))
        out["constant"][g] = float((ec[g] * w).sum() / max(w.sum(), 1))
    scale = max(out["constant"].values())
    ratios = []
    for g in GROUPS:
        c = out["constant"][g]
        # a group the constant baseline gets right up to float32 rounding has no meaningful ratio
        r = out["model"][g] / c if c > 1e-8 * scale and c > 0 else math.nan
        out[g] = r
        if not math.isnan(r):
            ratios.append(r)
    out["mean"] = float(np.mean(ratios)) if ratios else math.nan
    return out


def rollout_error(model, dataset, split: str = "valid", horizon: int = 20, sequences: int | None = None) -> float:
    """Mean normalized rollout error over ``horizon`` steps (the validation metric of D.8)."""
    pred, true, inst = rollout_predictions(model, dataset, split, horizon, sequences)
    const = np.broadcast_to(true[:, :1], true.shape)
    r = normalized_errors(pred[:, 1:], true[:, 1:], const[:, 1:], movable_mask(dataset, inst))["mean"]
    return r if math.isfinite(r) else math.inf


def evaluate(model, dataset, split: str = "test", sequences: int | None = None,
             horizons: tuple[int, ...] = (20, 100), keep_predictions: bool = False) -> dict:
    """{"one_step": errors, "rollout_20": errors, "rollout_100": errors, ...} (see
    ``normalized_errors``) on the first ``sequences`` sequences of ``split``. Horizons longer than
    the sequences are cut to their length (the key keeps the asked horizon and "steps" says how
    many were used). ``keep_predictions``: also return the longest rollout under "predictions"."""
    was_training = model.training
    model.eval()
    try:
        out = {}
        pred, true, inst = one_step_predictions(model, dataset, split, sequences)
        mask = movable_mask(dataset, inst)
        out["one_step"] = normalized_errors(pred, true[:, 1:], true[:, :-1], mask)
        out["one_step"]["steps"] = 1
        H = max(horizons) if horizons else 0
        if H:
            pred, true, inst = rollout_predictions(model, dataset, split, H, sequences)
            const = np.broadcast_to(true[:, :1], true.shape)
            for h in horizons:
                k = min(h, pred.shape[1] - 1)
                out[f"rollout_{h}"] = normalized_errors(pred[:, 1:k + 1], true[:, 1:k + 1], const[:, 1:k + 1], mask)
                out[f"rollout_{h}"]["steps"] = k
            # stability: the rollout stayed finite
            out["finite"] = bool(np.isfinite(pred).all())
            if keep_predictions:
                out["predictions"] = {"pred": pred, "true": true, "instance": inst}
        out["sequences"] = int(mask.shape[0])
        return out
    finally:
        model.train(was_training)


# -- reporting --------------------------------------------------------------------------------

def _fmt(x: float) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "n/a"
    return f"{x:.3g}"


def markdown_table(results: dict[str, dict], system: str = "") -> str:
    """Markdown tables of normalized errors: ``results`` is {model name: ``evaluate`` output}; a
    "constant" row (1 by definition) is added. First the mean over groups per horizon, then the
    per-group ratios of each horizon."""
    keys = [k for k in next(iter(results.values())) if k == "one_step" or k.startswith("rollout_")]
    head = {k: ("one-step" if k == "one_step" else f"{k.split('_')[1]}-step rollout") for k in keys}
    lines = [f"Normalized error{f' on {system}' if system else ''} (model / constant-prediction baseline; "
             f"lower is better):", "", "| model | " + " | ".join(head[k] for k in keys) + " |",
             "|---|" + "---|" * len(keys)]
    for name, r in results.items():
        lines.append(f"| {name} | " + " | ".join(_fmt(r[k]["mean"]) for k in keys) + " |")
    lines.append("| constant | " + " | ".join("1" for _ in keys) + " |")
    lines += ["", "Per state group (position, orientation, linear and angular velocity):", "",
              "| model | horizon | pos | quat | linvel | angvel |", "|---|---|---|---|---|---|"]
    for name, r in results.items():
        for k in keys:
            lines.append(f"| {name} | {head[k]} | " + " | ".join(_fmt(r[k][g]) for g in GROUPS) + " |")
    return "\n".join(lines) + "\n"


def plot_errors(results: dict[str, dict], path, title: str = "") -> Path:
    """Bar chart of normalized errors per horizon, one bar per model plus the constant baseline
    (log scale, like the paper's Figs. 4-5)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    keys = [k for k in next(iter(results.values())) if k == "one_step" or k.startswith("rollout_")]
    names = list(results) + ["constant"]
    vals = np.array([[results[n][k]["mean"] if n != "constant" else 1.0 for k in keys] for n in names])
    fig, ax = plt.subplots(figsize=(1.6 + 1.6 * len(keys), 3.2))
    width = 0.8 / len(names)
    colors = ["tab:red", "tab:blue", "tab:green", "tab:purple", "tab:orange", "0.6"]
    for i, n in enumerate(names):
        c = "0.6" if n == "constant" else colors[i % (len(colors) - 1)]
        ax.bar(np.arange(len(keys)) + (i - (len(names) - 1) / 2) * width, vals[i], width, label=n, color=c)
    ax.set_xticks(np.arange(len(keys)))
    ax.set_xticklabels(["one-step" if k == "one_step" else f"{k.split('_')[1]}-step" for k in keys])
    ax.set_yscale("log")
    ax.set_ylabel("error / constant baseline")
    ax.set_title(title)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_state_traces(true: np.ndarray, preds: dict[str, np.ndarray], dt: float, path, title: str = "") -> Path:
    """The 13 state variables of one body along a rollout, true vs predicted (like Fig. H.1).
    ``true`` [H+1, 13], ``preds`` {name: [H+1, 13]}."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    t = np.arange(true.shape[0]) * dt
    fig, axes = plt.subplots(4, 4, figsize=(12, 8), sharex=True)
    styles = [("tab:red", "--"), ("tab:blue", ":"), ("tab:green", "-.")]
    for k, ax in enumerate(axes.flat):
        if k >= true.shape[1]:
            ax.axis("off")
            continue
        ax.plot(t, true[:, k], color="k", lw=1.5, label="true")
        for j, (name, p) in enumerate(preds.items()):
            c, ls = styles[j % len(styles)]
            ax.plot(t, p[:, k], color=c, ls=ls, lw=1.2, label=name)
        ax.set_title(DYN_NODE_NAMES[k], fontsize=9)
        ax.tick_params(labelsize=7)
    axes.flat[0].legend(fontsize=7)
    for ax in axes[-1]:
        ax.set_xlabel("time (s)", fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# -- animation ----------------------------------------------------------------------------------

def _rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors v [..., 3] by unit quaternions q [..., 4] (w, x, y, z)."""
    w, u = q[..., :1], q[..., 1:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def _geom_segments(system) -> list[tuple[int, np.ndarray, np.ndarray, float]]:
    """(body, local end a, local end b, radius) per drawable geom of a MuJoCo model's moving bodies:
    capsules and cylinders along their axis, boxes and ellipsoids along their longest axis, spheres
    as points."""
    import mujoco
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
        a = _rotate(quat, axis)
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
    from gnwarp import systems
    return systems.make(**_system_spec(dataset, instance))


def _world_segments(body: np.ndarray, segs, edges) -> np.ndarray:
    """[T, n_seg, 2, 3] world end points (and radius handled by caller) from states [T, B, 13]."""
    if segs:
        ids = np.array([s[0] for s in segs])
        a = np.stack([s[1] for s in segs])
        b = np.stack([s[2] for s in segs])
        p, q = body[:, ids, 0:3], body[:, ids, 3:7]
        q = q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), 1e-12)
        return np.stack([p + _rotate(q, np.broadcast_to(a, p.shape)), p + _rotate(q, np.broadcast_to(b, p.shape))], 2)
    snd, rcv = edges  # fallback: a stick figure along the graph's edges
    return np.stack([body[:, snd, 0:3], body[:, rcv, 0:3]], 2)


def animate(true: np.ndarray, preds: dict[str, np.ndarray], dataset, instances, path, dt: float | None = None,
            fps_max: float = 25.0, title: str = "", renderer: str = "matplotlib") -> Path:
    """GIF of true vs predicted motion for a few rollouts.

    ``true`` [K, H+1, B, 13], ``preds`` {name: [K, H+1, B, 13]}, ``instances`` [K] system instance
    of each rollout. ``renderer``:

    - "mujoco": MuJoCo's offscreen renderer (EGL/OSMesa, see ``gnwarp.render``): one row per
      rollout, columns true, then each prediction in order; raises ``RenderUnavailable`` without GL.
    - "matplotlib": bodies drawn from their poses with the system's capsules, boxes and spheres
      (a stick figure along the graph's edges when the system cannot be rebuilt), true in grey
      under the predictions, projected on the two world axes along which the motion spreads most.
    - "auto": "mujoco" where it works, else "matplotlib".
    """
    if renderer not in ("auto", "mujoco", "matplotlib"):
        raise ValueError(f"renderer must be 'auto', 'mujoco' or 'matplotlib', got {renderer!r}")
    if renderer in ("auto", "mujoco"):
        from gnwarp.render import RenderUnavailable, render_rollouts
        try:
            specs = [_system_spec(dataset, int(i)) for i in instances]
            return render_rollouts(true, preds, specs, path, dt or float(dataset.meta.get("dt", 0.02)), fps_max)
        except (RenderUnavailable, ValueError):
            if renderer == "mujoco":
                raise
    import imageio.v3 as iio
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
    for tw, pw, _ in panels:
        pts = np.concatenate([tw.reshape(-1, 3)] + [v.reshape(-1, 3) for v in pw.values()])[:, axes]
        pts = pts[np.isfinite(pts).all(1)]
        lo, hi = np.percentile(pts, 1, 0), np.percentile(pts, 99, 0)
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
        txt = ax.set_title("", fontsize=9)
        artists.append((lines, txt))
    handles = [plt.Line2D([], [], color="0.55", lw=5, label="true")]
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
    path = Path(path)
    iio.imwrite(path, np.stack(frames), duration=int(round(1000 * stride * dt)), loop=0)
    return path
