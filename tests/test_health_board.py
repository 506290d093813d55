"""The health board and the data monitor core, driven with plain calls and fake time."""

from __future__ import annotations

import json
import math
from typing import Any

import pytest

from components.assembly import ResolvedAssembly, from_document
from components.data_monitor.alarms import Alarm
from components.data_monitor.board import STALE_AFTER, HealthBoard
from components.data_monitor.core import (
    DataMonitorConfig,
    DataMonitorCore,
    aggregate,
    alarm_from_message,
    alarm_message,
)
from components.data_monitor.measures import RateMeter, sparkline
from components.data_monitor.model import MAX_MESSAGE, MAX_NAME
from components.data_monitor.plan import board_for, watched
from components.executor.core import RecordingOutbox
from components.messages import (
    ERROR,
    OK,
    STALE,
    WARN,
    Level,
    diagnostic_array,
    diagnostic_status,
    msg,
)
from msctl.assembler import resolve


@pytest.fixture(scope="module")
def dragon() -> ResolvedAssembly:
    return from_document(resolve("dragon").document)


def health(slot: str, *items: tuple[str, int, str, dict[str, Any]], summary: int = 0) -> Any:
    """A module's health array as its monitor publishes it: summary first."""
    statuses = [diagnostic_status(slot, summary, "summary", "unit-1", {})]
    statuses += [diagnostic_status(f"{slot}/{n}", lv, m, "unit-1", v) for n, lv, m, v in items]
    return diagnostic_array(statuses)


def good(slot: str) -> Any:
    return health(
        slot,
        ("components/joint_manager", 0, f"/{slot}/joint_manager running", {}),
        ("topics/joint_states", 0, "200.0 Hz", {"rate_hz": "200.0"}),
        ("topics/joint_read", 0, "1.0 Hz", {"rate_hz": "1.0"}),
        ("motors/j1", 0, "OK", {"position": "0.5", "temperature": "41.0", "voltage": "24.1"}),
        ("motors/j2", 0, "OK", {"position": "0.1", "temperature": "45.5", "voltage": "23.2"}),
        ("host/cpu", 0, "CPU load 10%", {"cpu_percent": "10.0"}),
    )


def all_healthy(board: HealthBoard, now: float) -> None:
    for spec in board.watched:
        if not spec.station:
            board.on_health(spec.name, good(spec.name), now)


# ---------------------------------------------------------------------------- plan
def test_the_board_watches_every_module_and_station_of_the_assembly(dragon) -> None:
    specs = {s.name: s for s in watched(dragon)}
    assert list(specs) == ["limb1", "limb2", "wheel1", "wheel2", "gc1"]
    limb = specs["limb1"]
    assert limb.health_topic == "/limb1/health" and not limb.station
    nodes = {e.label: e for e in limb.expected}
    assert {"joint_manager", "health_monitor", "motor_interface"} <= set(nodes)
    # The simulator stands in for the motor interface; supervisors list it as sim/simulator.
    motors = nodes["motor_interface"]
    assert motors.nodes == ("/limb1/motor_interface", "/sim/simulator")
    assert motors.components == ("limb1/motor_interface", "sim/simulator")
    station = specs["gc1"]
    assert station.station and station.host == "ground1"
    kinds = {e.kind for e in station.expected} | {k for _, k in station.planned}
    assert kinds == {"human_operator", "data_monitor"}
    assert not station.planned  # both are built: their nodes are expected
    assert all(e.node == f"/gc1/{e.label}" for e in station.expected)


# ---------------------------------------------------------------------------- levels
def test_modules_wait_stale_then_turn_ok_with_their_health(dragon) -> None:
    board = board_for(dragon)
    first = board.evaluate(0.0)
    assert first.level is STALE
    assert all(r.level is STALE for r in first.modules)
    assert first.row("limb1").message == "limb1/health: waiting for /limb1/health"
    assert board.take_alarms() == []  # waiting is not news
    all_healthy(board, 0.5)
    snap = board.evaluate(0.6)
    assert [r.level for r in snap.modules] == [OK] * 4
    row = snap.row("limb1")
    assert (row.joint_states_hz, row.joint_read_hz) == (200.0, 1.0)
    assert (row.temperature, row.voltage) == (45.5, 23.2)
    assert row.host == dragon.module("limb1").host
    assert board.take_alarms() == []  # first seen OK: not news either


