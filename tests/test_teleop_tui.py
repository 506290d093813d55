"""The ``msctl teleop`` screen under textual's Pilot, on real Zenoh sessions.

limb1 and wheel1 of a Dragon run their real joint managers (over emulated motors) in this
process; the teleop opens its real link to them and an observer on its own session watches
the wire (``joint_set``, ``cmd_vel``). In every mode a key puts a command on the wire, the
deadman's timeout gives exactly one stop and then silence, and focus loss stops. Space
e-stops through the joint managers' ``halt``, Esc stops and quits.

Waits are on events (samples arriving, the operator going idle), with generous bounds: the
machine may be loaded, and nothing here measures speed.
"""

from __future__ import annotations

import asyncio
import itertools
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import pytest
from conftest import quick_peer_settings, quick_router, resolved_assembly, wait_until
from teleop_rig import ModulesRig

from components.assembly import ResolvedAssembly
from components.comm.node import Node
from components.comm.qos import SENSOR
from components.comm.session import SessionSettings, open_session
from components.messages import JOINT_STATE, joint_samples, msg
from msctl.teleop.app import TeleopApp, bar, key_name
from msctl.teleop.core import Stop, TeleopCore, TeleopSettings
from msctl.teleop.keys import DRIVE, IK, JOINT
from msctl.teleop.link import Link
from msctl.teleop.operator import Operator, Sent
from msctl.teleop.wire import TWIST

SLOTS = ["limb1", "wheel1"]
#: Bound on every wait (never a speed test).
PATIENCE = 60.0


@pytest.fixture(scope="module")
def router_endpoint() -> Iterator[str]:
    yield from quick_router()


@pytest.fixture(scope="module")
def session_settings(router_endpoint: str) -> SessionSettings:
    return quick_peer_settings(router_endpoint)


@pytest.fixture(scope="module")
def dragon(tmp_path_factory: pytest.TempPathFactory) -> ResolvedAssembly:
    return resolved_assembly(tmp_path_factory.mktemp("teleop"), "dragon")


@pytest.fixture(scope="module")
def rig(dragon: ResolvedAssembly, session_settings: SessionSettings) -> Iterator[ModulesRig]:
    rig = ModulesRig(dragon, SLOTS, session_settings)
    try:
        yield rig
    finally:
        rig.close()


#: What routes are probed with: an empty JointState commands nothing (the joint manager
#: takes it as no command), and no Twist has a z speed but this one (nothing listens but
#: the observer).
PROBES = {
    JOINT_STATE: msg(JOINT_STATE),
    TWIST: msg(TWIST, linear=msg("geometry_msgs/msg/Vector3", z=1234.5)),
}


def is_probe(message: Any) -> bool:
    if hasattr(message, "linear"):
        return message.linear.z == 1234.5
    return len(message.name) == 0


@dataclass
class Wire:
    """Everything seen on the command topics, in arrival order."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    samples: list[tuple[float, str, Any]] = field(default_factory=list)
    motor_reports: int = 0

    probed: set[str] = field(default_factory=set)

    def on(self, topic: str) -> Callable[[Any], None]:
        def record(message: Any) -> None:
            with self.lock:
                if is_probe(message):
                    self.probed.add(topic)
                else:
                    self.samples.append((time.monotonic(), topic, message))

        return record

    def on_motors(self, _message: Any) -> None:
        with self.lock:
            self.motor_reports += 1

    def clear(self) -> None:
        with self.lock:
            self.samples.clear()

    def seen(self, topic: str | None = None) -> list[Any]:
        with self.lock:
            return [m for _, t, m in self.samples if topic is None or t == topic]


@dataclass
class Teleop:
    """A teleop's link and operator on their own session, and an observer of the wire."""

    link: Link
    operator: Operator
    wire: Wire
    sent: list[Sent]

    def app(self, **kw: Any) -> TeleopApp:
        return TeleopApp(self.operator, self.link, template="dragon", **kw)


