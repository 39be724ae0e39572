"""Rollout videos: MuJoCo's offscreen renderer and the matplotlib fallback."""
import numpy as np
import pytest

from gnwarp import data
from gnwarp import eval as ev
from gnwarp.eval.render import RenderUnavailable, render_rollouts
from gnwarp.state import geom_poses


@pytest.fixture(scope="module")
def cartpole():
    return data.generate("cartpole", (2, 1, 2), num_steps=12, seed=0, backend="mujoco", progress=False)


def test_geom_poses_match_mujoco_kinematics():
    import mujoco

    from gnwarp.sim.body_state import body_states
    from gnwarp.sim import systems
    s = systems.make("cheetah")
    d = mujoco.MjData(s.model)
    d.qpos[:] = np.random.default_rng(0).uniform(-0.5, 0.5, s.model.nq)
    mujoco.mj_forward(s.model, d)
    xpos, xmat = geom_poses(s.model, body_states(s.model, d))
    np.testing.assert_allclose(xpos, d.geom_xpos, atol=1e-9)
    np.testing.assert_allclose(xmat, d.geom_xmat, atol=1e-9)


def _render_or_skip(*a, **k):
    try:
        return render_rollouts(*a, **k)
    except RenderUnavailable as e:
        pytest.skip(f"no OpenGL for MuJoCo here: {e}")


def test_mujoco_video_shows_true_and_predicted(cartpole, tmp_path):
    import imageio.v3 as iio
    te = cartpole["test"]
    true = te.body
    pred = true.copy()
    pred[:, :, 2, 0] += 0.3  # the pole knocked sideways in the prediction
    spec = [{"name": "cartpole", "params": None}] * 2
    p = _render_or_skip(true, {"moved": pred, "same": true}, spec, tmp_path / "v.gif", cartpole.dt, width=96,
                        height=80)
    v = iio.imread(p)
    assert v.shape[1:] == (2 * 80, 3 * 96, 3)  # rows: rollouts; columns: true, moved, same
    col = lambda j: v[:, :80, j * 96:(j + 1) * 96].astype(float)  # noqa: E731
    assert col(0).max() > 50                      # something was drawn
    assert np.abs(col(0) - col(2)).max() < 1e-6   # an exact prediction looks exactly like the truth
    assert np.abs(col(0) - col(1)).mean() > 0.1   # a wrong one does not


def test_animate_falls_back_without_gl(cartpole, tmp_path, monkeypatch):
    monkeypatch.setenv("MUJOCO_GL", "no-such-backend")
    te = cartpole["test"]
    with pytest.raises(RenderUnavailable):
        ev.animate(te.body, {"GN": te.body}, cartpole, te.instance, tmp_path / "a.gif", renderer="mujoco")
    p = ev.animate(te.body, {"GN": te.body}, cartpole, te.instance, tmp_path / "b.gif", renderer="auto")
    assert p.exists() and p.stat().st_size > 0
    with pytest.raises(ValueError, match="renderer"):
        ev.animate(te.body, {}, cartpole, te.instance, tmp_path / "c.gif", renderer="povray")


def test_marks_are_drawn_where_they_are(cartpole, tmp_path):
    """A target per rollout: a red circle at its world point (matplotlib), in view; a bad shape or
    the MuJoCo renderer is refused."""
    import imageio.v3 as iio
    te = cartpole["test"]
    K = te.body.shape[0]
    at_cart = te.body[:, 0, 1, :3].astype(np.float64)
    far = at_cart + np.array([3.0, 0.0, 0.0])                 # beyond the motion: the view takes it in
    plain = iio.imread(ev.animate(te.body, {}, cartpole, te.instance, tmp_path / "a.gif", renderer="matplotlib"))
    marked = iio.imread(ev.animate(te.body, {}, cartpole, te.instance, tmp_path / "b.gif", renderer="auto",
                                   marks=far))
    assert plain.shape == marked.shape
    top = int(0.85 * plain.shape[1])                           # above the legend
    red = lambda v: ((v[:top, :, 0] > 150) & (v[:top, :, 1] < 120) & (v[:top, :, 2] < 120)).sum()  # noqa: E731
    assert red(marked[0]) > red(plain[0]) + 20                 # the circle, in the panel
    with pytest.raises(ValueError, match=r"marks must be \[K, 3\]"):
        ev.animate(te.body, {}, cartpole, te.instance, tmp_path / "c.gif", marks=np.zeros((K + 1, 3)))
    with pytest.raises(ValueError, match="marks must be finite"):
        ev.animate(te.body, {}, cartpole, te.instance, tmp_path / "e.gif", marks=far * np.nan)
    with pytest.raises(ValueError, match="matplotlib"):
        ev.animate(te.body, {}, cartpole, te.instance, tmp_path / "d.gif", renderer="mujoco", marks=at_cart)


def test_a_video_is_checked_first_and_written_whole(tmp_path, monkeypatch):
    """A path whose ending names no video format is refused before drawing and an existing file
    there is left as it was; a write that fails midway leaves the old video and no temporary."""
    import imageio.v3 as iio

    from gnwarp.eval.video import check_video_path, write_video
    from gnwarp.sim import systems
    pend = systems.make("pendulum")
    states = np.zeros((1, 3, pend.nbody, 13))
    states[..., 3] = 1.0   # unit quaternions
    data_file = tmp_path / "data.h5"
    data_file.write_bytes(b"precious")
    with pytest.raises(ValueError, match=r"\.h5 video.*\.gif"):
        ev.animate_system(states, pend, data_file, renderer="matplotlib")
    assert data_file.read_bytes() == b"precious"
    with pytest.raises(FileNotFoundError):
        check_video_path(tmp_path / "missing" / "v.gif")
    for suffix in (".gif", ".webp", ".png"):
        out = ev.animate_system(states, pend, tmp_path / f"v{suffix}", renderer="matplotlib")
        assert iio.imread(out, index=0).ndim == 3
    old = (tmp_path / "v.gif").read_bytes()

    def broken(path, *a, **k):
        open(path, "wb").write(b"half a video")
        raise OSError("disk full")
    monkeypatch.setattr(iio, "imwrite", broken)
    with pytest.raises(OSError, match="disk full"):
        write_video(tmp_path / "v.gif", np.zeros((2, 4, 4, 3), np.uint8), 40)
    assert (tmp_path / "v.gif").read_bytes() == old
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data.h5", "v.gif", "v.png", "v.webp"]
