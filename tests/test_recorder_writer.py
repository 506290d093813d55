"""The bag writer: rosbag2 (MCAP) bags that readers we did not write open, splits that lose
nothing, and crash safety (what a SIGKILL or a power loss leaves is recovered)."""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from components.comm.qos import LATCHED, QoS
from components.comm.types import registry
from components.messages import msg
from components.recording.definitions import message_definition, qos_profiles
from components.recording.errors import BagError
from components.recording.metadata import read_metadata
from components.recording.writer import BagWriter, TopicSpec
from msctl.recorder.bag import inspect
from msctl.recorder.recover import recover

STRING = "std_msgs/msg/String"
JOINT_STATE = "sensor_msgs/msg/JointState"
STORE = get_typestore(Stores.ROS2_JAZZY)


def spec(name: str, type_name: str, qos: QoS | None = None) -> TopicSpec:
    return TopicSpec(
        name,
        type_name,
        registry().type_hash(type_name),
        tuple(qos_profiles([qos or QoS()])),
        message_definition(type_name),
    )


def joint_state(i: int) -> bytes:
    message = msg(JOINT_STATE, name=[f"joint{k}" for k in range(6)], position=np.full(6, i * 0.1))
    return registry().serializer(JOINT_STATE)(message)


def string(i: int) -> bytes:
    return registry().serializer(STRING)(msg(STRING, data=f"hello {i}"))


def rosbags_messages(path: Path) -> list[tuple[str, int, object]]:
    """(topic, log time, decoded message) of every message, read by rosbags."""
    out = []
    with Reader(path) as reader:
        for connection, timestamp, raw in reader.messages():
            out.append(
                (connection.topic, timestamp, STORE.deserialize_cdr(raw, connection.msgtype))
            )
    return out


def write_bag(directory: Path, count: int, start: int = 0, **options: object) -> Path:
    with BagWriter(directory, **options) as writer:
        chatter = writer.add_topic(spec("/chatter", STRING))
        joints = writer.add_topic(spec("/limb1/joint_read", JOINT_STATE, LATCHED))
        start = start or time.time_ns()
        for i in range(count):
            writer.write(chatter, start + i * 1000, string(i), start + i * 1000 - 7, i + 1)
            writer.write(joints, start + i * 1000 + 1, joint_state(i), 0, i + 1)
    return directory


# --------------------------------------------------------------------------- format
def test_definitions_parse_back_to_the_registry_types_for_every_message_type() -> None:
    types = registry()
    # Service parts (pkg/srv/X_Request) are named differently by rosbags' parser.
    for name in [n for n in registry().message_names() if "/msg/" in n]:
        text = message_definition(name)
        assert text is not None
        parsed = get_types_from_msg(text, name)
        for type_name, definition in parsed.items():
            fields = [(f, d) for f, d in definition[1]]
            assert fields == list(types.definition(type_name)[1]), (name, type_name)


def test_definition_has_dependencies_after_80_equals_and_msg_lines() -> None:
    text = message_definition(JOINT_STATE)
    assert text is not None
    assert text.startswith("std_msgs/Header header\nstring[] name\n")
    # Named as the field names them, as rosbag2 writes them (tests/test_bag_foxglove.py).
    assert f"\n\n{'=' * 80}\nMSG: std_msgs/Header\n" in text
    assert f"{'=' * 80}\nMSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n" in text
    assert message_definition("nobody_msgs/msg/Custom") is None


