"""Every conversion between drive units (counts, velocity units, per-mille of rated torque)
and SI joint units, for one motor."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from components.motors.base import MotorError, MotorSpec


@dataclass(frozen=True)
class Conversion:
    """Every unit conversion of one motor: drive units on one side, raw joint SI on the other.

    Position units are encoder counts of the motor (``counts_per_rev`` per motor revolution,
    ``gear_ratio`` motor revolutions per joint revolution). Velocity units are counts/s unless
    ``velocity_units`` says ``rpm`` or ``0.1rpm`` (motor shaft). Torque and current are
    per-mille of the motor's rated torque (``rated_torque``, N·m at the motor); the joint sees
    it multiplied by the gear ratio. A linear joint driven through a rack and pinion or a
    screw (``meters_per_rad``: metres of travel per output radian) is in metres, m/s and
    newtons instead of radians, rad/s and N·m; the method names keep saying "rad".
    """

    counts_per_rad: float
    velocity_units_per_rad_s: float
    permille_per_nm: float

    @classmethod
    def from_spec(cls, spec: MotorSpec) -> Conversion:
        """Build from ``MotorSpec.params``.

        Raises:
            MotorError: If a parameter is missing its sense (non-positive, unknown unit).
        """
        params = spec.params
        counts_per_rev = _positive(spec, "counts_per_rev", params.get("counts_per_rev", 4096))
        gear_ratio = _positive(spec, "gear_ratio", params.get("gear_ratio", 1.0))
        rated_torque = _positive(spec, "rated_torque", params.get("rated_torque", 1.0))
        units = str(params.get("velocity_units", "counts/s"))
        # Output radians per joint unit: 1 for a revolute joint, 1/meters_per_rad for a
        # linear one (a finger), so its positions are metres as in the URDF.
        rad_per_unit = 1.0 / _positive(spec, "meters_per_rad", params.get("meters_per_rad", 1.0))
        counts_per_rad = counts_per_rev * gear_ratio / (2 * math.pi) * rad_per_unit
        motor_rpm_per_rad_s = gear_ratio * 60.0 / (2 * math.pi) * rad_per_unit
        per_rad_s = {
            "counts/s": counts_per_rad,
            "rpm": motor_rpm_per_rad_s,
            "0.1rpm": motor_rpm_per_rad_s * 10.0,
        }
        if units not in per_rad_s:
            raise MotorError(
                f"{spec.joint}: motor_params.velocity_units={units!r} is not one of "
                f"{', '.join(per_rad_s)}; fix the joint's motor_params in the module data"
            )
        per_nm = 1000.0 / (rated_torque * gear_ratio)
        return cls(counts_per_rad, per_rad_s[units], per_nm / rad_per_unit)

    def position(self, counts: int) -> float:
        """Position actual (counts) to joint radians."""
        return counts / self.counts_per_rad

    def position_counts(self, rad: float) -> int:
        """Joint radians to a target position in counts (clamped to INTEGER32)."""
        return _clamp_int(rad * self.counts_per_rad, -(2**31), 2**31 - 1)

    def velocity(self, units: int) -> float:
        """Velocity actual (drive velocity units) to joint rad/s."""
        return units / self.velocity_units_per_rad_s

    def velocity_units(self, rad_s: float) -> int:
        """Joint rad/s to drive velocity units (clamped to INTEGER32)."""
        return _clamp_int(rad_s * self.velocity_units_per_rad_s, -(2**31), 2**31 - 1)

    def acceleration_units(self, rad_s2: float) -> int:
        """Joint rad/s² to drive acceleration units (velocity units per second, UNSIGNED32)."""
        return _clamp_int(abs(rad_s2) * self.velocity_units_per_rad_s, 1, 2**32 - 1)

    def effort(self, permille: int) -> float:
        """Torque or current actual (per-mille of rated) to joint N·m."""
        return permille / self.permille_per_nm

    def effort_permille(self, nm: float) -> int:
        """A joint torque limit (N·m) to max torque per-mille (UNSIGNED16)."""
        return _clamp_int(abs(nm) * self.permille_per_nm, 0, 0xFFFF)


def _positive(spec: MotorSpec, name: str, value: Any) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        number = float("nan")
    if not number > 0:
        raise MotorError(
            f"{spec.joint}: motor_params.{name}={value!r} must be a positive number; "
            "fix the joint's motor_params in the module data"
        )
    return number


def _clamp_int(value: float, lower: int, upper: int) -> int:
    if not math.isfinite(value):
        return 0 if lower <= 0 <= upper else lower
    return max(lower, min(upper, round(value)))
