"""The ``msctl health`` screen under textual's Pilot, headless.

A board fed by hand (:class:`~msctl.health.source.BoardSource`) for navigation, actions and
the snapshots of a simulated Dragon; a live board on real Zenoh sessions, with in-process
publishers standing in for modules, for a component that dies and a monitor that stops.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from conftest import quick_peer_settings, quick_router
from test_health_board import good, health
from test_health_live import FakeModule

from components.assembly import ResolvedAssembly, from_document
from components.comm.node import Node
from components.comm.session import SessionSettings, open_session
from components.data_monitor.measures import RateStats
from components.data_monitor.plan import board_for
from components.messages import diagnostic_array, diagnostic_status
from msctl.assembler import resolve
from msctl.health.alarms_screen import AlarmsScreen
from msctl.health.app import REFRESH_PERIOD, HealthApp
from msctl.health.confirm_screen import ConfirmScreen
from msctl.health.live import LiveHealth
from msctl.health.log_screen import LogScreen
from msctl.health.module_screen import ModuleScreen
from msctl.health.overview_screen import OverviewScreen
from msctl.health.source import BoardSource, TopicRow
from msctl.health.topics_screen import TopicsScreen

#: 2026-01-02 03:04:05 UTC, the clock of every canned screen.
FIXED_WALL = 1767323045.0


@pytest.fixture(scope="module")
def dragon() -> ResolvedAssembly:
    return from_document(resolve("dragon").document)


@pytest.fixture
def utc(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TZ", "UTC")
    time.tzset()
    yield
    monkeypatch.undo()
    time.tzset()


def sim_health(slot: str, joints: list[str], cpu: float = 23.0) -> Any:
    """A health array shaped as a simulated module's monitor publishes it (fixed values)."""
    items = [
        (f"components/{label}", 0, f"/{slot}/{label} running", {"node": f"/{slot}/{label}"})
        for label in ("joint_manager", "location_base")
    ]
    items += [
        (
            "topics/joint_states",
            0,
            "200.0 Hz",
            {"topic": f"/{slot}/joint_states", "rate_hz": "200.0"},
        ),
        ("topics/joint_read", 0, "1.0 Hz", {"topic": f"/{slot}/joint_read", "rate_hz": "1.0"}),
        ("topics/diagnostics", 0, "3.0 Hz", {"topic": f"/{slot}/diagnostics", "rate_hz": "3.0"}),
    ]
    for index, joint in enumerate(joints):
        values = {
            "position": f"{0.1 * index:.3f}",
            "velocity": "0.0",
            "effort": f"{2.5 * index:.2f}",
            "temperature": f"{38 + index}",
            "voltage": "24.0",
        }
        items.append((f"motors/{joint}", 0, "OK", values))
    items.append(("motors/bus", 0, "simulated (MuJoCo)", {"joints": str(len(joints))}))
    items += [
        ("host/cpu", 1 if cpu >= 85 else 0, f"CPU load {cpu:.0f}%", {"cpu_percent": f"{cpu:.1f}"}),
        ("host/memory", 0, "memory in use 7%", {"memory_percent": "6.8"}),
        ("host/disk", 0, "disk / in use 22%", {"disk_percent": "22.3"}),
    ]
    statuses = [diagnostic_status(slot, 0, "summary", "unit", {})]
    statuses += [diagnostic_status(f"{slot}/{n}", lv, m, "unit", v) for n, lv, m, v in items]
    return diagnostic_array(statuses)


