"""Health monitor core with fake time and fake host metrics: every item's transitions,
thresholds from module data, and publication (1 Hz, and at once when something gets worse)."""

from __future__ import annotations

from typing import Any

import pytest

from components.build import BuildError, build_component
from components.health_monitor.core import ExpectedComponent, HealthMonitorCore
from components.health_monitor.motors import MotorWatch
from components.health_monitor.thresholds import HealthThresholds, TopicWatch
from components.messages import (
    ERROR,
    OK,
    STALE,
    WARN,
    diagnostic_array,
    diagnostic_status,
    diagnostic_values,
    joint_state,
)

JM = "/limb1/joint_manager"
MI = "/limb1/motor_interface"


class FakeHost:
    """Host metrics the test sets; raises when told to."""

    def __init__(self) -> None:
        self.metrics: dict[str, Any] = {
            "cpu_percent": 10.0,
            "memory_percent": 20.0,
            "disk_percent": 30.0,
            "temperature": 45.0,
            "temperature_sensor": "coretemp/Package id 0",
        }
        self.fail: Exception | None = None

    def __call__(self) -> dict[str, Any]:
        if self.fail is not None:
            raise self.fail
        return dict(self.metrics)


def make(health: dict[str, Any] | None = None, host: FakeHost | None = None) -> HealthMonitorCore:
    core = HealthMonitorCore(
        "limb1/health_monitor",
        module="limb1",
        components=[
            ExpectedComponent("motor_interface", MI),
            ExpectedComponent("joint_manager", JM),
        ],
        motors=[MotorWatch("limb1_joint1", "joint1"), MotorWatch("limb1_joint2", "joint2")],
        thresholds=HealthThresholds.from_mapping(health or {}),
        read_host_metrics=host or FakeHost(),
        unit="hlv1-limb-01",
        host="hl-limb-01",
    )
    core.start(0.0)
    return core


def items(core: HealthMonitorCore) -> dict[str, Any]:
    """The statuses of the last publication, by name."""
    return {s.name: s for s in core.outbox.on("health")[-1].status}


def level(core: HealthMonitorCore, name: str) -> int:
    """An item's level in the last publication."""
    return items(core)[f"limb1/{name}"].level


def items_now(core: HealthMonitorCore, now: float) -> dict[str, Any]:
    """Every item at ``now`` as a DiagnosticStatus, by name."""
    return {
        i.name: diagnostic_status(i.name, i.level, i.message, i.hardware_id, i.values)
        for i in core.evaluate(now)
    }


def level_now(core: HealthMonitorCore, name: str, now: float) -> int:
    """An item's level at ``now`` (improvements are only published at the 1 Hz slot)."""
    return {i.name: i.level for i in core.evaluate(now)}[f"limb1/{name}"]


def feed_joint_states(core: HealthMonitorCore, start: float, end: float, hz: float) -> float:
    """Deliver joint_states at ``hz`` from ``start`` to ``end``, ticking at 10 Hz; returns end."""
    t, step, next_tick = start, 1.0 / hz, start
    message = joint_state([])
    while t < end:
        core.on_joint_states(message, t)
        if t >= next_tick:
            core.tick(t)
            next_tick += 0.1
        t += step
    return t


def diagnostics(*statuses: tuple[str, int, str, dict[str, Any]]) -> Any:
    return diagnostic_array(
        [diagnostic_status(n, lvl, msg, "can0", values) for n, lvl, msg, values in statuses]
    )


# ---------------------------------------------------------------------------- components


def test_start_publishes_summary_first_and_components_stale_during_grace() -> None:
    core = make()
    published = core.outbox.on("health")
    assert len(published) == 1
    assert published[0].status[0].name == "limb1"
    assert level(core, "components/joint_manager") == STALE
    assert (
        "waiting for /limb1/joint_manager" in items(core)["limb1/components/joint_manager"].message
    )


