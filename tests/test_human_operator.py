"""The human_operator component kind: its relay and second deadman (core, fake time), its
routes from the assembly, and the component run for real in-process on Zenoh: a screen
attaches, its claims are held by the human operator's node, its commands are relayed, and a
relayed stream that stops gets exactly one stop, then silence."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest
from conftest import quick_peer_settings, quick_router, wait_until

from components import kinds
from components.assembly import ResolvedAssembly, from_document
from components.build import build_component
from components.claims import Claims
from components.comm.node import Node
from components.comm.session import SessionSettings, open_session
from components.executor.core import RecordingOutbox
from components.executor.runner import run_built
from components.human_operator.client import (
    AttachRefused,
    attach,
    detach,
    station_operator,
)
from components.human_operator.core import HumanOperatorConfig, HumanOperatorCore, twist
from components.human_operator.routes import DRIVE, routes_of
from components.messages import JOINT_STATE, TWIST, JointSample, joint_samples, joint_state
from msctl.assembler import resolve
from msctl.launcher.plan import plan_host

OPERATOR = "/gc1/human_operator"


@pytest.fixture(scope="module")
def dragon() -> ResolvedAssembly:
    return from_document(resolve("dragon").document)


@pytest.fixture
def router_endpoint() -> Iterator[str]:
    yield from quick_router()


@pytest.fixture
def session_settings(router_endpoint: str) -> SessionSettings:
    return quick_peer_settings(router_endpoint)


# ---------------------------------------------------------------------------- the kind
def test_the_kind_is_a_runnable_station_kind_with_a_bounded_deadman(dragon) -> None:
    entry = kinds.get("human_operator")
    assert entry.placement is kinds.Placement.STATION and entry.runnable
    kinds.check_params(entry, {"deadman_timeout": 0.5})
    with pytest.raises(kinds.KindError, match="deadman_timeout must be > 0"):
        kinds.check_params(entry, {"deadman_timeout": 0.0})
    with pytest.raises(kinds.KindError, match=r"at most 2\.0 s"):
        kinds.check_params(entry, {"deadman_timeout": 30.0})
    plan = plan_host(dragon, "a-laptop")
    (run,) = [c for c in plan.components if c.kind == "human_operator"]
    assert run.node_fqn == OPERATOR and run.first_output == "/gc1/diagnostics"
    assert not plan.not_built or "human_operator" not in {k for _, k in plan.not_built}
    assert station_operator(dragon, "ground1") == OPERATOR
    assert station_operator(dragon, "a-laptop") is None


def test_routes_are_each_modules_joint_set_and_each_robots_cmd_vel(dragon) -> None:
    routes = {r.target: r for r in routes_of(dragon, OPERATOR)}
    assert set(routes) == {
        "/limb1/joint_set",
        "/limb2/joint_set",
        "/wheel1/joint_set",
        "/wheel2/joint_set",
        "/cmd_vel",
    }
    assert routes["/limb1/joint_set"].relay == f"{OPERATOR}/relay/limb1/joint_set"
    assert routes["/limb1/joint_set"].modules == ("limb1",)
    assert routes["/cmd_vel"].kind == DRIVE and routes["/cmd_vel"].msg_type == TWIST
    assert set(routes["/cmd_vel"].modules) == {"limb1", "limb2", "wheel1", "wheel2"}
    two = from_document(resolve("two_dragons").document)
    drives = {r.target: r.modules for r in routes_of(two, "/gc_front/human_operator")}
    assert set(drives["/d2_limb1/cmd_vel"]) == {"d2_limb1", "d2_limb2", "d2_wheel1", "d2_wheel2"}
    assert "/cmd_vel" not in drives


# ---------------------------------------------------------------------------- the core
def core_for(dragon, timeout: float = 0.3) -> tuple[HumanOperatorCore, RecordingOutbox]:
    core = HumanOperatorCore(
        "gc1/human_operator", routes_of(dragon, OPERATOR), HumanOperatorConfig(timeout)
    )
    outbox = RecordingOutbox()
    core.bind(outbox)
    return core, outbox


def test_a_twist_stream_that_stops_gets_exactly_one_zero_twist_after_the_timeout(dragon):
    core, outbox = core_for(dragon)
    now = 0.0
    for _ in range(10):  # a screen at 20 Hz
        core.on_relay("/cmd_vel", twist(0.2), now)
        core.tick(now)
        now += 0.05
    assert [m.linear.x for m in outbox.take("/cmd_vel")] == [0.2] * 10
    last = now - 0.05
    core.tick(last + 0.29)  # inside the timeout: nothing yet
    assert outbox.take("/cmd_vel") == []
    core.tick(last + 0.31)
    (stop,) = outbox.take("/cmd_vel")
    assert stop.linear.x == 0.0 and stop.angular.z == 0.0
    for later in (0.5, 1.0, 5.0):  # then silence
        core.tick(last + later)
    assert outbox.take("/cmd_vel") == []
    assert core.streams["/cmd_vel"].deadman_stops == 1


def test_a_screen_that_sends_its_own_stop_gets_no_second_one(dragon):
    core, outbox = core_for(dragon)
    core.on_relay("/cmd_vel", twist(0.2), 0.0)
    core.on_relay("/cmd_vel", twist(), 0.05)  # the screen's own one stop
    for now in (0.4, 1.0):
        core.tick(now)
    assert [m.linear.x for m in outbox.take("/cmd_vel")] == [0.2, 0.0]


def test_joint_streams_stop_velocity_joints_at_0_and_hold_position_joints(dragon):
    core, outbox = core_for(dragon)
    wheel = [JointSample("wheel1_wheel_left", None, 1.5, None)]
    core.on_relay("/wheel1/joint_set", joint_state(wheel), 0.0)
    for i, position in enumerate((0.10, 0.11, 0.12)):  # a jog: a new target each time
        core.on_relay(
            "/limb1/joint_set", joint_state([JointSample("limb1_joint2", position)]), i * 0.05
        )
    outbox.take()
    core.tick(0.5)
    (wheel_stop,) = outbox.take("/wheel1/joint_set")
    assert joint_samples(wheel_stop) == [JointSample("wheel1_wheel_left", None, 0.0, None)]
    (limb_stop,) = outbox.take("/limb1/joint_set")
    assert joint_samples(limb_stop) == [JointSample("limb1_joint2", 0.12, None, None)]
    core.tick(2.0)
    assert outbox.take("/wheel1/joint_set") == outbox.take("/limb1/joint_set") == []


def test_a_hold_is_no_motion_and_letting_go_stops_what_moves(dragon):
    core, outbox = core_for(dragon)
    hold = joint_state([JointSample("limb1_joint2", 0.3)])
    core.on_relay("/limb1/joint_set", hold, 0.0)  # first target: moves
    core.on_relay("/limb1/joint_set", hold, 0.05)  # the same target again: a hold
    core.tick(1.0)
    assert len(outbox.take("/limb1/joint_set")) == 2  # relayed, and no stop of its own
    core.on_relay("/cmd_vel", twist(0.1, 0.0, 0.3), 1.0)
    outbox.take()
    assert core.end(["wheel2"], 1.01) == ["/cmd_vel"]  # the robot's cmd_vel touches wheel2
    (stop,) = outbox.take("/cmd_vel")
    assert stop.angular.z == 0.0
    core.on_relay("/cmd_vel", twist(0.1), 2.0)
    core.stop(2.01)  # the component stops: one stop for what moves
    assert [m.linear.x for m in outbox.take("/cmd_vel")] == [0.1, 0.0]


# ---------------------------------------------------------------------------- live
class Wire:
    """What arrives on the targets, with arrival times."""

    def __init__(self, node: Node) -> None:
        self.lock = threading.Lock()
        self.seen: dict[str, list[tuple[float, Any]]] = {}
        for topic, msg_type in (("/cmd_vel", TWIST), ("/wheel1/joint_set", JOINT_STATE)):
            node.subscription(topic, msg_type, lambda m, t=topic: self._on(t, m))

    def _on(self, topic: str, message: Any) -> None:
        with self.lock:
            self.seen.setdefault(topic, []).append((time.monotonic(), message))

    def on(self, topic: str) -> list[tuple[float, Any]]:
        with self.lock:
            return list(self.seen.get(topic, ()))


@pytest.fixture
def running(dragon, session_settings) -> Iterator[Any]:
    """The dragon's gc1/human_operator run in-process on the test router."""
    built = build_component(dragon.component("gc1/human_operator"), dragon, {})
    ready = threading.Event()
    executors: list[Any] = []

    def on_ready(executor: Any) -> None:
        executors.append(executor)
        ready.set()

    runner = threading.Thread(
        target=run_built, args=([built], session_settings), kwargs={"on_ready": on_ready}
    )
    runner.start()
    try:
        assert ready.wait(30.0)
        yield built
    finally:
        if executors:
            executors[0].stop()
        runner.join(timeout=30.0)


