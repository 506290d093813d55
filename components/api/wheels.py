"""The wheel-drive helper: a linear and angular speed of the whole assembly -> wheel speeds.

Geometry comes from the composed URDF of the resolved assembly, not from constants: each
wheel's centre and spin axis are the forward kinematics of its joint (origin and ``<axis>``)
at the current limb angles, expressed in the robot's root link, and its radius is the
cylinder (or sphere) of the wheel link's collision geometry (visual if it has none). The
drive plane is the root link's xy plane, x forward, z up (the Dragon lies flat along x).

For a body velocity ``(v, w)`` the ground point under a wheel centred at ``p`` moves at
``v x + w z x p``; a wheel spinning at ``s`` about its unit axis ``a`` rolls its centre at
``s r (a x z)``; the wheel speed is the projection ``s = (v_p . (a x z)) / r``. Lateral
components (skid-steer on four wheels) cannot be produced by the wheels and are dropped,
as every skid-steer drive does. This covers two-wheel differential drives and four-wheel
skid steer alike, whatever the wheels' layout.

The geometry depends on the limbs' angles (the wheels sit at their tips): make a new drive
(``robot.drive()``) after moving the limbs.
"""

from __future__ import annotations

import asyncio
import math
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from components.api.errors import ApiError
from components.api.joints import JointHandler
from components.api.motion import Motion
from components.api.syncer import Commander
from components.messages import JointSample


@dataclass(frozen=True)
class Wheel:
    """One wheel in the root link's frame.

    Attributes:
        joint: Its joint (``wheel1_wheel_left``).
        center: Centre (m).
        axis: Unit spin axis (positive rotation by the right-hand rule).
        radius: Rolling radius (m).
        rolling: Unit direction the centre moves for a positive spin (``axis x z``).
    """

    joint: str
    center: np.ndarray
    axis: np.ndarray
    radius: float
    rolling: np.ndarray


@dataclass(frozen=True)
class WheelGeometry:
    """Every driven wheel of the assembly, and the layout figures derived from them.

    Attributes:
        wheels: The wheels.
        root_link: The frame they are expressed in.
    """

    wheels: tuple[Wheel, ...]
    root_link: str

    @property
    def track_width(self) -> float:
        """Lateral spread of the wheels (m): largest minus smallest ``y`` of their centres."""
        ys = [w.center[1] for w in self.wheels]
        return float(max(ys) - min(ys))

    @property
    def wheel_radius(self) -> float:
        """The mean wheel radius (m)."""
        return float(np.mean([w.radius for w in self.wheels]))

    def wheel_speeds(self, linear: float, angular: float) -> dict[str, float]:
        """Wheel angular speeds (rad/s) for a body speed ``linear`` (m/s, along x) and
        ``angular`` (rad/s, about z)."""
        out = {}
        for w in self.wheels:
            ground = np.array([linear - angular * w.center[1], angular * w.center[0], 0.0])
            out[w.joint] = float(ground @ w.rolling) / w.radius
        return out

    @classmethod
    def from_urdf(
        cls,
        urdf_text: str,
        root_link: str,
        joints: Sequence[str],
        positions: Mapping[str, float] | None = None,
    ) -> WheelGeometry:
        """Wheels ``joints`` of the composed URDF, at the limb angles ``positions``.

        Raises:
            ApiError: If a joint, its wheel link or the link's radius is missing.
        """
        import pinocchio as pin

        robot = ET.fromstring(urdf_text)
        links = {link.get("name"): link for link in robot.findall("link")}
        elements = {j.get("name"): j for j in robot.findall("joint")}
        model = pin.buildModelFromXML(urdf_text)
        data = model.createData()
        q = pin.neutral(model)
        for name, value in (positions or {}).items():
            if not model.existJointName(name):
                continue
            joint = model.joints[model.getJointId(name)]
            if joint.nq == 1:  # revolute/prismatic; continuous (cos, sin) wheels stay at 0
                q[joint.idx_q] = value
        pin.framesForwardKinematics(model, data, q)

        def placement(link: str) -> pin.SE3:
            if not model.existFrame(link, pin.BODY):
                raise ApiError(f"the composed URDF has no link {link!r}")
            return data.oMf[model.getFrameId(link, pin.BODY)]

        root = placement(root_link).inverse()
        up = np.array([0.0, 0.0, 1.0])
        wheels = []
        for name in joints:
            element = elements.get(name)
            if element is None:
                raise ApiError(f"the composed URDF has no joint {name!r}")
            child = element.find("child").get("link")  # type: ignore[union-attr]
            local_axis = np.array(
                [float(v) for v in (element.find("axis").get("xyz", "1 0 0")).split()]  # type: ignore[union-attr]
                if element.find("axis") is not None
                else [1.0, 0.0, 0.0]
            )
            pose = root * placement(child)
            axis = pose.rotation @ (local_axis / np.linalg.norm(local_axis))
            rolling = np.cross(axis, up)
            norm = float(np.linalg.norm(rolling))
            if norm < 1e-6:
                raise ApiError(f"wheel {name}: its axis is vertical, it cannot roll on the ground")
            wheels.append(
                Wheel(
                    name,
                    pose.translation.copy(),
                    axis,
                    _radius(links.get(child), name),
                    rolling / norm,
                )
            )
        return cls(tuple(wheels), root_link)


