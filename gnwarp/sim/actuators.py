"""One record of a model's actuators: their control ranges, which are limited, and how MuJoCo
clamps controls; every reader of ``actuator_ctrlrange`` reads it from here.

A limited actuator (``ctrllimited``) has a control range ``[low, high]``; MuJoCo clamps its control
into it unless the model disables clamping (``<flag clampctrl="disable"/>``). An unlimited one
(MuJoCo's default range [0, 0], ``ctrllimited`` false) takes any control, so its range is
(-inf, inf), and random controls (excitation, random actions) are drawn in ``UNLIMITED_SAMPLE_RANGE``:

    >>> act = Actuators.from_model(system.model)     # or system.actuators
    >>> lo, hi = act.low, act.high                   # [U]: planners' box (+-inf where unlimited)
    >>> lo, hi = act.clamp_bounds()                  # [U]: what the simulator clamps controls to
    >>> act.sample_range()                           # [U, 2]: where random controls are drawn
"""
from __future__ import annotations

import dataclasses

import mujoco
import numpy as np

__all__ = ["Actuators", "UNLIMITED_SAMPLE_RANGE"]

# Random controls of an actuator without limits: a unit range around 0, the scale of a motor's
# default gear (1 N or N m per unit control); choose limits in the MJCF to excite it differently.
UNLIMITED_SAMPLE_RANGE = (-1.0, 1.0)


@dataclasses.dataclass(frozen=True, eq=False)
class Actuators:
    """The actuators of one model, as [U] arrays.

    ``low`` / ``high``: the control range of limited actuators, -inf / inf for unlimited ones
    (the box planners keep controls in). ``limited``: ``actuator_ctrllimited``. ``clamped``: the
    simulator clamps the control into the range (limited, and clamping not disabled).
    """

    low: np.ndarray
    high: np.ndarray
    limited: np.ndarray
    clamped: np.ndarray

    @classmethod
    def from_model(cls, model: mujoco.MjModel) -> "Actuators":
        """The record of a compiled ``mujoco.MjModel`` (its ranges as they are now)."""
        limited = np.asarray(model.actuator_ctrllimited).reshape(-1).astype(bool)
        cr = np.asarray(model.actuator_ctrlrange, dtype=np.float64).reshape(-1, 2)
        no_clamp = int(model.opt.disableflags) & int(mujoco.mjtDisableBit.mjDSBL_CLAMPCTRL)
        return cls(low=np.where(limited, cr[:, 0], -np.inf), high=np.where(limited, cr[:, 1], np.inf),
                   limited=limited, clamped=limited & (no_clamp == 0))

    @property
    def nu(self) -> int:
        return int(self.limited.shape[0])

    def clamp_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) [U] the simulator clamps controls to: the range where ``clamped``, else +-inf."""
        return np.where(self.clamped, self.low, -np.inf), np.where(self.clamped, self.high, np.inf)

    def sample_range(self) -> np.ndarray:
        """[U, 2] where random controls are drawn: the range of limited actuators,
        ``UNLIMITED_SAMPLE_RANGE`` for unlimited ones."""
        lo = np.where(self.limited, self.low, UNLIMITED_SAMPLE_RANGE[0])
        hi = np.where(self.limited, self.high, UNLIMITED_SAMPLE_RANGE[1])
        return np.stack([lo, hi], axis=1)

    def mid_half(self) -> tuple[np.ndarray, np.ndarray]:
        """(mid, half width) [U] of the range: (0, inf) for unlimited actuators."""
        with np.errstate(invalid="ignore"):  # unlimited ranges are +-inf: their sums are discarded
            mid = np.where(self.limited, 0.5 * (self.low + self.high), 0.0)
            half = np.where(self.limited, 0.5 * (self.high - self.low), np.inf)
        return mid, half

    def same_ranges(self, other: "Actuators") -> bool:
        """Whether ``other`` has the same actuators' limits and ranges."""
        return (self.nu == other.nu and np.array_equal(self.limited, other.limited)
                and np.array_equal(self.low, other.low) and np.array_equal(self.high, other.high))
