"""The joint syncer's planner with plain calls, and the syncer over fake modules (no Zenoh):
the L-infinity ball around the measured state, the slowest joint pacing the others, asap
clipping, speed_safe bounds, desync re-sync, missing joints, a new motion cancelling the last.
"""

from __future__ import annotations

import asyncio
import math
from typing import Any

import numpy as np
import pytest

from components.api.errors import JointNotReadyError, UnknownJointError
from components.api.joints import JointHandler, JointInfo
from components.api.planner import (
    ASAP,
    LERP,
    SPEED_SAFE,
    UNSAFE,
    SyncPlanner,
    SyncSettings,
    lerp_fraction,
)
from components.api.syncer import JointSyncer
from components.messages import joint_samples, joint_state

pytestmark = pytest.mark.e2e

DT = 0.025


def planner(n: int = 3, delta: float = 0.1, speed: float = 100.0, **kw: Any) -> SyncPlanner:
    settings = SyncSettings(delta=delta, speed=speed, tolerance=0.01, limit_margin=0.0)
    return SyncPlanner(
        [f"j{i}" for i in range(n)], [-3.0] * n, [3.0] * n, [100.0] * n, settings, **kw
    )


def test_lerp_stays_in_the_ball_around_the_measured_state_and_on_the_line() -> None:
    p = planner()
    measured = np.array([0.0, 0.0, 0.0])
    target = np.array([1.0, -0.5, 0.25])
    step = p.step(LERP, measured, DT, target=target)
    assert np.abs(step.command - measured).max() == pytest.approx(0.1)
    # On the straight line: every joint covered the same fraction of its way.
    fractions = step.command / target
    assert np.allclose(fractions, fractions[0])
    assert not step.arrived


def test_lerp_slowest_joint_paces_the_rest() -> None:
    p = planner()
    target = np.array([1.0, 1.0, 1.0])
    measured = np.zeros(3)
    for _ in range(5):
        step = p.step(LERP, measured, DT, target=target)
        # Joints 0 and 1 follow their commands exactly; joint 2 is stuck where it is.
        measured = np.array([step.command[0], step.command[1], 0.0])
    # Joint 2 never moved, so nobody got farther than delta from its start.
    assert np.allclose(step.command, 0.1)
    assert not step.arrived


def test_lerp_arrives_when_the_target_is_inside_the_ball_and_measured_within_tolerance() -> None:
    p = planner()
    target = np.array([0.05, -0.05, 0.0])
    step = p.step(LERP, np.zeros(3), DT, target=target)
    assert np.allclose(step.command, target) and not step.arrived
    step = p.step(LERP, target + 0.005, DT, target=target)
    assert step.arrived


def test_lerp_speed_caps_the_fastest_joint() -> None:
    p = planner(speed=0.4)
    step = p.step(LERP, np.zeros(3), DT, target=np.array([1.0, 0.5, 0.0]))
    assert step.command[0] == pytest.approx(0.4 * DT)
    assert step.command[1] == pytest.approx(0.2 * DT)


def test_lerp_fraction_is_the_largest_inside_the_ball() -> None:
    start = np.array([0.05, 0.0])
    measured = np.zeros(2)
    goal = np.array([1.0, -1.0])
    a = lerp_fraction(start, goal, measured, 0.1, np.full(2, np.inf))
    point = start + a * (goal - start)
    assert np.abs(point - measured).max() == pytest.approx(0.1)
    assert point[0] == pytest.approx(0.1)  # joint 0 leaned toward its goal already


def test_asap_clips_each_joint_independently() -> None:
    p = planner()
    step = p.step(ASAP, np.zeros(3), DT, target=np.array([1.0, 0.02, -0.5]))
    assert np.allclose(step.command, [0.1, 0.02, -0.1])


def test_unsafe_goes_straight_to_the_target_within_limits() -> None:
    p = planner()
    step = p.step(UNSAFE, np.zeros(3), DT, target=np.array([1.0, 5.0, -0.5]))
    assert np.allclose(step.command, [1.0, 3.0, -0.5])


