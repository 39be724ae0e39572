"""Random spline controls (C.1)."""
import numpy as np
import pytest

from gnwarp.sim.excitation import random_spline_controls


def test_controls_in_range_smooth_and_seeded():
    cr = np.array([[-1.0, 1.0], [0.0, 3.0], [-0.2, -0.1]])
    u = random_spline_controls(64, 100, cr, rng=3)
    assert u.shape == (64, 100, 3)
    assert np.all(u >= cr[:, 0]) and np.all(u <= cr[:, 1])
    # uses the range: not stuck at one value
    span = u.max(axis=(0, 1)) - u.min(axis=(0, 1))
    assert np.all(span > 0.8 * (cr[:, 1] - cr[:, 0]))
    # spline, not white noise: steps are much smaller than the spread
    steps = np.abs(np.diff(u, axis=1)).mean(axis=(0, 1))
    assert np.all(steps < 0.15 * u.std(axis=(0, 1)) * 3)
    np.testing.assert_array_equal(u, random_spline_controls(64, 100, cr, rng=3))
    assert not np.array_equal(u, random_spline_controls(64, 100, cr, rng=4))
    # sequences differ from each other
    assert np.abs(u[0] - u[1]).max() > 0.1


def test_controls_bad_input():
    with pytest.raises(ValueError, match="upper < lower"):
        random_spline_controls(2, 5, np.array([[1.0, -1.0]]))
    with pytest.raises(ValueError, match="num_steps"):
        random_spline_controls(2, 0, np.array([[-1.0, 1.0]]))


def test_kept_sequences_are_those_of_the_full_draw_and_the_stream_ends_alike():
    import numpy as np
    from gnwarp.sim.excitation import random_spline_controls
    r = np.array([[-1.0, 1.0], [0.0, 2.0]])
    full_rng, kept_rng = np.random.default_rng(4), np.random.default_rng(4)
    full = random_spline_controls(9, 15, r, full_rng)
    kept = random_spline_controls(9, 15, r, kept_rng, keep=np.arange(9) % 4 == 1)
    assert kept.shape == (2, 15, 2) and np.array_equal(kept, full[1::4])
    assert full_rng.random() == kept_rng.random()
