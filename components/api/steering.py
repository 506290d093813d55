"""Steering with the limbs: a wheel module at a limb's tip turns about the vertical when the
limb's joints do.

Which joints can do that, where a module faces and the joint targets that turn it to a new
heading about its own centre, keeping it level, are forward and inverse kinematics of the
composed URDF (the movable joints on the path from the root link to the module). With the
modules pointed along a direction, :meth:`~components.api.wheels.WheelDrive.travel` drives
the assembly along it without turning the body (crab steering).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from components.api.errors import ApiError
from components.api.wheels import WheelGeometry
from components.kinematics_manager.ik import IkSettings, IkSolver
from components.kinematics_manager.model import ChainModel, ModelError, chain_model

#: A joint turns a wheel module about the vertical when its axis is this close (rad) to it.
VERTICAL_TOLERANCE = 0.05


def _wrap(angle: float) -> float:
    """``angle`` in (-pi, pi]."""
    return math.pi - (math.pi - angle) % (2.0 * math.pi)


@dataclass(frozen=True)
class _Steered:
    """One wheel module and the joints that move it."""

    link: str
    chain: ChainModel
    solver: IkSolver | None  # None: nothing moves the module
    forward: np.ndarray  # the first wheel's rolling direction, in the module link's frame
    rest: pin.SE3  # the module link's placement with every joint at 0
    rest_heading: float  # where it faces then (rad)


class WheelSteering:
    """Turning wheel modules about the vertical with the limbs that carry them.

    Everything is in the root link's frame (x forward, z up). A module's *heading* is the
    direction (rad, counter-clockwise from x) in which a positive spin of its first wheel
    rolls it; its *centre* is the origin of its link (the wheels' parent: the middle of
    the axle). The joints that move a module are the movable joints on the URDF path from
    the root link to that link.

    A module turns about its own centre only when some of those joints have vertical axes
    (:meth:`steering_joints`) and the limb is bent: a stretched limb cannot keep the centre
    in place while the module turns. :meth:`turn` and :meth:`path` give joint targets that
    keep the centre where it is (at its height with every joint at 0) and the module level
    (its attitude with every joint at 0, turned about the vertical); they are inverse
    kinematics warm-started from the pose given, so they stay on that pose's branch (elbow
    side, roll).

    Args:
        urdf_text: The composed URDF.
        root_link: The frame of every result (the assembly's root link).
        modules: Wheel module slot -> its wheel joints.
        settings: Inverse kinematics tuning (default: the kinematics manager's, with the
            joint managers' 0.02 limit margin).
    """

    def __init__(
        self,
        urdf_text: str,
        root_link: str,
        modules: Mapping[str, Sequence[str]],
        settings: IkSettings | None = None,
    ) -> None:
        self.urdf_text = urdf_text
        self.root_link = root_link
        self.modules = {slot: tuple(joints) for slot, joints in modules.items()}
        self.settings = settings or IkSettings()
        self._steered: dict[str, _Steered] = {}  # built on first use: pure driving needs none

    def geometry(self, positions: Mapping[str, float] | None = None) -> WheelGeometry:
        """Every module's wheels at the joint angles ``positions`` (default: all 0)."""
        joints = [j for wheels in self.modules.values() for j in wheels]
        return WheelGeometry.from_urdf(self.urdf_text, self.root_link, joints, positions)

    def _module(self, slot: str) -> _Steered:
        found = self._steered.get(slot)
        if found is not None:
            return found
        if slot not in self.modules:
            raise ApiError(f"no wheel module {slot!r}; wheel modules: {', '.join(self.modules)}")
        wheels = self.modules[slot]
        if not wheels:
            raise ApiError(f"wheel module {slot} has no wheel joint")
        robot = ET.fromstring(self.urdf_text)
        parents = set()
        for joint in robot.findall("joint"):
            if joint.get("name") in wheels:
                parents.add(joint.find("parent").get("link"))  # type: ignore[union-attr]
        if len(parents) != 1:
            raise ApiError(
                f"wheel module {slot}: its wheels {', '.join(wheels)} should share one parent "
                f"link in the composed URDF, found {sorted(parents) or 'none'}"
            )
        link = parents.pop()
        try:
            chain = chain_model(self.urdf_text, self.root_link, link)
        except ModelError as exc:
            raise ApiError(f"wheel module {slot}: {exc}") from exc
        rest = chain.tip(np.zeros(chain.nq))
        rolling = WheelGeometry.from_urdf(self.urdf_text, self.root_link, wheels[:1], {})
        at_rest = rolling.wheels[0].rolling
        forward = rest.rotation.T @ at_rest
        solver = IkSolver(chain, self.settings) if chain.nq else None
        heading = math.atan2(at_rest[1], at_rest[0])
        found = _Steered(link, chain, solver, forward, rest, heading)
        self._steered[slot] = found
        return found

    def _pose(self, slot: str, positions: Mapping[str, float]) -> tuple[_Steered, np.ndarray]:
        module = self._module(slot)
        return module, module.chain.configuration(positions)

    def heading(self, slot: str, positions: Mapping[str, float]) -> float:
        """Where module ``slot`` faces (rad) at the joint angles ``positions``."""
        module, q = self._pose(slot, positions)
        rolling = module.chain.tip(q).rotation @ module.forward
        return math.atan2(rolling[1], rolling[0])

    def center(self, slot: str, positions: Mapping[str, float]) -> np.ndarray:
        """Where module ``slot``'s centre is (m) at the joint angles ``positions``."""
        module, q = self._pose(slot, positions)
        return module.chain.tip(q).translation.copy()

    def steering_joints(
        self, slot: str, positions: Mapping[str, float], tolerance: float = VERTICAL_TOLERANCE
    ) -> tuple[str, ...]:
        """The joints that turn module ``slot`` about the vertical at ``positions``: those on
        its path from the root whose axis is within ``tolerance`` rad of vertical."""
        module, q = self._pose(slot, positions)
        model, data = module.chain.model, module.chain.data
        pin.computeJointJacobians(model, data, q)  # columns in the root frame: axes at q
        out = []
        for name in module.chain.joint_names:
            joint = model.joints[model.getJointId(name)]
            axis = data.J[3:, joint.idx_v]
            norm = float(np.linalg.norm(axis))
            if norm > 0 and abs(axis[2]) / norm >= math.cos(tolerance):
                out.append(name)
        return tuple(out)

    def turn(self, slot: str, heading: float, positions: Mapping[str, float]) -> dict[str, float]:
        """Joint targets that turn module ``slot`` to face ``heading`` (rad) about its centre.

        The centre stays where it is at ``positions`` in the ground plane, at its height
        with every joint at 0, and the module level (its attitude then, turned about the
        vertical); the solution is the one nearest ``positions``.

        Raises:
            ApiError: If the limb cannot do it from there (no vertical joint, stretched, or
                a joint limit in the way).
        """
        module, q = self._pose(slot, positions)
        # The centre keeps its place in the ground plane and its height at the zero pose:
        # taking the measured height would carry the limbs' sag under gravity into the
        # target, and turn after turn the body would sink.
        centre = module.chain.tip(q).translation.copy()
        centre[2] = module.rest.translation[2]
        target = pin.SE3(_yaw(heading - module.rest_heading) @ module.rest.rotation, centre)
        result = None if module.solver is None else module.solver.solve(target, q)
        if result is None or not result.reachable:
            raise ApiError(
                f"wheel module {slot} cannot turn to {math.degrees(heading):.0f} deg about "
                "its centre from this pose: bend the limb so that joints with vertical axes "
                "(steering_joints) can turn it; see examples/dragon_square.py"
            )
        return {n: float(v) for n, v in zip(module.chain.joint_names, result.q, strict=True)}

    def path(
        self,
        direction: float,
        positions: Mapping[str, float],
        step: float = math.radians(15.0),
    ) -> list[dict[str, float]]:
        """Waypoints turning every module so its wheels roll along ``direction`` (rad).

        A module rolls either way along a line, so each one turns to whichever of
        ``direction`` and ``direction + pi`` is nearer the way it faces with every joint at 0
        (no module turns more than 90 degrees from there; on a tie, the nearer to where it
        faces now), the shortest way from where it faces at ``positions``. Consecutive
        waypoints differ by at most ``step`` in heading, so the joint-space line between them
        (a ``lerp``) keeps each centre within millimetres of its place (one lerp over a
        large turn would swing the centre by centimetres).

        Returns:
            Joint targets, one dict per waypoint (the last one is the goal); empty when every
            module already faces along ``direction``.

        Raises:
            ApiError: See :meth:`turn`.
        """
        if not step > 0:
            raise ValueError(f"path: step must be > 0, not {step}")
        turns = {}
        for slot in self.modules:
            rest = self._module(slot).rest_heading
            now = self.heading(slot, positions)
            # Nearer the rest heading first (rounded: a tie is a tie), then nearer now.
            goal = min(
                (direction, direction + math.pi),
                key=lambda h: (round(abs(_wrap(h - rest)), 9), abs(_wrap(h - now))),
            )
            turns[slot] = (now, _wrap(goal - now))
        largest = max((abs(t) for _, t in turns.values()), default=0.0)
        # Within a milliradian counts as there (the IK's own tolerance is below it).
        count = math.ceil(largest / step - 1e-9) if largest > 1e-3 else 0
        waypoints: list[dict[str, float]] = []
        current = dict(positions)
        for k in range(1, count + 1):
            waypoint: dict[str, float] = {}
            for slot, (now, turn) in turns.items():
                waypoint.update(self.turn(slot, now + turn * k / count, current))
            current.update(waypoint)
            waypoints.append(waypoint)
        return waypoints


def _yaw(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
