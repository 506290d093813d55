"""The data_archiver component kind: its pure core (selection, QoS rule, losses, status),
its registry entry, its plan in two_dragons, and a real run in-process on Zenoh."""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import quick_peer_settings, quick_router, wait_until
from rosbags.rosbag2 import Reader

from components import kinds
from components.assembly import ResolvedAssembly, from_document
from components.build import BuildError, build_component
from components.comm import LATCHED, SENSOR, QoS
from components.comm.node import Node
from components.comm.session import SessionSettings, open_session
from components.data_archiver.core import (
    ArchiverConfig,
    ArchiverCore,
    DataArchiverCore,
    RecorderStatus,
    SequenceTracker,
    TopicSelection,
    subscription_qos,
)
from components.executor.runner import run_built
from components.messages import DIAGNOSTIC_ARRAY, Level, diagnostic_values, msg
from msctl.assembler import resolve
from msctl.health.live import LiveHealth
from msctl.launcher.plan import plan_host
from msctl.recorder.bag import inspect

STRING = "std_msgs/msg/String"


@pytest.fixture(scope="module")
def two_dragons() -> ResolvedAssembly:
    return from_document(resolve("two_dragons").document)


@pytest.fixture
def router_endpoint() -> Iterator[str]:
    yield from quick_router()


@pytest.fixture
def session_settings(router_endpoint: str) -> SessionSettings:
    return quick_peer_settings(router_endpoint)


# --------------------------------------------------------------------------- core
def test_selection_by_names_all_regex_and_exclude() -> None:
    everything = TopicSelection.from_text("*", exclude="^/sim/")
    assert everything.wildcard
    assert everything.matches("/limb1/joint_read")
    assert not everything.matches("/sim/base_pose")
    assert not everything.matches("/_hidden")
    named = TopicSelection.from_text("limb1/joint_read, /cmd_vel")
    assert named.topics == ("/limb1/joint_read", "/cmd_vel") and not named.wildcard
    assert named.matches("/cmd_vel") and not named.matches("/limb1/joint_set")
    regex = TopicSelection(topics=("/limb1/joint_set",), regex="joint_", exclude="_set$")
    assert regex.matches("/limb1/joint_read")
    assert regex.matches("/limb1/joint_set")  # named: taken whatever --exclude says
    assert not regex.matches("/limb2/joint_set")
    with pytest.raises(ValueError, match="nothing to record"):
        TopicSelection()
    with pytest.raises(ValueError, match=r"--regex '\(' is not a regular expression"):
        TopicSelection(regex="(")


def test_subscription_qos_follows_rosbag2s_rule() -> None:
    assert subscription_qos([]) == QoS()
    assert subscription_qos([QoS(), SENSOR]).reliability == "best_effort"
    assert subscription_qos([LATCHED, LATCHED]).durability == "transient_local"
    assert subscription_qos([LATCHED, QoS()]).durability == "volatile"
    assert subscription_qos([QoS(depth=3), QoS(depth=50)]).depth == 50


def test_sequence_tracker_counts_gaps_per_publisher_and_forgives_restarts() -> None:
    tracker = SequenceTracker()
    assert tracker.observe(0, b"a", 1) == 0
    assert tracker.observe(0, b"a", 4) == 2
    assert tracker.observe(0, b"b", 10) == 0  # another publisher starts where it is
    assert tracker.observe(0, b"a", 1) == 0  # a restart
    assert tracker.observe(1, b"a", 7) == 0
    assert tracker.lost == {0: 2} and tracker.total == 2
    # A topic sampled on its way (a radio link's downsampling) jumps by design: not counted.
    tracker.thinned.add(2)
    assert tracker.count(2, b"a", 1) is None
    assert tracker.count(2, b"a", 11) is None
    assert tracker.count(2, b"a", 12) == 0
    assert tracker.lost == {0: 2}


