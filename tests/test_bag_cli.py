"""``msctl record`` and ``msctl bag info/play/recover``: real subprocesses (e2e) for recording,
SIGTERM, SIGKILL and a full disk; in-process for info, play and the bad-input paths."""

from __future__ import annotations

import json
import os
import re
import resource
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import quick_peer_settings, quick_router, wait_until
from mcap.reader import make_reader
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from typer.testing import CliRunner

from components.comm import LATCHED, Node
from components.comm.session import SessionSettings
from components.comm.types import registry
from components.messages import msg
from components.recording.definitions import message_definition, qos_profiles
from components.recording.errors import BagError
from components.recording.metadata import read_metadata
from components.recording.writer import BagWriter, TopicSpec
from msctl.app import app
from msctl.recorder.bag import inspect
from msctl.recorder.player import Player, is_command_topic, parse_remaps

MSCTL = shutil.which("msctl") or str(Path(sys.executable).with_name("msctl"))
STRING = "std_msgs/msg/String"
JOINT_STATE = "sensor_msgs/msg/JointState"
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


@pytest.fixture
def client(router_endpoint: str) -> Iterator[Any]:
    """A client session, as ``msctl bag play`` opens (no peer links coming up mid-play)."""
    from components.comm.session import open_session

    session = open_session(
        SessionSettings(mode="client", connect=(router_endpoint,), listen=(), multicast=False)
    )
    try:
        yield session
    finally:
        session.close()


@pytest.fixture
def env(zenoh_env: dict[str, str], tmp_path: Path) -> dict[str, str]:
    return {**os.environ, **zenoh_env, "MSCTL_HOME": str(tmp_path / "home")}


def cli(*args: str) -> Any:
    """Run msctl in this process (the bag commands need no network)."""
    return CliRunner().invoke(app, list(args), catch_exceptions=True)


def string_bag(directory: Path, count: int) -> Path:
    serialize = registry().serializer(STRING)
    with BagWriter(directory) as writer:
        topic = writer.add_topic(
            TopicSpec(
                "/chatter",
                STRING,
                registry().type_hash(STRING),
                tuple(qos_profiles([LATCHED])),
                message_definition(STRING),
            )
        )
        start = time.time_ns()
        for i in range(count):
            writer.write(topic, start + i * 10_000_000, serialize(msg(STRING, data=f"m{i}")))
    return directory


def strings_of(path: Path, topic: str) -> list[str]:
    with Reader(path) as reader:
        return [
            STORE.deserialize_cdr(raw, connection.msgtype).data
            for connection, _, raw in reader.messages()
            if connection.topic == topic
        ]


# --------------------------------------------------------------------------- info
def test_bag_info_prints_what_ros2_bag_info_prints(tmp_path: Path) -> None:
    bag = string_bag(tmp_path / "bag", 30)
    result = cli("bag", "info", str(bag))
    assert result.exit_code == 0, result.output
    text = result.stdout
    labels = ("Files:", "Bag size:", "Storage id:", "ROS Distro:", "Duration:", "Start:", "End:")
    for label in (*labels, "Messages:", "Topic information:"):
        assert label in text
    assert "Storage id:        mcap" in text
    assert "Messages:          30" in text
    assert (
        "Topic: /chatter | Type: std_msgs/msg/String | Count: 30 | Serialization Format: cdr"
        in text
    )
    document = json.loads(cli("bag", "info", str(bag), "--json").stdout)
    assert document["message_count"] == 30
    assert document["topics"][0]["count"] == 30
    assert document["duration_ns"] == 290_000_000
    assert document["needs_recovery"] is False


def test_bag_info_and_play_name_what_is_missing(tmp_path: Path) -> None:
    (tmp_path / "not_a_bag").mkdir()
    for args in (("info",), ("play",), ("recover",)):
        result = cli("bag", *args, str(tmp_path / "not_a_bag"))
        assert isinstance(result.exception, BagError)
        assert "metadata.yaml" in str(result.exception)
        assert str(tmp_path / "not_a_bag") in str(result.exception)
    result = cli("bag", "info", str(tmp_path / "nowhere"))
    assert "no such bag directory" in str(result.exception)