def test_component_ok_when_seen_error_at_once_when_gone_ok_again_when_back() -> None:
    core = make()
    core.on_component_seen(JM, True, 0.2)
    core.tick(1.0)
    assert level(core, "components/joint_manager") == OK
    before = len(core.outbox.on("health"))
    core.on_component_seen(JM, False, 1.3)
    # Published by the event itself, not at the next tick or 1 Hz slot.
    assert len(core.outbox.on("health")) == before + 1
    status = items(core)["limb1/components/joint_manager"]
    assert status.level == ERROR
    assert "disappeared" in status.message and JM in status.message
    assert items(core)["limb1"].level == ERROR
    core.on_component_seen(JM, True, 4.0)
    core.tick(4.0)
    assert level(core, "components/joint_manager") == OK
    assert diagnostic_values(items(core)["limb1/components/joint_manager"])["appearances"] == "2"


def test_component_never_seen_becomes_error_after_grace() -> None:
    core = make({"component_grace": 2.0})
    core.tick(1.9)
    assert level(core, "components/motor_interface") == STALE
    core.tick(2.1)
    status = items(core)["limb1/components/motor_interface"]
    assert status.level == ERROR and "has not appeared" in status.message


def test_shared_node_name_expects_every_instance() -> None:
    """Two location publishers share /limb1/location_publisher: one dying is an ERROR."""
    node = "/limb1/location_publisher"
    core = HealthMonitorCore("h", "limb1", [ExpectedComponent("location_publisher", node, 2)])
    core.start(0.0)
    core.on_component_instances(node, 1, 0.1)
    assert level_now(core, "components/location_publisher", 0.2) == STALE  # still starting
    core.on_component_instances(node, 2, 0.3)
    assert level_now(core, "components/location_publisher", 1.5) == OK
    core.on_component_instances(node, 1, 2.0)
    status = items(core)["limb1/components/location_publisher"]
    assert status.level == ERROR and "only 1 of 2" in status.message
    assert diagnostic_values(status)["instances"] == "1/2"


def test_simulator_stands_in_for_the_motor_interface() -> None:
    expected = ExpectedComponent("motor_interface", MI, alternatives=("/sim/simulator",))
    core = HealthMonitorCore("h", "limb1", [expected])
    core.start(0.0)
    core.on_component_seen("/sim/simulator", True, 0.5)
    status = {i.name: i for i in core.evaluate(0.5)}["limb1/components/motor_interface"]
    assert status.level == OK and "/sim/simulator running" in status.message
    core.on_component_seen("/sim/simulator", False, 1.0)
    assert level(core, "components/motor_interface") == ERROR


def test_graph_feed_counts_node_tokens_and_posts_changes_only() -> None:
    from components.build import BuiltComponent
    from components.comm.liveliness import Entity, EntityKind
    from components.executor.interface import InterfaceSpec
    from components.health_monitor.build import GraphFeed

    posted: list[tuple[str, int]] = []
    feed = GraphFeed(BuiltComponent(None, InterfaceSpec(), "/limb1", "h"), {JM})  # type: ignore[arg-type]
    feed._post = lambda node, count: posted.append((node, count))

    def node(zid: str, kind: EntityKind = EntityKind.NODE, ns: str = "/limb1") -> Entity:
        return Entity(0, zid, 0, 0, kind, ns, "joint_manager")

    feed._on_change(node("a"), True)
    feed._on_change(node("a", EntityKind.PUBLISHER), True)  # not a node token
    feed._on_change(node("b", ns="/limb2"), True)  # not followed
    feed._on_change(node("c"), True)  # a restart overlapping its predecessor
    feed._on_change(node("a"), False)
    feed._on_change(node("a"), False)  # repeated vanish: no change
    feed._on_change(node("c"), False)
    assert posted == [(JM, 1), (JM, 2), (JM, 1), (JM, 0)]


def test_other_nodes_are_ignored() -> None:
    core = make()
    core.on_component_seen("/limb2/joint_manager", True, 0.1)
    core.tick(1.0)
    assert level(core, "components/joint_manager") == STALE


# ---------------------------------------------------------------------------- topics