def attach_when_served(node: Node, holder: str, modules: list[str], take: bool = False) -> Any:
    """Attach, asking again while the fresh session has no route to the service yet."""
    from components.comm.services import ServiceError

    deadline = time.monotonic() + 30.0
    while True:
        try:
            return attach(node, OPERATOR, holder, modules, take=take)
        except ServiceError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)


def test_a_screen_attaches_its_commands_are_relayed_and_a_frozen_stream_gets_one_stop(
    running, session_settings
) -> None:
    screens = open_session(session_settings)
    other = open_session(session_settings)
    watcher = open_session(session_settings)
    screen = Node(screens, "teleop", "/ground1")
    intruder = Node(other, "teleop", "/elsewhere")
    observer = Node(watcher, "observer")
    claims = Claims(watcher, 0)
    try:
        wire = Wire(observer)
        modules = ["limb1", "limb2", "wheel1", "wheel2"]
        attached = attach_when_served(screen, "ana@ground1", modules)
        assert attached.operator == OPERATOR and set(attached.claimed) == set(modules)
        assert attached.relays["/cmd_vel"] == f"{OPERATOR}/relay/cmd_vel"
        # The human operator's node holds the claims, in the screen's operator's name.
        wait_until(lambda: set(claims.holders()) == set(modules), 10.0, "the four claims")
        held = claims.holders()["wheel1"]
        assert (held.holder, held.node) == ("ana@ground1", OPERATOR)
        relay = screen.publisher(attached.relays["/cmd_vel"], TWIST)
        stray = intruder.publisher(attached.relays["/cmd_vel"], TWIST)
        # A screen that did not attach is refused on the relay; the attached one is relayed.
        for _ in range(5):
            stray.publish(twist(9.0))
            time.sleep(0.02)
        wait_until(
            lambda: relay.publish(twist(0.2)) or wire.on("/cmd_vel"), 10.0, "a relayed Twist"
        )
        for _ in range(10):  # 20 Hz, then the screen freezes
            relay.publish(twist(0.2))
            time.sleep(0.05)
        frozen = time.monotonic()
        wait_until(
            lambda: any(m.linear.x == 0.0 for _, m in wire.on("/cmd_vel")), 10.0, "the one stop"
        )
        time.sleep(1.0)  # then silence
        seen = wire.on("/cmd_vel")
        assert all(m.linear.x in (0.2, 0.0) for _, m in seen), "the stray 9 m/s got through"
        stops = [(t, m) for t, m in seen if m.linear.x == 0.0]
        assert len(stops) == 1 and stops[0] == seen[-1]
        # Within the timeout (0.3 s) and a tick, plus what a busy machine adds on the way.
        print(f"\nstop {stops[0][0] - frozen:.3f} s after the screen's last command")
        # Letting go releases the claims.
        detach(screen, OPERATOR)
        wait_until(lambda: not claims.holders(), 10.0, "the claims released")
    finally:
        claims.close()
        for node in (screen, intruder, observer):
            node.close()
        for session in (screens, other, watcher):
            session.close()


