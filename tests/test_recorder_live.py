"""The live recorder on real Zenoh sessions (loopback router, random port): discovery,
latched topics, pause, unknown types, drops and upstream losses."""

from __future__ import annotations

import json
import os
import socket
import struct
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import quick_peer_settings, quick_router, wait_until
from mcap.reader import make_reader
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from components.comm import LATCHED, SENSOR, Node
from components.comm.graph import snapshot
from components.comm.liveliness import EntityKind
from components.comm.session import SessionSettings
from components.data_archiver.core import TopicSelection
from components.messages import msg
from components.recording.errors import BagError
from components.recording.keys import parse_key
from components.recording.metadata import read_metadata
from components.recording.recorder import Recorder
from msctl.recorder.bag import inspect, read_messages

STRING = "std_msgs/msg/String"
STORE = get_typestore(Stores.ROS2_JAZZY)


@pytest.fixture
def router_endpoint() -> Iterator[str]:
    yield from quick_router()


@pytest.fixture
def session_settings(router_endpoint: str) -> SessionSettings:
    return quick_peer_settings(router_endpoint)


@pytest.fixture
def talker(open_sessions: Callable[[], Any]) -> Iterator[Node]:
    node = Node(open_sessions(), "talker", "/robot")
    try:
        yield node
    finally:
        node.close()


def read_bag(path: Path) -> dict[str, list[Any]]:
    """Topic -> decoded messages, read by rosbags."""
    out: dict[str, list[Any]] = {}
    with Reader(path) as reader:
        for connection, _, raw in reader.messages():
            if connection.msgdef.data:
                out.setdefault(connection.topic, []).append(
                    STORE.deserialize_cdr(raw, connection.msgtype)
                )
            else:
                out.setdefault(connection.topic, []).append(raw)
    return out


def subscribed(session: Any, topic: str) -> bool:
    """Whether the recorder's subscription to ``topic`` is on the graph."""
    info = snapshot(session, timeout=0.5).topics().get(topic)
    return info is not None and info.subscribers > 0


def warm_up(recorder: Recorder, publish: Callable[[], None]) -> None:
    """Publish until the recorder has a message: its subscription has reached the sender."""
    wait_until(
        lambda: publish() or recorder.status().messages > 0,
        interval=0.1,
        what="the recorder's subscription",
    )


def test_parse_key_reads_topic_type_and_hash() -> None:
    key = "0/limb1/joint_read/sensor_msgs::msg::dds_::JointState_/RIHS01_ab"
    parsed = parse_key(key, 0)
    assert parsed is not None
    assert (parsed.topic, parsed.type, parsed.type_hash) == (
        "/limb1/joint_read",
        "sensor_msgs/msg/JointState",
        "RIHS01_ab",
    )
    assert parse_key(key, 1) is None
    assert parse_key("0/plain/key", 0) is None
    assert parse_key("@ros2_lv/0/x/y/z", 0) is None


def test_records_everything_from_the_first_message_and_latched_samples(
    tmp_path: Path, open_sessions: Callable[[], Any], talker: Node
) -> None:
    early = talker.publisher("robot_description", STRING, LATCHED)
    early.publish(msg(STRING, data="<robot/>"))
    recorder = Recorder(open_sessions(), tmp_path / "bag", TopicSelection(all_topics=True))
    recorder.start()
    try:
        wait_until(lambda: recorder.status().messages == 1, what="the early latched sample")
        # A latched topic that appears after the start: its cached sample is fetched too.
        late = talker.publisher("plan", STRING, LATCHED)
        late.publish(msg(STRING, data="plan A"))
        # A topic that appears later is recorded from its very first message.
        chatter = talker.publisher("chatter", STRING)
        for i in range(200):
            chatter.publish(msg(STRING, data=f"hi {i}"))
        wait_until(lambda: recorder.status().messages == 202, what="every message")
        wait_until(lambda: subscribed(talker.session, "/robot/chatter"), what="our token")
    finally:
        status = recorder.stop()
    assert status.topics == 3 and status.dropped == 0 and status.lost == 0
    bag = read_bag(tmp_path / "bag")
    assert [m.data for m in bag["/robot/robot_description"]] == ["<robot/>"]
    assert [m.data for m in bag["/robot/plan"]] == ["plan A"]
    assert [m.data for m in bag["/robot/chatter"]] == [f"hi {i}" for i in range(200)]
    with Reader(tmp_path / "bag") as reader:
        qos = {c.topic: c.ext.offered_qos_profiles for c in reader.connections}
    assert qos["/robot/robot_description"][0].durability.name == "TRANSIENT_LOCAL"
    assert qos["/robot/chatter"][0].durability.name == "VOLATILE"
    who = read_metadata(tmp_path / "bag").custom_data
    assert who == {
        "recorded_by": f"msctl /msctl_record_{os.getpid()}",
        "host": socket.gethostname(),
        # An uninterrupted recording says so: no gap, nothing lost upstream.
        "msctl.gaps": "[]",
        "msctl.lost": "{}",
        "msctl.thinned": "{}",
    }