def _radius(link: ET.Element | None, joint: str) -> float:
    if link is not None:
        for tag in ("collision", "visual"):
            for part in link.findall(tag):
                shape = part.find("geometry")
                if shape is None:
                    continue
                for kind in ("cylinder", "sphere"):
                    found = shape.find(kind)
                    if found is not None and found.get("radius"):
                        return float(found.get("radius"))  # type: ignore[arg-type]
    raise ApiError(f"wheel {joint}: its link has no cylinder or sphere radius in the URDF")


class WheelDrive(Commander):
    """Drive the assembly with its wheels: body speeds in, wheel velocity commands out.

    Speeds ramp at ``acceleration`` / ``angular_acceleration``; wheel speeds over a joint's
    limit scale every wheel down together (the path's curvature is kept). Commands are sent
    at ``rate`` for the whole motion (the joint managers' watchdogs stop the wheels when they
    stop coming), and every motion ends with the wheels commanded to 0: a velocity is never
    left behind.

    Args:
        handlers: The wheel modules.
        geometry: Their wheels (see :meth:`WheelGeometry.from_urdf`).
        acceleration: m/s².
        angular_acceleration: rad/s².
        rate: Commands per second.
    """

    def __init__(
        self,
        handlers: Sequence[JointHandler],
        geometry: WheelGeometry,
        acceleration: float = 0.5,
        angular_acceleration: float = 1.5,
        rate: float = 40.0,
    ) -> None:
        super().__init__(handlers)
        self.geometry = geometry
        self.acceleration = acceleration
        self.angular_acceleration = angular_acceleration
        self.rate = rate
        self._owner = {n: h for h in handlers for n in h.joints}
        missing = [w.joint for w in geometry.wheels if w.joint not in self._owner]
        if missing:
            raise ApiError(f"wheels {', '.join(missing)} belong to no module of this drive")
        self._speed = (0.0, 0.0)

    def speeds(self, linear: float, angular: float) -> dict[str, float]:
        """Wheel speeds for a body speed, scaled down together to the joints' limits."""
        speeds = self.geometry.wheel_speeds(linear, angular)
        scale = 1.0
        for name, value in speeds.items():
            limit = self._owner[name].joints[name].max_velocity
            if abs(value) > limit > 0:
                scale = min(scale, limit / abs(value))
        return {n: v * scale for n, v in speeds.items()}

    def _send(self, linear: float, angular: float) -> None:
        per_module: dict[str, list[JointSample]] = {}
        for name, value in self.speeds(linear, angular).items():
            per_module.setdefault(self._owner[name].slot, []).append(
                JointSample(name, None, value, None)
            )
        for slot, rows in per_module.items():
            self.handlers[slot].send(rows)

    def move(self, linear: float, angular: float = 0.0, duration: float | None = None) -> Motion:
        """Drive at ``linear`` m/s and ``angular`` rad/s for ``duration`` seconds (ramping up,
        then down to a stop), or until another motion or a stop when None."""
        for value, what in ((linear, "linear"), (angular, "angular"), (duration, "duration")):
            if value is not None and not math.isfinite(value):
                raise ValueError(f"move: {what} must be finite, not {value}")

        async def body(motion: Motion) -> None:
            await self._drive(linear, angular, duration)
            motion.finish(True)

        return self._launch(f"drive {linear:g} m/s {angular:g} rad/s", body)

    def forward(self, distance: float, speed: float = 0.2) -> Motion:
        """Drive ``distance`` metres straight (negative: backwards) at ``speed`` m/s."""
        speed = math.copysign(abs(speed), distance)
        return self.move(speed, 0.0, self._time_for(abs(distance), abs(speed), self.acceleration))

    def turn(self, angle: float, speed: float = 0.5) -> Motion:
        """Turn ``angle`` radians in place (positive: counter-clockwise) at ``speed`` rad/s."""
        speed = math.copysign(abs(speed), angle)
        return self.move(
            0.0, speed, self._time_for(abs(angle), abs(speed), self.angular_acceleration)
        )

    @staticmethod
    def _time_for(distance: float, speed: float, acceleration: float) -> float:
        # Time at full speed such that ramp up + cruise + ramp down covers the distance
        # (each ramp covers speed²/2a, and the cruise time counts from the ramp's start).
        if speed <= 0:
            return 0.0
        return distance / speed

    async def _drive(self, linear: float, angular: float, duration: float | None) -> None:
        loop = asyncio.get_running_loop()
        period = 1.0 / self.rate
        began = wake = loop.time()
        v, w = self._speed
        try:
            while duration is None or loop.time() - began < duration:
                v = _toward(v, linear, self.acceleration * period)
                w = _toward(w, angular, self.angular_acceleration * period)
                self._speed = (v, w)
                self._send(v, w)
                wake += period
                await asyncio.sleep(max(wake - loop.time(), 0.0))
            while abs(v) > 1e-9 or abs(w) > 1e-9:
                v = _toward(v, 0.0, self.acceleration * period)
                w = _toward(w, 0.0, self.angular_acceleration * period)
                self._speed = (v, w)
                self._send(v, w)
                wake += period
                await asyncio.sleep(max(wake - loop.time(), 0.0))
        finally:
            if (v, w) != (0.0, 0.0):
                # Cancelled mid-motion: the next motion ramps from here; a stop sends zeros.
                self._speed = (v, w)

    async def stop(self) -> None:
        """Cancel the motion and command every wheel to 0 at once."""
        await super().stop()
        self._speed = (0.0, 0.0)
        self._send(0.0, 0.0)


def _toward(value: float, goal: float, step: float) -> float:
    if abs(goal - value) <= step:
        return goal
    return value + math.copysign(step, goal - value)