def test_topic_rate_ok_then_stale_when_silent() -> None:
    core = make()
    t = feed_joint_states(core, 0.0, 2.0, 100.0)
    core.tick(t)
    status = items(core)["limb1/topics/joint_states"]
    assert status.level == OK
    assert 95.0 <= float(diagnostic_values(status)["rate_hz"]) <= 105.0
    # Default stale_after for joint_states is the module's stale_after (0.5 s).
    core.tick(t + 0.4)
    assert level(core, "topics/joint_states") == OK
    before = len(core.outbox.on("health"))
    core.tick(t + 0.6)
    assert len(core.outbox.on("health")) == before + 1  # worse: published at once
    status = items(core)["limb1/topics/joint_states"]
    assert status.level == STALE and "silent" in status.message


def test_rate_is_measured_over_what_was_seen_before_a_full_window() -> None:
    core = make()
    t = feed_joint_states(core, 0.0, 0.5, 100.0)
    rate = float(diagnostic_values(items_now(core, t)["limb1/topics/joint_states"])["rate_hz"])
    assert 90.0 <= rate <= 110.0


def test_topic_below_min_rate_warns_only_after_a_full_window() -> None:
    core = make({"min_rate": 50.0})
    feed_joint_states(core, 0.0, 0.5, 20.0)
    assert level_now(core, "topics/joint_states", 0.5) == OK  # too early to judge a rate
    t = feed_joint_states(core, 0.5, 2.0, 20.0)
    core.tick(t)
    status = items(core)["limb1/topics/joint_states"]
    assert status.level == WARN and "expected at least 50 Hz" in status.message


def test_topic_thresholds_come_from_module_data() -> None:
    core = make({"stale_after": 0.2, "topics": {"joint_read": {"stale_after": 0.3}}})
    core.on_joint_read(joint_state([]), 1.0)
    core.on_joint_states(joint_state([]), 1.0)
    core.tick(1.25)
    assert level(core, "topics/joint_states") == STALE
    assert level(core, "topics/joint_read") == OK
    core.tick(1.35)
    assert level(core, "topics/joint_read") == STALE


def test_joint_read_keepalive_is_not_stale_between_keepalives() -> None:
    core = make()
    for second in range(5):
        core.on_joint_read(joint_state([]), float(second))
        assert level_now(core, "topics/joint_read", second + 0.95) == OK


def test_topic_watches_defaults_and_overrides() -> None:
    watches = HealthThresholds.from_mapping(
        {"min_rate": 80, "topics": {"diagnostics": {"stale_after": 5, "min_rate": 0.5}}}
    ).topic_watches()
    assert watches == (
        TopicWatch("joint_states", 0.5, 80.0),
        TopicWatch("joint_read", 2.5, None),
        TopicWatch("diagnostics", 5.0, 0.5),
    )


@pytest.mark.parametrize(
    "data",
    [{"stale_after": "fast"}, {"cpu_warn": True}, {"topics": {"joint_read": {"rate": 1}}}],
)
def test_bad_thresholds_name_the_key(data: dict[str, Any]) -> None:
    with pytest.raises(ValueError, match=r"\[health\]"):
        HealthThresholds.from_mapping(data)


def test_unused_module_keys_are_ignored() -> None:
    assert HealthThresholds.from_mapping({"max_current": 3.0}) == HealthThresholds()


# ---------------------------------------------------------------------------- tracking


