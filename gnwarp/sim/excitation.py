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
    knots, t = np.asarray(knots), np.asarray(t)
    lead = np.broadcast_shapes(knots.shape[:-1], t.shape[:-1])
    # segment and offset at t's own shape (times shared by several curves computed once); four
    # gathers from the flat knots, one row per curve: faster than take_along_axis, same values
    i = np.clip(np.floor(t).astype(np.int64), 0, k - 2)
    s = t - i
    flat = np.broadcast_to(knots, lead + (k,)).reshape(-1)
    row = (np.arange(int(np.prod(lead, dtype=np.int64)), dtype=np.int64) * k).reshape(lead + (1,))
    p0 = flat[row + np.clip(i - 1, 0, k - 1)]
    p1 = flat[row + i]
    p2 = flat[row + i + 1]
    p3 = flat[row + np.clip(i + 2, 0, k - 1)]
    s2, s3 = s * s, s * s * s
    return 0.5 * ((2 * p1) + (-p0 + p2) * s + (2 * p0 - 5 * p1 + 4 * p2 - p3) * s2
                  + (-p0 + 3 * p1 - 3 * p2 + p3) * s3)


def random_spline_controls(num_sequences: int, num_steps: int, ctrlrange: np.ndarray,
                           rng: np.random.Generator | int | None = None, knot_every: int = 10,
                           oversample: int = 3, keep=None) -> np.ndarray:
    """Random control sequences, [num_sequences, num_steps, nu], inside ``ctrlrange`` [nu, 2].

    ``keep``: indices (or a boolean mask) of the sequences to return, [len(keep), num_steps, nu];
    every sequence's random numbers are drawn all the same, so ``rng`` ends where it would and
    each kept sequence is the one the full call returns (what a rank of a sharded generation uses).

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
    times = rng.uniform(0.0, n_knots - 1, size=(num_sequences, 1, num_steps))
    if keep is not None:
        knots, times = knots[keep], times[keep]
    times = np.sort(times, axis=-1)
    u = np.clip(catmull_rom(knots, times), 0.0, 1.0)   # times [S, 1, T]: shared by the actuators
    lo, hi = ctrlrange[:, 0], ctrlrange[:, 1]
    u = lo[None, :, None] + u * (hi - lo)[None, :, None]   # [kept sequences, nu, T]
    return np.ascontiguousarray(np.transpose(u, (0, 2, 1)))


def control_range(model) -> np.ndarray:
    """[nu, 2] range excitation controls are drawn in for a MjModel: ``Actuators.sample_range``
    (the control range of limited actuators, ``UNLIMITED_SAMPLE_RANGE`` [-1, 1] for the others)."""
    return Actuators.from_model(model).sample_range()