def test_round_trip_rosbags_and_mcap_readers_agree_with_metadata(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "bag", 200, compression="zstd")
    metadata = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert metadata["version"] == 9
    assert metadata["storage_identifier"] == "mcap"
    assert metadata["ros_distro"] == "jazzy"
    assert metadata["relative_file_paths"] == ["bag_0.mcap"]
    assert metadata["message_count"] == 400
    topics = {t["topic_metadata"]["name"]: t for t in metadata["topics_with_message_count"]}
    assert topics["/chatter"]["message_count"] == 200
    latched = topics["/limb1/joint_read"]["topic_metadata"]
    assert latched["offered_qos_profiles"][0]["durability"] == "transient_local"
    assert latched["type_description_hash"] == registry().type_hash(JOINT_STATE)
    assert metadata["files"][0]["message_count"] == 400

    read = rosbags_messages(bag)
    assert len(read) == 400
    chatter = [m for topic, _, m in read if topic == "/chatter"]
    assert [m.data for m in chatter] == [f"hello {i}" for i in range(200)]
    joints = [m for topic, _, m in read if topic == "/limb1/joint_read"]
    assert list(joints[-1].name) == [f"joint{k}" for k in range(6)]

    with open(bag / "bag_0.mcap", "rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        header = reader.get_header()
        assert header.profile == "ros2"
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count == 400
        assert summary.chunk_indexes and all(c.compression == "zstd" for c in summary.chunk_indexes)
        for schema in summary.schemas.values():
            assert schema.encoding == "ros2msg"
        for channel in summary.channels.values():
            assert channel.message_encoding == "cdr"
            assert channel.metadata["topic_type_hash"].startswith("RIHS01_")
            assert yaml.safe_load(channel.metadata["offered_qos_profiles"])[0]["history"]
        decoded = list(reader.iter_decoded_messages(topics=["/chatter"]))
        assert decoded[5].decoded_message.data == "hello 5"
        assert decoded[5].message.publish_time == decoded[5].message.log_time - 7
        assert decoded[5].message.sequence == 6
        stored = {m.name: m.metadata for m in reader.iter_metadata()}
        inner = yaml.safe_load(stored["rosbag2"]["serialized_metadata"])
        assert inner["rosbag2_bagfile_information"]["message_count"] == 400
        assert stored["rosbag2"]["ROS_DISTRO"] == "jazzy"


@pytest.mark.parametrize("compression", [None, "zstd"])
def test_the_lean_chunk_builder_writes_exactly_the_librarys_files(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, compression: str | None
) -> None:
    import io

    from mcap.writer import Writer

    import components.recording.writer as writer_module

    assert writer_module._use_lean_chunks(Writer(io.BytesIO()))  # this mcap takes it
    (tmp_path / "lean").mkdir()
    (tmp_path / "library").mkdir()
    options: dict[str, object] = {"compression": compression, "max_bytes": 200_000}
    lean = write_bag(tmp_path / "lean" / "bag", 3000, 1_767_323_045_000_000_000, **options)
    used: list[bool] = []
    monkeypatch.setattr(writer_module, "_use_lean_chunks", lambda writer: used.append(0) or False)
    library = write_bag(tmp_path / "library" / "bag", 3000, 1_767_323_045_000_000_000, **options)
    assert used  # the second bag was written by the library's own chunk builder
    names = sorted(p.name for p in lean.glob("*.mcap"))
    assert len(names) >= 2 and names == sorted(p.name for p in library.glob("*.mcap"))
    # Same inputs, same times: the same bytes, chunks, indexes and summaries alike.
    for name in names:
        assert (lean / name).read_bytes() == (library / name).read_bytes(), name


def test_unknown_type_is_recorded_with_its_name_hash_and_an_empty_definition(
    tmp_path: Path,
) -> None:
    with BagWriter(tmp_path / "bag") as writer:
        custom = writer.add_topic(
            TopicSpec("/custom", "their_msgs/msg/Thing", "RIHS01_" + "ab" * 32, (), None)
        )
        writer.write(custom, time.time_ns(), b"\x00\x01\x00\x00\x07\x00\x00\x00")
    with Reader(tmp_path / "bag") as reader:
        (connection,) = reader.connections
        assert connection.msgtype == "their_msgs/msg/Thing"
        assert connection.digest == "RIHS01_" + "ab" * 32
        assert [raw for _, _, raw in reader.messages()] == [b"\x00\x01\x00\x00\x07\x00\x00\x00"]
    with open(tmp_path / "bag" / "bag_0.mcap", "rb") as stream:
        (schema,) = make_reader(stream).get_summary().schemas.values()
    assert (schema.name, schema.encoding, schema.data) == ("their_msgs/msg/Thing", "", b"")


def test_an_existing_directory_is_never_overwritten(tmp_path: Path) -> None:
    (tmp_path / "bag").mkdir()
    (tmp_path / "bag" / "keep.txt").write_text("mine")
    with pytest.raises(BagError, match="already exists"):
        BagWriter(tmp_path / "bag")
    assert (tmp_path / "bag" / "keep.txt").read_text() == "mine"
    with pytest.raises(BagError, match="does not exist"):
        BagWriter(tmp_path / "missing" / "bag")


# --------------------------------------------------------------------------- splits
def _sequences(bag: Path, topic: str) -> list[int]:
    out = []
    for path in sorted(bag.glob("*.mcap"), key=lambda p: int(p.stem.rsplit("_", 1)[1])):
        with open(path, "rb") as stream:
            for _, channel, message in make_reader(stream).iter_messages(log_time_order=False):
                if channel.topic == topic:
                    out.append(message.sequence)
    return out


def test_split_by_size_loses_nothing_and_every_file_is_finished(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "bag", 2000, max_bytes=64 * 1024)
    metadata = read_metadata(bag)
    assert len(metadata.files) >= 3
    assert [f.path for f in metadata.files] == [f"bag_{i}.mcap" for i in range(len(metadata.files))]
    assert sum(f.message_count for f in metadata.files) == metadata.message_count == 4000
    for record in metadata.files:
        size = (bag / record.path).stat().st_size
        assert size < 64 * 1024 + 64 * 1024  # at most one chunk over the limit
        with open(bag / record.path, "rb") as stream:
            assert make_reader(stream).get_summary().statistics.message_count == (
                record.message_count
            )
    assert _sequences(bag, "/chatter") == list(range(1, 2001))
    assert _sequences(bag, "/limb1/joint_read") == list(range(1, 2001))
    assert len(rosbags_messages(bag)) == 4000
    assert not inspect(bag).needs_recovery


def test_each_split_finishes_its_file_and_rewrites_the_metadata_at_once(tmp_path: Path) -> None:
    """Not only at close: a crash after a split loses nothing of the finished files."""
    writer = BagWriter(tmp_path / "bag", max_bytes=64 * 1024)
    chatter = writer.add_topic(spec("/chatter", STRING))
    start = time.time_ns()
    i = 0
    while writer.file_count < 3:
        writer.write(chatter, start + i * 1000, string(i), 0, i + 1)
        i += 1
    try:
        on_disk = read_metadata(tmp_path / "bag")  # the bag still being written
        assert [f.path for f in on_disk.files] == ["bag_0.mcap", "bag_1.mcap", "bag_2.mcap"]
        finished = on_disk.files[:2]
        assert all(f.message_count > 0 and f.duration > 0 for f in finished)
        assert on_disk.message_count == sum(f.message_count for f in finished)
        assert on_disk.topics[0].message_count == on_disk.message_count
        for record in finished:
            with open(tmp_path / "bag" / record.path, "rb") as stream:
                summary = make_reader(stream).get_summary()
            assert summary is not None
            assert summary.statistics.message_count == record.message_count
    finally:
        writer.close()
    assert read_metadata(tmp_path / "bag").message_count == i


def test_metadata_yaml_has_every_field_ros2_bag_writes(tmp_path: Path) -> None:
    start = 1_767_323_045_000_000_000
    with BagWriter(tmp_path / "bag", compression="zstd", custom_data={"who": "test"}) as writer:
        chatter = writer.add_topic(spec("/chatter", STRING, LATCHED))
        for i in range(5):
            writer.write(chatter, start + i * 250_000_000, string(i), 0, i + 1)
    document = yaml.safe_load((tmp_path / "bag" / "metadata.yaml").read_text())
    assert list(document) == ["rosbag2_bagfile_information"]
    info = document["rosbag2_bagfile_information"]
    assert set(info) == {
        "version",
        "storage_identifier",
        "duration",
        "starting_time",
        "message_count",
        "topics_with_message_count",
        "compression_format",
        "compression_mode",
        "relative_file_paths",
        "files",
        "custom_data",
        "ros_distro",
    }
    assert (info["version"], info["storage_identifier"], info["ros_distro"]) == (9, "mcap", "jazzy")
    assert info["duration"] == {"nanoseconds": 1_000_000_000}
    assert info["starting_time"] == {"nanoseconds_since_epoch": start}
    assert info["message_count"] == 5
    # Compression is inside the MCAP chunks, as rosbag2's MCAP storage does it.
    assert (info["compression_format"], info["compression_mode"]) == ("", "")
    assert info["custom_data"] == {"who": "test"}
    (topic,) = info["topics_with_message_count"]
    assert topic["message_count"] == 5
    meta = topic["topic_metadata"]
    assert meta["name"] == "/chatter" and meta["type"] == STRING
    assert meta["serialization_format"] == "cdr"
    assert meta["type_description_hash"] == registry().type_hash(STRING)
    (profile,) = meta["offered_qos_profiles"]  # v9: a list of maps, not a YAML string
    assert isinstance(profile, dict) and profile["durability"] == "transient_local"
    assert info["relative_file_paths"] == ["bag_0.mcap"]
    assert info["files"] == [
        {
            "path": "bag_0.mcap",
            "starting_time": {"nanoseconds_since_epoch": start},
            "duration": {"nanoseconds": 1_000_000_000},
            "message_count": 5,
        }
    ]


def test_split_by_duration_uses_log_time(tmp_path: Path) -> None:
    with BagWriter(tmp_path / "bag", max_duration=1.0) as writer:
        chatter = writer.add_topic(spec("/chatter", STRING))
        start = time.time_ns()
        for i in range(50):  # 50 messages 0.1 s apart: 5 s
            writer.write(chatter, start + i * 100_000_000, string(i), 0, i + 1)
    metadata = read_metadata(tmp_path / "bag")
    assert [f.message_count for f in metadata.files] == [10, 10, 10, 10, 10]
    assert all(f.duration == 900_000_000 for f in metadata.files)
    assert metadata.duration == 4_900_000_000
    assert _sequences(tmp_path / "bag", "/chatter") == list(range(1, 51))


# --------------------------------------------------------------------------- crash safety
def _crashed_copy(tmp_path: Path, count: int, flush_every: int, **options: object) -> tuple:
    """A bag copied off the disk while its writer was still writing (what SIGKILL leaves):
    ``(copy, messages flushed before the copy)``."""
    writer = BagWriter(tmp_path / "live", **options)
    chatter = writer.add_topic(spec("/chatter", STRING))
    start = time.time_ns()
    flushed = 0
    for i in range(count):
        writer.write(chatter, start + i * 1000, string(i), 0, i + 1)
        if (i + 1) % flush_every == 0:
            writer.flush()
            flushed = i + 1
    copy = tmp_path / "live_copy"
    shutil.copytree(tmp_path / "live", copy)
    # Files keep their names: a bag's files are named after its directory.
    for path in copy.glob("live_*.mcap"):
        path.rename(copy / path.name.replace("live_", "live_copy_"))
    text = (copy / "metadata.yaml").read_text().replace("live_", "live_copy_")
    (copy / "metadata.yaml").write_text(text)
    writer.close()
    return copy, flushed


def test_bag_info_scans_an_unrecovered_bag_and_says_it_needs_recovery(tmp_path: Path) -> None:
    copy, flushed = _crashed_copy(tmp_path, 1000, 300)
    info = inspect(copy)
    assert info.needs_recovery
    assert any("unfinished" in r for r in info.reasons)
    assert info.metadata.message_count >= flushed
    (topic,) = info.metadata.topics
    assert topic.name == "/chatter" and topic.message_count == info.metadata.message_count


@pytest.mark.parametrize("compression", [None, "zstd"])
def test_recover_after_a_kill_loses_only_the_unflushed_tail(
    tmp_path: Path, compression: str | None
) -> None:
    copy, flushed = _crashed_copy(tmp_path, 1000, 300, compression=compression)
    with pytest.raises(Exception):  # noqa: B017  (a finished-bag reader refuses it as is)
        rosbags_messages(copy)
    report = recover(copy)
    assert [f.action for f in report.files] == ["rebuilt"]
    read = rosbags_messages(copy)
    assert len(read) >= flushed == 900
    assert [m.data for _, _, m in read] == [f"hello {i}" for i in range(len(read))]
    assert report.metadata.message_count == len(read)
    assert read_metadata(copy).message_count == len(read)
    assert not inspect(copy).needs_recovery


def test_recover_reads_past_a_truncated_chunk_at_any_offset(tmp_path: Path) -> None:
    """Power loss: the file cut anywhere. Every message of every complete chunk comes back,
    and the whole messages of an uncompressed truncated chunk too."""
    bag = write_bag(tmp_path / "bag", 600, chunk_size=8 * 1024)
    original = bag / "bag_0.mcap"
    data = original.read_bytes()
    with open(original, "rb") as stream:
        chunks = make_reader(stream).get_summary().chunk_indexes
    starts = sorted(c.chunk_start_offset for c in chunks)
    ends = sorted(c.chunk_start_offset + c.chunk_length for c in chunks)
    for cut, inside_a_chunk in ((starts[3] + 400, True), (ends[5], False), (len(data) - 40, False)):
        target = tmp_path / f"cut{cut}" / "bag"
        target.mkdir(parents=True)
        (target / "bag_0.mcap").write_bytes(data[:cut])
        (target / "metadata.yaml").write_text((bag / "metadata.yaml").read_text())
        whole = _messages_in(
            original, [c for c in chunks if c.chunk_start_offset + c.chunk_length <= cut]
        )
        (outcome,) = recover(target).files
        read = rosbags_messages(target)
        if inside_a_chunk:
            assert outcome.salvaged >= 1 and outcome.lost_bytes > 0
            assert len(read) == whole + outcome.salvaged
        else:
            assert len(read) == whole
        chatter = [m.data for topic, _, m in read if topic == "/chatter"]
        assert chatter == [f"hello {i}" for i in range(len(chatter))], cut
    assert whole == 1200  # the last cut is in the summary: every message is back


def _messages_in(path: Path, chunks: list) -> int:
    """Messages in some chunks of a finished file, read with the mcap library alone."""
    from mcap.data_stream import ReadDataStream
    from mcap.records import Chunk, Message
    from mcap.stream_reader import breakup_chunk

    total = 0
    with open(path, "rb") as stream:
        for index in chunks:
            stream.seek(index.chunk_start_offset + 9)
            chunk = Chunk.read(ReadDataStream(stream))
            total += sum(isinstance(r, Message) for r in breakup_chunk(chunk))
    return total


def test_recover_skips_a_corrupted_chunk_and_keeps_the_others(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "bag", 600, chunk_size=8 * 1024)
    path = bag / "bag_0.mcap"
    data = bytearray(path.read_bytes())
    with open(path, "rb") as stream:
        summary = make_reader(stream).get_summary()
    victim = summary.chunk_indexes[2]
    middle = victim.chunk_start_offset + victim.chunk_length // 2
    data[middle : middle + 16] = b"\xff" * 16
    # Cut the footer off too, so the file counts as unfinished and is rebuilt.
    path.write_bytes(bytes(data[: summary.chunk_indexes[-1].chunk_start_offset - 1]))
    report = recover(bag)
    (outcome,) = report.files
    assert outcome.damaged_chunks == 1
    assert any("CRC" in p for p in outcome.problems)
    read = rosbags_messages(bag)
    assert 0 < len(read) < 1200
    assert report.lost_anything


def test_recover_of_a_finished_bag_changes_nothing(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "bag", 50)
    before = (bag / "bag_0.mcap").read_bytes()
    report = recover(bag)
    assert [f.action for f in report.files] == ["kept"]
    assert (bag / "bag_0.mcap").read_bytes() == before
    assert not report.lost_anything


def test_a_file_killed_before_its_first_flush_is_recovered_empty(tmp_path: Path) -> None:
    writer = BagWriter(tmp_path / "bag")
    writer.add_topic(spec("/chatter", STRING))
    writer.tick()  # the recorder's housekeeping: metadata.yaml names the topic
    writer.write(0, time.time_ns(), string(0))  # still in the open chunk
    copy = tmp_path / "copy"
    copy.mkdir()
    (copy / "copy_0.mcap").write_bytes((tmp_path / "bag" / "bag_0.mcap").read_bytes())
    (copy / "metadata.yaml").write_text(
        (tmp_path / "bag" / "metadata.yaml").read_text().replace("bag_0", "copy_0")
    )
    writer.close()
    report = recover(copy)
    assert report.metadata.message_count == 0
    assert [t.name for t in report.metadata.topics] == ["/chatter"]
    assert rosbags_messages(copy) == []


# --------------------------------------------------------------------------- bad input
def test_not_a_bag_is_named(tmp_path: Path) -> None:
    with pytest.raises(BagError, match="no such bag directory"):
        inspect(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(BagError, match=r"has no metadata\.yaml"):
        inspect(tmp_path / "empty")
    with pytest.raises(BagError, match="not a bag"):
        recover(tmp_path / "empty")
    bag = write_bag(tmp_path / "bag", 5)
    (bag / "bag_0.mcap").unlink()
    with pytest.raises(BagError, match=r"lists bag_0\.mcap, which is missing"):
        inspect(bag)
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "metadata.yaml").write_text("rosbag2_bagfile_information:\n  version: 9\n")
    with pytest.raises(BagError, match=r"broken/metadata\.yaml.*lacks the key"):
        inspect(broken)
    (broken / "metadata.yaml").write_text("just: text\n")
    with pytest.raises(BagError, match="not a rosbag2 bag"):
        inspect(broken)