def test_a_second_screen_is_refused_then_takes_over_and_a_crashed_screen_lets_go(
    running, session_settings
) -> None:
    first_session = open_session(session_settings)
    second_session = open_session(session_settings)
    watcher = open_session(session_settings)
    first = Node(first_session, "teleop", "/ground1")
    second = Node(second_session, "teleop_b", "/ground1")
    claims = Claims(watcher, 0)
    observer = Node(watcher, "observer")
    try:
        wire = Wire(observer)
        attach_when_served(first, "ana@ground1", ["wheel1"])
        with pytest.raises(AttachRefused, match="wheel1 is claimed by ana@ground1") as refused:
            attach_when_served(second, "bo@ground1", ["wheel1"])
        assert refused.value.holder is None or refused.value.holder.holder == "ana@ground1"
        attach_when_served(second, "bo@ground1", ["wheel1"], take=True)
        wait_until(
            lambda: getattr(claims.holder("wheel1"), "holder", "") == "bo@ground1",
            10.0,
            "bo's claim",
        )
        # The first screen's relay is closed now, the second's open.
        relay = f"{OPERATOR}/relay/wheel1/joint_set"
        old = first.publisher(relay, JOINT_STATE)
        new = second.publisher(relay, JOINT_STATE)
        spin = joint_state([JointSample("wheel1_wheel_left", None, 1.0, None)])
        slow = joint_state([JointSample("wheel1_wheel_left", None, 0.5, None)])
        for _ in range(5):
            old.publish(spin)
            time.sleep(0.02)
        wait_until(lambda: new.publish(slow) or wire.on("/wheel1/joint_set"), 10.0, "relayed")
        velocities = [joint_samples(m)[0].velocity for _, m in wire.on("/wheel1/joint_set")]
        assert 1.0 not in velocities and 0.5 in velocities
        # The second screen crashes (its session goes, no detach): the desk lets go, after
        # the moving stream's one stop.
        second.close()
        second_session.close()
        wait_until(lambda: claims.holder("wheel1") is None, 15.0, "the crashed screen's claim")
        stops = [m for _, m in wire.on("/wheel1/joint_set") if joint_samples(m)[0].velocity == 0]
        assert len(stops) == 1
    finally:
        claims.close()
        for node in (first, second, observer):
            node.close()
        for session in (first_session, second_session, watcher):
            session.close()


