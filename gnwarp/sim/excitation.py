"""Random spline controls (paper, section C.1).

Control sequences are random values at spline knots, interpolated by a cubic (Catmull-Rom)
spline, and then sampled at randomly selected, sorted time steps of that dense curve, so a
sequence speeds up and slows down at random; values stay inside each actuator's control range.
Everything is vectorized over the batch and the actuators.
"""
from __future__ import annotations

import numpy as np

from gnwarp.sim.actuators import Actuators

__all__ = ["random_spline_controls", "control_range", "catmull_rom"]


def catmull_rom(knots: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Evaluate a uniform Catmull-Rom spline through ``knots`` [..., K] at times ``t`` [..., M] in [0, K-1]."""
    k = knots.shape[-1]
    i = np.clip(np.floor(t).astype(np.int64), 0, k - 2)
    s = t - i
    idx = np.stack([np.clip(i - 1, 0, k - 1), i, i + 1, np.clip(i + 2, 0, k - 1)], -1)
    p = np.take_along_axis(knots[..., None, :], idx, axis=-1)  # [..., M, 4]
    p0, p1, p2, p3 = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    s2, s3 = s * s, s * s * s
    return 0.5 * ((2 * p1) + (-p0 + p2) * s + (2 * p0 - 5 * p1 + 4 * p2 - p3) * s2
                  + (-p0 + 3 * p1 - 3 * p2 + p3) * s3)


def random_spline_controls(num_sequences: int, num_steps: int, ctrlrange: np.ndarray,
                           rng: np.random.Generator | int | None = None, knot_every: int = 10,
                           oversample: int = 3) -> np.ndarray:
    """Random control sequences, [num_sequences, num_steps, nu], inside ``ctrlrange`` [nu, 2].

    ``knot_every``: data steps between spline knots of the dense curve; ``oversample``: the dense
    curve is ``oversample`` times longer than the sequence, and ``num_steps`` sorted random time
    points of it are kept (the random time steps of C.1).
    """
    rng = np.random.default_rng(rng)
    ctrlrange = np.asarray(ctrlrange, dtype=np.float64).reshape(-1, 2)
    nu = ctrlrange.shape[0]
    if num_sequences < 1 or num_steps < 1:
        raise ValueError(f"need num_sequences >= 1 and num_steps >= 1, got {num_sequences}, {num_steps}")
    if nu == 0:
        return np.zeros((num_sequences, num_steps, 0))
    if np.any(ctrlrange[:, 1] < ctrlrange[:, 0]):
        raise ValueError(f"control range with upper < lower bound: {ctrlrange.tolist()}")
    dense = num_steps * oversample
    n_knots = max(2, int(np.ceil(dense / knot_every)) + 1)
    knots = rng.uniform(0.0, 1.0, size=(num_sequences, nu, n_knots))
    # random, sorted sample times over the dense curve (in knot units)
    times = np.sort(rng.uniform(0.0, n_knots - 1, size=(num_sequences, 1, num_steps)), axis=-1)
    u = np.clip(catmull_rom(knots, np.broadcast_to(times, (num_sequences, nu, num_steps))), 0.0, 1.0)
    lo, hi = ctrlrange[:, 0], ctrlrange[:, 1]
    u = lo[None, :, None] + u * (hi - lo)[None, :, None]
    return np.ascontiguousarray(np.transpose(u, (0, 2, 1)))


def control_range(model) -> np.ndarray:
    """[nu, 2] range excitation controls are drawn in for a MjModel: ``Actuators.sample_range``
    (the control range of limited actuators, ``UNLIMITED_SAMPLE_RANGE`` [-1, 1] for the others)."""
    return Actuators.from_model(model).sample_range()