@dataclass
class Plane:
    """The teleop's link on its own session, and the observer of the wire on another."""

    link: Link
    wire: Wire


@pytest.fixture(scope="module")
def plane(
    rig: ModulesRig, dragon: ResolvedAssembly, session_settings: SessionSettings
) -> Iterator[Plane]:
    """One link for every test (a link is the slow part: it waits for the joint managers'
    answers and readings); each test makes its own core and operator on it."""
    opened: list[Any] = []
    try:
        observer_session = open_session(session_settings)
        opened.append(observer_session)
        wire = Wire()
        observer = Node(observer_session, "observer")
        opened.append(observer)
        for slot in SLOTS:
            topic = f"/{slot}/joint_set"
            observer.subscription(topic, JOINT_STATE, wire.on(topic))
        observer.subscription("/cmd_vel", TWIST, wire.on("/cmd_vel"))
        observer.subscription("/limb1/joint_states", JOINT_STATE, wire.on_motors, SENSOR)
        session = open_session(session_settings)
        opened.append(session)
        node = Node(session, "teleop_test")
        opened.append(node)
        # Claims are tested below with links of their own: this one claims nothing.
        link = Link.open(node, dragon, SLOTS, health=False, timeout=PATIENCE, claim=False)
        opened.append(link)
        # Readings come in, and the routes from this session to the observer are up.
        for handler in link.handlers.values():
            asyncio.run(handler.wait_ready(PATIENCE))
        probe = Node(session, "probe")
        opened.append(probe)
        probes = [*((f"/{s}/joint_set", JOINT_STATE) for s in SLOTS), ("/cmd_vel", TWIST)]
        for topic, msg_type in probes:
            publisher = probe.publisher(topic, msg_type)
            wait_until(
                lambda p=publisher, t=topic, m=PROBES[msg_type]: p.publish(m) or t in wire.probed,
                timeout=PATIENCE,
                what=f"a route to the observer on {topic}",
                interval=0.05,
            )
        yield Plane(link, wire)
    finally:
        for thing in reversed(opened):
            thing.close()


@pytest.fixture
def teleop(plane: Plane, rig: ModulesRig) -> Iterator[Callable[..., Teleop]]:
    """A fresh core and operator on the shared link; the wire's record starts empty."""
    operators: list[Operator] = []

    def make(mode: str = JOINT, **settings: float) -> Teleop:
        link = plane.link
        core = TeleopCore(
            TeleopSettings(**settings), link.joints(), link.limbs, link.drive_target, mode
        )
        sent: list[Sent] = []
        operator = Operator(core, link.outputs(), on_sent=sent.append).start()
        operators.append(operator)
        plane.wire.clear()
        return Teleop(link, operator, plane.wire, sent)

    try:
        yield make
    finally:
        for operator in operators:
            operator.close()
        # A test that e-stopped and failed must not leave the next one halted.
        if any(m.core.halted for m in rig.managers.values()):
            plane.link.recover()


async def until(pilot: Any, predicate: Callable[[], Any], what: str) -> Any:
    """Let the app run until ``predicate`` holds (bounded by :data:`PATIENCE`)."""
    deadline = time.monotonic() + PATIENCE
    while not (value := predicate()):
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {PATIENCE} s: {what}")
        await pilot.pause(0.02)
    return value


async def first_on_the_wire(pilot: Any, t: Teleop, topic: str, key: str) -> None:
    """Press ``key`` once; wait for its command on the wire."""
    await pilot.press(key)
    await until(pilot, lambda: t.wire.seen(topic), f"a command on {topic}")


def trace(t: Teleop) -> list[tuple[Any, ...]]:
    """What the operator sent, short, for failure messages."""
    return [
        (round(x.at, 3), x.command.reason if isinstance(x.command, Stop) else x.command.velocity)
        for x in t.sent
    ]


