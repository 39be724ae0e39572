"""How long planning takes: the first control step apart from the steady state, and the real-time
factor, from the per-step wall times ``run_episodes`` returns (``plan_seconds``).

The first control step carries one-off costs (the first state's warm-up, kernel loading, the
recording of a CUDA graph on the steps after it), so a mean over every step mixes two things a
user waits for differently: the first action, and every action after it. ``plan_timing`` keeps
them apart; the steady time is the median over the steps after the first ``STEADY_AFTER`` (a
captured planning iteration records on its first call by default, ``capture_warmup`` 0).

    >>> plan_timing(out["plan_seconds"], control_timestep(system))
    {'first_step_ms': 812.0, 'steady_ms': 14.1, 'real_time_factor': 1.42, 'steady_steps': 97, ...}
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["STEADY_AFTER", "plan_timing", "control_timestep"]

STEADY_AFTER = 3   # steps left out of the steady median: the first, and the steps that may still capture


def control_timestep(system) -> float:
    """Seconds between two control steps of ``system`` (a ``System``: its data step ``dt``, the
    physics stepping ``substeps`` times inside it)."""
    dt = getattr(system, "dt", None)
    if dt is None or not math.isfinite(float(dt)) or float(dt) <= 0:
        raise ValueError(f"{getattr(system, 'name', system)!r} has no positive control timestep (dt), got {dt!r}")
    return float(dt)


def plan_timing(plan_seconds, control_dt: float | None = None, after: int = STEADY_AFTER) -> dict:
    """Summary of per-step planning wall times ``plan_seconds`` [steps] (seconds).

    Returns {"first_step_ms": the first step, "steady_ms": the median of the steps after the
    first ``after`` (of the steps after the first when there are no more than ``after``; None for
    one step), "steady_after": how many leading steps that median leaves out, "steady_steps": how
    many it reads, "mean_ms": every step's mean, "steps", "control_dt_ms" and "real_time_factor"
    = control_dt / steady time (> 1: faster than real time; None without ``control_dt`` or a
    steady time)}."""
    s = np.asarray(plan_seconds, dtype=np.float64).reshape(-1)
    if s.size == 0:
        raise ValueError("plan_seconds holds no steps")
    if not np.isfinite(s).all() or (s < 0).any():
        raise ValueError(f"plan_seconds must be finite and >= 0, got {s.tolist()[:8]}")
    if isinstance(after, bool) or not isinstance(after, int) or after < 1:
        raise ValueError(f"after must be an integer >= 1 (the first step is never steady), got {after!r}")
    if control_dt is not None and not (math.isfinite(control_dt) and control_dt > 0):
        raise ValueError(f"control_dt must be a number of seconds > 0, got {control_dt!r}")
    skip = after if s.size > after else 1
    steady = s[skip:]
    steady_ms = 1e3 * float(np.median(steady)) if steady.size else None
    rtf = None
    if control_dt is not None and steady_ms is not None:
        rtf = math.inf if steady_ms == 0 else 1e3 * control_dt / steady_ms
    return {"first_step_ms": 1e3 * float(s[0]), "steady_ms": steady_ms, "steady_after": skip if steady.size else None,
            "steady_steps": int(steady.size), "mean_ms": 1e3 * float(s.mean()), "steps": int(s.size),
            "control_dt_ms": None if control_dt is None else 1e3 * control_dt, "real_time_factor": rtf}
