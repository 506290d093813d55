"""What the steering operator does with a Twist before the wheels see it. Pure, time passed in.

* :class:`TwistGate`: a ``cmd_vel`` Twist in, a planar body velocity out, or nothing. NaN and
  infinity are refused; a speed above the maximum is clamped (the direction kept); each is
  counted, and nothing a sender puts in a Twist raises.
* :class:`Ramp`: the body velocity the wheels are given, moving toward the target at bounded
  accelerations (the linear part along a straight line, so its direction holds).
* :func:`crab_direction`: where the wheel modules must face for a velocity, if anywhere.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

#: A planar body velocity: forward (m/s), sideways (m/s, left), turn (rad/s, counter-clockwise).
Velocity = tuple[float, float, float]
STILL: Velocity = (0.0, 0.0, 0.0)
#: Below this a speed is none (m/s or rad/s).
EPSILON = 1e-6


@dataclass
class TwistGate:
    """Checks and clamps each Twist.

    Args:
        max_speed: Largest linear speed (m/s) over the ground, forward and sideways together.
        max_turn: Largest turn rate (rad/s).

    Attributes:
        taken: Twists passed on (clamped or not).
        refused: Twists refused (a NaN or infinite component it uses or ignores).
        clamped: Twists passed on slower than asked.
        ignored: Twists asking for a motion the ground plane has not (linear z, roll,
            pitch): passed on without that part.
    """

    max_speed: float
    max_turn: float
    taken: int = 0
    refused: int = 0
    clamped: int = 0
    ignored: int = 0
    last_refusal: str = field(default="", repr=False)

    def __post_init__(self) -> None:
        for name in ("max_speed", "max_turn"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, not {value!r}")

    def take(self, twist: Any) -> Velocity | None:
        """The velocity a Twist asks for, clamped; None when it is refused."""
        try:
            values = [
                float(twist.linear.x),
                float(twist.linear.y),
                float(twist.linear.z),
                float(twist.angular.x),
                float(twist.angular.y),
                float(twist.angular.z),
            ]
        except (AttributeError, TypeError, ValueError) as exc:
            self.refused += 1
            self.last_refusal = f"not a Twist: {exc}"
            return None
        if not all(math.isfinite(v) for v in values):
            self.refused += 1
            self.last_refusal = f"not finite: {values}"
            return None
        vx, vy, vz, wx, wy, wz = values
        if vz or wx or wy:
            self.ignored += 1
        speed = math.hypot(vx, vy)
        clamped = False
        if speed > self.max_speed:
            vx, vy = vx * self.max_speed / speed, vy * self.max_speed / speed
            clamped = True
        if abs(wz) > self.max_turn:
            wz = math.copysign(self.max_turn, wz)
            clamped = True
        self.clamped += clamped
        self.taken += 1
        return (vx, vy, wz)


@dataclass
class Ramp:
    """The commanded body velocity, ramping toward a target.

    Args:
        acceleration: m/s² for the linear part.
        angular_acceleration: rad/s² for the turn.
    """

    acceleration: float
    angular_acceleration: float
    current: Velocity = STILL

    def step(self, target: Velocity, dt: float) -> Velocity:
        """Advance ``dt`` seconds toward ``target``; the new commanded velocity."""
        v, u, w = self.current
        tv, tu, tw = target
        step = self.acceleration * dt
        dx, dy = tv - v, tu - u
        gap = math.hypot(dx, dy)
        if gap <= step:
            v, u = tv, tu
        else:
            v, u = v + dx * step / gap, u + dy * step / gap
        turn = self.angular_acceleration * dt
        w = tw if abs(tw - w) <= turn else w + math.copysign(turn, tw - w)
        self.current = (v, u, w)
        return self.current

    @property
    def still(self) -> bool:
        """Whether the commanded velocity is zero."""
        return all(abs(c) < EPSILON for c in self.current)

    def halt(self) -> None:
        """Forget the current velocity (the wheels were stopped by other means)."""
        self.current = STILL


def crab_direction(velocity: Velocity) -> float | None:
    """The direction (rad, counter-clockwise from forward) the wheel modules must face to
    make ``velocity``: that of its linear part; None when it has none (a turn on the spot,
    or a stop: the modules stay as they are)."""
    vx, vy, _ = velocity
    if math.hypot(vx, vy) < EPSILON:
        return None
    if abs(vy) < EPSILON:
        return 0.0  # forward and backward alike: the modules face along the body
    return math.atan2(vy, vx)


def aligned(heading: float, direction: float, tolerance: float) -> bool:
    """Whether a module facing ``heading`` rolls along ``direction`` (either way)."""
    off = math.remainder(heading - direction, math.pi)
    return abs(off) <= tolerance