async def one_stop_then_silence(pilot: Any, t: Teleop, topic: str) -> list[Any]:
    """Wait for the stop and for the wire to carry all the operator sent; then time passes
    (30 reports of the emulated motors, 0.3 s at their rate: six of the teleop's periods)
    and brings nothing new."""
    await until(
        pilot, lambda: t.operator.stops_sent == 1 and t.operator.idle, f"the stop: {trace(t)}"
    )
    total = t.operator.moves_sent + t.operator.stops_sent
    await until(pilot, lambda: len(t.wire.seen(topic)) >= total, "every command on the wire")
    reports = t.wire.motor_reports
    await until(pilot, lambda: t.wire.motor_reports >= reports + 30, "motor reports later")
    seen = t.wire.seen(topic)
    assert len(seen) == total, "commands after the stop"
    assert t.operator.stops_sent == 1
    assert [type(s.command).__name__ for s in t.sent].count("Stop") == 1
    assert type(t.sent[-1].command).__name__ == "Stop"
    return seen


# ------------------------------------------------------------------------------ joint mode
def test_joint_mode_w_jogs_the_joint_and_the_timeout_gives_exactly_one_stop(teleop) -> None:
    t = teleop()

    async def scenario() -> None:
        async with t.app().run_test(size=(120, 40)) as pilot:
            start = t.link.handlers["limb1"].positions()["limb1_joint1"]
            await first_on_the_wire(pilot, t, "/limb1/joint_set", "w")
            seen = await one_stop_then_silence(pilot, t, "/limb1/joint_set")
            positions = [joint_samples(m)[0] for m in seen]
            assert {p.name for p in positions} == {"limb1_joint1"}
            # w jogs upward at the jog speed: each step at most the speed times two periods
            # (a late tick never makes a bigger one).
            assert positions[0].position > start
            steps = [b.position - a.position for a, b in itertools.pairwise(positions[:-1])]
            assert all(0.0 < step <= 0.2 * 2 * 0.05 + 1e-9 for step in steps)
            # The stop holds the joint at the last command (no sag to the measurement).
            assert positions[-1].position == pytest.approx(positions[-2].position)
            assert t.sent[-1].command.reason == "deadman"
            # The screen says it stopped, and why.
            assert "stopped (deadman)" in str(app_text(pilot, "#deadman"))

    asyncio.run(scenario())


def test_joint_mode_jogs_a_wheel_in_velocity_and_stops_it_with_velocity_zero(teleop) -> None:
    t = teleop()

    async def scenario() -> None:
        async with t.app().run_test(size=(120, 40)) as pilot:
            await pilot.press("tab")  # wheel1
            assert t.operator.view().module == "wheel1"
            await first_on_the_wire(pilot, t, "/wheel1/joint_set", "s")
            seen = await one_stop_then_silence(pilot, t, "/wheel1/joint_set")
            velocities = [joint_samples(m)[0].velocity for m in seen]
            assert all(v == pytest.approx(-0.2) for v in velocities[:-1])
            assert velocities[-1] == 0.0  # exactly one zero, the stop

    asyncio.run(scenario())


def test_the_selected_joint_is_drawn_as_a_bar_between_its_limbs_limits(teleop) -> None:
    t = teleop()

    async def scenario() -> None:
        async with t.app().run_test(size=(140, 40)) as pilot:
            await pilot.press("down")
            await pilot.pause(0.2)
            text = str(app_text(pilot, "#target"))
            assert "> limb1_joint2" in text and "●" in text
            assert "mode JOINT" in str(app_text(pilot, "#header"))
            assert "w/s jog" in str(app_text(pilot, "#help"))

    asyncio.run(scenario())


