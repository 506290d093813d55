"""Opening a bag to describe it (``msctl bag info``) or read its messages (``bag play``).

A bag is a directory with ``metadata.yaml`` and MCAP files; a single ``.mcap`` file is taken
as a bag of one file. Finished files are described from their summaries; a file a crash left
unfinished (or one ``metadata.yaml`` does not list yet) is scanned record by record, and the
bag is then said to need recovery (``msctl bag recover``).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from components.recording.errors import BagError
from components.recording.metadata import (
    METADATA_FILE,
    BagMetadata,
    FileRecord,
    TopicRecord,
    read_metadata,
)
from msctl.recorder.scan import FileScan, NotMcapError, ScannedMessage, is_complete


@dataclass
class FileInfo:
    """One data file as found on disk.

    Attributes:
        path: The file.
        size: Bytes.
        complete: Finished by its writer (has a summary).
        message_count: Messages in it (from its summary, or counted by a scan).
        starting_time: First log time, ns (0 when empty).
        end_time: Last log time, ns.
        topic_counts: Messages per topic name.
        lost_bytes: Bytes a scan could not read (unfinished files only).
        problems: What a scan found wrong.
        topics: The topics its channels describe.
    """

    path: Path
    size: int = 0
    complete: bool = True
    message_count: int = 0
    starting_time: int = 0
    end_time: int = 0
    topic_counts: dict[str, int] = field(default_factory=dict)
    lost_bytes: int = 0
    problems: list[str] = field(default_factory=list)
    topics: list[TopicRecord] = field(default_factory=list)


@dataclass
class BagInfo:
    """A bag as ``msctl bag info`` describes it.

    Attributes:
        path: The bag directory (or the single file).
        metadata: Its metadata: ``metadata.yaml`` when it agrees with the files, else rebuilt
            from them (counts, times, new topics).
        files: Every data file.
        needs_recovery: A crash left it unfinished; ``msctl bag recover`` completes it.
        reasons: Why it needs recovery.
    """

    path: Path
    metadata: BagMetadata
    files: list[FileInfo]
    needs_recovery: bool = False
    reasons: list[str] = field(default_factory=list)

    @property
    def size(self) -> int:
        """Bytes of all data files."""
        return sum(f.size for f in self.files)

    @property
    def end_time(self) -> int:
        """Last log time, ns."""
        return self.metadata.starting_time + self.metadata.duration


def data_files(directory: Path) -> list[Path]:
    """The MCAP files of a bag directory named as msctl and rosbag2 name them, in order."""
    pattern = re.compile(rf"^{re.escape(directory.name)}_(\d+)\.mcap$")
    found = []
    for path in directory.glob("*.mcap"):
        match = pattern.match(path.name)
        if match:
            found.append((int(match.group(1)), path))
    return [p for _, p in sorted(found)]


def inspect(path: Path) -> BagInfo:
    """Describe a bag, scanning what its summaries and ``metadata.yaml`` cannot vouch for.

    Raises:
        BagError: If the path is not a bag (naming what is missing) or a file is unreadable.
    """
    path = Path(path)
    if path.is_file():
        return _inspect_single(path)
    metadata_missing = path.is_dir() and not (path / METADATA_FILE).exists()
    if metadata_missing and data_files(path):
        metadata = BagMetadata()
        reasons = [f"it has no {METADATA_FILE}"]
    else:
        metadata = read_metadata(path)
        reasons = []
    listed = [path / f.path for f in metadata.files]
    missing = [p.name for p in listed if not p.exists()]
    if missing:
        raise BagError(
            f"bag {path}: {METADATA_FILE} lists {', '.join(missing)}, which "
            f"{'is' if len(missing) == 1 else 'are'} missing from the directory"
        )
    extra = [p for p in data_files(path) if p not in listed]
    if extra:
        reasons.append(f"{METADATA_FILE} does not list {', '.join(p.name for p in extra)}")
    files = [_file_info(p) for p in [*listed, *extra]]
    for info in files:
        if not info.complete:
            reasons.append(f"{info.path.name} is unfinished (no summary)")
    counted = sum(f.message_count for f in files)
    if not reasons and counted != metadata.message_count:
        reasons.append(
            f"{METADATA_FILE} counts {metadata.message_count} messages, the files hold {counted}"
        )
    if reasons:
        metadata = rebuilt_metadata(metadata, files, _channels_of(files))
    return BagInfo(path, metadata, files, needs_recovery=bool(reasons), reasons=reasons)


def _inspect_single(path: Path) -> BagInfo:
    info = _file_info(path)
    metadata = rebuilt_metadata(BagMetadata(), [info], _channels_of([info]))
    reasons = [] if info.complete else [f"{path.name} is unfinished (no summary)"]
    return BagInfo(path, metadata, [info], needs_recovery=bool(reasons), reasons=reasons)


def _channels_of(files: Iterable[FileInfo]) -> list[TopicRecord]:
    return [topic for info in files for topic in info.topics]


def _file_info(path: Path) -> FileInfo:
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise BagError(f"cannot read {path}: {exc.strerror}") from exc
    if is_complete(path):
        try:
            return _from_summary(path, size)
        except BagError:
            raise
        except Exception:
            pass  # a damaged summary: scan it like an unfinished file
    return _from_scan(path, size)


def _from_summary(path: Path, size: int) -> FileInfo:
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as stream:
            summary = make_reader(stream).get_summary()
    except OSError as exc:
        raise BagError(f"cannot read {path}: {exc.strerror}") from exc
    if summary is None or summary.statistics is None:
        raise ValueError("no statistics")
    stats = summary.statistics
    counts: dict[str, int] = {}
    for channel_id, count in stats.channel_message_counts.items():
        channel = summary.channels.get(channel_id)
        if channel is not None:
            counts[channel.topic] = counts.get(channel.topic, 0) + count
    return FileInfo(
        path=path,
        size=size,
        complete=True,
        message_count=stats.message_count,
        starting_time=stats.message_start_time if stats.message_count else 0,
        end_time=stats.message_end_time if stats.message_count else 0,
        topic_counts=counts,
        topics=[
            topic_from_channel(c, summary.schemas.get(c.schema_id))
            for c in summary.channels.values()
        ],
    )


def _from_scan(path: Path, size: int) -> FileInfo:
    from mcap.records import Channel, Schema

    info = FileInfo(path=path, size=size, complete=False)
    if size < 8:
        info.lost_bytes = size
        info.problems.append("the file is empty or shorter than the MCAP magic")
        return info
    scan = FileScan(path)
    schemas: dict[int, Any] = {}
    channels: dict[int, Any] = {}
    first = last = None
    try:
        for record in scan.records():
            if isinstance(record, ScannedMessage):
                channel = channels.get(record.channel_id)
                topic = channel.topic if channel is not None else f"<channel {record.channel_id}>"
                info.topic_counts[topic] = info.topic_counts.get(topic, 0) + 1
                first = record.log_time if first is None else min(first, record.log_time)
                last = record.log_time if last is None else max(last, record.log_time)
            elif isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record
    except NotMcapError as exc:
        raise BagError(str(exc)) from None
    except OSError as exc:
        raise BagError(f"cannot read {path}: {exc.strerror}") from exc
    info.message_count = scan.report.messages
    info.starting_time = first or 0
    info.end_time = last or 0
    info.lost_bytes = scan.report.lost_bytes
    info.problems = list(scan.report.problems)
    info.topics = [topic_from_channel(c, schemas.get(c.schema_id)) for c in channels.values()]
    return info


def topic_from_channel(channel: Any, schema: Any) -> TopicRecord:
    """A topic described by an MCAP channel (and its schema), as rosbag2 writes them."""
    import yaml

    profiles: list[dict[str, Any]] = []
    text = channel.metadata.get("offered_qos_profiles", "")
    if text:
        try:
            loaded = yaml.safe_load(text)
            if isinstance(loaded, list):
                profiles = [p for p in loaded if isinstance(p, dict)]
        except yaml.YAMLError:
            pass
    return TopicRecord(
        name=channel.topic,
        type=schema.name if schema is not None else "",
        type_hash=channel.metadata.get("topic_type_hash", ""),
        offered_qos_profiles=profiles,
        serialization_format=channel.message_encoding or "cdr",
    )


def rebuilt_metadata(
    old: BagMetadata, files: list[FileInfo], found: Iterable[TopicRecord]
) -> BagMetadata:
    """Metadata made to agree with the files: counts and times from them, topics from the
    old metadata (order, QoS, hashes) and from the files' channels."""
    topics: dict[str, TopicRecord] = {}
    for topic in old.topics:
        topics[topic.name] = TopicRecord(
            topic.name,
            topic.type,
            topic.type_hash,
            list(topic.offered_qos_profiles),
            0,
            topic.serialization_format,
        )
    for topic in found:
        known = topics.get(topic.name)
        if known is None:
            topics[topic.name] = TopicRecord(
                topic.name,
                topic.type,
                topic.type_hash,
                list(topic.offered_qos_profiles),
                0,
                topic.serialization_format,
            )
        else:
            known.type = known.type or topic.type
            known.type_hash = known.type_hash or topic.type_hash
            known.offered_qos_profiles = known.offered_qos_profiles or topic.offered_qos_profiles
    for info in files:
        for name, count in info.topic_counts.items():
            if name in topics:
                topics[name].message_count += count
    with_messages = [f for f in files if f.message_count]
    first = min((f.starting_time for f in with_messages), default=0)
    last = max((f.end_time for f in with_messages), default=0)
    return BagMetadata(
        topics=list(topics.values()),
        files=[
            FileRecord(
                path=f.path.name,
                starting_time=f.starting_time,
                duration=(f.end_time - f.starting_time) if f.message_count else 0,
                message_count=f.message_count,
            )
            for f in files
        ],
        starting_time=first,
        duration=last - first if with_messages else 0,
        message_count=sum(f.message_count for f in files),
        compression_format=old.compression_format,
        compression_mode=old.compression_mode,
        custom_data=old.custom_data,
        ros_distro=old.ros_distro or "jazzy",
        storage_identifier=old.storage_identifier,
    )