def test_silence_turns_a_module_stale_after_the_bound_and_stale_stays_stale(dragon) -> None:
    board = board_for(dragon)
    all_healthy(board, 0.0)
    board.on_health("limb2", health("limb2", ("host/cpu", 2, "CPU load 100%", {}), summary=2), 0.0)
    board.evaluate(0.1)
    board.take_alarms()
    for t in (1.0, 2.0, 2.5):
        board.on_health("limb1", good("limb1"), t)
    assert board.evaluate(STALE_AFTER - 0.01).row("wheel1").level is OK
    snap = board.evaluate(STALE_AFTER + 0.01)
    wheel = snap.row("wheel1")
    assert wheel.level is STALE
    assert wheel.message.startswith("wheel1/health: no health for 2.5 s")
    # limb2's last report said ERROR; that is old news now: STALE, not ERROR.
    limb2 = snap.row("limb2")
    assert limb2.level is STALE
    cpu = next(i for i in limb2.items if i.name == "limb2/host/cpu")
    assert (cpu.level, cpu.reported) == (STALE, ERROR) and cpu.message.startswith("last ERROR")
    assert snap.row("limb1").level is OK
    assert snap.level is STALE
    alarms = {(a.module, a.item, a.before, a.after) for a in board.take_alarms()}
    assert ("wheel1", "wheel1", OK, STALE) in alarms
    assert ("wheel1", "wheel1/health", OK, STALE) in alarms
    # Items keep the level their source reported: no flood of item alarms.
    assert not any(item.endswith("host/cpu") for _, item, _, _ in alarms)


def test_the_overall_level_ranks_error_over_stale_over_warn_over_ok(dragon) -> None:
    board = board_for(dragon)
    all_healthy(board, 0.0)
    board.on_health("limb1", health("limb1", ("topics/joint_states", 1, "slow", {})), 0.0)
    assert board.evaluate(0.1).level is WARN
    board.on_health("limb2", health("limb2", ("motors/j1", 2, "overheated", {})), 0.0)
    snap = board.evaluate(0.2)
    assert snap.level is ERROR
    assert [r.name for r in snap.modules] == ["limb2", "limb1", "wheel1", "wheel2"]
    assert snap.row("limb2").message == "limb2/motors/j1: overheated"
    board.on_health("limb2", good("limb2"), 0.3)
    for slot in ("limb1", "limb2"):
        board.on_health(slot, good(slot), 3.0)
    snap = board.evaluate(3.0)
    assert snap.level is STALE  # the wheels went quiet: STALE, never folded into ERROR
    assert [r.name for r in snap.modules] == ["wheel1", "wheel2", "limb1", "limb2"]


def test_alarms_record_every_level_change_with_time_and_message(dragon) -> None:
    board = board_for(dragon, wall_offset=1000.0)
    all_healthy(board, 0.0)
    board.evaluate(0.0)
    board.on_health("wheel1", health("wheel1", ("motors/j9", 2, "too hot", {})), 1.0)
    board.evaluate(1.0)
    board.on_health("wheel1", good("wheel1"), 2.0)
    board.evaluate(2.0)
    alarms = board.take_alarms()
    changes = [(a.item, a.before, a.after) for a in alarms if a.module == "wheel1"]
    assert ("wheel1/motors/j9", None, ERROR) in changes  # first seen already ERROR
    assert ("wheel1", OK, ERROR) in changes and ("wheel1", ERROR, OK) in changes
    first = next(a for a in alarms if a.after is ERROR and a.item == "wheel1")
    assert first.at == 1001.0 and first.message == "wheel1/motors/j9: too hot"
    assert list(board.alarms)[-len(alarms) :] == alarms
    assert board.take_alarms() == []
    line = first.line()
    assert "wheel1 wheel1 OK -> ERROR wheel1/motors/j9: too hot" in line