def test_teleop_on_the_station_attaches_to_its_human_operator_and_elsewhere_runs_alone(
    dragon, running, session_settings
) -> None:
    """``msctl teleop``'s link: on the station's computer its claims are the human
    operator's and its commands go through the relay (to real joint managers over emulated
    motors); on another computer it claims and commands for itself."""
    from teleop_rig import ModulesRig

    from msctl.teleop.link import Link

    rig = ModulesRig(dragon, ["wheel1"], session_settings)
    session = open_session(session_settings)
    watcher = open_session(session_settings)
    node = Node(session, "teleop", "/ground1")
    claims = Claims(watcher, 0)
    link = None
    try:
        link = Link.open(node, dragon, ["wheel1"], health=False, timeout=30.0, station="ground1")
        assert link.through == OPERATOR
        wait_until(lambda: claims.holder("wheel1") is not None, 10.0, "the claim")
        assert claims.holder("wheel1").node == OPERATOR
        handler = link.handlers["wheel1"]
        assert handler.relay == f"{OPERATOR}/relay/wheel1/joint_set"
        motors = rig.motors["wheel1"]

        def spun() -> bool:
            handler.send([JointSample("wheel1_wheel_left", None, 0.5, None)])
            return any(c.velocity for c in list(motors.commands))

        wait_until(spun, 30.0, "a relayed command reaching the motors")
        link.close()
        link = None
        wait_until(lambda: claims.holder("wheel1") is None, 10.0, "the claim released")
        alone = Link.open(node, dragon, ["wheel1"], health=False, timeout=30.0, station="ground9")
        try:
            assert alone.through is None and not isinstance(alone.handlers["wheel1"], type(handler))
            wait_until(lambda: claims.holder("wheel1") is not None, 10.0, "its own claim")
            assert claims.holder("wheel1").node == node.fqn
        finally:
            alone.close()
    finally:
        if link is not None:
            link.close()
        claims.close()
        node.close()
        session.close()
        watcher.close()
        rig.close()