def test_recover_cli_reports_files_and_json(tmp_path: Path) -> None:
    bag = string_bag(tmp_path / "bag", 20)
    document = json.loads(cli("bag", "recover", str(bag), "--json").stdout)
    assert document["files"][0]["action"] == "kept"
    assert document["message_count"] == 20 and not document["lost_anything"]


# --------------------------------------------------------------------------- play
class Inbox:
    """A subscription collecting message data (strings) in arrival order."""

    def __init__(self, node: Node, topic: str, type_name: str = STRING) -> None:
        self.items: list[Any] = []
        self.subscription = node.subscription(topic, type_name, self.items.append)


def ready(node: Node, topic: str) -> None:
    """Wait until a subscription to ``topic`` is on the graph (seen from ``node``)."""
    from components.comm.graph import snapshot

    wait_until(
        lambda: (snapshot(node.session, timeout=0.3).topics().get(topic) or _NONE).subscribers
    )


class _NoTopic:
    subscribers = 0


_NONE = _NoTopic()


def test_play_then_echo_with_timing_rate_offset_and_remap(
    tmp_path: Path, client: Any, talker: Node
) -> None:
    bag = string_bag(tmp_path / "bag", 30)  # 10 ms apart: 0.29 s
    inbox = Inbox(talker, "/replayed")
    player_node = Node(client, "player")
    try:
        ready(player_node, "/replayed")
        player = Player(
            player_node,
            inspect(bag),
            rate=2.0,
            start_offset=0.1,
            remap=parse_remaps(["/chatter:=/replayed"]),
        )
        started = time.monotonic()
        report = player.play(threading.Event())
        elapsed = time.monotonic() - started
    finally:
        player_node.close()
    assert report.published == 20  # from 0.1 s on
    assert report.topics == {"/replayed": 20}
    wait_until(lambda: len(inbox.items) == 20)
    assert [m.data for m in inbox.items] == [f"m{i}" for i in range(10, 30)]
    assert elapsed >= 0.19 / 2  # the spacing is kept (scaled by the rate), never compressed


def test_play_loops_only_the_topics_asked_through_real_publishers(
    tmp_path: Path, client: Any, talker: Node
) -> None:
    """--loop and --topics; what goes out carries rmw_zenoh's key, hash, a fresh 33-byte
    attachment per sample, and a publisher token on the graph (the player's own node)."""
    from components.comm.graph import snapshot

    bag = tmp_path / "bag"
    serialize = registry().serializer(STRING)
    with BagWriter(bag) as writer:
        chatter = writer.add_topic(
            TopicSpec(
                "/chatter", STRING, registry().type_hash(STRING), (), message_definition(STRING)
            )
        )
        other = writer.add_topic(
            TopicSpec(
                "/other", STRING, registry().type_hash(STRING), (), message_definition(STRING)
            )
        )
        start = time.time_ns()
        for i in range(10):
            writer.write(chatter, start + i * 1_000_000, serialize(msg(STRING, data=f"m{i}")))
            writer.write(other, start + i * 1_000_000 + 1, serialize(msg(STRING, data="no")))
    chatter_inbox = Inbox(talker, "/chatter")
    other_inbox = Inbox(talker, "/other")
    attachments: list[bytes] = []
    raw = talker.session.declare_subscriber(
        f"0/chatter/std_msgs::msg::dds_::String_/{registry().type_hash(STRING)}",
        lambda sample: attachments.append(sample.attachment.to_bytes()),
    )
    player_node = Node(client, "player")
    stop = threading.Event()
    player = Player(player_node, inspect(bag), topics=["chatter"], loop=True)
    seen_publisher: list[bool] = []

    def play() -> None:
        player.play(stop)

    thread = threading.Thread(target=play, daemon=True)
    try:
        ready(player_node, "/chatter")
        thread.start()
        wait_until(lambda: len(chatter_inbox.items) >= 25, timeout=30, what="two passes and more")
        # One graph query may be cut off on a loaded machine: ask until the token shows.
        wait_until(
            lambda: any(
                e.kind.name == "PUBLISHER" and e.topic == "/chatter" and e.node_fqn == "/player"
                for e in snapshot(talker.session, timeout=1.0).entities()
            ),
            timeout=30,
            what="the player's publisher on the graph",
        )
        seen_publisher.append(True)
    finally:
        stop.set()
        thread.join(timeout=30)
        player_node.close()
        raw.undeclare()
    report = player.report
    assert report.loops >= 2 and set(report.topics) == {"/chatter"}
    received = [m.data for m in chatter_inbox.items]
    assert received[:25] == [f"m{i % 10}" for i in range(25)]
    assert other_inbox.items == []
    assert seen_publisher == [True]
    assert all(len(a) == 33 for a in attachments)
    sequences = [int.from_bytes(a[:8], "little") for a in attachments]
    assert sequences[:25] == list(range(1, 26))  # one publisher, numbering on across loops