def test_a_joint_stalled_off_its_target_is_warn_after_the_grace() -> None:
    from components.messages import JointSample, joint_state

    core = make({"max_tracking_error": 0.2, "tracking_grace": 1.0})
    core.start(0.0)
    core.on_joint_commands(joint_state([JointSample("limb1_joint1", 1.0)]), 0.0)
    core.on_joint_commands(joint_state([JointSample("limb1_joint2", 0.5)]), 0.0)
    for t in (0.5, 1.0, 1.6):
        core.on_joint_states(
            joint_state(
                [
                    JointSample("limb1_joint1", 0.6, 0.0, 0.0),  # stuck 0.4 short, still
                    JointSample("limb1_joint2", 0.45, 0.0, 0.0),  # a servo's sag: fine
                ]
            ),
            t,
        )
    assert level_now(core, "tracking", 1.4) == OK  # stalled 0.9 s: within the grace
    status = items_now(core, 1.6)["limb1/tracking"]
    assert status.level == WARN
    assert "limb1_joint1" in status.message and "limb1_joint2" not in status.message
    # A new target gives it a new chance; reaching it clears the item.
    core.on_joint_commands(joint_state([JointSample("limb1_joint1", 0.6)]), 1.7)
    core.on_joint_states(joint_state([JointSample("limb1_joint1", 0.6, 0.0, 0.0)]), 1.8)
    assert level_now(core, "tracking", 3.0) == OK


def test_a_moving_joint_or_a_velocity_command_is_not_a_tracking_fault() -> None:
    from components.messages import JointSample, joint_state

    core = make({"max_tracking_error": 0.2, "tracking_grace": 0.5})
    core.start(0.0)
    core.on_joint_commands(joint_state([JointSample("limb1_joint1", 2.0)]), 0.0)
    for t in (0.2, 0.6, 1.0):  # far from target but on its way
        core.on_joint_states(joint_state([JointSample("limb1_joint1", t, 1.0, 0.0)]), t)
    assert level_now(core, "tracking", 1.0) == OK
    core.on_joint_commands(joint_state([JointSample("limb1_joint1", None, 0.0)]), 1.1)
    core.on_joint_states(joint_state([JointSample("limb1_joint1", 1.0, 0.0, 0.0)]), 1.2)
    assert level_now(core, "tracking", 3.0) == OK  # velocity mode: nothing to track


def test_without_a_limit_in_module_data_there_is_no_tracking_item() -> None:
    core = make()
    core.start(0.0)
    assert "limb1/tracking" not in items_now(core, 0.1)


# ---------------------------------------------------------------------------- motors


def test_motor_takes_the_worst_fresh_source_and_goes_stale_without_diagnostics() -> None:
    core = make()
    core.on_diagnostics(
        diagnostics(
            ("limb1_joint1", OK, "ok", {"temperature": "40.0"}),
            ("limb1/joint_manager/limb1_joint1", WARN, "commands clamped", {}),
            ("limb1/joint_manager", OK, "OK", {}),
        ),
        1.0,
    )
    status = items(core)["limb1/motors/limb1_joint1"]  # WARN is worse: published at once
    assert status.level == WARN and status.message == "commands clamped"
    assert diagnostic_values(status)["source"] == "limb1/joint_manager/limb1_joint1"
    # joint2 is named by its raw name by this source.
    core.on_diagnostics(diagnostics(("joint2", ERROR, "joint2: drive fault 0x2310", {})), 1.1)
    status = items(core)["limb1/motors/limb1_joint2"]
    assert status.level == ERROR and "0x2310" in status.message
    core.tick(1.0 + 3.5)  # diagnostics_stale_after defaults to 3 s
    assert level(core, "motors/limb1_joint1") == STALE
    assert "no diagnostics for" in items(core)["limb1/motors/limb1_joint1"].message


def test_motor_temperature_and_voltage_limits_from_module_data() -> None:
    core = make({"max_temperature": 70.0, "temperature_margin": 5.0, "min_voltage": 11.0})
    core.on_diagnostics(diagnostics(("limb1_joint1", OK, "ok", {"temperature": "66"})), 1.0)
    assert level(core, "motors/limb1_joint1") == WARN
    core.on_diagnostics(diagnostics(("limb1_joint1", OK, "ok", {"temperature_c": "71"})), 1.1)
    status = items(core)["limb1/motors/limb1_joint1"]
    assert status.level == ERROR and "module limit 70" in status.message
    core.on_diagnostics(diagnostics(("limb1_joint2", OK, "ok", {"input_voltage_v": "10.5"})), 1.2)
    # STALE (no news) -> WARN ranks as better, so this shows at the next regular slot.
    assert level_now(core, "motors/limb1_joint2", 1.2) == WARN


