"""Planning times: the first control step apart from the steady state, and the real-time factor."""
import math

import pytest

from gnwarp import systems
from gnwarp.control import control_timestep, plan_timing


def test_first_step_and_steady_median_apart():
    secs = [2.0, 0.5, 0.3, 0.010, 0.012, 0.011, 0.100]
    t = plan_timing(secs, 0.02)
    assert t["first_step_ms"] == pytest.approx(2000.0)
    assert t["steady_after"] == 3 and t["steady_steps"] == 4
    assert t["steady_ms"] == pytest.approx(11.5)             # median of 10, 12, 11, 100 ms
    assert t["real_time_factor"] == pytest.approx(20.0 / 11.5) and t["control_dt_ms"] == pytest.approx(20.0)
    assert t["mean_ms"] == pytest.approx(1e3 * sum(secs) / len(secs)) and t["steps"] == 7


def test_short_runs_and_bad_input():
    t = plan_timing([1.0, 0.2, 0.4], 0.05)                  # no more than 3 steps: those after the first
    assert t["steady_after"] == 1 and t["steady_ms"] == pytest.approx(300.0)
    assert t["real_time_factor"] == pytest.approx(50.0 / 300.0)
    one = plan_timing([0.5], 0.05)
    assert one["steady_ms"] is None and one["real_time_factor"] is None and one["first_step_ms"] == 500.0
    assert plan_timing([1.0, 0.0], 0.05)["real_time_factor"] == math.inf
    assert plan_timing([1.0, 0.1])["real_time_factor"] is None
    with pytest.raises(ValueError, match="no steps"):
        plan_timing([])
    with pytest.raises(ValueError, match="finite"):
        plan_timing([1.0, float("nan")])
    with pytest.raises(ValueError, match="control_dt"):
        plan_timing([1.0], 0.0)


def test_control_timestep_is_the_data_step():
    pend = systems.make("pendulum")
    assert control_timestep(pend) == pytest.approx(pend.dt) == pytest.approx(pend.timestep * pend.substeps)