def test_a_bag_written_by_rosbags_plays_with_its_own_definitions(
    tmp_path: Path, client: Any, talker: Node
) -> None:
    """Another tool's bag (rosbags' Writer, its own file naming), with a type msctl lacks."""
    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(
        get_types_from_msg("float64 x\nstring label\n", "field_msgs/msg/Probe")
        | get_types_from_msg(
            "field_msgs/Probe[] probes\nuint8 STATION=3\n", "field_msgs/msg/ProbeArray"
        )
    )
    probe_cls = store.types["field_msgs/msg/Probe"]
    array_cls = store.types["field_msgs/msg/ProbeArray"]
    path = tmp_path / "theirs"
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        probes = writer.add_connection("/probes", "field_msgs/msg/ProbeArray", typestore=store)
        chatter = writer.add_connection("/chatter", STRING, typestore=store)
        start = time.time_ns()
        for i in range(5):
            value = array_cls(probes=[probe_cls(x=float(i), label=f"p{i}")])
            writer.write(probes, start + i * 1000, store.serialize_cdr(value, value.__msgtype__))
            text = store.types[STRING](data=f"c{i}")
            writer.write(chatter, start + i * 1000 + 1, store.serialize_cdr(text, STRING))
    described = inspect(path)
    assert described.metadata.message_count == 10 and not described.needs_recovery
    assert not registry().known("field_msgs/msg/ProbeArray")
    # The custom type is received as raw CDR (this process does not know it either).
    received: list[bytes] = []
    (probes,) = [t for t in described.metadata.topics if t.name == "/probes"]
    raw = talker.session.declare_subscriber(
        f"0/probes/field_msgs::msg::dds_::ProbeArray_/{probes.type_hash}",
        lambda sample: received.append(sample.payload.to_bytes()),
    )
    strings = Inbox(talker, "/chatter")
    player_node = Node(client, "player")
    try:
        ready(player_node, "/chatter")
        report = Player(player_node, described).play(threading.Event())
        assert report.published == 10 and not report.skipped
        wait_until(lambda: len(received) == 5 and len(strings.items) == 5)
    finally:
        player_node.close()
        raw.undeclare()
    decoded = [store.deserialize_cdr(r, "field_msgs/msg/ProbeArray") for r in received]
    assert [m.probes[0].label for m in decoded] == [f"p{i}" for i in range(5)]
    assert [m.data for m in strings.items] == [f"c{i}" for i in range(5)]
    # Registered from the bag's definition, with the hash the other tool wrote.
    assert registry().type_hash("field_msgs/msg/ProbeArray") == probes.type_hash