def test_bus_item_appears_when_the_bus_reports() -> None:
    core = make()
    assert "limb1/motors/bus" not in items(core)
    core.on_diagnostics(diagnostics(("limb1/bus", ERROR, "motor bus can0 is not open", {})), 1.0)
    assert level(core, "motors/bus") == ERROR


# ---------------------------------------------------------------------------- host


@pytest.mark.parametrize(
    ("key", "item", "value", "expected"),
    [
        ("cpu_percent", "cpu", 50.0, OK),
        ("cpu_percent", "cpu", 90.0, WARN),
        ("cpu_percent", "cpu", 99.0, ERROR),
        ("memory_percent", "memory", 90.0, WARN),
        ("memory_percent", "memory", 96.0, ERROR),
        ("disk_percent", "disk", 91.0, WARN),
        ("disk_percent", "disk", 98.0, ERROR),
        ("temperature", "temperature", 85.0, WARN),
        ("temperature", "temperature", 95.0, ERROR),
    ],
)
def test_host_default_thresholds(key: str, item: str, value: float, expected: int) -> None:
    host = FakeHost()
    core = make(host=host)
    host.metrics[key] = value
    core.on_host_timer(1.0)
    core.tick(1.0)
    assert level(core, f"host/{item}") == expected


def test_host_thresholds_from_module_data_and_missing_sensor() -> None:
    host = FakeHost()
    host.metrics.update(cpu_percent=60.0, temperature=None)
    core = make({"cpu_warn": 50, "cpu_error": 70}, host=host)
    core.tick(1.0)
    assert level(core, "host/cpu") == WARN
    status = items(core)["limb1/host/temperature"]
    assert status.level == OK and "not readable" in status.message


def test_host_read_failure_is_stale_not_a_crash() -> None:
    host = FakeHost()
    core = make(host=host)
    host.fail = OSError("sensor gone")
    core.on_host_timer(2.0)
    core.tick(2.0)
    status = items(core)["limb1/host/cpu"]
    assert status.level == STALE and "sensor gone" in status.message
    host.fail = None
    core.on_host_timer(4.0)
    core.tick(4.0)
    assert level(core, "host/cpu") == OK


def test_no_host_reader_means_no_host_items() -> None:
    core = HealthMonitorCore("h", "limb1", [ExpectedComponent("joint_manager", JM)])
    core.start(0.0)
    assert not [n for n in items(core) if "/host/" in n]


# ---------------------------------------------------------------------------- publication


def test_publishes_at_1hz_when_nothing_changes_and_at_once_when_worse() -> None:
    core = make()
    core.on_component_seen(JM, True, 0.0)
    core.on_component_seen(MI, True, 0.0)
    core.outbox.take()
    for tenth in range(1, 31):
        core.tick(tenth / 10)
    assert len(core.outbox.take("health")) == 3
    core.on_component_seen(MI, False, 3.05)  # worse: at once
    assert len(core.outbox.take("health")) == 1
    core.on_component_seen(MI, True, 3.1)  # better: waits for the regular slot
    assert core.outbox.take("health") == []
    core.tick(4.06)
    assert len(core.outbox.take("health")) == 1


def test_summary_counts_and_names_the_bad_items() -> None:
    core = make()
    core.on_component_seen(JM, True, 0.1)
    core.on_component_seen(JM, False, 0.2)
    summary = items(core)["limb1"]
    assert summary.level == ERROR
    assert summary.message.startswith("components/joint_manager ERROR")
    values = diagnostic_values(summary)
    assert values["error"] == "1"
    assert int(values["items"]) == len(items(core)) - 1


def test_stamp_uses_wall_offset() -> None:
    core = make()
    core.wall_offset = 1000.0
    core.tick(1.5)
    header = core.outbox.on("health")[-1].header
    assert header.stamp.sec == 1001 and header.stamp.nanosec == 500_000_000


# ---------------------------------------------------------------------------- builder