def canned_dragon(dragon: ResolvedAssembly) -> BoardSource:
    """A simulated Dragon, as a board fed by hand: wheel1 hot CPU (WARN), wheel2 silent."""
    board = board_for(dragon, wall_offset=FIXED_WALL - 100.0)
    board.watch_graph(0.0)
    for spec in board.watched:
        for expected in spec.expected:
            board.on_node(expected.node, expected.count, 0.0)
    board.on_supervisors(
        [
            {
                "host": "laptop",
                "components": [
                    {
                        "name": name,
                        "process": name.split("/")[0],
                        "state": "running",
                        "pid": 1000 + index,
                        "uptime": 300.0,
                        "restarts": 0,
                        "last_error": "",
                    }
                    for index, name in enumerate(
                        [c.name for c in dragon.components] + ["sim/simulator"]
                    )
                ],
            }
        ],
        99.5,
    )
    for module in dragon.modules:
        joints = [j.name for j in module.actuated_joints]
        cpu = 91.0 if module.slot == "wheel1" else 23.0
        at = 90.0 if module.slot == "wheel2" else 99.0
        board.on_health(module.slot, sim_health(module.slot, joints, cpu), at)
    board.evaluate(99.0)
    source = BoardSource(board, now=100.0)
    source.history = {
        f"limb1_joint{i}": [0.1 * i + 0.05 * ((k * (i + 1)) % 5) for k in range(16)]
        for i in range(1, 8)
    }
    source.topic_rows = [
        TopicRow("/limb1/joint_states", ("sensor_msgs/msg/JointState",), 1, 3,
                 RateStats(200.0, 0.004, 0.006, 0.0004, 12000, 0.0)),
        TopicRow("/limb1/joint_read", ("sensor_msgs/msg/JointState",), 1, 4,
                 RateStats(1.0, 1.0, 1.0, 0.0, 60, 0.4)),
    ]  # fmt: skip
    source.logs = {"limb1/joint_manager": [f"line {i}" for i in range(60)]}
    return source


def canned_app(source: BoardSource) -> HealthApp:
    return HealthApp(source, clock=lambda: FIXED_WALL, fetch_history=False)


def cell(app: HealthApp, table_id: str, row: str, column: str) -> str:
    from textual.widgets import DataTable

    table = app.screen.query_one(table_id, DataTable)
    return str(table.get_cell(row, column))


# ---------------------------------------------------------------------------- canned board
def test_overview_rows_are_ordered_by_severity_then_name(dragon) -> None:
    async def scenario() -> None:
        app = canned_app(canned_dragon(dragon))
        async with app.run_test(size=(160, 48)) as pilot:
            await pilot.pause()
            assert isinstance(app.screen, OverviewScreen)
            from textual.widgets import DataTable

            table = app.screen.query_one("#overview", DataTable)
            order = [str(table.get_row_at(i)[1]) for i in range(table.row_count)]
            assert order == ["wheel2", "wheel1", "limb1", "limb2", "gc1 (station)"]
            assert cell(app, "#overview", "wheel2", "level") == "STALE"
            assert cell(app, "#overview", "wheel1", "level") == "WARN"
            assert "wheel2/health: no health for 10.0 s" in cell(
                app, "#overview", "wheel2", "worst item: message"
            )

    asyncio.run(scenario())


def test_navigation_drill_down_alarms_topics_and_back(dragon) -> None:
    async def scenario() -> None:
        source = canned_dragon(dragon)
        app = canned_app(source)
        async with app.run_test(size=(160, 48)) as pilot:
            await pilot.pause()
            await pilot.press("down", "down", "enter")  # limb1
            assert isinstance(app.screen, ModuleScreen) and app.screen.module == "limb1"
            await pilot.pause()
            assert cell(app, "#components", "joint_manager", "state") == "running"
            assert cell(app, "#motors", "limb1/motors/limb1_joint3", "temp") == "40°C"
            assert cell(app, "#motors", "limb1/motors/limb1_joint3", "recent positions")
            assert cell(app, "#topics", "/limb1/joint_states", "rate Hz") == "200.0"
            assert cell(app, "#host", "limb1/host/cpu", "value") == "23.0"
            assert ("watch_joints", "limb1") in source.calls
            await pilot.press("escape")
            assert isinstance(app.screen, OverviewScreen)
            assert ("watch_joints", "") in source.calls  # stopped measuring on leaving
            await pilot.press("a")
            assert isinstance(app.screen, AlarmsScreen)
            await pilot.press("escape", "t")
            assert isinstance(app.screen, TopicsScreen)
            await pilot.pause()
            assert cell(app, "#topics-all", "/limb1/joint_read", "subs") == "4"
            await pilot.press("escape", "q")

    asyncio.run(scenario())