def test_command_topics_are_refused_onto_a_running_assembly(tmp_path: Path) -> None:
    assert is_command_topic("/limb1/joint_set") and is_command_topic("/cmd_vel")
    assert not is_command_topic("/limb1/joint_read")
    with BagWriter(tmp_path / "bag") as writer:
        for name in ("/limb1/joint_set", "/limb1/joint_read"):
            topic = writer.add_topic(
                TopicSpec(name, JOINT_STATE, registry().type_hash(JOINT_STATE), (), None)
            )
            writer.write(topic, time.time_ns(), b"\x00\x01\x00\x00")
    described = inspect(tmp_path / "bag")
    listened = {"/limb1/joint_set"}
    with pytest.raises(BagError, match=r"refusing to play command topic\(s\) /limb1/joint_set"):
        Player(None, described).check_commands(listened.__contains__)
    Player(None, described, allow_commands=True).check_commands(listened.__contains__)
    Player(None, described, topics=["/limb1/joint_read"]).check_commands(listened.__contains__)
    remapped = Player(None, described, remap={"/limb1/joint_set": "/test/joint_set"})
    remapped.check_commands(listened.__contains__)  # nobody listens where it would go
    with pytest.raises(BagError, match="no topic /nope"):
        Player(None, described, topics=["/nope"])
    with pytest.raises(BagError, match="OLD:=NEW"):
        parse_remaps(["/a=/b"])


# --------------------------------------------------------------------------- record (e2e)
def start_record(env: dict[str, str], *args: str, **popen: Any) -> subprocess.Popen:
    return subprocess.Popen(
        [MSCTL, "record", *args],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **popen,
    )


class Flood:
    """Publishes numbered strings on a thread until closed."""

    def __init__(self, node: Node, topic: str = "chatter", period: float = 0.002) -> None:
        self.publisher = node.publisher(topic, STRING)
        self.sent = 0
        #: Set: publish nothing (as if the link were down) until cleared.
        self.paused = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(period,), daemon=True)
        self._thread.start()

    def _run(self, period: float) -> None:
        while not self._stop.wait(period):
            if self.paused.is_set():
                continue
            self.sent += 1
            self.publisher.publish(msg(STRING, data=str(self.sent)))

    def close(self) -> None:
        self._stop.set()
        self._thread.join()


def recorded_so_far(bag: Path) -> int:
    """Messages on disk now (scanning the open file)."""
    try:
        return inspect(bag).metadata.message_count
    except BagError:
        return 0


def consecutive(values: list[str]) -> bool:
    numbers = [int(v) for v in values]
    return numbers == list(range(numbers[0], numbers[0] + len(numbers)))


@pytest.mark.e2e
def test_record_sigterm_closes_cleanly_and_readers_agree(
    tmp_path: Path, env: dict[str, str], talker: Node
) -> None:
    latched = talker.publisher("robot_description", STRING, LATCHED)
    latched.publish(msg(STRING, data="<robot/>"))
    # No -o: rosbag2's default name, in the current directory.
    proc = start_record(env, "--all", "--json", "--compression", "zstd", cwd=tmp_path)
    flood = Flood(talker)
    try:
        bag = wait_until(
            lambda: next((p for p in tmp_path.glob("rosbag2_*") if p.is_dir()), None),
            timeout=30,
            what="the bag directory",
        )
        wait_until(lambda: recorded_so_far(bag) > 300, timeout=30, what="messages on disk")
    finally:
        flood.close()
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    summary = json.loads(out)
    assert summary["messages"] == summary["topics"]["/robot/chatter"] + 1
    chatter = strings_of(bag, "/robot/chatter")
    assert consecutive(chatter) and len(chatter) == summary["topics"]["/robot/chatter"]
    assert strings_of(bag, "/robot/robot_description") == ["<robot/>"]
    with Reader(bag) as reader:
        assert sum(c.msgcount for c in reader.connections) == reader.message_count
        assert reader.message_count == summary["messages"]
    assert re.fullmatch(r"rosbag2_\d{4}_\d\d_\d\d-\d\d_\d\d_\d\d", bag.name), bag.name
    assert summary["directory"] == bag.name and summary["files"] == [f"{bag.name}_0.mcap"]
    with open(bag / f"{bag.name}_0.mcap", "rb") as stream:
        assert make_reader(stream).get_summary().statistics.message_count == summary["messages"]
    assert not inspect(bag).needs_recovery