def test_builder_reads_module_health_and_expects_the_module_components() -> None:
    from components.assembly import from_document
    from msctl.assembler import resolve

    assembly = from_document(resolve("dragon").document)
    plan = assembly.component("limb1/health_monitor")
    built = build_component(
        plan, assembly, {"launched": ["limb1/joint_manager", "limb1/motor_interface"]}
    )
    core = built.core
    assert isinstance(core, HealthMonitorCore)
    assert (built.namespace, built.node_name) == ("/limb1", "health_monitor")
    assert core.thresholds.max_temperature == assembly.module("limb1").health["max_temperature"]
    nodes = sorted(s.expected.node for s in core._components.values())
    assert nodes == [JM, MI]
    sim = build_component(plan, assembly, {"sim": True, "launched": ["limb1/motor_interface"]})
    assert [s.expected.node for s in sim.core._components.values()] == ["/sim/simulator"]
    assert built.on_bound is not None
    # Without a launch list: every kind the launcher starts, each under its own node name
    # (the module's two location publishers are two nodes, two items).
    default = build_component(plan, assembly, {})
    counts = {s.expected.label: s.expected.count for s in default.core._components.values()}
    locations = sorted(
        c.name
        for c in assembly.components_on(assembly.module("limb1").host)
        if c.module == "limb1" and c.kind == "location_publisher"
    )
    assert counts["joint_manager"] == 1
    assert {f"{n.rsplit('/', 1)[-1]}": 1 for n in locations}.items() <= counts.items()
    default.close()
    built.close()
    sim.close()


def test_builder_refuses_a_bad_threshold_naming_module_and_key() -> None:
    from dataclasses import replace

    from components.assembly import from_document
    from msctl.assembler import resolve

    assembly = from_document(resolve("dragon").document)
    plan = assembly.component("limb1/health_monitor")
    bad = replace(plan, params={**plan.params, "thresholds": {"cpu_warn": "high"}})
    with pytest.raises(BuildError, match=r"limb1.*cpu_warn"):
        build_component(bad, assembly, {})


# ---------------------------------------------------------------------------- bounded state


def test_a_100k_name_flood_is_refused_whole_and_nothing_of_it_is_stored() -> None:
    """Issue 10, finding 3: the monitor stored every name it saw and starved the process."""
    import numpy as np

    from components.messages import JOINT_STATE, JointSample, joint_state, msg

    core = make({"max_tracking_error": 0.2})
    names = [f"limb1_x{i}" for i in range(100_000)]
    flood = msg(JOINT_STATE, name=names, position=np.zeros(len(names)))
    core.on_joint_commands(flood, 0.1)
    core.on_joint_states(flood, 0.1)
    assert core.counters["refused_oversize"] == 2
    assert core._targets == {} and core._tracking_errors == {}
    assert core._topics["joint_states"].count == 0  # not a sample either
    # Within the size, names that are not the module's motors are not kept either.
    core.on_joint_commands(joint_state([JointSample("limb9_joint1", 1.0)]), 0.2)
    core.on_joint_commands(joint_state([JointSample("limb1_joint1", 1.0)]), 0.2)
    assert set(core._targets) == {"limb1_joint1"}
    values = diagnostic_values(items_now(core, 0.3)["limb1"])
    assert values["refused_oversize"] == "2"


def test_invented_diagnostics_sources_and_nodes_are_bounded() -> None:
    from components.health_monitor.motors import MAX_SOURCES

    core = make()
    flood = diagnostics(*((f"x{i}/limb1_joint1", OK, "ok", {}) for i in range(1000)))
    core.on_diagnostics(flood, 0.1)
    assert len(core._motor_reports["limb1_joint1"]) == MAX_SOURCES
    assert core.counters["dropped_sources"] == 1000 - MAX_SOURCES
    # Once they are silent, a real source gets a place.
    core.on_diagnostics(diagnostics(("limb1_joint1", OK, "ok", {})), 10.0)
    assert "limb1_joint1" in core._motor_reports["limb1_joint1"]
    for i in range(1000):
        core.on_component_seen(f"/intruder_{i}", True, 0.2)
    assert core._instances == {}
