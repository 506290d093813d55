"""Steering wheel modules with the limbs, on the Dragon's composed URDF (no Zenoh, no sim):
which joints turn a module about the vertical, the joint targets that turn it about its own
centre, waypoints along a direction, and driving along it without turning (crab steering).
"""

from __future__ import annotations

import asyncio
import itertools
import math
from typing import Any

import numpy as np
import pytest

from components.api.errors import ApiError
from components.api.joints import JointHandler, JointInfo
from components.api.steering import WheelSteering
from components.api.wheels import WheelDrive
from components.messages import joint_samples

pytestmark = pytest.mark.e2e

LIMBS = ("limb1", "limb2")
WHEELS = {s: (f"{s}_wheel_left", f"{s}_wheel_right") for s in ("wheel1", "wheel2")}
# The example's poses: rolled a quarter turn at joint1 and back at joint7, then bent flat.
ROLLED = {"joint1": math.pi / 2, "joint7": -math.pi / 2}
BENT = {**ROLLED, "joint2": -0.73, "joint4": 1.56, "joint6": -0.83}


def both(angles: dict[str, float]) -> dict[str, float]:
    return {f"{limb}_{j}": a for limb in LIMBS for j, a in angles.items()}


@pytest.fixture(scope="module")
def dragon() -> tuple[str, str]:
    from components.assembly import from_document
    from msctl.assembler import resolve

    resolved = resolve("dragon", {})
    return resolved.urdf, from_document(resolved.document).root_links[0]


@pytest.fixture
def steering(dragon: tuple[str, str]) -> WheelSteering:
    return WheelSteering(dragon[0], dragon[1], WHEELS)


def level(steering: WheelSteering, positions: dict[str, float]) -> float:
    """Largest tilt (rad) of a wheel axis out of the ground plane."""
    return max(abs(math.asin(w.axis[2])) for w in steering.geometry(positions).wheels)


def test_the_rolled_limbs_pitch_joints_are_the_steering_joints(steering: WheelSteering) -> None:
    # Lying straight, no joint of a limb turns its module about the vertical.
    assert steering.steering_joints("wheel1", {}) == ()
    assert steering.steering_joints("wheel2", {}) == ()
    # Rolled at joint1 and back at joint7: the pitch joints 2, 4 and 6 turn vertical.
    for wheel, limb in (("wheel1", "limb1"), ("wheel2", "limb2")):
        found = steering.steering_joints(wheel, both(ROLLED))
        assert found == tuple(f"{limb}_joint{i}" for i in (2, 4, 6))
    # The modules face away from each other (limb2 is limb1 turned half a turn).
    assert steering.heading("wheel1", {}) == pytest.approx(0.0, abs=1e-9)
    assert abs(steering.heading("wheel2", {})) == pytest.approx(math.pi)


def test_turn_keeps_the_centre_in_place_and_the_module_level(steering: WheelSteering) -> None:
    bent = both(BENT)
    assert level(steering, bent) < 1e-6
    centre = steering.center("wheel1", bent)
    # The bend brings the module in (from 1.30 m), still on the body's axis.
    assert centre[0] == pytest.approx(1.07, abs=0.01) and abs(centre[1]) < 1e-3
    targets = steering.turn("wheel1", math.radians(40.0), bent)
    assert set(targets) == {f"limb1_joint{i}" for i in range(1, 8)}
    turned = {**bent, **targets}
    assert steering.heading("wheel1", turned) == pytest.approx(math.radians(40.0), abs=1e-3)
    assert np.linalg.norm(steering.center("wheel1", turned) - centre) < 1e-3
    assert level(steering, turned) < 2e-3
    # The limbs keep the joint managers' margin from every limit (limb joints 2 and 6: +-2).
    assert all(abs(targets[f"limb1_joint{i}"]) <= 2.0 - 0.02 + 1e-9 for i in (2, 6))


def test_a_stretched_limb_cannot_turn_its_module_about_its_centre(
    steering: WheelSteering,
) -> None:
    with pytest.raises(ApiError, match=r"wheel module wheel1 cannot turn .* bend the limb"):
        steering.turn("wheel1", math.radians(20.0), both(ROLLED))
    with pytest.raises(ApiError, match="no wheel module 'wheel9'"):
        steering.heading("wheel9", {})


def test_path_turns_every_module_in_small_steps_the_short_way(steering: WheelSteering) -> None:
    bent = both(BENT)
    centres = {s: steering.center(s, bent) for s in WHEELS}
    path = steering.path(math.radians(45.0), bent)
    assert len(path) == 3  # 45 degrees in steps of at most 15
    headings = [{s: steering.heading(s, bent) for s in WHEELS}]
    positions = dict(bent)
    for waypoint in path:
        positions.update(waypoint)
        headings.append({s: steering.heading(s, positions) for s in WHEELS})
        for slot in WHEELS:
            assert np.linalg.norm(steering.center(slot, positions) - centres[slot]) < 1e-3
    for before, after in itertools.pairwise(headings):
        for slot in WHEELS:
            step = abs(math.remainder(after[slot] - before[slot], 2 * math.pi))
            assert step <= math.radians(15.0) + 1e-3
    # wheel2 faces backwards: it rolls along the line at 225 degrees, turning 45 like wheel1.
    assert headings[-1]["wheel1"] == pytest.approx(math.radians(45.0), abs=1e-3)
    assert math.remainder(headings[-1]["wheel2"] - math.radians(225.0), 2 * math.pi) == (
        pytest.approx(0.0, abs=1e-3)
    )
    # To 135 degrees: each module takes the way along the line nearer its rest heading
    # (wheel1 -45, wheel2 135), both turning 90 degrees clockwise.
    across = steering.path(math.radians(135.0), positions)
    assert len(across) == 6
    positions.update(across[-1])
    assert steering.heading("wheel1", positions) == pytest.approx(math.radians(-45.0), abs=1e-3)
    assert steering.heading("wheel2", positions) == pytest.approx(math.radians(135.0), abs=1e-3)
    # Already there: nothing to do.
    assert steering.path(math.radians(-45.0), positions) == []