def test_status_levels_and_rates() -> None:
    core = ArchiverCore("/gc1/data_archiver")
    level, message, values = core.report(RecorderStatus(messages=0, bytes=0, topics=2), 10.0)
    assert level is Level.OK and "2 topic(s)" in message
    level, _, values = core.report(RecorderStatus(messages=500, bytes=50_000, topics=2), 11.0)
    assert values["rate_hz"] == "500.0" and values["bytes_per_s"] == "50000"
    assert core.report(RecorderStatus(dropped=3), 12.0)[0] is Level.WARN
    assert core.report(RecorderStatus(paused=True), 13.0)[1].startswith("paused: ")
    _, message, _ = core.report(
        RecorderStatus(current_file="b_3.mcap", topics=4, messages=900, bytes=2_500_000), 14.0
    )
    assert message == (
        "recording 4 topic(s): 900 msgs, 2.5 MB, 900 msg/s, 0 dropped, 0 lost upstream, "
        "file b_3.mcap"
    )
    level, message, _ = core.report(RecorderStatus(error="the disk is full"), 14.0)
    assert level is Level.ERROR and "the disk is full" in message
    # A link down: it still records what arrives, and says what it does not receive.
    level, message, values = core.report(
        RecorderStatus(topics=2, gaps=1, silent=("/limb1/joint_states",)), 15.0
    )
    assert level is Level.WARN
    assert message.startswith("not receiving /limb1/joint_states (a link down?)")
    assert values["gaps"] == "1" and values["not_receiving"] == "/limb1/joint_states"


def test_the_core_publishes_its_status_on_diagnostics() -> None:
    status = RecorderStatus(directory="/bags/b", current_file="b_0.mcap", messages=7, topics=1)
    core = DataArchiverCore("gc1/data_archiver", lambda: status, hardware_id="ground1")
    core.tick(1.0)
    (array,) = core.outbox.on("diagnostics")
    (entry,) = array.status
    assert entry.name == "gc1/data_archiver" and entry.hardware_id == "ground1"
    values = diagnostic_values(entry)
    assert values["current_file"] == "b_0.mcap" and values["messages"] == "7"


# --------------------------------------------------------------------------- kind and plan
def test_the_kind_is_a_runnable_station_kind_with_checked_parameters() -> None:
    entry = kinds.get("data_archiver")
    assert entry.placement is kinds.Placement.STATION and entry.runnable
    assert entry.healthy_output == "diagnostics"
    kinds.check_params(entry, {"topics": "*", "exclude": "^/sim/", "max_bag_size": 100_000_000})
    with pytest.raises(kinds.KindError, match="max_bag_size must be >= 0"):
        kinds.check_params(entry, {"max_bag_size": -1})
    with pytest.raises(kinds.KindError, match="not a regular expression"):
        kinds.check_params(entry, {"regex": "[joint"})
    with pytest.raises(kinds.KindError, match="compression must be 'zstd' or 'none'"):
        kinds.check_params(entry, {"compression": "lz4"})
    with pytest.raises(kinds.KindError, match="no parameter 'output'"):
        kinds.check_params(entry, {"output": "x"})
    with pytest.raises(ValueError, match="nothing to record"):
        ArchiverConfig(topics="")


def test_two_dragons_starts_its_two_data_archivers(two_dragons: ResolvedAssembly) -> None:
    plan = plan_host(two_dragons, "a-laptop")
    archivers = [c for c in plan.components if c.kind == "data_archiver"]
    assert sorted(c.name for c in archivers) == ["gc_front/data_archiver", "gc_rear/data_archiver"]
    assert "data_archiver" not in {k for _, k in plan.not_built}


def test_a_bad_parameter_fails_the_build_naming_the_component(
    two_dragons: ResolvedAssembly,
) -> None:
    plan = two_dragons.component("gc_front/data_archiver")
    bad = dataclasses.replace(plan, params={"max_bag_duration": -5.0})
    with pytest.raises(BuildError, match=r"gc_front/data_archiver: .*max_bag_duration"):
        build_component(bad, two_dragons, {})