def test_speed_safe_advances_at_the_speed_and_stays_in_the_ball() -> None:
    p = planner(delta=0.1)
    velocity = np.array([1.0, -2.0, 0.0])
    step = p.step(SPEED_SAFE, np.zeros(3), DT, velocity=velocity)
    assert np.allclose(step.command, velocity * DT)
    # The joints do not follow: the commands stop at the ball's edge, never beyond.
    for _ in range(50):
        step = p.step(SPEED_SAFE, np.zeros(3), DT, velocity=velocity)
    assert np.allclose(step.command, [0.1, -0.1, 0.0])
    assert not step.arrived


def test_commands_never_leave_the_limits_with_margin() -> None:
    settings = SyncSettings(delta=0.5, speed=100.0, limit_margin=0.02)
    p = SyncPlanner(["a", "b"], [-1.0, -math.inf], [1.0, math.inf], [10.0, 10.0], settings)
    step = p.step(UNSAFE, np.zeros(2), DT, target=np.array([2.0, 50.0]))
    assert step.command[0] == pytest.approx(0.98)
    assert step.command[1] == 50.0  # an unbounded (continuous) joint has no limit
    step = p.step(SPEED_SAFE, np.array([0.97, 0.0]), DT, velocity=np.array([10.0, 0.0]))
    assert step.command[0] <= 0.98


def test_desync_restarts_from_the_measurement() -> None:
    p = planner(last=[0.0, 0.0, 0.0])
    # Someone pushed joint 1 by 0.3: the last command is 0.3 away, beyond delta.
    measured = np.array([0.0, 0.3, 0.0])
    step = p.step(LERP, measured, DT, target=np.array([0.0, 0.3, 1.0]))
    assert step.resynced and p.resyncs == 1
    assert np.abs(step.command - measured).max() <= 0.1 + 1e-12
    # In sync now: no more resyncs.
    step = p.step(LERP, step.command, DT, target=np.array([0.0, 0.3, 1.0]))
    assert not step.resynced and p.resyncs == 1


def test_first_step_starts_from_the_measurement() -> None:
    p = planner()
    step = p.step(LERP, np.array([0.5, 0.5, 0.5]), DT, target=np.array([0.5, 0.5, 0.55]))
    assert np.allclose(step.command, [0.5, 0.5, 0.55])


def test_settings_refuse_nonsense() -> None:
    with pytest.raises(ValueError, match="delta"):
        SyncSettings(delta=0.0)
    with pytest.raises(ValueError, match="unknown mode"):
        planner().step("teleport", np.zeros(3), DT, target=np.zeros(3))


# ---------------------------------------------------------------------- the syncer, no Zenoh
class FakeEndpoint:
    def __init__(self, topic: str, callback: Any = None) -> None:
        self.topic = topic
        self.callback = callback
        self.sent: list[Any] = []

    def publish(self, message: Any) -> None:
        self.sent.append(message)

    def close(self) -> None:
        pass


class FakeNode:
    """Stands in for a comm Node: publishers record, subscriptions are fed by the test."""

    def __init__(self) -> None:
        self.endpoints: dict[str, FakeEndpoint] = {}

    def publisher(self, topic: str, _type: str) -> FakeEndpoint:
        return self.endpoints.setdefault(topic, FakeEndpoint(topic))

    def subscription(self, topic: str, _type: str, callback: Any) -> FakeEndpoint:
        return self.endpoints.setdefault(topic, FakeEndpoint(topic, callback))


def fake_limb(node: FakeNode, slot: str = "limb1", n: int = 3) -> JointHandler:
    infos = [JointInfo(f"{slot}_joint{i + 1}", "revolute", -2.0, 2.0, 1.5, 100.0) for i in range(n)]
    infos.append(JointInfo(f"{slot}_joint9", "revolute", -2.0, 2.0, 1.5, 100.0, locked=True))
    return JointHandler(node, slot, infos)