def test_alarm_json_round_trips_and_names_a_bad_field() -> None:
    alarm = Alarm(12.5, "limb1", "limb1/host/cpu", None, STALE, "quiet")
    assert Alarm.from_json(json.loads(json.dumps(alarm.to_json()))) == alarm
    assert alarm.to_json()["from"] == "-"
    with pytest.raises(ValueError, match="'to'"):
        Alarm.from_json({**alarm.to_json(), "to": "BAD"})
    with pytest.raises(ValueError, match="'at'"):
        Alarm.from_json({**alarm.to_json(), "at": "noon"})
    with pytest.raises(ValueError, match="object"):
        Alarm.from_json([1, 2])


# ---------------------------------------------------------------------------- components
def _seen(board: HealthBoard, slot: str, now: float) -> None:
    for spec in board.watched:
        if spec.name == slot:
            for expected in spec.expected:
                board.on_node(expected.node, 1, now)


def test_a_node_leaving_the_graph_is_error_when_its_process_died(dragon) -> None:
    board = board_for(dragon)
    board.watch_graph(0.0)
    all_healthy(board, 0.0)
    _seen(board, "limb1", 0.0)
    snap = board.evaluate(0.1)
    limb = snap.row("limb1")
    manager = next(c for c in limb.components if c.label == "joint_manager")
    assert manager.level is OK and manager.message == "/limb1/joint_manager running"
    assert board.take_alarms() == []
    board.on_node("/limb1/joint_manager", 0, 1.0)
    document = {
        "host": "laptop",
        "components": [
            {
                "name": "limb1/joint_manager",
                "process": "limb1",
                "state": "restarting",
                "pid": 42,
                "uptime": 3.0,
                "restarts": 1,
                "last_error": "killed by SIGKILL",
            }
        ],
    }
    board.on_supervisors([document], 1.05)
    snap = board.evaluate(1.1)
    limb = snap.row("limb1")
    assert limb.level is ERROR
    manager = next(c for c in limb.components if c.label == "joint_manager")
    assert manager.state == "restarting" and manager.pid == 42 and manager.restarts == 1
    assert "process limb1 restarting (killed by SIGKILL)" in manager.message
    assert limb.components_ok == limb.components_expected - 1
    alarms = [(a.item, a.before, a.after) for a in board.take_alarms()]
    assert ("limb1/components/joint_manager", OK, ERROR) in alarms


def test_a_node_off_the_graph_whose_process_runs_is_stale_not_error(dragon) -> None:
    board = board_for(dragon)
    board.watch_graph(0.0)
    all_healthy(board, 0.0)
    _seen(board, "wheel1", 0.0)
    board.on_node("/wheel1/joint_manager", 0, 1.0)
    running = {"name": "wheel1/joint_manager", "process": "wheel1", "state": "running"}
    board.on_supervisors([{"host": "laptop", "components": [running]}], 1.0)
    row = board.evaluate(1.2).row("wheel1")
    assert row.level is STALE
    assert "frozen, or its link is down" in row.message
    # The supervisor stops answering: still no proof of death.
    row = board.evaluate(10.0).row("wheel1")
    manager = next(c for c in row.components if c.label == "joint_manager")
    assert row.level is STALE and manager.level is STALE
    assert "supervisor of laptop does not answer" in manager.message


def test_no_supervisor_means_a_vanished_node_is_an_error(dragon) -> None:
    board = board_for(dragon)
    board.watch_graph(0.0)
    all_healthy(board, 0.0)
    _seen(board, "wheel2", 0.0)
    board.on_node("/wheel2/joint_manager", 0, 1.0)
    row = board.evaluate(1.5).row("wheel2")
    assert row.level is ERROR and "left the graph 0.5 s ago" in row.message


def test_nodes_not_seen_yet_wait_through_the_grace_then_are_errors(
    dragon, monkeypatch: pytest.MonkeyPatch
) -> None:
    import components.data_monitor.plan as plan

    # A kind with no code yet is listed as planned, never expected on the graph.
    monkeypatch.setattr(plan, "buildable", lambda kind: kind != "human_operator")
    board = board_for(dragon)
    board.watch_graph(0.0)
    all_healthy(board, 0.0)
    early = board.evaluate(1.0).row("limb1")
    assert early.level is STALE and "waiting for" in early.message
    assert board.take_alarms() == []
    late = board.evaluate(6.0)
    assert late.row("limb1").level is ERROR
    assert "is not on the graph" in late.row("limb1").message
    station = late.row("gc1")
    assert station.station
    assert station.level is (ERROR if station.components_expected else OK)
    planned = next(i for i in station.items if i.name == "gc1/components/human_operator")
    assert planned.level is OK and "not built yet" in planned.message