def test_wheel_speeds_along_the_steered_direction_and_none_across(
    steering: WheelSteering,
) -> None:
    positions = dict(both(BENT))
    for waypoint in steering.path(math.radians(45.0), positions):
        positions.update(waypoint)
    geometry = steering.geometry(positions)
    along = geometry.wheel_speeds(0.2 * math.cos(math.pi / 4), 0.0, 0.2 * math.sin(math.pi / 4))
    assert all(abs(v) == pytest.approx(0.2 / 0.16, rel=1e-3) for v in along.values())
    across = geometry.wheel_speeds(
        0.2 * math.cos(3 * math.pi / 4), 0.0, 0.2 * math.sin(3 * math.pi / 4)
    )
    assert all(abs(v) < 1e-3 for v in across.values())


# ---------------------------------------------------------------------- the drive, no Zenoh
class _Endpoint:
    def __init__(self) -> None:
        self.sent: list[Any] = []

    def publish(self, message: Any) -> None:
        self.sent.append(message)

    def close(self) -> None:
        pass


class _Node:
    def __init__(self) -> None:
        self.endpoints: dict[str, _Endpoint] = {}

    def publisher(self, topic: str, _type: str) -> _Endpoint:
        return self.endpoints.setdefault(topic, _Endpoint())

    def subscription(self, topic: str, _type: str, _callback: Any) -> _Endpoint:
        return self.endpoints.setdefault(topic, _Endpoint())


def test_travel_drives_along_the_direction_and_ends_at_zero(steering: WheelSteering) -> None:
    positions = dict(both(BENT))
    for waypoint in steering.path(math.radians(45.0), positions):
        positions.update(waypoint)

    async def scenario() -> tuple[list[dict[str, float]], dict[str, float]]:
        node = _Node()
        handlers = []
        for slot, joints in WHEELS.items():
            infos = [
                JointInfo(j, "continuous", -math.inf, math.inf, 6.0, 30.0, control="velocity")
                for j in joints
            ]
            handlers.append(JointHandler(node, slot, infos))
        drive = WheelDrive(
            handlers,
            steering.geometry({}),  # stale on purpose: travel refreshes it from the limbs
            acceleration=2.0,
            rate=100.0,
            steering=steering,
            positions=lambda: positions,
        )
        assert drive.headings()["wheel1"] == pytest.approx(math.radians(45.0), abs=1e-3)
        assert drive.steering_joints()["wheel1"] == ("limb1_joint2", "limb1_joint4", "limb1_joint6")
        assert drive.steer_path(math.radians(45.0)) == []
        assert await drive.travel(0.1, math.radians(45.0), speed=0.2)
        sent: list[dict[str, float]] = []
        for slot in WHEELS:
            for message in node.endpoints[f"/{slot}/joint_set"].sent:
                sent.append({n: v for n, _p, v, _e in joint_samples(message)})
        return sent, drive.speeds(0.2 * math.cos(math.pi / 4), 0.0, 0.2 * math.sin(math.pi / 4))

    sent, cruise = asyncio.run(scenario())
    # At cruise every wheel rolls at 0.2 m/s: 1.25 rad/s, the sign its mounting gives.
    assert all(abs(v) == pytest.approx(1.25, rel=1e-3) for v in cruise.values())
    peak = {n: max((abs(s[n]) for s in sent if n in s), default=0.0) for n in cruise}
    assert all(v == pytest.approx(1.25, rel=1e-3) for v in peak.values())
    finals = {}
    for message in sent:
        finals.update(message)
    assert finals and all(v == 0.0 for v in finals.values())  # a velocity is never left behind


def test_a_wheel_module_s_flaps_are_no_wheels() -> None:
    """The second Dragon of two_dragons rolls on H-line wheel V2 modules, whose position-
    controlled flaps are joints of the module too: the steering took them for wheels and
    failed ("its link has no cylinder or sphere radius"); only velocity joints are wheels."""
    from types import SimpleNamespace

    from components.api.wheels import wheel_joints
    from components.assembly import from_document
    from msctl.assembler import resolve

    resolved = resolve("two_dragons", {})
    assembly = from_document(resolved.document)
    handlers = []
    for slot in ("d2_wheel1", "d2_wheel2"):
        module = assembly.module(slot)
        assert any(j.control == "position" for j in module.joints)  # the flaps
        infos = {
            j.name: JointInfo(j.name, j.type, -math.inf, math.inf, 6.0, 30.0, control=j.control)
            for j in module.joints
        }
        handlers.append(SimpleNamespace(slot=slot, joints=infos))
    wheels = wheel_joints(handlers)
    assert wheels == {
        slot: (f"{slot}_wheel_left", f"{slot}_wheel_right") for slot in ("d2_wheel1", "d2_wheel2")
    }
    root = next(m.root_link for m in assembly.modules if m.slot == "d2_limb1")
    geometry = WheelSteering(resolved.urdf, root, wheels).geometry({})
    assert len(geometry.wheels) == 4 and all(w.radius > 0 for w in geometry.wheels)