@pytest.mark.e2e
def test_sigkill_mid_recording_then_recover(
    tmp_path: Path, env: dict[str, str], talker: Node
) -> None:
    bag = tmp_path / "bag"
    proc = start_record(env, "/robot/chatter", "-o", str(bag))
    flood = Flood(talker)
    try:
        wait_until(lambda: recorded_so_far(bag) > 400, timeout=30, what="flushed messages")
        flushed = recorded_so_far(bag)
        proc.kill()
        proc.communicate(timeout=10)
    finally:
        flood.close()
    info = subprocess.run(
        [MSCTL, "bag", "info", str(bag)], env=env, capture_output=True, text=True, check=False
    )
    assert info.returncode == 0, info.stderr
    assert "needs recovery" in info.stderr and "msctl bag recover" in info.stderr
    with pytest.raises(Exception):  # noqa: B017  (readers need the summary)
        strings_of(bag, "/robot/chatter")
    result = subprocess.run(
        [MSCTL, "bag", "recover", str(bag), "--json"],
        env=env,
        capture_output=True,
        text=True,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["files"][0]["action"] == "rebuilt"
    chatter = strings_of(bag, "/robot/chatter")
    assert len(chatter) >= flushed and consecutive(chatter)
    with Reader(bag) as reader:
        assert reader.message_count == len(chatter)


@pytest.mark.e2e
def test_record_splits_by_size_and_duration_without_losing_a_message(
    tmp_path: Path, env: dict[str, str], talker: Node
) -> None:
    for name, option in (("by_size", ("-b", "16K")), ("by_time", ("-d", "0.5"))):
        bag = tmp_path / name
        proc = start_record(env, "/robot/chatter", "-o", str(bag), *option)
        flood = Flood(talker)
        try:
            wait_until(
                lambda bag=bag: len(list(bag.glob("*.mcap"))) >= 3, timeout=30, what="3 files"
            )
        finally:
            flood.close()
            proc.send_signal(signal.SIGINT)
            _, err = proc.communicate(timeout=30)
        assert proc.returncode == 0, err
        chatter = strings_of(bag, "/robot/chatter")
        assert consecutive(chatter), name
        # Across every split, the senders' sequence numbers (from the attachments) follow on.
        sequences = []
        for path in sorted(bag.glob("*.mcap"), key=lambda p: int(p.stem.rsplit("_", 1)[1])):
            with open(path, "rb") as stream:
                reader = make_reader(stream)
                sequences += [m.sequence for _, _, m in reader.iter_messages(log_time_order=False)]
        assert sequences == list(range(sequences[0], sequences[0] + len(chatter))), name
        described = inspect(bag)
        assert len(described.files) >= 3 and all(f.complete for f in described.files)
        assert not described.needs_recovery


@pytest.mark.e2e
def test_a_full_disk_stops_cleanly_and_keeps_what_was_written(
    tmp_path: Path, env: dict[str, str], talker: Node
) -> None:
    """The file size limit (RLIMIT_FSIZE) stands in for a full disk: writes fail with EFBIG."""

    def limit() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (256 * 1024, 256 * 1024))

    bag = tmp_path / "bag"
    proc = start_record(env, "/robot/chatter", "-o", str(bag), preexec_fn=limit)
    flood = Flood(talker, period=0.0005)
    try:
        _, err = proc.communicate(timeout=60)
    finally:
        flood.close()
    assert proc.returncode == 6, err
    assert "file size limit" in err and "msctl bag recover" in err
    assert "Traceback" not in err
    subprocess.run([MSCTL, "bag", "recover", str(bag)], env=env, check=True, capture_output=True)
    chatter = strings_of(bag, "/robot/chatter")
    assert len(chatter) > 100 and consecutive(chatter)


@pytest.mark.e2e
def test_record_refuses_an_existing_directory_and_bad_options(
    tmp_path: Path, env: dict[str, str]
) -> None:
    (tmp_path / "bag").mkdir()
    for args, words in (
        (("--all", "-o", str(tmp_path / "bag")), "already exists"),
        ((), "nothing to record"),
        (
            (
                "--regex",
                "(",
            ),
            "not a regular expression",
        ),
        (("--all", "-b", "lots"), "not a size"),
    ):
        result = subprocess.run(
            [MSCTL, "record", *args], env=env, capture_output=True, text=True, check=False
        )
        assert result.returncode == 2, (args, result.stderr)
        assert words in result.stderr and "Traceback" not in result.stderr