class FollowingLimb:
    """Feeds joint_read with the last command (a perfect, instant limb)."""

    def __init__(self, node: FakeNode, slot: str, positions: dict[str, float]) -> None:
        self.node, self.slot, self.positions = node, slot, dict(positions)
        self.read = node.endpoints[f"/{slot}/joint_read"]
        self.set = node.endpoints[f"/{slot}/joint_set"]
        self.seen = 0
        self.publish()

    def publish(self) -> None:
        from components.messages import JointSample

        self.read.callback(joint_state([JointSample(n, p) for n, p in self.positions.items()]))

    def follow(self) -> None:
        for message in self.set.sent[self.seen :]:
            for name, position, _v, _e in joint_samples(message):
                if position is not None:
                    self.positions[name] = position
        self.seen = len(self.set.sent)
        self.publish()


async def run_following(limb: FollowingLimb, seconds: float) -> None:
    end = asyncio.get_running_loop().time() + seconds
    while asyncio.get_running_loop().time() < end:
        limb.follow()
        await asyncio.sleep(0.005)


def test_syncer_lerp_arrives_and_a_new_motion_cancels_the_previous() -> None:
    async def scenario() -> None:
        node = FakeNode()
        handler = fake_limb(node)
        limb = FollowingLimb(node, "limb1", {f"limb1_joint{i}": 0.0 for i in (1, 2, 3, 9)})
        syncer = JointSyncer([handler], SyncSettings(speed=2.0, rate=100.0))
        first = syncer.lerp({"joint1": 1.0, "joint2": -1.0})
        follower = asyncio.create_task(run_following(limb, 3.0))
        await asyncio.sleep(0.1)
        second = syncer.lerp({"limb1_joint1": 0.2})
        assert await first is False  # superseded, resolves without raising
        assert await second.wait(timeout=2.0) is True
        await asyncio.sleep(0.05)
        assert limb.positions["limb1_joint1"] == pytest.approx(0.2)
        # joint2 was left where the first motion had taken it (within the ball), not moved on.
        assert -1.0 < limb.positions["limb1_joint2"] < 0.0
        follower.cancel()
        # The locked joint is never commanded.
        for message in limb.set.sent:
            assert "limb1_joint9" not in message.name

    asyncio.run(scenario())


def test_syncer_missing_joints_raise_naming_them() -> None:
    async def scenario() -> None:
        node = FakeNode()
        handler = fake_limb(node)
        syncer = JointSyncer([handler])
        with pytest.raises(UnknownJointError, match="joint7"):
            syncer.lerp({"joint7": 0.1})
        with pytest.raises(UnknownJointError, match="locked"):
            syncer.lerp({"joint9": 0.1})
        with pytest.raises(JointNotReadyError, match="limb1_joint2"):
            syncer.lerp({"joint2": 0.1})  # no joint_read yet

    asyncio.run(scenario())


def test_syncer_stop_holds_at_the_measured_state() -> None:
    async def scenario() -> None:
        node = FakeNode()
        handler = fake_limb(node)
        limb = FollowingLimb(node, "limb1", {f"limb1_joint{i}": 0.3 for i in (1, 2, 3)})
        syncer = JointSyncer([handler])
        motion = syncer.speed_safe({"joint1": 0.5})
        await asyncio.sleep(0.05)
        await syncer.stop()
        assert await motion is False
        last = joint_samples(limb.set.sent[-1])
        assert {s.name: s.position for s in last} == {f"limb1_joint{i}": 0.3 for i in (1, 2, 3)}
        assert all(s.velocity is None for s in last)

    asyncio.run(scenario())