@pytest.mark.parametrize(
    ("mode", "key", "topic"),
    [(JOINT, "w", "/limb1/joint_set"), (IK, "i", "/limb1/joint_set"), (DRIVE, "i", "/cmd_vel")],
)
def test_focus_loss_stops_at_once_with_one_stop(teleop, mode, key, topic) -> None:
    from textual import events

    # A long deadman: only the focus loss can end this motion within the test.
    t = teleop(mode=mode, first_timeout=600.0, repeat_timeout=600.0)

    async def scenario() -> None:
        app = t.app()
        async with app.run_test(size=(120, 40)) as pilot:
            await first_on_the_wire(pilot, t, topic, key)
            app.post_message(events.AppBlur())
            seen = await one_stop_then_silence(pilot, t, topic)
            assert len(seen) >= 2
            assert t.sent[-1].command.reason == "focus lost"

    asyncio.run(scenario())


def test_a_mode_change_while_moving_gives_one_stop(teleop) -> None:
    t = teleop(first_timeout=600.0, repeat_timeout=600.0)

    async def scenario() -> None:
        async with t.app().run_test(size=(120, 40)) as pilot:
            await first_on_the_wire(pilot, t, "/limb1/joint_set", "w")
            await pilot.press("3")
            assert t.operator.view().mode == DRIVE
            await one_stop_then_silence(pilot, t, "/limb1/joint_set")
            assert t.sent[-1].command.reason == "mode changed"
            assert not t.wire.seen("/cmd_vel")  # a mode change moves nothing

    asyncio.run(scenario())


# --------------------------------------------------------------------------------- IK mode
def test_ik_mode_i_moves_the_tip_up_through_ik_and_the_timeout_stops_it(teleop) -> None:
    t = teleop(mode=IK)

    async def scenario() -> None:
        async with t.app().run_test(size=(140, 40)) as pilot:
            syncer = t.link.tips.syncer
            before = t.link.tips.tip("limb1").translation.copy()
            await first_on_the_wire(pilot, t, "/limb1/joint_set", "i")
            seen = await one_stop_then_silence(pilot, t, "/limb1/joint_set")
            chain = set(syncer.limbs["limb1"].names)
            assert {s.name for s in joint_samples(seen[0])} == chain
            # The emulated motors follow at once: the tip went up, not sideways much.
            after = await until(
                pilot,
                lambda: (
                    (p := t.link.tips.tip("limb1").translation)[2] > before[2] + 1e-4 and tuple(p)
                ),
                "the tip higher",
            )
            assert abs(after[0] - before[0]) < after[2] - before[2] + 1e-3
            assert "tip of limb1" in str(app_text(pilot, "#target"))

    asyncio.run(scenario())


# ------------------------------------------------------------------------------ drive mode
def test_drive_mode_i_publishes_a_twist_and_the_timeout_one_zero_twist(teleop) -> None:
    t = teleop(mode=DRIVE)

    async def scenario() -> None:
        async with t.app().run_test(size=(120, 40)) as pilot:
            await pilot.press("w")  # linear speed x1.1
            await first_on_the_wire(pilot, t, "/cmd_vel", "i")
            seen = await one_stop_then_silence(pilot, t, "/cmd_vel")
            assert all(m.linear.x == pytest.approx(0.22) for m in seen[:-1])
            assert all(m.angular.z == 0.0 for m in seen)
            last = seen[-1]
            assert (last.linear.x, last.linear.y, last.angular.z) == (0.0, 0.0, 0.0)

    asyncio.run(scenario())


def test_drive_mode_shift_moves_sideways_and_another_key_turns_without_a_stop(teleop) -> None:
    from textual import events

    # A long deadman: the keys below come whenever a loaded machine lets them.
    t = teleop(mode=DRIVE, first_timeout=600.0, repeat_timeout=600.0)

    async def scenario() -> None:
        app = t.app()
        async with app.run_test(size=(120, 40)) as pilot:
            await first_on_the_wire(pilot, t, "/cmd_vel", "J")
            first = t.wire.seen("/cmd_vel")[0]
            assert (first.linear.x, first.linear.y) == (0.0, pytest.approx(0.2))
            await pilot.press(",")  # straight back, within the same motion
            await until(
                pilot, lambda: any(m.linear.x < 0 for m in t.wire.seen("/cmd_vel")), "backward"
            )
            app.post_message(events.AppBlur())
            await one_stop_then_silence(pilot, t, "/cmd_vel")

    asyncio.run(scenario())


