"""``msctl health``'s live board on real Zenoh sessions (in-process publishers standing in for
modules), its alarm file, and the command's refusals."""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import quick_peer_settings, quick_router, wait_until
from test_health_board import good, health

from components.assembly import ResolvedAssembly, from_document
from components.comm.node import Node
from components.comm.session import SessionSettings, open_session
from components.data_monitor.alarms import Alarm
from components.messages import DIAGNOSTIC_ARRAY, ERROR, OK, STALE, WARN
from msctl.assembler import resolve
from msctl.errors import InputError, NotFoundError
from msctl.health.alarms import ROTATE_BYTES, AlarmLog, alarm_path, last_session
from msctl.health.live import LiveHealth


@pytest.fixture
def router_endpoint() -> Iterator[str]:
    yield from quick_router()


@pytest.fixture
def session_settings(router_endpoint: str) -> SessionSettings:
    return quick_peer_settings(router_endpoint)


@pytest.fixture(scope="module")
def dragon() -> ResolvedAssembly:
    return from_document(resolve("dragon").document)


class FakeModule:
    """A module's nodes on the graph and its health monitor publishing at 5 Hz."""

    def __init__(self, session: Any, assembly: ResolvedAssembly, slot: str) -> None:
        from components.data_monitor.plan import watched

        spec = next(s for s in watched(assembly) if s.name == slot)
        self.nodes = {
            e.label: Node(session, e.node.rsplit("/", 1)[-1], e.node.rsplit("/", 1)[0] or "/")
            for e in spec.expected
        }
        self.publisher = self.nodes["health_monitor"].publisher("health", DIAGNOSTIC_ARRAY)
        self.slot = slot
        self.message = good(slot)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.2):
            self.publisher.publish(self.message)

    def silence(self) -> None:
        self._stop.set()
        self._thread.join()

    def close(self) -> None:
        self.silence()
        for node in self.nodes.values():
            node.close()


@pytest.fixture
def live(session_settings: SessionSettings, dragon: ResolvedAssembly) -> Iterator[LiveHealth]:
    session = open_session(session_settings)
    node = Node(session, "health_view")
    view = LiveHealth(node, dragon, grace=30.0).start()
    try:
        yield view
    finally:
        view.close()
        node.close()
        session.close()


@pytest.fixture
def module_session(session_settings: SessionSettings) -> Iterator[Any]:
    session = open_session(session_settings)
    try:
        yield session
    finally:
        session.close()


def _level(view: LiveHealth, slot: str) -> Any:
    return view.evaluate().row(slot).level


def test_module_health_read_directly_turns_stale_when_it_stops(
    live: LiveHealth, module_session: Any, dragon: ResolvedAssembly
) -> None:
    module = FakeModule(module_session, dragon, "wheel1")
    try:
        wait_until(lambda: _level(live, "wheel1") is OK, timeout=15.0, what="wheel1 OK")
        module.message = health("wheel1", ("topics/joint_states", 1, "12.0 Hz", {}))
        wait_until(lambda: _level(live, "wheel1") is WARN, timeout=15.0, what="wheel1 WARN")
        module.silence()  # its monitor stops; its nodes stay on the graph
        wait_until(lambda: _level(live, "wheel1") is STALE, timeout=15.0, what="wheel1 STALE")
        row = live.evaluate().row("wheel1")
        assert row.message.startswith("wheel1/health: no health for")
        changes = [(a.item, a.before, a.after) for a in live.alarms() if a.module == "wheel1"]
        assert ("wheel1", WARN, STALE) in changes
    finally:
        module.close()


def test_a_node_leaving_the_graph_turns_its_module_error(
    live: LiveHealth, module_session: Any, dragon: ResolvedAssembly
) -> None:
    module = FakeModule(module_session, dragon, "limb2")
    try:
        wait_until(lambda: _level(live, "limb2") is OK, timeout=15.0, what="limb2 OK")
        module.nodes["joint_manager"].close()
        wait_until(lambda: _level(live, "limb2") is ERROR, timeout=15.0, what="limb2 ERROR")
        row = live.evaluate().row("limb2")
        assert row.worst_item == "limb2/components/joint_manager"
        assert "/limb2/joint_manager left the graph" in row.message
        assert row.components_ok == row.components_expected - 1
    finally:
        module.close()


