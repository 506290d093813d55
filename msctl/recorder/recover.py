"""``msctl bag recover``: complete a bag a crash (SIGKILL, power loss, full disk) left behind.

Each unfinished file is rebuilt from its records (:mod:`.scan`): every message of every
complete chunk, and every whole message of a truncated last chunk, is written into a new
file with a summary and indexes, which then replaces the old one (write to a temporary file,
fsync, rename: an interrupted recovery leaves the bag as it was). Then ``metadata.yaml`` is
rewritten from the files. What could not be read is reported, file by file.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from components.recording.errors import BagError, BagWriteError
from components.recording.metadata import (
    METADATA_FILE,
    ROS_DISTRO,
    BagMetadata,
    TopicRecord,
    read_metadata,
    write_metadata,
)
from msctl.recorder.bag import FileInfo, _file_info, data_files, rebuilt_metadata
from msctl.recorder.scan import FileScan, NotMcapError, ScannedMessage, ScanReport


@dataclass
class FileRecovery:
    """What recovery did to one file.

    Attributes:
        path: The file.
        action: ``kept`` (finished, untouched) or ``rebuilt``.
        messages: Messages the file holds now.
        salvaged: Of those, read out of a truncated last chunk.
        lost_bytes: Bytes that could not be read (their messages are lost).
        damaged_chunks: Whole chunks skipped (CRC mismatch).
        orphans: Messages dropped because their channel's description was lost.
        problems: What was found wrong, one line each.
        fixed_schemas: Schemas rewritten in rosbag2's form (``--fix-schemas``).
    """

    path: Path
    action: str
    messages: int = 0
    salvaged: int = 0
    lost_bytes: int = 0
    damaged_chunks: int = 0
    orphans: int = 0
    problems: list[str] = field(default_factory=list)
    fixed_schemas: int = 0


@dataclass
class RecoveryReport:
    """The outcome of :func:`recover`."""

    directory: Path
    files: list[FileRecovery]
    metadata: BagMetadata
    notes: list[str] = field(default_factory=list)

    @property
    def lost_anything(self) -> bool:
        """Whether some bytes or messages could not be brought back."""
        return any(f.lost_bytes or f.damaged_chunks or f.orphans for f in self.files)

    @property
    def rebuilt(self) -> list[FileRecovery]:
        """The files that were rebuilt."""
        return [f for f in self.files if f.action == "rebuilt"]


def recover(
    directory: Path,
    progress: Callable[[str, int, int], None] | None = None,
    fix_schemas: bool = False,
) -> RecoveryReport:
    """Rebuild every unfinished file of a bag and its ``metadata.yaml``.

    Args:
        directory: The bag directory, or one ``.mcap`` file (its bag's, which is then
            recovered whole, or a file alone, rebuilt in place with no ``metadata.yaml``).
        progress: Called with ``(file name, bytes done, bytes total)`` as files are read.
        fix_schemas: Also rebuild finished files whose ``ros2msg`` schemas name dependencies
            ``MSG: pkg/msg/Type`` (msctl before it followed rosbag2; Foxglove cannot decode
            them), writing ``MSG: pkg/Type``; the messages are copied byte for byte.

    An unreadable ``metadata.yaml`` is rebuilt from the files (the old one kept as
    ``metadata.yaml.unreadable``), said in :attr:`RecoveryReport.notes`.

    Raises:
        BagError: If the directory is not a bag (no metadata and no data files).
        BagWriteError: If the rebuilt files cannot be written (the bag is left as it was).
    """
    directory = Path(directory)
    if directory.is_file():
        return _recover_file(directory, progress, fix_schemas)
    if not directory.is_dir():
        raise BagError(f"no such bag directory: {directory}")
    notes: list[str] = []
    old = BagMetadata()
    if (directory / METADATA_FILE).exists():
        try:
            old = read_metadata(directory)
        except BagError as exc:
            # The files are the record; metadata.yaml only summarizes them (a crash while
            # it was rewritten, a hand edit): rebuilt from the files, the old one kept aside.
            aside = directory / f"{METADATA_FILE}.unreadable"
            notes.append(
                f"{exc.message}: rebuilt from the MCAP files (the old one kept as {aside.name})"
            )
    paths = [directory / f.path for f in old.files if (directory / f.path).exists()]
    paths += [p for p in data_files(directory) if p not in paths]
    if not paths and notes:
        # With no metadata to name them, any MCAP file here is the bag's (a renamed bag).
        paths = sorted(directory.glob("*.mcap"))
    if not paths:
        raise BagError(
            f"{directory} is not a bag: no {METADATA_FILE} names a data file there, and no "
            f"{directory.name}_<N>.mcap file is in it"
        )
    total = sum(p.stat().st_size for p in paths)
    done = 0
    outcomes: list[FileRecovery] = []
    infos: list[FileInfo] = []
    for path in paths:
        info = _file_info(path)
        stale_schemas = fix_schemas and info.complete and _has_stale_schemas(path)
        if info.complete and not stale_schemas:
            outcomes.append(FileRecovery(path, "kept", messages=info.message_count))
        else:
            metadata_so_far = rebuilt_metadata(old, [*infos, info], _topics([*infos, info]))
            outcome = _rebuild(path, old, metadata_so_far, fix_schemas)
            if stale_schemas:
                outcome.action = "schemas fixed"
            outcomes.append(outcome)
            info = _file_info(path)
        infos.append(info)
        done += path.stat().st_size if path.exists() else 0
        if progress is not None:
            progress(path.name, done, total)
    metadata = rebuilt_metadata(old, infos, _topics(infos))
    if not metadata.ros_distro:
        metadata.ros_distro = ROS_DISTRO
    try:
        if notes:
            os.replace(directory / METADATA_FILE, directory / f"{METADATA_FILE}.unreadable")
        write_metadata(directory, metadata)
    except OSError as exc:
        raise BagWriteError(f"cannot write {directory / METADATA_FILE}: {exc}") from exc
    return RecoveryReport(directory, outcomes, metadata, notes)


def _recover_file(
    path: Path, progress: Callable[[str, int, int], None] | None, fix_schemas: bool
) -> RecoveryReport:
    """Recover one ``.mcap`` file: the bag it belongs to, if its directory is one (its
    ``metadata.yaml`` must agree with it), else the file alone (no ``metadata.yaml``)."""
    directory = path.parent
    listed: set[str] = set()
    try:
        if (directory / METADATA_FILE).exists():
            listed = {f.path for f in read_metadata(directory).files}
    except BagError:
        listed = set()
    if path.name in listed or path in data_files(directory):
        report = recover(directory, progress, fix_schemas)
        report.notes.insert(0, f"{path.name} is part of the bag {directory}: recovered the bag")
        return report
    if path.suffix != ".mcap":
        raise BagError(
            f"{path} is not a bag: give a bag directory or one .mcap file",
        )
    info = _file_info(path)
    stale_schemas = fix_schemas and info.complete and _has_stale_schemas(path)
    if info.complete and not stale_schemas:
        outcome = FileRecovery(path, "kept", messages=info.message_count)
    else:
        found = _topics([info])
        metadata = rebuilt_metadata(BagMetadata(), [info], found)
        outcome = _rebuild(path, BagMetadata(), metadata, fix_schemas)
        if stale_schemas:
            outcome.action = "schemas fixed"
        info = _file_info(path)
    if progress is not None:
        progress(path.name, path.stat().st_size, path.stat().st_size)
    metadata = rebuilt_metadata(BagMetadata(), [info], _topics([info]))
    return RecoveryReport(
        directory, [outcome], metadata, [f"{path.name} recovered alone (not part of a bag)"]
    )


def _topics(infos: list[FileInfo]) -> list[TopicRecord]:
    return [t for info in infos for t in info.topics]


def _has_stale_schemas(path: Path) -> bool:
    """Whether a finished file holds a ``ros2msg`` schema in msctl's old ``MSG:`` form."""
    from mcap.reader import make_reader

    from components.recording.definitions import needs_fixing

    with open(path, "rb") as stream:
        summary = make_reader(stream).get_summary()
    schemas = summary.schemas.values() if summary else ()
    return any(
        s.encoding == "ros2msg" and needs_fixing(s.data.decode(errors="replace")) for s in schemas
    )