def _tmux(*args: str) -> str:
    return subprocess.run(
        ["tmux", *args], capture_output=True, text=True, timeout=30.0, check=True
    ).stdout


@pytest.mark.e2e
@pytest.mark.skipif(shutil.which("tmux") is None, reason="tmux is not installed")
def test_in_a_terminal_a_live_line_shows_progress_and_space_pauses_and_resumes(
    tmp_path: Path, env: dict[str, str], talker: Node
) -> None:
    """The real command in tmux: the rich progress line, space to pause and resume (nothing
    written while paused), Ctrl-C, then the summary."""
    bag = tmp_path / "bag"
    exports = " ".join(
        f"{k}={v}" for k, v in env.items() if k.startswith("MSCTL_") or k == "CYDR_CACHE_DIR"
    )
    # The pane stays after the command ends, so its last words can be read. The screen's
    # width is the pane's (this process's COLUMNS, inherited by tmux, would say 80).
    command = (
        f"env -u COLUMNS -u LINES {exports} {MSCTL} record /robot/chatter -o {bag}; "
        "echo EXITED $?; sleep 600"
    )
    session = f"msctl-record-{os.getpid()}"
    _tmux("new-session", "-d", "-s", session, "-x", "160", "-y", "20", command)
    flood = Flood(talker, period=0.005)

    def screen() -> str:
        return _tmux("capture-pane", "-p", "-t", session)

    def shown() -> tuple[str, int, str] | None:
        match = re.search(r"(recording|\[paused\]) (\d\d:\d\d:\d\d)\s+([\d,]+) msgs", screen())
        return None if match is None else (match[1], int(match[3].replace(",", "")), match[2])

    def after_tick(state: str) -> tuple[str, int, str]:
        """The line once its clock moved on, in ``state``."""
        first = wait_until(lambda: (v := shown()) and v[0] == state and v, timeout=60)
        return wait_until(
            lambda: (v := shown()) and v[0] == state and v[2] != first[2] and v, timeout=60
        )

    try:
        moving = wait_until(lambda: (v := shown()) and v[1] > 0 and v, timeout=60, what="msgs")
        assert moving[0] == "recording" and "(space: pause, Ctrl-C: stop)" in screen()
        _tmux("send-keys", "-t", session, "Space")
        held = after_tick("[paused]")
        assert "(space: resume)" in screen()
        assert after_tick("[paused]")[1] == held[1]  # nothing written while paused
        _tmux("send-keys", "-t", session, "Space")
        wait_until(
            lambda: (v := shown()) and v[0] == "recording" and v[1] > held[1],
            timeout=60,
            what="recording again",
        )
        _tmux("send-keys", "-t", session, "C-c")
        text = wait_until(lambda: "EXITED" in (t := screen()) and t, timeout=90, what="the end")
    finally:
        flood.close()
        subprocess.run(["tmux", "kill-session", "-t", session], capture_output=True, check=False)
    assert "EXITED 0" in text
    assert re.search(rf"bag {re.escape(str(bag))}: [\d,]+ messages on 1 topic\(s\)", text), text
    chatter = strings_of(bag, "/robot/chatter")
    numbers = [int(v) for v in chatter]
    assert numbers == sorted(numbers) and len(numbers) < numbers[-1] - numbers[0] + 1  # a gap