def test_publish_time_and_sequence_come_from_the_attachment(
    tmp_path: Path, open_sessions: Callable[[], Any], talker: Node
) -> None:
    publisher = talker.publisher("chatter", STRING)
    with Recorder(
        open_sessions(), tmp_path / "bag", TopicSelection(topics=("/robot/chatter",))
    ) as recorder:
        warm_up(recorder, lambda: publisher.publish(msg(STRING, data="warm-up")))
        before = time.time_ns()
        for i in range(5):
            publisher.publish(msg(STRING, data=f"test {i}"))
        wait_until(lambda: recorder.status().messages >= 6)
        wait_until(lambda: _tests_in(recorder) == 5)
    with open(tmp_path / "bag" / "bag_0.mcap", "rb") as stream:
        messages = [m for _, _, m in make_reader(stream).iter_messages()]
    sequences = [m.sequence for m in messages]
    assert sequences == list(range(sequences[0], sequences[0] + len(messages)))
    for message in messages[-5:]:
        assert before <= message.publish_time <= message.log_time


def recorded(recorder: Recorder, topic: str) -> list[str]:
    """The ``data`` of every message of ``topic`` recorded so far (read back from disk)."""
    assert recorder.sync()
    return [
        STORE.deserialize_cdr(m.data, STRING).data
        for m in read_messages(inspect(recorder.directory), topics=[topic])
    ]


def _tests_in(recorder: Recorder) -> int:
    return sum(d.startswith("test") for d in recorded(recorder, "/robot/chatter"))


def test_selection_by_name_regex_and_exclude(
    tmp_path: Path, open_sessions: Callable[[], Any], talker: Node
) -> None:
    names = ("joint_read", "joint_set", "cmd_vel", "diagnostics")
    publishers = {n: talker.publisher(n, STRING) for n in names}
    selection = TopicSelection(topics=("/robot/cmd_vel",), regex="joint_", exclude="_set$")
    with Recorder(open_sessions(), tmp_path / "bag", selection) as recorder:
        warm_up(recorder, lambda: publishers["joint_read"].publish(msg(STRING, data="warm")))
        for publisher in publishers.values():
            publisher.publish(msg(STRING, data="x"))
        # Give the excluded ones every chance to arrive: one more on a recorded topic.
        publishers["joint_read"].publish(msg(STRING, data="last"))
        wait_until(lambda: "/robot/cmd_vel" in {t.name for t in recorder.topics}, timeout=30)
        # "last" itself, not a count: warm_up may have recorded several "warm"s already.
        wait_until(lambda: "last" in recorded(recorder, "/robot/joint_read"), timeout=30)
    bag = read_bag(tmp_path / "bag")
    assert set(bag) == {"/robot/joint_read", "/robot/cmd_vel"}
    assert [m.data for m in bag["/robot/joint_read"]][-2:] == ["x", "last"]


def test_pause_keeps_latched_samples_for_the_resume(
    tmp_path: Path, open_sessions: Callable[[], Any], talker: Node
) -> None:
    latched = talker.publisher("robot_description", STRING, LATCHED)
    chatter = talker.publisher("chatter", STRING)
    recorder = Recorder(
        open_sessions(), tmp_path / "bag", TopicSelection(all_topics=True), start_paused=True
    )
    recorder.start()
    try:
        latched.publish(msg(STRING, data="<robot/>"))
        wait_until(lambda: recorder.held == 1, what="the latched sample, held")
        wait_until(
            lambda: chatter.publish(msg(STRING, data="paused")) or recorder.held == 2,
            interval=0.1,
            what="samples seen while paused",
        )
        assert recorder.status().messages == 0 and recorder.paused
        recorder.resume()
        chatter.publish(msg(STRING, data="resumed"))
        wait_until(lambda: "resumed" in recorded(recorder, "/robot/chatter"))
    finally:
        recorder.stop()
    bag = read_bag(tmp_path / "bag")
    assert [m.data for m in bag["/robot/robot_description"]] == ["<robot/>"]
    # What was sent while paused is not recorded (a "paused" sample still on its way at the
    # resume may be, after the latched one).
    assert [m.data for m in bag["/robot/chatter"]][-1] == "resumed"
    assert len(bag["/robot/chatter"]) <= 2