def test_an_action_asks_first_and_no_does_nothing(dragon) -> None:
    async def scenario() -> None:
        source = canned_dragon(dragon)
        app = canned_app(source)
        async with app.run_test(size=(160, 48)) as pilot:
            await pilot.pause()
            await pilot.press("down", "down", "enter", "down")  # limb1, joint_manager
            await pilot.press("r")
            assert isinstance(app.screen, ConfirmScreen)
            assert "Restart limb1/joint_manager (process limb1" in app.screen.question
            await pilot.press("n")
            assert isinstance(app.screen, ModuleScreen)
            assert not [c for c in source.calls if c[0] == "restart"]
            await pilot.press("r", "y")
            await app.workers.wait_for_complete()
            await pilot.pause()
            assert ("restart", "limb1/joint_manager") in source.calls
            assert app.action_results[-1] == ("restart limb1/joint_manager on laptop: done", True)
            await pilot.press("h")
            assert isinstance(app.screen, ConfirmScreen) and "Halt limb1" in app.screen.question
            await pilot.press("y")
            await app.workers.wait_for_complete()
            assert ("trigger", "/limb1/halt") in source.calls
            await pilot.press("u", "escape")  # recover asked, then declined
            assert ("trigger", "/limb1/recover") not in source.calls
            await pilot.press("l")
            await app.workers.wait_for_complete()
            await pilot.pause()
            assert isinstance(app.screen, LogScreen)
            assert app.screen.lines[-1] == "line 59" and len(app.screen.lines) == 40

    asyncio.run(scenario())


def test_the_screen_is_refreshed_at_a_bounded_rate_however_fast_data_comes(dragon) -> None:
    source = canned_dragon(dragon)
    evaluations = 0
    evaluate = source.evaluate

    def counting(now: float | None = None) -> Any:
        nonlocal evaluations
        evaluations += 1
        return evaluate(now)

    source.evaluate = counting  # type: ignore[method-assign]

    async def scenario() -> tuple[float, int]:
        app = canned_app(source)
        async with app.run_test(size=(160, 48)) as pilot:
            started, before = time.monotonic(), evaluations
            for _ in range(20):
                for _ in range(500):  # 500 health arrays between two frames
                    source.board.on_health("limb1", good("limb1"), 99.0)
                await pilot.pause()
            # Counted over the same window as the time (not the app's start and teardown).
            return time.monotonic() - started, evaluations - before

    elapsed, during = asyncio.run(scenario())
    # One evaluation per refresh period at most (a window may hold one more), whatever
    # arrived: not one per health array.
    assert during <= elapsed / REFRESH_PERIOD + 2


# ---------------------------------------------------------------------------- snapshots
def test_snapshot_of_the_overview_of_a_simulated_dragon(dragon, utc, snap_compare) -> None:
    assert snap_compare(canned_app(canned_dragon(dragon)), terminal_size=(160, 40))


def test_snapshot_of_the_drill_down_of_a_simulated_limb(dragon, utc, snap_compare) -> None:
    assert snap_compare(
        canned_app(canned_dragon(dragon)),
        press=["down", "down", "enter"],
        terminal_size=(160, 60),
    )


# ---------------------------------------------------------------------------- live board
@pytest.fixture
def router_endpoint() -> Iterator[str]:
    yield from quick_router()


@pytest.fixture
def session_settings(router_endpoint: str) -> SessionSettings:
    return quick_peer_settings(router_endpoint)


@pytest.fixture
def sessions(session_settings: SessionSettings) -> Iterator[Callable[[], Any]]:
    opened: list[Any] = []

    def make() -> Any:
        opened.append(open_session(session_settings))
        return opened[-1]

    try:
        yield make
    finally:
        for session in reversed(opened):
            session.close()