# --------------------------------------------------------------------------- a simulated Dragon
@pytest.mark.e2e
@pytest.mark.timeout(400)
def test_round_trip_of_a_simulated_dragon(tmp_path: Path) -> None:
    from running import Up

    up = Up(tmp_path / "home", "dragon")
    try:
        bag = tmp_path / "dragon_bag"
        proc = subprocess.Popen(
            [MSCTL, "record", "--all", "-o", str(bag), "--json"],
            env=up.env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            wait_until(
                lambda: recorded_so_far(bag) > 1000,
                timeout=60,
                interval=0.2,
                what="1000 messages of the Dragon",
            )
        finally:
            proc.send_signal(signal.SIGINT)
            out, err = proc.communicate(timeout=60)
        assert proc.returncode == 0, err
    finally:
        up.down()
    summary = json.loads(out)
    metadata = inspect(bag).metadata
    assert metadata.message_count == summary["messages"]
    counts = {t.name: t.message_count for t in metadata.topics}
    assert any(name.endswith("/joint_read") for name in counts)
    decoded = 0
    with Reader(bag) as reader:
        assert {c.topic: c.msgcount for c in reader.connections} == counts
        for connection, _, raw in reader.messages():
            STORE.deserialize_cdr(raw, connection.msgtype)  # every payload decodes
            decoded += 1
    assert decoded == metadata.message_count
    from mcap_ros2.decoder import DecoderFactory

    with open(bag / f"{bag.name}_0.mcap", "rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        joints = [
            m.decoded_message
            for m in reader.iter_decoded_messages()
            if m.channel.topic.endswith("/joint_read")
        ]
    assert joints and all(len(j.name) == len(j.position) for j in joints)
    assert np.isfinite([p for j in joints for p in j.position]).all()


class Lines:
    """The lines a process writes to a pipe, read on a thread as they come."""

    def __init__(self, pipe: Any) -> None:
        self.lines: list[str] = []
        self._thread = threading.Thread(target=self._read, args=(pipe,), daemon=True)
        self._thread.start()

    def _read(self, pipe: Any) -> None:
        for line in pipe:
            self.lines.append(line.rstrip("\n"))

    def count(self, text: str) -> int:
        return sum(text in line for line in list(self.lines))

    def text(self) -> str:
        self._thread.join(timeout=30)
        return "\n".join(self.lines)


@pytest.mark.e2e
def test_record_tells_each_interruption_and_exits_3_when_it_ends_without_data(
    tmp_path: Path, env: dict[str, str], talker: Node
) -> None:
    """A topic that stops arriving (a link down) is said when it stops and when it comes
    back, each gap is in the summary and the bag's metadata, and a recording that ended while
    the topic was silent exits 3 naming it, not 0 with a normal summary."""
    bag = tmp_path / "bag"
    flood = Flood(talker, period=0.01)
    proc = start_record(env, "/robot/chatter", "-o", str(bag), "--json")
    assert proc.stderr is not None
    notices = Lines(proc.stderr)
    try:
        wait_until(lambda: recorded_so_far(bag) > 100, timeout=60, what="messages on disk")
        flood.paused.set()
        wait_until(lambda: notices.count("not receiving: /robot/chatter") == 1, 60, "silence told")
        flood.paused.clear()
        wait_until(lambda: notices.count("back: /robot/chatter: silent for") == 1, 60, "return")
        flood.paused.set()  # and this time it does not come back before the end
        wait_until(lambda: notices.count("not receiving: /robot/chatter") == 2, 60, "2nd silence")
    finally:
        flood.close()
        proc.send_signal(signal.SIGINT)
        # Not communicate(): it would read stderr too, racing Lines' thread for the last lines.
        proc.wait(timeout=60)
        assert proc.stdout is not None
        out = proc.stdout.read()
    stderr = notices.text()
    assert proc.returncode == 3, stderr
    said = " ".join(stderr.split())  # the error line is wrapped at the console's width
    assert "stopped receiving 1 topic(s) before it ended: /robot/chatter" in said, stderr
    summary = json.loads(out)
    closed, still_open = summary["gaps"]
    assert closed["topic"] == still_open["topic"] == "/robot/chatter"
    assert closed["end_ns"] > closed["start_ns"] and closed["seconds"] > 1.0
    assert closed["lost"] == 0  # nothing was published meanwhile: nothing is missing
    assert still_open["end_ns"] is None and still_open["start_ns"] >= closed["end_ns"]
    custom = read_metadata(bag).custom_data
    assert json.loads(custom["msctl.gaps"]) == summary["gaps"]
    assert json.loads(custom["msctl.lost"]) == {}
    assert strings_of(bag, "/robot/chatter")  # everything received is kept