def test_bad_supervisor_documents_are_skipped(dragon) -> None:
    board = board_for(dragon)
    board.on_supervisors(
        [None, "x", {"host": 5, "components": "many"}, {"components": [7, {"name": 3}]}], 0.0
    )
    # Nothing of them is kept: every component is as on a board that heard no supervisor.
    untouched = board_for(dragon).evaluate(0.1)
    snapshot = board.evaluate(0.1)
    assert [(r.name, r.level, r.components) for r in (*snapshot.modules, *snapshot.stations)] == [
        (r.name, r.level, r.components) for r in (*untouched.modules, *untouched.stations)
    ]
    # An entry with a name is kept; its pid that is no integer is dropped, not shown.
    board.on_supervisors([{"components": [{"name": "limb1/joint_manager", "pid": "x"}]}], 0.0)
    views = [c for c in board.evaluate(0.2).row("limb1").components if c.label == "joint_manager"]
    assert [(v.component, v.pid, v.state, v.level) for v in views] == [
        ("limb1/joint_manager", None, "", OK)
    ]


# ---------------------------------------------------------------------------- bad input
def test_thousands_of_statuses_are_capped_with_a_more_row_of_their_worst_level(dragon) -> None:
    board = board_for(dragon, max_items=20)
    items = [(f"bulk/item{i}", 0, "fine", {}) for i in range(5000)]
    items[4321] = ("bulk/item4321", 2, "the one that is bad", {})
    items[17] = ("bulk/item17", 3, "quiet", {})
    board.on_health("limb1", health("limb1", *items), 0.0)
    row = board.evaluate(0.1).row("limb1")
    names = [i.name for i in row.items]
    assert len(names) == 1 + 20  # the board's own health item, then the capped items
    assert "limb1/bulk/item4321" in names and "limb1/bulk/item17" in names
    more = row.items[-1]
    assert more.name == "limb1/+4981 more" and more.level is OK
    assert row.level is ERROR and row.message == "limb1/bulk/item4321: the one that is bad"


def test_huge_strings_unknown_levels_and_nan_are_shown_bounded(dragon) -> None:
    board = board_for(dragon)
    huge = "x" * 1_000_000
    values = {f"k{i}": "v" for i in range(100)}
    array = health(
        "limb1",
        (huge, 0, huge, {huge: huge}),
        ("motors/j1", 7, "weird\x1b[2Jsender\nline", values),
        ("topics/joint_states", 0, "?", {"rate_hz": "nan"}),
        ("motors/j2", 0, "OK", {"temperature": "nan", "voltage": "inf"}),
    )
    board.on_health("limb1", array, 0.0)
    row = board.evaluate(0.1).row("limb1")
    long = next(i for i in row.items if i.name.startswith("limb1/xxx"))
    assert len(long.name) == MAX_NAME and long.name.endswith("…")
    assert len(long.message) == MAX_MESSAGE
    assert all(len(k) <= 32 and len(v) <= 48 for k, v in long.values.items())
    weird = next(i for i in row.items if i.name == "limb1/motors/j1")
    assert weird.level is ERROR
    assert weird.message.startswith("unknown level 7: weird")
    assert "\x1b" not in weird.message and "\n" not in weird.message
    assert len(weird.values) <= 18 and "…" in weird.values
    assert row.level is ERROR
    assert row.joint_states_hz is None and row.temperature is None and row.voltage is None
    document = board.evaluate(0.2).to_json()
    json.dumps(document)  # no NaN or objects leak into JSON
    limb = next(m for m in document["modules"] if m["name"] == "limb1")
    assert {"name": "limb1/motors/j1", "level": "ERROR"}.items() <= next(
        i for i in limb["items"] if i["name"] == "limb1/motors/j1"
    ).items()


def test_health_for_no_watched_module_is_counted_not_shown(dragon) -> None:
    board = board_for(dragon)
    board.on_health("limb9", good("limb9"), 0.0)
    board.on_health("limb1", msg("std_msgs/msg/String", data="not an array"), 0.0)
    assert board.unknown == 1
    assert board.evaluate(0.1).row("limb9") is None