# ----------------------------------------------------------------------- e-stop and quit
def test_space_halts_every_commanded_module_and_ctrl_r_recovers(teleop, rig) -> None:
    t = teleop(first_timeout=600.0, repeat_timeout=600.0)

    async def scenario() -> None:
        app = t.app()
        async with app.run_test(size=(140, 40)) as pilot:
            await first_on_the_wire(pilot, t, "/limb1/joint_set", "w")
            await pilot.press("space")
            await until(pilot, lambda: len(app.answers) == len(SLOTS), "every halt answered")
            assert all(verb == "halt" and a.ok for verb, a in app.answers)
            assert all(rig.managers[s].core.halted for s in SLOTS)
            assert t.sent[-1].command.reason == "e-stop"
            assert "E-STOPPED: limb1, wheel1" in str(app_text(pilot, "#estop"))
            assert "halt: limb1 ok" in app.status
            await pilot.press("ctrl+r")
            await until(pilot, lambda: len(app.answers) == 2 * len(SLOTS), "recovered")
            assert not any(rig.managers[s].core.halted for s in SLOTS)
            assert app.estopped == []

    asyncio.run(scenario())


def test_escape_stops_then_quits(teleop) -> None:
    t = teleop(first_timeout=600.0, repeat_timeout=600.0)

    async def scenario() -> None:
        app = t.app()
        async with app.run_test(size=(120, 40)) as pilot:
            await first_on_the_wire(pilot, t, "/limb1/joint_set", "w")
            await pilot.press("escape")
        # The stop went out before the app ended.
        assert t.operator.stops_sent == 1 and t.sent[-1].command.reason == "quit"

    asyncio.run(scenario())
    total = t.operator.moves_sent + 1
    deadline = time.monotonic() + PATIENCE
    while len(t.wire.seen("/limb1/joint_set")) < total:
        assert time.monotonic() < deadline, "the stop never arrived"
        time.sleep(0.02)


def test_the_latest_alarm_from_health_is_on_screen(teleop, dragon) -> None:
    from test_health_board import health

    from components.data_monitor.plan import board_for
    from msctl.health.source import BoardSource

    t = teleop()
    board = board_for(dragon)
    board.start(0.0)
    board.evaluate(0.0)
    cpu = ("host/cpu", 1, "CPU load 91%", {"cpu_percent": "91.0"})
    board.on_health("limb1", health("limb1", cpu, summary=1), 0.5)
    t.link.health = BoardSource(board, now=1.0)

    async def scenario() -> None:
        async with t.app().run_test(size=(140, 40)) as pilot:
            await pilot.pause(0.3)
            text = str(app_text(pilot, "#alarm"))
            assert "WARN" in text and "limb1" in text

    try:
        asyncio.run(scenario())
    finally:
        t.link.health = None  # the canned board has nothing to close


def app_text(pilot: Any, selector: str) -> Any:
    from textual.widgets import Static

    return pilot.app.query_one(selector, Static).render()


# ----------------------------------------------------------------------------- helpers
def test_bar_draws_the_position_between_the_limits() -> None:
    assert bar(0.0, -1.0, 1.0, width=5) == "[──●──]"
    assert bar(-5.0, -1.0, 1.0, width=5) == "[●────]"
    assert bar(1.0, -1.0, 1.0, width=5) == "[────●]"
    assert bar(None, -1.0, 1.0, width=3) == "[???]"
    assert "continuous" in bar(0.3, float("-inf"), float("inf"))


def test_key_names_are_characters_when_printable() -> None:
    from textual import events

    assert key_name(events.Key("comma", ",")) == ","
    assert key_name(events.Key("W", "W")) == "W"
    assert key_name(events.Key("tab", "\t")) == "tab"
    assert key_name(events.Key("shift+tab", None)) == "shift+tab"
    assert key_name(events.Key("up", None)) == "up"