def test_unknown_type_is_recorded_and_counted(
    tmp_path: Path, open_sessions: Callable[[], Any]
) -> None:
    sender = open_sessions()
    key = "0/custom/their_msgs::msg::dds_::Thing_/RIHS01_" + "cd" * 32
    payload = b"\x00\x01\x00\x00\x2a\x00\x00\x00"
    with Recorder(open_sessions(), tmp_path / "bag", TopicSelection(all_topics=True)) as recorder:
        publisher = sender.declare_publisher(key)
        try:
            attachment = struct.pack("<qqB16s", 1, time.time_ns(), 16, b"g" * 16)
            wait_until(
                lambda: (
                    publisher.put(payload, attachment=attachment) or recorder.status().messages > 0
                ),
                what="a sample of the custom type",
            )
            assert recorder.status().unknown_types == ("their_msgs/msg/Thing",)
        finally:
            publisher.undeclare()
    with Reader(tmp_path / "bag") as reader:
        (connection,) = reader.connections
        assert connection.msgtype == "their_msgs/msg/Thing"
        assert connection.digest == "RIHS01_" + "cd" * 32
        assert {raw for _, _, raw in reader.messages()} == {payload}


def test_a_full_queue_drops_and_counts(
    tmp_path: Path, open_sessions: Callable[[], Any], talker: Node
) -> None:
    chatter = talker.publisher("chatter", STRING)
    with Recorder(
        open_sessions(), tmp_path / "bag", TopicSelection(all_topics=True), queue_messages=0
    ) as recorder:
        wait_until(lambda: chatter.publish(msg(STRING, data="x")) or recorder.status().dropped >= 3)
        assert recorder.status().messages == 0


def test_gaps_in_sequence_numbers_are_counted_as_lost_upstream(
    tmp_path: Path, open_sessions: Callable[[], Any], talker: Node
) -> None:
    chatter = talker.publisher("chatter", STRING, SENSOR)
    with Recorder(
        open_sessions(), tmp_path / "bag", TopicSelection(topics=("/robot/chatter",))
    ) as recorder:
        warm_up(recorder, lambda: chatter.publish(msg(STRING, data="warm-up")))
        next(chatter._seq), next(chatter._seq)  # two samples "lost on the way"
        chatter.publish(msg(STRING, data="after the gap"))
        wait_until(lambda: recorder.status().lost == 2)

        def recorders() -> list[Any]:
            # A loaded router can answer the graph query after its first bound: ask again.
            entities = snapshot(talker.session, timeout=3.0).entities()
            return [
                e
                for e in entities
                if e.kind is EntityKind.SUBSCRIPTION and e.node_name.startswith("msctl_record")
            ]

        mine = wait_until(recorders, 30.0, "the recorder's subscription on the graph")
        assert [e.topic for e in mine] == ["/robot/chatter"]
        assert mine[0].qos.split(":")[0] == "2"  # best effort, as the publisher offers


def test_a_topic_sampled_on_the_radio_counts_no_loss_and_says_so(
    tmp_path: Path, open_sessions: Callable[[], Any], talker: Node
) -> None:
    # A robot's router sends its joint_states at 10 Hz on the radio: the ground's recorder
    # sees the sequence numbers jump by ten, by design. No loss is counted for it; a topic
    # that is not sampled still counts its own.
    thinned = talker.publisher("joint_states", STRING, SENSOR)
    whole = talker.publisher("chatter", STRING, SENSOR)
    with Recorder(
        open_sessions(),
        tmp_path / "bag",
        TopicSelection(topics=("/robot/joint_states", "/robot/chatter")),
        thinned={"/robot/joint_states": 10.0},
    ) as recorder:
        warm_up(recorder, lambda: thinned.publish(msg(STRING, data="warm-up")))
        warm_up(recorder, lambda: whole.publish(msg(STRING, data="warm-up")))
        for _ in range(3):
            for _ in range(9):
                next(thinned._seq)  # nine samples the router did not send on
            thinned.publish(msg(STRING, data="1 in 10"))
        next(whole._seq)  # one sample lost on the way
        whole.publish(msg(STRING, data="after the loss"))
        wait_until(lambda: recorder.status().lost == 1, what="the loss of the other topic")
        assert recorder.thinned() == {"/robot/joint_states": 10.0}
    custom = read_metadata(tmp_path / "bag").custom_data
    assert json.loads(custom["msctl.lost"]) == {"/robot/chatter": 1}
    assert json.loads(custom["msctl.thinned"]) == {"/robot/joint_states": 10.0}


def test_an_existing_bag_directory_is_refused_before_subscribing(
    tmp_path: Path, open_sessions: Callable[[], Any]
) -> None:
    (tmp_path / "bag").mkdir()
    with pytest.raises(BagError, match="already exists"):
        Recorder(open_sessions(), tmp_path / "bag", TopicSelection(all_topics=True))