def test_the_json_snapshot_has_exactly_the_documented_shape(dragon) -> None:
    board = board_for(dragon)
    all_healthy(board, 0.0)
    document = board.evaluate(0.1).to_json()
    assert set(document) == {"assembly", "level", "modules", "stations"}
    assert document["assembly"] == "dragon" and document["level"] == "OK"
    for row in document["modules"] + document["stations"]:
        assert set(row) == {"name", "host", "level", "message", "items"}
        for item in row["items"]:
            assert set(item) == {"name", "level", "message"}
    assert [s["name"] for s in document["stations"]] == ["gc1"]


def test_the_board_refuses_nonsense_settings(dragon) -> None:
    with pytest.raises(ValueError, match="stale_after"):
        board_for(dragon, stale_after=0)
    with pytest.raises(ValueError, match="max_items"):
        board_for(dragon, max_items=0)
    with pytest.raises(ValueError, match=r"DataMonitorConfig\.min_period"):
        DataMonitorConfig(min_period=-1.0)


# ---------------------------------------------------------------------------- measures
def test_rate_meter_measures_rate_intervals_and_jitter_from_arrival_times() -> None:
    meter = RateMeter(window=1.0)
    for i in range(101):
        meter.arrive(i * 0.01)
    stats = meter.stats(1.0)
    assert stats.rate == pytest.approx(100.0, rel=0.02)
    assert stats.min_interval == pytest.approx(0.01) and stats.max_interval == pytest.approx(0.01)
    assert stats.jitter == pytest.approx(0.0, abs=1e-9) and stats.count == 101
    later = meter.stats(5.0)
    assert later.rate == 0.0 and later.age == pytest.approx(4.0)
    assert RateMeter().stats(1.0).count == 0


def test_sparkline_scales_and_leaves_gaps_for_nan() -> None:
    assert sparkline([0.0, 0.5, 1.0]) == "▁▄█"
    assert sparkline([1.0, math.nan, 1.0]) == "▁ ▁"
    assert sparkline([]) == "" and len(sparkline(range(100), width=10)) == 10


# ---------------------------------------------------------------------------- the core
def test_the_core_publishes_the_aggregator_tree_and_the_top_level(dragon) -> None:
    core = DataMonitorCore("gc1/data_monitor", board_for(dragon))
    core.start(0.0)
    for spec in core.board.watched:
        if not spec.station:
            getattr(core, f"on_health_{spec.name}")(good(spec.name), 0.1)
    core.tick(1.2)
    agg = core.outbox.on("/diagnostics_agg")[-1]
    names = [s.name for s in agg.status]
    assert names[0] == "/dragon"
    assert {"/dragon/limb1", "/dragon/limb1/components", "/dragon/gc1"} <= set(names)
    assert "/dragon/limb1/components/joint_manager" in names
    assert "/dragon/limb1/motors/j1" in names
    by_name = {s.name: s for s in agg.status}
    assert by_name["/dragon/limb1"].level == 0
    top = core.outbox.on("/diagnostics_toplevel_state")[-1]
    assert top.name == "toplevel_state" and top.level == agg.status[0].level


def test_the_core_publishes_a_change_at_once_but_at_most_every_min_period(dragon) -> None:
    core = DataMonitorCore("gc1/data_monitor", board_for(dragon), DataMonitorConfig())
    core.start(0.0)
    for spec in core.board.watched:
        if not spec.station:
            core.on_health(spec.name, good(spec.name), 0.0)
    core.tick(1.0)
    count = core.publications
    core.on_health("limb1", health("limb1", ("motors/j1", 2, "hot", {})), 1.05)
    core.tick(1.1)  # changed, but only 0.1 s after the last publication
    assert core.publications == count
    core.tick(1.25)
    assert core.publications == count + 1
    levels = {s.name: s.level for s in core.outbox.on("/diagnostics_agg")[-1].status}
    assert levels["/dragon/limb1"] == 2 and levels["/dragon"] == 2
    core.tick(1.5)  # nothing new, period not due
    assert core.publications == count + 1