# --------------------------------------------------------------------------- a real run
def test_the_archiver_records_and_reports_on_diagnostics(
    two_dragons: ResolvedAssembly,
    session_settings: SessionSettings,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("MSCTL_HOME", str(tmp_path / "home"))
    plan = dataclasses.replace(
        two_dragons.component("gc_front/data_archiver"),
        params={"topics": "/d1_limb1/joint_read", "directory": "archive", "max_bag_size": 8192},
    )
    built = build_component(plan, two_dragons, {})
    ready = threading.Event()
    executors: list[Any] = []

    def on_ready(executor: Any) -> None:
        executors.append(executor)
        ready.set()

    runner = threading.Thread(
        target=run_built, args=([built], session_settings), kwargs={"on_ready": on_ready}
    )
    runner.start()
    session = open_session(session_settings)
    node = Node(session, "joint_manager", "/d1_limb1")
    reports: list[Any] = []
    live: LiveHealth | None = None
    try:
        assert ready.wait(30.0)
        node.subscription("/gc_front/diagnostics", DIAGNOSTIC_ARRAY, reports.append)
        publisher = node.publisher("joint_read", STRING)
        other = node.publisher("joint_set", STRING)

        def recorded() -> tuple[int, int]:
            publisher.publish(msg(STRING, data="x" * 200))
            other.publish(msg(STRING, data="not recorded"))
            if not reports:
                return 0, 0
            values = diagnostic_values(reports[-1].status[0])
            return int(values["messages"]), int(values["files"])

        # 100 messages of 200 bytes split at 8 KiB; the file count follows the writer
        # thread, a moment after the messages are counted.
        wait_until(
            lambda: (counts := recorded())[0] >= 100 and counts[1] >= 2,
            timeout=60.0,
            interval=0.01,
            what="100 recorded in two files or more",
        )
        entry = reports[-1].status[0]
        assert entry.level == Level.OK and entry.name == "gc_front/data_archiver"
        # `msctl health` shows it on the station's row (its board, read live).
        live = LiveHealth(node, two_dragons, supervisors=False).start()

        def shown() -> Any:
            row = live.evaluate().row("gc_front")
            return next((i for i in row.group("status") if i.level is Level.OK), None)

        item = wait_until(shown, timeout=30.0, what="the archiver's status in msctl health")
        assert item.name == "gc_front/status/data_archiver"
        assert item.message.startswith("recording 1 topic(s): ") and "file " in item.message
        assert item.values["current_file"].startswith("gc_front_data_archiver_")
    finally:
        if live is not None:
            live.close()
        if executors:
            executors[0].stop()
        runner.join(timeout=30.0)
        node.close()
        session.close()
    (bag,) = (tmp_path / "home" / "archive").iterdir()
    assert bag.name.startswith("gc_front_data_archiver_")
    with Reader(bag) as reader:
        assert {c.topic for c in reader.connections} == {"/d1_limb1/joint_read"}
        assert reader.message_count >= 100
    described = inspect(bag)
    assert len(described.files) >= 2 and not described.needs_recovery


def test_a_recorder_on_the_ground_knows_which_topics_the_radio_samples(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from components.recording.thinned import radio_thinned
    from msctl.assembler import resolve
    from msctl.assembler.store import write_resolution

    monkeypatch.setenv("MSCTL_HOME", str(tmp_path))
    monkeypatch.delenv("MSCTL_SECURE", raising=False)
    assert radio_thinned("ground1") == {}  # nothing resolved here
    write_resolution(tmp_path / "assembly", resolve("dragon", {}), mjcf=False)
    assert radio_thinned("ground1") == {}  # plain links filter nothing
    monkeypatch.setenv("MSCTL_SECURE", "1")  # as a secure fleet's agents run
    thinned = radio_thinned("ground1")
    assert thinned["/limb1/joint_states"] == 10.0 and thinned["/wheel2/joint_read"] == 10.0
    assert "/limb1/health" not in thinned  # never sampled
    assert "/limb1/joint_states" not in radio_thinned("hl-limb-01")  # its own, whole
    assert radio_thinned("laptop") == {}  # not one of the assembly's computers