def _rebuild(
    path: Path, old: BagMetadata, metadata: BagMetadata, fix_schemas: bool = False
) -> FileRecovery:
    from mcap.records import Channel, Metadata, Schema
    from mcap.writer import CompressionType, Writer

    from components.recording.definitions import fixed_definition, needs_fixing

    outcome = FileRecovery(path, "rebuilt")
    temporary = path.with_name(f".{path.name}.recovering")
    scan = FileScan(path)
    report = scan.report
    try:
        with open(temporary, "wb") as stream:
            writer: Any = None
            schema_ids: dict[int, int] = {}
            channel_ids: dict[int, int] = {}
            extra_metadata: list[Any] = []
            records = iter(scan.records()) if path.stat().st_size >= 8 else iter(())
            pending: list[Any] = []
            # The header (profile, library) is read with the first record; the writer waits.
            for record in records:
                pending.append(record)
                break
            compression = _compression_of(path)
            writer = Writer(
                stream,
                compression=CompressionType.ZSTD if compression == "zstd" else CompressionType.NONE,
            )
            writer.start(profile=report.profile or "ros2", library=report.library or "msctl")
            ours = report.library.startswith("msctl")
            for record in [*pending, *records]:
                if isinstance(record, ScannedMessage):
                    channel_id = channel_ids.get(record.channel_id)
                    if channel_id is None and ours:
                        channel_id = _channel_from_metadata(
                            writer, old, record.channel_id, schema_ids, channel_ids
                        )
                    if channel_id is None:
                        outcome.orphans += 1
                        continue
                    writer.add_message(
                        channel_id,
                        record.log_time,
                        record.data,
                        record.publish_time,
                        record.sequence,
                    )
                    outcome.messages += 1
                elif isinstance(record, Schema):
                    data = record.data
                    if fix_schemas and record.encoding == "ros2msg":
                        text = data.decode(errors="replace")
                        if needs_fixing(text):
                            data = fixed_definition(text).encode()
                            outcome.fixed_schemas += 1
                    schema_ids[record.id] = writer.register_schema(
                        record.name, record.encoding, data
                    )
                elif isinstance(record, Channel):
                    channel_ids[record.id] = writer.register_channel(
                        record.topic,
                        record.message_encoding,
                        schema_ids.get(record.schema_id, 0),
                        dict(record.metadata),
                    )
                elif isinstance(record, Metadata) and record.name != "rosbag2":
                    extra_metadata.append(record)
            writer.flush()
            for record in extra_metadata:
                writer.add_metadata(record.name, dict(record.metadata))
            writer.add_metadata(
                "rosbag2",
                {"serialized_metadata": metadata.to_yaml(), "ROS_DISTRO": ROS_DISTRO},
            )
            writer.finish()
            stream.flush()
            os.fsync(stream.fileno())
        _check_readable(temporary, outcome.messages)
        os.replace(temporary, path)
    except NotMcapError as exc:
        _remove(temporary)
        raise BagError(f"cannot recover {path}: {exc}") from None
    except BagWriteError:
        _remove(temporary)
        raise
    except OSError as exc:
        _remove(temporary)
        raise BagWriteError(f"cannot rebuild {path}: {exc}; the bag is left as it was") from exc
    except BaseException:
        _remove(temporary)
        raise
    _fill(outcome, report)
    if outcome.orphans:
        outcome.problems.append(
            f"{outcome.orphans} message(s) dropped: their channel's description was lost"
        )
    return outcome


