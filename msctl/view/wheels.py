"""A wheel module's commanded twist, from the wheel velocities it was asked for: pure.

What a wheel module is told to do is its ``joint_set``: a velocity (rad/s) per wheel joint
(its velocity-controlled joints; an H-line wheel V2's flaps are position-controlled and no
wheels). A wheel spinning at ``s`` about its unit axis ``a`` (in the world, from forward
kinematics at the viewer) rolls its centre at ``s r (a x z)``, as
:mod:`components.api.wheels` drives it. The module's commanded twist is the planar rigid
motion that fits its wheels' rolling velocities: the linear velocity of their mean centre
(the mean of the wheels' velocities) and the turn rate about the vertical (each wheel's
velocity relative to that, about the mean centre). Drawn as an arrow at the module.

A joint manager stops its wheels when commands stop coming (its watchdog):
:meth:`WheelCommands.expire` does the same for the picture.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

#: Seconds without a command after which a joint manager's watchdog stops the wheels (the
#: joint manager's default ``watchdog_timeout``).
COMMAND_TIMEOUT = 0.5
#: Below this (m/s, rad/s) a twist is drawn again only if it changed by more.
TWIST_TOLERANCE = 1e-3

Vec = tuple[float, float, float]


@dataclass(frozen=True)
class WheelJoint:
    """One wheel of a module, as the composed URDF says.

    Attributes:
        joint: Its joint (``wheel1_wheel_left``).
        link: The link it turns (its centre is the link's origin).
        axis: Its spin axis in that link's frame (unit).
        radius: Its rolling radius (m).
    """

    joint: str
    link: str
    axis: tuple[float, float, float]
    radius: float


@dataclass(frozen=True)
class WheelTwist:
    """A wheel module's commanded twist, in the world.

    Attributes:
        origin: The mean centre of its wheels (m).
        linear: The velocity of that point (m/s).
        yaw_rate: The turn rate about the vertical (rad/s, counter-clockwise seen from above).
    """

    origin: Vec
    linear: Vec
    yaw_rate: float

    @property
    def speed(self) -> float:
        """The linear speed (m/s)."""
        return math.hypot(*self.linear)

    def label(self, slot: str) -> str:
        """``wheel1: 0.20 m/s, +0.10 rad/s``."""
        return f"{slot}: {self.speed:.2f} m/s, {self.yaw_rate:+.2f} rad/s"

    def differs(self, other: WheelTwist | None) -> bool:
        """Whether it should be drawn again after ``other``."""
        if other is None:
            return True
        mine = (*self.origin, *self.linear, self.yaw_rate)
        theirs = (*other.origin, *other.linear, other.yaw_rate)
        return any(abs(a - b) > TWIST_TOLERANCE for a, b in zip(mine, theirs, strict=True))


def wheel_joints(urdf: ET.Element, joints: Sequence[str]) -> list[WheelJoint]:
    """The wheels among ``joints`` of a composed URDF: those whose link has a radius (a
    cylinder or sphere in its collision or visual geometry); the others are left out."""
    links = {link.get("name"): link for link in urdf.findall("link")}
    elements = {joint.get("name"): joint for joint in urdf.findall("joint")}
    out = []
    for name in joints:
        element = elements.get(name)
        child = element.find("child") if element is not None else None
        if child is None:
            continue
        link = child.get("link", "")
        radius = _radius(links.get(link))
        axis_element = element.find("axis")
        text = axis_element.get("xyz", "1 0 0") if axis_element is not None else "1 0 0"
        axis = np.array([float(v) for v in text.split()])
        norm = float(np.linalg.norm(axis))
        if radius is None or norm < 1e-9:
            continue
        axis = axis / norm
        out.append(WheelJoint(name, link, (float(axis[0]), float(axis[1]), float(axis[2])), radius))
    return out


def _radius(link: ET.Element | None) -> float | None:
    if link is None:
        return None
    for tag in ("collision", "visual"):
        for part in link.findall(tag):
            geometry = part.find("geometry")
            for kind in ("cylinder", "sphere"):
                found = geometry.find(kind) if geometry is not None else None
                if found is not None and found.get("radius"):
                    return float(found.get("radius", 0))
    return None


def twist_of(
    wheels: Sequence[WheelJoint], velocities: Mapping[str, float], world: Mapping[str, Any]
) -> WheelTwist | None:
    """A module's commanded twist.

    Args:
        wheels: Its wheels.
        velocities: Wheel joint -> commanded velocity (rad/s); a wheel not named is still.
        world: Link -> its placement in the world (a Pinocchio ``SE3``: ``rotation``,
            ``translation``).

    Returns:
        The twist, or ``None`` when no wheel is placed or none can roll (vertical axes).
    """
    up = np.array([0.0, 0.0, 1.0])
    centres, velocities_at = [], []
    for wheel in wheels:
        placement = world.get(wheel.link)
        if placement is None:
            continue
        axis = np.asarray(placement.rotation) @ np.array(wheel.axis)
        rolling = np.cross(axis, up)
        norm = float(np.linalg.norm(rolling))
        if norm < 1e-6:
            continue
        spin = velocities.get(wheel.joint) or 0.0
        centres.append(np.asarray(placement.translation, dtype=float))
        velocities_at.append(spin * wheel.radius * rolling / norm)
    if not centres:
        return None
    centre = np.mean(centres, axis=0)
    linear = np.mean(velocities_at, axis=0)
    turns = []
    for c, u in zip(centres, velocities_at, strict=True):
        arm = (c - centre)[:2]
        reach = float(arm @ arm)
        if reach > 1e-9:
            relative = (u - linear)[:2]
            turns.append(float(arm[0] * relative[1] - arm[1] * relative[0]) / reach)
    yaw = float(np.mean(turns)) if turns else 0.0
    return WheelTwist(
        (float(centre[0]), float(centre[1]), float(centre[2])),
        (float(linear[0]), float(linear[1]), float(linear[2])),
        yaw,
    )


class WheelCommands:
    """The last wheel velocities each wheel module was commanded, and when (pure).

    Args:
        wheels: Slot -> its wheels.
    """

    def __init__(self, wheels: Mapping[str, Sequence[WheelJoint]]) -> None:
        self.wheels = {slot: list(w) for slot, w in wheels.items() if w}
        self._velocities: dict[str, dict[str, float]] = {}
        self._seen: dict[str, float] = {}

    def command(self, slot: str, velocities: Mapping[str, float | None], at: float) -> None:
        """Take a module's ``joint_set`` velocities (joints without one are not commanded).

        Args:
            slot: The module.
            velocities: Joint -> velocity (rad/s) or ``None``.
            at: When (s, the caller's clock: wall or bag time).
        """
        if slot not in self.wheels:
            return
        names = {w.joint for w in self.wheels[slot]}
        taken = {
            name: float(value)
            for name, value in velocities.items()
            if name in names and value is not None and math.isfinite(value)
        }
        if taken:
            self._velocities.setdefault(slot, {}).update(taken)
            self._seen[slot] = at

    def expire(self, now: float, after: float = COMMAND_TIMEOUT) -> list[str]:
        """Stop the wheels of modules commanded nothing for ``after`` seconds, as their joint
        managers' watchdogs do; returns those modules."""
        stopped = []
        for slot, seen in self._seen.items():
            moving = any(v != 0.0 for v in self._velocities.get(slot, {}).values())
            if moving and now - seen > after:
                self._velocities[slot] = dict.fromkeys(self._velocities[slot], 0.0)
                stopped.append(slot)
        return stopped

    def reset(self) -> None:
        """Forget every command (a bag's picture jumping to another time)."""
        self._velocities.clear()
        self._seen.clear()

    def commanded(self) -> list[str]:
        """Modules commanded at least once."""
        return list(self._velocities)

    def velocities(self, slot: str) -> dict[str, float]:
        """A module's last commanded wheel velocities."""
        return dict(self._velocities.get(slot, {}))