# ---------------------------------------------------------------------- wheels and IK lines
def test_wheel_geometry_comes_from_the_dragon_urdf() -> None:
    from components.api.wheels import WheelGeometry
    from components.assembly import from_document
    from msctl.assembler import resolve

    resolved = resolve("dragon", {})
    assembly = from_document(resolved.document)
    wheels = [j.name for slot in ("wheel1", "wheel2") for j in assembly.module(slot).joints]
    geometry = WheelGeometry.from_urdf(resolved.urdf, assembly.root_links[0], wheels)
    assert geometry.wheel_radius == pytest.approx(0.16)  # the wheel link's cylinder
    assert geometry.track_width == pytest.approx(0.38, abs=1e-6)  # joint origins at +-0.19 m
    straight = geometry.wheel_speeds(0.32, 0.0)
    # Every wheel rolls the body forward at 0.32 m/s: |speed| = v / r, whatever its mounting.
    assert all(abs(v) == pytest.approx(2.0) for v in straight.values())
    # The two wheel modules face opposite ways (limb2 is turned by 180 degrees).
    assert straight["wheel1_wheel_left"] == pytest.approx(-straight["wheel2_wheel_left"])
    spin = geometry.wheel_speeds(0.0, 1.0)
    left = [w for w in geometry.wheels if w.center[1] > 0]
    right = [w for w in geometry.wheels if w.center[1] < 0]
    # Turning left: the ground under the left wheels goes back, under the right ones forward.
    for w in left:
        assert spin[w.joint] * (w.rolling @ np.array([1.0, 0.0, 0.0])) < 0
    for w in right:
        assert spin[w.joint] * (w.rolling @ np.array([1.0, 0.0, 0.0])) > 0


def test_cartesian_waypoints_stay_on_the_line_and_in_the_ball() -> None:
    import pinocchio as pin

    from components.api.ik_syncer import CartesianPlanner, IkSyncSettings, Line

    planner = CartesianPlanner(IkSyncSettings(delta_position=0.02, speed=10.0))
    start = pin.SE3(np.eye(3), np.zeros(3))
    line = Line(start, pin.SE3(np.eye(3), np.array([0.1, 0.0, 0.0])))
    # The measured tip lags 1 cm off the line: the waypoint is the farthest point of the
    # line within 2 cm of it.
    measured = pin.SE3(np.eye(3), np.array([0.0, 0.01, 0.0]))
    progress, _ = planner.reach(line, measured, 0.025, False)
    point = line.at(progress).translation
    assert point[1] == 0.0 and point[2] == 0.0
    assert np.linalg.norm(point - measured.translation) == pytest.approx(0.02)
    # A tip pushed far off the line holds the progress where it was, never goes back.
    line.progress = progress
    far = pin.SE3(np.eye(3), np.array([0.0, 0.5, 0.0]))
    assert planner.reach(line, far, 0.025, False)[0] == progress
    assert planner.held == 1


def test_a_resync_at_a_motions_start_is_quiet_and_a_lagging_joint_warns_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    joints = {f"limb1_joint{i}": 0.0 for i in (1, 2, 3, 9)}

    async def scenario() -> None:
        node = FakeNode()
        syncer = JointSyncer([fake_limb(node)], SyncSettings(speed=2.0, rate=100.0))
        limb = FollowingLimb(node, "limb1", joints)
        follower = asyncio.create_task(run_following(limb, 10.0))
        assert await syncer.lerp({"joint1": 0.5}).wait(timeout=5.0)
        # Moved by hand between motions: the next motion starts from the measurement.
        limb.positions["limb1_joint1"] = -0.5
        limb.publish()
        with caplog.at_level("DEBUG", logger="components.api.syncer"):
            assert await syncer.lerp({"joint1": 0.0}).wait(timeout=5.0)
            start_only = [r for r in caplog.records if r.name == "components.api.syncer"]
            assert [r.levelname for r in start_only] == ["DEBUG"]
            caplog.clear()
            # Pushed back twice during one motion: one warning, in plain words.
            motion = syncer.lerp({"joint1": 1.5})
            for _ in range(2):
                await asyncio.sleep(0.1)
                limb.positions["limb1_joint1"] -= 0.5
                limb.publish()
            assert await motion.wait(timeout=5.0)
        follower.cancel()
        warnings = [r for r in caplog.records if r.levelname == "WARNING"]
        assert len(warnings) == 1, [r.getMessage() for r in caplog.records]
        assert "the joints lag the command" in warnings[0].getMessage()

    asyncio.run(scenario())