@dataclass(frozen=True, slots=True)
class BagMessage:
    """One message read from a bag."""

    topic: str
    type: str
    log_time: int
    publish_time: int
    sequence: int
    data: bytes


@dataclass
class TopicDefinition:
    """What a reader of a bag knows about one topic: type, hash, QoS and definition."""

    name: str
    type: str
    type_hash: str = ""
    definition: str = ""
    encoding: str = ""
    offered_qos_profiles: list[dict[str, Any]] = field(default_factory=list)


def read_messages(
    info: BagInfo,
    topics: Iterable[str] | None = None,
    on_definition: Callable[[TopicDefinition], None] | None = None,
) -> Iterator[BagMessage]:
    """Every message of a bag, file by file; finished files in log-time order.

    Args:
        info: From :func:`inspect`.
        topics: Only these topic names (all when ``None``).
        on_definition: Called once per topic, before its first message, with its definition.

    Raises:
        BagError: If a file cannot be read, or the bag's messages are not CDR.
    """
    wanted = None if topics is None else set(topics)
    described: set[str] = set()
    qos = {t.name: t for t in info.metadata.topics}
    for file_info in info.files:
        if file_info.complete:
            source = _summary_messages(file_info.path, wanted)
        else:
            source = _scanned_messages(file_info.path, wanted)
        for schema, channel, message in source:
            if channel.message_encoding not in ("cdr", ""):
                raise BagError(
                    f"{file_info.path}: topic {channel.topic} is {channel.message_encoding}, "
                    "not CDR; only ROS 2 (CDR) bags can be played"
                )
            type_name = schema.name if schema is not None else qos.get(channel.topic, _NO).type
            if channel.topic not in described:
                described.add(channel.topic)
                if on_definition is not None:
                    known = qos.get(channel.topic)
                    on_definition(
                        TopicDefinition(
                            name=channel.topic,
                            type=type_name,
                            type_hash=channel.metadata.get("topic_type_hash", "")
                            or (known.type_hash if known else ""),
                            definition=schema.data.decode() if schema is not None else "",
                            encoding=schema.encoding if schema is not None else "",
                            offered_qos_profiles=list(known.offered_qos_profiles) if known else [],
                        )
                    )
            yield BagMessage(
                channel.topic,
                type_name,
                message.log_time,
                message.publish_time,
                message.sequence,
                bytes(message.data),
            )


_NO = TopicRecord("", "")


def _summary_messages(path: Path, wanted: set[str] | None) -> Iterator[tuple[Any, Any, Any]]:
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as stream:
            reader = make_reader(stream)
            yield from reader.iter_messages(
                topics=None if wanted is None else sorted(wanted), log_time_order=True
            )
    except OSError as exc:
        raise BagError(f"cannot read {path}: {exc.strerror}") from exc


def _scanned_messages(path: Path, wanted: set[str] | None) -> Iterator[tuple[Any, Any, Any]]:
    from mcap.records import Channel, Schema

    if path.stat().st_size < 8:
        return
    schemas: dict[int, Any] = {}
    channels: dict[int, Any] = {}
    try:
        for record in FileScan(path).records():
            if isinstance(record, ScannedMessage):
                channel = channels.get(record.channel_id)
                if channel is None or (wanted is not None and channel.topic not in wanted):
                    continue
                yield schemas.get(channel.schema_id), channel, record
            elif isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record
    except NotMcapError as exc:
        raise BagError(str(exc)) from None