def test_topics_view_and_drill_down_measure_rates_and_keep_joint_positions(
    live: LiveHealth, module_session: Any, dragon: ResolvedAssembly
) -> None:
    """The topics view lists the graph's topics with type and counts; measured topics get
    their rate from arrival times (no decoding); the drill-down keeps a joint's positions."""
    from components.comm.qos import SENSOR
    from components.messages import JOINT_STATE, JointSample, joint_state

    node = Node(module_session, "joint_manager", "/limb1")
    publisher = node.publisher("joint_states", JOINT_STATE, SENSOR)
    sent = 0
    stop = threading.Event()

    def publish() -> None:
        nonlocal sent
        while not stop.wait(0.005):
            sent += 1
            samples = [JointSample("limb1_joint1", 0.001 * sent, 0.0, 0.0)]
            publisher.publish(joint_state(samples))

    thread = threading.Thread(target=publish, daemon=True)
    thread.start()
    try:
        rows = wait_until(
            lambda: {t.name: t for t in live.topics() if t.name == "/limb1/joint_states"},
            timeout=15.0,
            what="/limb1/joint_states on the graph",
        )
        row = rows["/limb1/joint_states"]
        assert row.types == (JOINT_STATE,) and row.publishers == 1 and row.stats is None
        live.watch_topics(["/limb1/joint_states"])
        live.watch_joints("limb1")

        def measured() -> Any:
            stats = next(t.stats for t in live.topics() if t.name == "/limb1/joint_states")
            return stats if stats is not None and stats.count >= 50 else None

        stats = wait_until(measured, timeout=30.0, what="50 arrivals measured")
        assert stats.rate > 0 and stats.age is not None
        assert 0 < stats.min_interval <= stats.max_interval and stats.jitter >= 0
        history = wait_until(
            lambda: (h := live.joint_history("limb1_joint1")) and len(h) >= 3 and h,
            timeout=30.0,
            what="positions kept for the sparkline",
        )
        assert history == sorted(history)  # the positions sent only grow
        live.watch_topics([])
        assert all(t.stats is None for t in live.topics())
    finally:
        stop.set()
        thread.join()
        node.close()


def test_wait_first_news_gives_up_after_its_timeout_when_modules_are_silent(
    live: LiveHealth,
) -> None:
    assert live.wait_first_news(0.3) is False
    snapshot = live.evaluate()
    assert snapshot.level is STALE
    assert live.router_connected()


# ---------------------------------------------------------------------------- alarm file
@pytest.fixture
def home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("MSCTL_HOME", str(tmp_path))
    return tmp_path


def test_the_alarm_file_gives_back_the_last_session(home: Path) -> None:
    first = AlarmLog("dragon", "msctl health")
    first.append([Alarm(1.0, "limb1", "limb1", OK, ERROR, "old")])
    second = AlarmLog("dragon", "msctl health --watch")
    alarms = [
        Alarm(2.0, "limb1", "limb1", ERROR, OK, "back"),
        Alarm(3.0, "wheel1", "wheel1/health", OK, STALE, "quiet"),
    ]
    second.append(alarms)
    assert alarm_path() == home / "health" / "alarms.jsonl"
    with alarm_path().open("a") as handle:
        handle.write("{not json\n")
        handle.write(json.dumps({"session": second.session, "to": "PURPLE"}) + "\n")
    session = last_session()
    assert session is not None
    assert session.source == "msctl health --watch" and session.assembly == "dragon"
    assert list(session.alarms) == alarms and session.skipped == 2
    assert session.to_json()["alarms"][1]["to"] == "STALE"


def test_the_alarm_file_is_rotated_past_its_bound(home: Path) -> None:
    path = alarm_path()
    path.parent.mkdir(parents=True)
    path.write_text("x" * (ROTATE_BYTES + 1))
    AlarmLog("dragon", "msctl health")
    assert path.with_name("alarms.jsonl.1").stat().st_size == ROTATE_BYTES + 1
    assert path.stat().st_size < 1000


def test_no_alarm_file_is_a_clear_not_found(home: Path) -> None:
    from msctl.commands.health import command

    assert last_session() is None
    with pytest.raises(NotFoundError, match=r"no alarms recorded in .*alarms\.jsonl"):
        command(once=False, watch=False, alarms=True, json_output=False, timeout=3.0, duration=0)


@pytest.mark.parametrize(
    ("options", "why"),
    [
        ({"once": True, "watch": True}, "--once and --watch cannot be combined"),
        ({"watch": True, "alarms": True}, "--watch and --alarms cannot be combined"),
        ({"json_output": True}, "--json goes with --once, --watch or --alarms"),
        ({"once": True, "timeout": 0.0}, "--timeout must be positive"),
        ({"watch": True, "duration": -1.0}, "--for must be 0 or more"),
    ],
)
def test_the_command_refuses_what_makes_no_sense(options: dict, why: str, home: Path) -> None:
    from msctl.commands.health import command

    arguments = {
        "once": False,
        "watch": False,
        "alarms": False,
        "json_output": False,
        "timeout": 3.0,
        "duration": 0.0,
        **options,
    }
    with pytest.raises(InputError, match=why):
        command(**arguments)