async def until(pilot: Any, predicate: Callable[[], bool], timeout: float, what: str) -> None:
    """Let the app run until ``predicate`` holds (a generous bound, never a speed test)."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {timeout} s: {what}")
        await pilot.pause(0.1)


def test_live_component_dying_turns_error_and_silence_turns_stale_on_screen(
    dragon, sessions
) -> None:
    modules_session, view_session = sessions(), sessions()
    node = Node(view_session, "health_view")
    live = LiveHealth(node, dragon, grace=60.0).start()
    limb = FakeModule(modules_session, dragon, "limb1")
    wheel = FakeModule(modules_session, dragon, "wheel1")

    async def scenario() -> None:
        app = HealthApp(live, fetch_history=False)
        async with app.run_test(size=(160, 48)) as pilot:

            def level(row: str) -> str:
                return cell(app, "#overview", row, "level")

            await until(pilot, lambda: level("limb1") == "OK", 20.0, "limb1 OK on screen")
            await until(pilot, lambda: level("wheel1") == "OK", 20.0, "wheel1 OK on screen")
            limb.nodes["joint_manager"].close()  # the component dies: its node leaves
            await until(pilot, lambda: level("limb1") == "ERROR", 20.0, "limb1 ERROR")
            message = cell(app, "#overview", "limb1", "worst item: message")
            assert "limb1/components/joint_manager" in message
            wheel.silence()  # its monitor stops: no more health, nodes still there
            await until(pilot, lambda: level("wheel1") == "STALE", 20.0, "wheel1 STALE")
            assert "no health for" in cell(app, "#overview", "wheel1", "worst item: message")
            await pilot.press("a")
            await pilot.pause()
            alarms = [(a.module, a.after.name) for a in live.alarms()]
            assert ("limb1", "ERROR") in alarms and ("wheel1", "STALE") in alarms

    try:
        asyncio.run(scenario())
    finally:
        live.close()
        limb.close()
        wheel.close()
        node.close()


def test_live_module_health_with_a_bad_sender_stays_bounded_on_screen(dragon, sessions) -> None:
    modules_session, view_session = sessions(), sessions()
    node = Node(view_session, "health_view")
    live = LiveHealth(node, dragon, grace=60.0).start()
    module = FakeModule(modules_session, dragon, "limb2")
    module.message = health(
        "limb2",
        *[(f"flood/item{i}", 0, "x" * 10_000, {"v": "nan"}) for i in range(3000)],
        ("motors/j1", 7, "level seven", {"temperature": "nan"}),
    )

    async def scenario() -> None:
        app = HealthApp(live, fetch_history=False)
        async with app.run_test(size=(160, 48)) as pilot:
            await until(
                pilot,
                lambda: cell(app, "#overview", "limb2", "level") == "ERROR",
                30.0,
                "limb2 ERROR (level 7)",
            )
            assert "unknown level 7" in cell(app, "#overview", "limb2", "worst item: message")
            await pilot.press("down")
            row = app.snapshot.row("limb2")
            assert any(i.name.endswith("more") for i in row.items)
            assert len(row.items) < 100

    try:
        asyncio.run(scenario())
    finally:
        live.close()
        module.close()
        node.close()


# ---------------------------------------------------------------------------- scale
def test_forty_emulated_modules_fill_the_overview_and_each_drills_down() -> None:
    import json

    from assemblies.fleet import fleet_document, health_array
    from components.assembly import decode_lock
    from components.data_monitor.plan import watched

    fleet = decode_lock(json.dumps(fleet_document(40)))
    assert fleet.template == "fleet40" and len(fleet.modules) == 40
    board = board_for(fleet)
    board.watch_graph(0.0)
    for spec in watched(fleet):
        for expected in spec.expected:
            board.on_node(expected.node, expected.count, 0.0)
        if not spec.station:
            labels = [e.label for e in spec.expected if e.label != "health_monitor"]
            board.on_health(spec.name, health_array(fleet.module(spec.name), labels, 5.0, 0.0), 0.5)
    source = BoardSource(board, now=1.0)
    snapshot = source.evaluate()
    assert [r.level.name for r in snapshot.modules] == ["OK"] * 40

    async def scenario() -> None:
        app = canned_app(source)
        async with app.run_test(size=(160, 48)) as pilot:
            await pilot.pause()
            from textual.widgets import DataTable

            table = app.screen.query_one("#overview", DataTable)
            assert table.row_count == 41
            await pilot.press(*["down"] * 39, "enter")
            assert isinstance(app.screen, ModuleScreen) and app.screen.module == "m39"
            await pilot.pause()
            assert cell(app, "#components", "joint_manager", "state") == "-"
            await pilot.press("escape", "q")

    asyncio.run(scenario())