def test_the_core_serves_its_alarm_history_oldest_first(dragon) -> None:
    core = DataMonitorCore("gc1/data_monitor", board_for(dragon, wall_offset=100.0))
    core.start(0.0)
    core.on_health("limb1", health("limb1", ("motors/j1", 2, "hot", {})), 0.5)
    core.tick(0.5)
    request = msg("msctl_msgs/srv/GetAlarms_Request", max_count=0)
    response = core.on_get_alarms(request, 1.0)
    assert response.source == "gc1/data_monitor"
    received = [alarm_from_message(a) for a in response.alarms]
    assert received == list(core.board.alarms) and received
    assert received[0].at == pytest.approx(100.5)
    one = core.on_get_alarms(msg("msctl_msgs/srv/GetAlarms_Request", max_count=1), 1.0)
    assert len(one.alarms) == 1
    assert alarm_from_message(alarm_message(received[0])) == received[0]


def test_a_bound_core_stamps_its_alarms_with_the_executors_wall_clock(dragon) -> None:
    # As the data monitor's build makes it: a board with no wall clock of its own.
    core = DataMonitorCore("gc1/data_monitor", board_for(dragon))
    core.bind(RecordingOutbox(), wall_offset=1_700_000_000.0)
    core.start(0.0)
    core.on_health("limb1", health("limb1", ("motors/j1", 2, "hot", {})), 0.5)
    core.tick(0.5)
    response = core.on_get_alarms(msg("msctl_msgs/srv/GetAlarms_Request", max_count=0), 1.0)
    stamps = [alarm_from_message(a).at for a in response.alarms]
    assert stamps and all(s == pytest.approx(1_700_000_000.5) for s in stamps)


def test_history_from_a_data_monitor_merges_without_duplicates(dragon) -> None:
    board = board_for(dragon)
    old = [Alarm(float(i), "limb1", "limb1", OK, ERROR, "x") for i in range(5)]
    assert board.merge_history(old) == 5
    assert board.merge_history(old) == 0
    assert [a.at for a in board.alarms] == [0.0, 1.0, 2.0, 3.0, 4.0]


def test_aggregate_names_stations_and_the_top_by_the_assembly(dragon) -> None:
    board = board_for(dragon)
    statuses = aggregate(board.evaluate(0.0))
    assert statuses[0][0] == "/dragon" and statuses[0][1] is STALE
    assert any(name == "/dragon/gc1" for name, *_ in statuses)


# ---------------------------------------------------------------------------- stations
@pytest.fixture(scope="module")
def two_dragons() -> ResolvedAssembly:
    return from_document(resolve("two_dragons").document)


def archiver_report(station: str, level: int, message: str) -> Any:
    """What a data archiver publishes on its station's diagnostics."""
    values = {"current_file": "b_0.mcap", "dropped": "0"}
    return diagnostic_array(
        [diagnostic_status(f"{station}/data_archiver", level, message, "", values)]
    )


def test_a_station_shows_what_its_components_report_and_their_silence(two_dragons) -> None:
    board = board_for(two_dragons)
    front = next(s for s in board.watched if s.name == "gc_front")
    assert front.station and front.health_topic == "/gc_front/diagnostics"
    board.on_health("gc_front", archiver_report("gc_front", 0, "recording 3 topic(s)"), 0.0)
    row = board.evaluate(0.1).row("gc_front")
    item = next(i for i in row.items if i.name == "gc_front/status/data_archiver")
    assert (item.level, item.message) == (OK, "recording 3 topic(s)")
    assert item.values["current_file"] == "b_0.mcap"
    assert row.group("status") == [item]
    board.take_alarms()
    board.on_health("gc_front", archiver_report("gc_front", 1, "12 dropped"), 1.0)
    row = board.evaluate(1.1).row("gc_front")
    assert row.level is WARN and row.message == "gc_front/status/data_archiver: 12 dropped"
    # It stops reporting: its last word is old news, shown STALE (and alarmed), never kept.
    row = board.evaluate(1.0 + STALE_AFTER + 0.01).row("gc_front")
    item = next(i for i in row.items if i.name == "gc_front/status/data_archiver")
    assert item.level is STALE and item.message.startswith("no report for 2.5 s; last WARN")
    alarms = {(a.item, a.after) for a in board.take_alarms()}
    assert ("gc_front/status/data_archiver", STALE) in alarms
    names = {name for name, *_ in aggregate(board.evaluate(5.0))}
    assert "/two_dragons/gc_front/status/data_archiver" in names


