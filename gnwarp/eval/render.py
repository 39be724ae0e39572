"""Rollout videos rendered with MuJoCo's offscreen renderer (EGL or OSMesa on a headless machine).

Body poses (true or predicted) are written straight into the scene: each geom's world pose is
its body's pose composed with the geom's local pose, so predicted states that break the joints
show as they are. Rendering runs in a child process with ``MUJOCO_GL`` set before MuJoCo is
imported (MuJoCo picks its GL backend at import), which also keeps a GL failure from taking the
caller down; ``render_rollouts`` raises ``RenderUnavailable`` then, and ``gnwarp.eval.animate``
falls back to drawing the poses with matplotlib.

Frames are laid out with one row per rollout and one column per trajectory: true first, then each
prediction in the order given.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from gnwarp.sim.systems import from_mjcf, make
from gnwarp.state import POS, QUAT, geom_poses
from gnwarp.eval.video import check_video_path, write_video
from gnwarp.files import temporary_of

__all__ = ["RenderUnavailable", "render_rollouts"]


class RenderUnavailable(RuntimeError):
    """No working OpenGL context for MuJoCo's offscreen renderer on this machine."""


def _render_job(job: dict, arrays: dict) -> None:
    """In the child process: render every frame and write the animation."""
    import mujoco

    W, H = job["width"], job["height"]
    names = ["true"] + job["pred_names"]
    trajs = [arrays["true"]] + [arrays[f"pred{j}"] for j in range(len(job["pred_names"]))]
    K, T1 = trajs[0].shape[:2]
    rows = []
    for k in range(K):
        spec = job["systems"][k]
        s = from_mjcf(spec["mjcf"]) if spec.get("mjcf") else make(spec["name"], params=spec["params"])
        m = s.model
        d = mujoco.MjData(m)
        mujoco.mj_forward(m, d)
        movable = np.asarray(m.geom_bodyid) != 0
        cam = mujoco.MjvCamera()
        cam.type = mujoco.mjtCamera.mjCAMERA_FREE
        size = np.ptp(trajs[0][k, 0, 1:m.nbody, 0:3], axis=0).max() if m.nbody > 2 else 0.0
        cam.distance = 3.0 * max(0.5, float(size))
        # the built-in scenes have no lights of their own: brighten the head light
        m.vis.headlight.ambient[:] = 0.35
        m.vis.headlight.diffuse[:] = 0.75
        span = np.ptp(trajs[0][k, :, 1:m.nbody, 0:3].reshape(-1, 3), axis=0)
        # motion in a horizontal plane (swimmers) is watched from above, the rest from the side
        cam.azimuth, cam.elevation = (90.0, -80.0) if span[2] < 0.2 * max(span[0], span[1], 1e-9) else (90.0, -15.0)
        with mujoco.Renderer(m, H, W) as r:
            frames = np.zeros((len(job["frames"]), H, W * len(names), 3), dtype=np.uint8)
            for f, t in enumerate(job["frames"]):
                cam.lookat[:] = trajs[0][k, t, 1 if trajs[0].shape[2] > 1 else 0, 0:3]
                for j, tr in enumerate(trajs):
                    b = tr[k, t, :m.nbody]
                    if not np.all(np.isfinite(b)):
                        continue  # a diverged prediction stays black
                    xpos, xmat = geom_poses(m, b)
                    d.geom_xpos[movable] = xpos[movable]
                    d.geom_xmat[movable] = xmat[movable]
                    d.xpos[:] = b[:, POS]
                    d.xquat[:] = b[:, QUAT]
                    r.update_scene(d, cam)
                    frames[f, :, j * W:(j + 1) * W] = r.render()
        rows.append(frames)
    video = np.concatenate(rows, axis=1)
    write_video(job["path"], video, job["duration_ms"])


def render_rollouts(true: np.ndarray, preds: dict[str, np.ndarray], system_specs: list[dict], path, dt: float,
                    fps_max: float = 25.0, width: int = 240, height: int = 200, gl: str | None = None,
                    timeout: float = 600.0) -> Path:
    """Render rollouts to an animated GIF (APNG or WebP by suffix) with MuJoCo's renderer.

    ``true`` [K, H+1, B, 13], ``preds`` {name: [K, H+1, B, 13]}, ``system_specs`` one dict per
    rollout: {"name", "params"} of a built-in system or {"mjcf": path}. ``gl``: MuJoCo's GL backend
    ("egl", "osmesa"; default: $MUJOCO_GL or "egl"). Raises ``RenderUnavailable`` when no GL
    context can be made.
    """
    path = check_video_path(path)
    K, H1 = true.shape[:2]
    stride = max(1, int(round(1.0 / (fps_max * dt))))
    job = {"pred_names": list(preds), "systems": system_specs, "width": width, "height": height,
           "frames": list(range(0, H1, stride)), "duration_ms": int(round(1000 * stride * dt)), "path": str(path)}
    with tempfile.TemporaryDirectory() as tmp:
        np.savez(Path(tmp) / "arrays.npz", true=true, **{f"pred{j}": p for j, p in enumerate(preds.values())})
        (Path(tmp) / "job.json").write_text(json.dumps(job))
        env = {**os.environ, "MUJOCO_GL": gl or os.environ.get("MUJOCO_GL", "egl")}
        if env["MUJOCO_GL"] == "osmesa":
            env.setdefault("PYOPENGL_PLATFORM", "osmesa")
        elif env["MUJOCO_GL"] == "egl":
            env.setdefault("PYOPENGL_PLATFORM", "egl")
        try:
            # gnwarp.eval imports this module before runpy runs it as __main__: silence runpy's note of that
            quiet = "ignore:'gnwarp.eval.render' found in sys.modules:RuntimeWarning"
            child = subprocess.Popen([sys.executable, "-W", quiet, "-m", "gnwarp.eval.render", tmp], env=env,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            out, err = child.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            child.kill()
            child.communicate()
            temporary_of(path, pid=child.pid).unlink(missing_ok=True)   # the killed child's half-written video
            raise RenderUnavailable(f"MuJoCo rendering did not finish in {timeout:g} s") from None
    if child.returncode != 0 or not path.exists():
        last = (err or out).strip().splitlines()[-1:] or ["no output"]
        raise RenderUnavailable(f"MuJoCo offscreen rendering failed (MUJOCO_GL={env['MUJOCO_GL']}): {last[0]}")
    return path


if __name__ == "__main__":  # child process: python -m gnwarp.eval.render <job folder>
    folder = Path(sys.argv[1])
    with np.load(folder / "arrays.npz") as z:
        _render_job(json.loads((folder / "job.json").read_text()), {k: z[k] for k in z.files})