# --------------------------------------------------------------------------------- claims
@pytest.fixture
def bob(session_settings: SessionSettings) -> Iterator[Any]:
    """Another operator on its own session: a node and its claims."""
    from components.claims import Claims

    session = open_session(session_settings)
    # A quick-opening session reaches the router a moment later; an operator's claims ask
    # the network, so it starts once linked (msctl's commands wait for their router too).
    wait_until(lambda: list(session.info.routers_zid()), timeout=PATIENCE, what="router link")
    node = Node(session, "bob_teleop", "/gc2")
    claims = Claims(session, 0, ["limb1", "limb2", "wheel1", "wheel2"])
    try:
        yield node, claims
    finally:
        claims.close()
        node.close()
        session.close()


def own_link(dragon: ResolvedAssembly, session_settings: SessionSettings, **kw: Any) -> Any:
    """A link of its own (claims of its own), on its own session; closed by the caller."""
    session = open_session(session_settings)
    wait_until(lambda: list(session.info.routers_zid()), timeout=PATIENCE, what="router link")
    node = Node(session, "teleop_claims")
    try:
        link = Link.open(node, dragon, ["limb1"], health=False, timeout=PATIENCE, **kw)
    except BaseException:
        node.close()
        session.close()
        raise
    return link, node, session


def test_a_module_held_by_another_operator_is_refused_naming_them_then_taken(
    rig, dragon, session_settings, bob
) -> None:
    from msctl.errors import MsctlError

    node, claims = bob
    theirs = claims.claim("limb1", "bob@gc2", node)
    with pytest.raises(MsctlError) as caught:
        own_link(dragon, session_settings)
    text = str(caught.value)
    assert "module limb1 is claimed by bob@gc2 (node /gc2/bob_teleop) since " in text
    assert theirs.info.since_text() in text and "--take" in text
    link, mine, session = own_link(dragon, session_settings, take=True)
    try:
        wait_until(theirs.lost.is_set, timeout=PATIENCE, what="bob told he lost limb1")
        assert link.claimed() == ["limb1"]
        wait_until(
            lambda: (h := claims.holder("limb1")) is not None and h.node == mine.fqn,
            timeout=PATIENCE,
            what="everyone seeing the new holder",
        )
    finally:
        link.close()
        mine.close()
        session.close()


def test_the_screen_says_at_once_when_another_operator_takes_the_claim(
    rig, dragon, session_settings, bob
) -> None:
    node, claims = bob
    link, mine, session = own_link(dragon, session_settings)
    asyncio.run(link.handlers["limb1"].wait_ready(PATIENCE))
    core = TeleopCore(
        TeleopSettings(first_timeout=600.0, repeat_timeout=600.0), link.joints(), link.limbs
    )
    sent: list[Sent] = []
    operator = Operator(core, link.outputs(), on_sent=sent.append).start()

    async def scenario() -> None:
        app = TeleopApp(operator, link, template="dragon")
        async with app.run_test(size=(160, 40)) as pilot:
            await pilot.press("w")
            await until(pilot, lambda: operator.moves_sent, "a move")
            assert "limb1" in str(app_text(pilot, "#claims"))
            claims.claim("limb1", "bob@gc2", node, take=True)
            await until(
                pilot, lambda: "TAKEN by bob@gc2" in str(app_text(pilot, "#claims")), "said"
            )
            assert "TAKEN OVER by bob@gc2" in app.status
            await until(pilot, lambda: operator.stops_sent == 1 and operator.idle, "the stop")
            assert sent[-1].command.reason == "claim lost"
            await pilot.press("w")
            assert operator.view().note.startswith("limb1 was TAKEN OVER")
            assert operator.moves_sent == len(sent) - 1  # nothing more went out
            assert link.claimed() == []

    try:
        asyncio.run(scenario())
    finally:
        operator.close()
        link.close()
        mine.close()
        session.close()