def test_a_station_keeps_a_bounded_number_of_reporters(two_dragons) -> None:
    board = board_for(two_dragons, max_items=5)
    flood = diagnostic_array(
        [diagnostic_status(f"gc_rear/thing{i}", 0, "x" * 5000, "", {}) for i in range(50)]
    )
    board.on_health("gc_rear", flood, 0.0)
    board.on_health("gc_rear", archiver_report("gc_rear", 0, "late"), 0.1)
    row = board.evaluate(0.2).row("gc_rear")
    reports = row.group("status")
    assert len(reports) == 5 and all(len(i.message) <= MAX_MESSAGE for i in reports)
    assert board.unknown == 1  # the archiver came after the bound: counted, not shown


# ---------------------------------------------------------------------------- evaluation cost
def test_rows_are_judged_again_only_on_news_thresholds_or_after_a_second(
    dragon, monkeypatch: pytest.MonkeyPatch
) -> None:
    board = board_for(dragon)
    board.watch_graph(0.0)
    all_healthy(board, 0.0)
    _seen(board, "limb1", 0.0)
    judged: list[str] = []
    row = board._row
    monkeypatch.setattr(
        board, "_row", lambda state, now: judged.append(state.spec.name) or row(state, now)
    )
    board.evaluate(0.1)
    assert len(judged) == 5  # every row once
    judged.clear()
    board.evaluate(0.3)
    assert judged == []  # nothing new: every row as it was
    board.on_health("limb1", good("limb1"), 0.4)
    assert board.evaluate(0.5).row("limb1").level is OK and judged == ["limb1"]
    judged.clear()
    board.evaluate(1.2)  # a second since the others were judged: their ages move on
    assert sorted(judged) == ["gc1", "limb2", "wheel1", "wheel2"]

    # Thresholds are met on time whatever the evaluation rate: stale just after 2.5 s.
    def wheel1_health(now: float) -> Level:
        row = board.evaluate(now).row("wheel1")
        return next(i.level for i in row.items if i.name == "wheel1/health")

    assert wheel1_health(STALE_AFTER - 0.01) is OK
    assert wheel1_health(STALE_AFTER + 0.001) is STALE
    # A supervisor's news (a new pid) is shown at once; the same answer again is not news.
    document = {
        "host": "laptop",
        "components": [
            {"name": "limb1/joint_manager", "process": "limb1", "state": "running", "pid": 7}
        ],
    }
    board.on_supervisors([document], 2.6)
    judged.clear()
    row = board.evaluate(2.61).row("limb1")
    assert next(c.pid for c in row.components if c.label == "joint_manager") == 7
    assert "limb1" in judged
    board.on_supervisors([document], 2.7)
    judged.clear()
    board.evaluate(2.71)
    assert judged == []


def test_the_aggregate_is_encoded_byte_for_byte_as_the_serializer_does(dragon) -> None:
    from components.comm.types import registry
    from components.data_monitor.encoding import AggregateEncoder
    from components.messages import DIAGNOSTIC_ARRAY

    serialize = registry().serializer(DIAGNOSTIC_ARRAY)
    board = board_for(dragon)
    all_healthy(board, 0.0)
    board.on_health("limb2", health("limb2", ("motors/j1", 7, "ünïcode ✓ " * 3, {"k": ""})), 0.0)
    entries = aggregate(board.evaluate(0.1))
    entries += [("/x", 3, "", "", {}), ("/xy", 1, "abc", "h", {"a": "b", "cc": "dd"})]
    encoder = AggregateEncoder()
    for stamp in (0.0, 1767323045.123456):
        expected = serialize(diagnostic_array([diagnostic_status(*e) for e in entries], stamp))
        assert encoder.encode(entries, stamp) == expected
    assert encoder.encoded == 0  # the second time, every status's bytes were kept
    changed = [entries[0], ("/x", 2, "now bad", "", {}), *entries[1:]]
    expected = serialize(diagnostic_array([diagnostic_status(*e) for e in changed], 5.0))
    assert encoder.encode(changed, 5.0) == expected and encoder.encoded == 1