def _fill(outcome: FileRecovery, report: ScanReport) -> None:
    outcome.salvaged = report.salvaged
    outcome.lost_bytes = report.lost_bytes
    outcome.damaged_chunks = report.damaged_chunks
    outcome.problems = list(report.problems)


def _channel_from_metadata(
    writer: Any,
    old: BagMetadata,
    channel_id: int,
    schema_ids: dict[int, int],
    channel_ids: dict[int, int],
) -> int | None:
    """msctl numbers channels by topic (channel = topic index + 1) and lists every topic in
    ``metadata.yaml``, so a channel whose record was in a lost chunk can be described again."""
    from components.recording.definitions import message_definition, profiles_yaml

    index = channel_id - 1
    if not 0 <= index < len(old.topics):
        return None
    topic = old.topics[index]
    definition = message_definition(topic.type)
    if definition is None:
        schema = writer.register_schema(topic.type, "", b"")
    else:
        schema = writer.register_schema(topic.type, "ros2msg", definition.encode())
    metadata = {"offered_qos_profiles": profiles_yaml(topic.offered_qos_profiles)}
    if topic.type_hash:
        metadata["topic_type_hash"] = topic.type_hash
    new = writer.register_channel(topic.name, "cdr", schema, metadata)
    channel_ids[channel_id] = new
    return new


def _compression_of(path: Path) -> str:
    """The compression of a file's first chunk (``""`` if none or unknown)."""
    import struct

    try:
        with open(path, "rb") as stream:
            stream.seek(8)
            while True:
                head = stream.read(9)
                if len(head) < 9:
                    return ""
                opcode, length = struct.unpack("<BQ", head)
                if opcode == 0x06:
                    fixed = stream.read(28 + 4)
                    (name_length,) = struct.unpack_from("<I", fixed, 28)
                    return stream.read(min(name_length, 16)).decode(errors="replace")
                if opcode not in range(1, 16) or length > 1 << 40:
                    return ""
                stream.seek(length, 1)
    except (OSError, struct.error):
        return ""


def _check_readable(path: Path, expected: int) -> None:
    from mcap.reader import make_reader

    with open(path, "rb") as stream:
        summary = make_reader(stream).get_summary()
    count = summary.statistics.message_count if summary and summary.statistics else 0
    if count != expected:
        raise BagWriteError(
            f"the rebuilt {path.name} reads back {count} messages, not {expected}; "
            "the bag is left as it was"
        )


def _remove(path: Path) -> None:
    try:
        path.unlink()
    except OSError:
        pass
