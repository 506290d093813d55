"""One managed joint's state: its limits in calibrated space, latest feedback, last command."""

from __future__ import annotations

import math

from components.joint_manager.config import CommandFilter
from components.joints import JointCalibration, JointSpec
from components.messages import JointSample

# Command modes, per joint: what the last accepted command asked of the motor.
IDLE, POSITION, VELOCITY, EFFORT, HOLD = "idle", "position", "velocity", "effort", "hold"


class ManagedJoint:
    """Mutable per-joint state (slots: this is touched at every message)."""

    __slots__ = (
        "cal",
        "cmd_effort",
        "cmd_velocity",
        "effort",
        "filters",
        "hi",
        "last_clamp",
        "last_command",
        "last_refusal",
        "lo",
        "local",
        "mode",
        "note",
        "pin",
        "pin_note",
        "position",
        "position_seen",
        "pub_effort",
        "pub_position",
        "pub_velocity",
        "raw_position",
        "seen",
        "spec",
        "target_raw",
        "velocity",
    )

    def __init__(
        self, spec: JointSpec, local: str, cal: JointCalibration, margin: float, fraction: float
    ) -> None:
        self.spec = spec
        self.local = local
        self.cal = cal
        if spec.bounded:
            # Relative to the range: a fixed margin would eat a short joint's whole travel.
            margin = min(margin, fraction * (spec.upper - spec.lower))
            lo, hi = spec.lower + margin, spec.upper - margin
            if lo > hi:
                # A range narrower than two margins: the only safe command is its middle.
                lo = hi = 0.5 * (spec.lower + spec.upper)
        else:
            lo, hi = -math.inf, math.inf
        self.lo, self.hi = lo, hi
        # Latest feedback, calibrated (None until the motor interface reported it).
        self.position: float | None = None
        self.velocity: float | None = None
        self.effort: float | None = None
        self.raw_position: float | None = None
        self.seen: float | None = None
        # When the latest finite position came (velocity or effort alone do not refresh it).
        self.position_seen: float | None = None
        # What joint_read last carried, for change detection.
        self.pub_position: float | None = None
        self.pub_velocity: float | None = None
        self.pub_effort: float | None = None
        # Command side.
        self.mode = IDLE
        self.last_command = -math.inf
        self.target_raw: float | None = None
        self.cmd_velocity = 0.0
        # Effort of the latest effort (or velocity + effort) command, calibrated; 0 if none.
        self.cmd_effort = 0.0
        self.filters: list[CommandFilter] = []
        self.pin: float | None = None
        self.pin_note: str | None = None
        self.last_clamp = -math.inf
        self.last_refusal = -math.inf
        self.note = ""

    def clamp_position(self, position: float) -> float:
        return min(max(position, self.lo), self.hi)


def moved(value: float | None, published: float | None, threshold: float) -> bool:
    if value is None:
        return False
    return published is None or abs(value - published) > threshold


def finite(sample: JointSample) -> bool:
    return all(
        v is None or math.isfinite(v) for v in (sample.position, sample.velocity, sample.effort)
    )


def or_nan(value: float | None) -> float:
    return math.nan if value is None else float(value)


def fmt(value: float | None) -> str:
    return "" if value is None else f"{value:.6g}"
