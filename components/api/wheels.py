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

The geometry depends on the limbs' angles (the wheels sit at their tips): a drive made by
``robot.drive()`` recomputes it from the measured angles at the start of every motion.

Steering with the limbs is :class:`~components.api.steering.WheelSteering`: with the
modules pointed along a direction, ``WheelDrive.travel`` drives the assembly along it
without turning the body (crab steering).
"""

from __future__ import annotations

import asyncio
import math
import xml.etree.ElementTree as ET
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import pinocchio as pin

from components.api.errors import ApiError
from components.api.joints import JointHandler
from components.api.motion import Motion
from components.api.syncer import Commander
from components.messages import JointSample

if TYPE_CHECKING:
    from components.api.steering import WheelSteering


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

    def wheel_speeds(self, linear: float, angular: float, lateral: float = 0.0) -> dict[str, float]:
        """Wheel angular speeds (rad/s) for a body speed ``linear`` (m/s, along x),
        ``angular`` (rad/s, about z) and ``lateral`` (m/s, along y: only wheels turned
        sideways, see :class:`WheelSteering`, can produce it)."""
        out = {}
        for w in self.wheels:
            ground = np.array(
                [linear - angular * w.center[1], lateral + angular * w.center[0], 0.0]
            )
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


def wheel_joints(handlers: Sequence[JointHandler]) -> dict[str, tuple[str, ...]]:
    """Each wheel module's wheels: its velocity-controlled joints (an H-line wheel V2's
    position-controlled flaps move the module but are no wheels: they have no radius).

    Args:
        handlers: The wheel modules' :class:`~components.api.joints.JointHandler`.
    """
    return {
        h.slot: tuple(name for name, info in h.joints.items() if info.control == "velocity")
        for h in handlers
    }


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

    With ``steering`` and ``positions`` (what ``robot.drive()`` gives), every motion starts
    from the geometry at the measured limb angles, and the drive can steer: where the
    modules face (:meth:`headings`), which joints turn them (:meth:`steering_joints`), the
    limb targets that point them along a direction (:meth:`steer_path`), and driving along
    it without turning (:meth:`travel`).

    Args:
        handlers: The wheel modules.
        geometry: Their wheels (see :meth:`WheelGeometry.from_urdf`).
        acceleration: m/s².
        angular_acceleration: rad/s².
        rate: Commands per second.
        steering: The limbs' steering of these modules (see :class:`WheelSteering`).
        positions: The measured angle of every joint of the assembly, when called.
    """

    def __init__(
        self,
        handlers: Sequence[JointHandler],
        geometry: WheelGeometry,
        acceleration: float = 0.5,
        angular_acceleration: float = 1.5,
        rate: float = 40.0,
        steering: WheelSteering | None = None,
        positions: Callable[[], Mapping[str, float]] | None = None,
    ) -> None:
        super().__init__(handlers)
        self.geometry = geometry
        self.acceleration = acceleration
        self.angular_acceleration = angular_acceleration
        self.rate = rate
        self.steering = steering
        self._positions = positions
        self._owner = {n: h for h in handlers for n in h.joints}
        missing = [w.joint for w in geometry.wheels if w.joint not in self._owner]
        if missing:
            raise ApiError(f"wheels {', '.join(missing)} belong to no module of this drive")
        self._speed = (0.0, 0.0, 0.0)  # linear, lateral, angular

    # ------------------------------------------------------------------ steering
    def _steering(self, what: str) -> tuple[WheelSteering, Mapping[str, float]]:
        if self.steering is None or self._positions is None:
            raise ApiError(
                f"{what} needs the limbs' kinematics and angles: make the drive with robot.drive()"
            )
        return self.steering, self._positions()

    def refresh(self) -> WheelGeometry:
        """Recompute the wheel geometry at the measured limb angles (every motion does it
        first when the drive has them); returns it."""
        if self.steering is not None and self._positions is not None:
            self.geometry = self.steering.geometry(self._positions())
        return self.geometry

    def headings(self) -> dict[str, float]:
        """Where each wheel module faces (rad in the root link's frame, see
        :class:`WheelSteering`), at the measured limb angles."""
        steering, positions = self._steering("headings")
        return {slot: steering.heading(slot, positions) for slot in self.handlers}

    def steering_joints(self) -> dict[str, tuple[str, ...]]:
        """For each wheel module, the joints whose axes are vertical now: those that turn it
        about the vertical (none while the Dragon's limbs lie straight and unrolled)."""
        steering, positions = self._steering("steering_joints")
        return {slot: steering.steering_joints(slot, positions) for slot in self.handlers}

    def steer_path(
        self, direction: float, step: float = math.radians(15.0)
    ) -> list[dict[str, float]]:
        """Limb joint targets that point every wheel module along ``direction`` (rad in the
        root link's frame), each turning about its own centre: give them in turn to the
        limbs' ``JointSyncer.lerp`` (see :meth:`WheelSteering.path`).

        Raises:
            ApiError: If a module cannot turn from the limbs' pose (bend the limb first).
        """
        steering, positions = self._steering("steer_path")
        return steering.path(direction, positions, step)

    # ------------------------------------------------------------------ driving
    def speeds(self, linear: float, angular: float, lateral: float = 0.0) -> dict[str, float]:
        """Wheel speeds for a body speed, scaled down together to the joints' limits."""
        speeds = self.geometry.wheel_speeds(linear, angular, lateral)
        scale = 1.0
        for name, value in speeds.items():
            limit = self._owner[name].joints[name].max_velocity
            if abs(value) > limit > 0:
                scale = min(scale, limit / abs(value))
        return {n: v * scale for n, v in speeds.items()}

    def _send(self, linear: float, lateral: float, angular: float) -> None:
        per_module: dict[str, list[JointSample]] = {}
        for name, value in self.speeds(linear, angular, lateral).items():
            per_module.setdefault(self._owner[name].slot, []).append(
                JointSample(name, None, value, None)
            )
        for slot, rows in per_module.items():
            self.handlers[slot].send(rows)

    def move(
        self,
        linear: float,
        angular: float = 0.0,
        duration: float | None = None,
        lateral: float = 0.0,
    ) -> Motion:
        """Drive at ``linear`` m/s, ``angular`` rad/s and ``lateral`` m/s (sideways: only
        with the wheel modules steered, see :meth:`travel`) for ``duration`` seconds (ramping
        up, then down to a stop), or until another motion or a stop when None."""
        for value, what in (
            (linear, "linear"),
            (angular, "angular"),
            (duration, "duration"),
            (lateral, "lateral"),
        ):
            if value is not None and not math.isfinite(value):
                raise ValueError(f"move: {what} must be finite, not {value}")
        self.refresh()

        async def body(motion: Motion) -> None:
            await self._drive(linear, lateral, angular, duration)
            motion.finish(True)

        description = f"drive {linear:g} m/s {angular:g} rad/s"
        if lateral:
            description += f" {lateral:g} m/s sideways"
        return self._launch(description, body)

    def forward(self, distance: float, speed: float = 0.2) -> Motion:
        """Drive ``distance`` metres straight (negative: backwards) at ``speed`` m/s."""
        speed = math.copysign(abs(speed), distance)
        return self.move(speed, 0.0, self._time_for(abs(distance), abs(speed), self.acceleration))

    def travel(self, distance: float, direction: float, speed: float = 0.2) -> Motion:
        """Drive ``distance`` metres along ``direction`` (rad in the root link's frame, 0 is
        forward) at ``speed`` m/s without turning the body.

        The wheels can only roll the assembly along where they face: point the wheel modules
        along ``direction`` first (:meth:`steer_path`), else the part of the motion across
        them is lost (and the wheels scrub).
        """
        if not math.isfinite(direction):
            raise ValueError(f"travel: direction must be finite, not {direction}")
        duration = self._time_for(abs(distance), abs(speed), self.acceleration)
        speed = math.copysign(abs(speed), distance)
        return self.move(
            speed * math.cos(direction), 0.0, duration, lateral=speed * math.sin(direction)
        )

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

    async def _drive(
        self, linear: float, lateral: float, angular: float, duration: float | None
    ) -> None:
        loop = asyncio.get_running_loop()
        period = 1.0 / self.rate
        began = wake = loop.time()
        v, u, w = self._speed
        # The body's velocity (linear, lateral) ramps along the straight line to its goal, so
        # its direction holds while the speed changes; the angular speed ramps on its own.
        step, turn = self.acceleration * period, self.angular_acceleration * period
        try:
            while duration is None or loop.time() - began < duration:
                v, u = _toward_vector((v, u), (linear, lateral), step)
                w = _toward(w, angular, turn)
                self._speed = (v, u, w)
                self._send(v, u, w)
                wake += period
                await asyncio.sleep(max(wake - loop.time(), 0.0))
            while abs(v) > 1e-9 or abs(u) > 1e-9 or abs(w) > 1e-9:
                v, u = _toward_vector((v, u), (0.0, 0.0), step)
                w = _toward(w, 0.0, turn)
                self._speed = (v, u, w)
                self._send(v, u, w)
                wake += period
                await asyncio.sleep(max(wake - loop.time(), 0.0))
        finally:
            if (v, u, w) != (0.0, 0.0, 0.0):
                # Cancelled mid-motion: the next motion ramps from here; a stop sends zeros.
                self._speed = (v, u, w)

    async def stop(self) -> None:
        """Cancel the motion and command every wheel to 0 at once."""
        await super().stop()
        self._speed = (0.0, 0.0, 0.0)
        self._send(0.0, 0.0, 0.0)


def _toward(value: float, goal: float, step: float) -> float:
    if abs(goal - value) <= step:
        return goal
    return value + math.copysign(step, goal - value)


def _toward_vector(
    value: tuple[float, float], goal: tuple[float, float], step: float
) -> tuple[float, float]:
    dx, dy = goal[0] - value[0], goal[1] - value[1]
    gap = math.hypot(dx, dy)
    if gap <= step:
        return goal
    return value[0] + dx * step / gap, value[1] + dy * step / gap
