"""What a joint is, to every component: its limits and its unit's calibration.

Joint names on the data plane are the names in the composed assembly URDF
(``<slot>_<joint>``, e.g. ``limb1_joint3``), so a message names a joint unambiguously across
modules and a joint manager can refuse commands meant for another module.

Calibration maps raw (motor) joint space to calibrated (URDF) joint space::

    calibrated = direction * (raw - zero_offset)
    raw        = zero_offset + direction * calibrated

Velocities and efforts only change sign with ``direction``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class JointSpec:
    """A joint's static description in calibrated (URDF) space, SI units.

    Attributes:
        name: Assembly-unique joint name (``limb1_joint3``).
        type: ``revolute``, ``continuous`` or ``prismatic``.
        lower: Lower position limit (``-inf`` for continuous joints).
        upper: Upper position limit (``inf`` for continuous joints).
        max_velocity: Largest commanded speed magnitude (rad/s or m/s).
        max_effort: Largest commanded effort magnitude (N·m or N).
    """

    name: str
    type: str = "revolute"
    lower: float = -math.pi
    upper: float = math.pi
    max_velocity: float = 1.0
    max_effort: float = 10.0

    @property
    def bounded(self) -> bool:
        """Whether the joint has finite position limits."""
        return math.isfinite(self.lower) and math.isfinite(self.upper)


@dataclass(frozen=True)
class JointCalibration:
    """One physical unit's calibration of one joint."""

    zero_offset: float = 0.0
    direction: int = 1

    def __post_init__(self) -> None:
        if self.direction not in (1, -1):
            raise ValueError(f"direction must be 1 or -1, not {self.direction}")

    def to_calibrated(self, raw: float) -> float:
        """Raw (motor) position to calibrated (URDF) position."""
        return self.direction * (raw - self.zero_offset)

    def to_raw(self, calibrated: float) -> float:
        """Calibrated (URDF) position to raw (motor) position."""
        return self.zero_offset + self.direction * calibrated

    def rate_to_calibrated(self, raw_rate: float) -> float:
        """Raw velocity or effort to calibrated (sign only)."""
        return self.direction * raw_rate

    def rate_to_raw(self, calibrated_rate: float) -> float:
        """Calibrated velocity or effort to raw (sign only)."""
        return self.direction * calibrated_rate
