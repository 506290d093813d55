"""The MCAP files of one bag: schemas, channels, messages, splits, and crash safety.

One :class:`BagWriter` owns a bag directory. It writes with the ``mcap`` library's low-level
writer (raw CDR bytes, profile ``ros2``, chunked, optionally zstd, a summary with indexes at
each file's close), never deserialising a payload.

Crash safety: the open chunk is closed and written out at least every ``flush_interval``
seconds (and the file fsynced), so a SIGKILL or a power loss loses at most that tail; every
file finished at a split carries its summary, and ``metadata.yaml`` is rewritten (atomically)
when a file opens, when a topic appears, at every split and at the close. What a crash leaves
is put right by :func:`msctl.recorder.recover.recover`.

Not thread-safe: one thread (the recorder's writer thread) calls it.
"""

from __future__ import annotations

import errno
import functools
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from components.recording.definitions import profiles_yaml
from components.recording.errors import BagError, BagWriteError
from components.recording.metadata import (
    METADATA_FILE,
    ROS_DISTRO,
    BagMetadata,
    FileRecord,
    TopicRecord,
    file_name,
    write_metadata,
)

#: MCAP profile of rosbag2 files.
PROFILE = "ros2"
#: Chunk size: big enough to compress well, small enough that a chunk is a short tail.
DEFAULT_CHUNK_SIZE = 1024 * 1024
#: Seconds between forced chunk flushes (the most a crash can lose of a slow stream).
DEFAULT_FLUSH_INTERVAL = 1.0
#: Compression names ``--compression`` accepts.
COMPRESSIONS = ("none", "zstd")
# A message record's bytes besides its payload: opcode, length, channel, sequence, 2 times,
# and its entry in the chunk's message index.
_MESSAGE_OVERHEAD = 1 + 8 + 2 + 4 + 8 + 8 + 16


@dataclass(frozen=True)
class TopicSpec:
    """A topic as the bag describes it.

    Attributes:
        name: Fully qualified topic name.
        type: ``pkg/msg/Name``.
        type_hash: ``RIHS01_...`` as the publishers announce it (empty if unknown).
        offered_qos_profiles: One profile per publisher (:func:`.definitions.qos_profiles`).
        definition: The ``ros2msg`` definition; ``None`` when msctl has none (a ROS node's
            custom type): recorded with an empty definition.
    """

    name: str
    type: str
    type_hash: str = ""
    offered_qos_profiles: tuple[dict[str, Any], ...] = ()
    definition: str | None = None


@dataclass
class _OpenFile:
    path: Path
    stream: Any
    mcap: Any
    channels: dict[int, int] = field(default_factory=dict)  # topic id -> channel id
    schemas: dict[str, int] = field(default_factory=dict)  # type -> schema id
    first_time: int | None = None
    last_time: int = 0
    messages: int = 0
    flushed_bytes: int = 0  # file size at the last flush
    pending_bytes: int = 0  # estimate of what is buffered since
    dirty: bool = False  # messages since the last flush


class BagWriter:
    """Writes one bag directory.

    Args:
        directory: The bag directory; it must not exist (a bag is never overwritten) and its
            parent must.
        compression: ``"zstd"`` to compress chunks, ``None``/``"none"`` not to.
        max_bytes: Split when the current file reaches this size (0: never).
        max_duration: Split when the current file spans this many seconds of log time
            (0: never).
        chunk_size: Bytes of messages per chunk.
        flush_interval: Most seconds between chunk flushes (the crash-loss window).
        fsync: Fsync each file at each flush (off only for benchmarks of the writer itself).
        custom_data: Key/value text for ``metadata.yaml``'s ``custom_data``.

    Raises:
        BagError: If the directory exists or its parent does not.
        BagWriteError: If the directory or first file cannot be created.
    """

    def __init__(
        self,
        directory: Path,
        *,
        compression: str | None = None,
        max_bytes: int = 0,
        max_duration: float = 0.0,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        flush_interval: float = DEFAULT_FLUSH_INTERVAL,
        fsync: bool = True,
        custom_data: dict[str, str] | None = None,
    ) -> None:
        if compression not in (None, *COMPRESSIONS):
            raise BagError(
                f"unknown compression {compression!r}; use one of {', '.join(COMPRESSIONS)}"
            )
        if max_bytes < 0 or max_duration < 0:
            raise BagError("--max-bag-size and --max-bag-duration cannot be negative")
        self.directory = Path(directory)
        self._compression = "zstd" if compression == "zstd" else ""
        self._max_bytes = int(max_bytes)
        self._max_duration_ns = int(max_duration * 1e9)
        # A small split size gets small chunks, so files end near the size asked for.
        self._chunk_size = (
            min(chunk_size, max(self._max_bytes // 4, 4096)) if max_bytes else (chunk_size)
        )
        self._flush_interval = flush_interval
        self._fsync = fsync
        self._custom_data = custom_data
        self._topics: list[TopicSpec] = []
        self._topic_counts: list[int] = []
        self._files: list[FileRecord] = []
        self._closed_bytes = 0
        self._file: _OpenFile | None = None
        self._last_flush = time.monotonic()
        self._bag_first: int | None = None
        self._bag_last = 0
        self._messages = 0
        self._closed = False
        self._metadata_dirty = False
        self._create_directory()
        self._open_file()

    # ------------------------------------------------------------------------ properties
    @property
    def topics(self) -> list[TopicSpec]:
        """Every topic added so far, by topic id."""
        return list(self._topics)

    @property
    def message_count(self) -> int:
        """Messages written so far (all files)."""
        return self._messages

    @property
    def bytes_written(self) -> int:
        """Bytes in the bag's data files so far (the open chunk estimated)."""
        current = self._file
        if current is None:
            return self._closed_bytes
        return self._closed_bytes + current.flushed_bytes + current.pending_bytes

    @property
    def current_file(self) -> Path | None:
        """The file being written (``None`` once closed)."""
        return None if self._file is None else self._file.path

    @property
    def file_count(self) -> int:
        """Data files so far, the open one included."""
        return len(self._files)

    # ------------------------------------------------------------------------ writing
    def add_topic(self, spec: TopicSpec) -> int:
        """Add a topic; returns its id for :meth:`write`.

        ``metadata.yaml`` is rewritten at the next :meth:`tick` (many topics appearing at
        once cost one rewrite, not one fsync each).
        """
        self._check_open()
        topic_id = len(self._topics)
        self._topics.append(spec)
        self._topic_counts.append(0)
        assert self._file is not None
        self._guard(lambda: self._register(self._file, topic_id), self._file.path)
        self._metadata_dirty = True
        return topic_id

    def write(
        self, topic_id: int, log_time: int, data: bytes, publish_time: int = 0, sequence: int = 0
    ) -> None:
        """Append one message (CDR bytes as received).

        Args:
            topic_id: From :meth:`add_topic`.
            log_time: Receive time, ns since the epoch.
            data: The payload, untouched.
            publish_time: The sender's timestamp (0: the log time).
            sequence: The sender's sequence number (kept modulo 2**32).

        Raises:
            BagWriteError: If the disk refuses; the bag written so far stays readable.
        """
        current = self._file
        if current is None:
            raise RuntimeError(f"bag {self.directory} is closed")
        if (
            self._max_duration_ns
            and current.first_time is not None
            and log_time - current.first_time >= self._max_duration_ns
        ):
            self.split()
            current = self._file
            assert current is not None
        try:
            current.mcap.add_message(
                topic_id + 1,
                log_time,
                data,
                publish_time or log_time,
                sequence & 0xFFFFFFFF,
            )
        except OSError as exc:
            self._fail(exc, current.path)
        if current.first_time is None:
            current.first_time = log_time
            if self._bag_first is None:
                self._bag_first = log_time
        current.last_time = log_time
        current.messages += 1
        current.dirty = True
        current.pending_bytes += len(data) + _MESSAGE_OVERHEAD
        self._bag_last = log_time
        self._messages += 1
        self._topic_counts[topic_id] += 1
        if self._max_bytes and current.flushed_bytes + current.pending_bytes >= self._max_bytes:
            self.split()
        elif current.pending_bytes >= self._chunk_size:
            # The mcap writer has written the chunk out by now: learn the file's true size.
            current.flushed_bytes = current.stream.tell()
            current.pending_bytes = 0

    def tick(self) -> None:
        """Rewrite ``metadata.yaml`` if topics were added, and flush the open chunk if
        ``flush_interval`` has passed since the last flush.

        Call it often (the recorder's writer thread calls it at least 5 times a second).
        """
        if self._metadata_dirty:
            self._write_metadata()
        if self._file is not None and time.monotonic() - self._last_flush >= self._flush_interval:
            self.flush()

    def flush(self) -> None:
        """Write out the open chunk and fsync the file: everything so far survives a crash."""
        current = self._file
        if current is None:
            return
        self._last_flush = time.monotonic()
        if not current.dirty:
            return

        def flush() -> None:
            current.mcap.flush()
            if self._fsync:
                os.fsync(current.stream.fileno())

        self._guard(flush, current.path)
        current.flushed_bytes = current.stream.tell()
        current.pending_bytes = 0
        current.dirty = False

    def split(self) -> None:
        """Finish the current file (with its summary), open the next, rewrite the metadata."""
        self._check_open()
        self._finish_file()
        self._open_file()

    def annotate(self, data: dict[str, str]) -> None:
        """Add or replace ``custom_data`` entries; ``metadata.yaml`` is rewritten at the next
        :meth:`tick` (and at :meth:`close`)."""
        self._custom_data = {**(self._custom_data or {}), **data}
        self._metadata_dirty = True

    def close(self) -> BagMetadata:
        """Finish the last file and write the final ``metadata.yaml`` (idempotent).

        Raises:
            BagWriteError: If the disk refuses; what was written stays recoverable.
        """
        if not self._closed:
            self._closed = True
            if self._file is not None:
                self._finish_file()
            self._write_metadata()
        return self.metadata()

    def abandon(self) -> None:
        """Stop without finishing (after a write error): close the handle, keep the bytes."""
        self._closed = True
        current, self._file = self._file, None
        if current is not None:
            try:
                current.stream.close()
            except OSError:
                pass

    def metadata(self) -> BagMetadata:
        """The bag's metadata as of now (the open file counted as far as written)."""
        files = list(self._files)
        if self._file is not None and files:
            files[-1] = self._file_record(self._file)
        first = self._bag_first or 0
        return BagMetadata(
            topics=[
                TopicRecord(
                    name=t.name,
                    type=t.type,
                    type_hash=t.type_hash,
                    offered_qos_profiles=[dict(p) for p in t.offered_qos_profiles],
                    message_count=self._topic_counts[i],
                )
                for i, t in enumerate(self._topics)
            ],
            files=files,
            starting_time=first,
            duration=(self._bag_last - first) if self._messages else 0,
            message_count=self._messages,
            custom_data=self._custom_data,
        )

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------------ internals
    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError(f"bag {self.directory} is closed")

    def _create_directory(self) -> None:
        if self.directory.exists() or self.directory.is_symlink():
            raise BagError(
                f"{self.directory} already exists; a bag is never overwritten",
                hint="give another name with -o, or remove it yourself",
            )
        parent = self.directory.parent
        if not parent.is_dir():
            raise BagError(
                f"cannot create bag {self.directory}: {parent} does not exist",
                hint="create it first, or give another place with -o",
            )
        try:
            self.directory.mkdir()
        except FileExistsError:
            raise BagError(f"{self.directory} already exists; a bag is never overwritten") from None
        except OSError as exc:
            raise BagWriteError(f"cannot create bag directory {self.directory}: {exc}") from exc

    def _open_file(self) -> None:
        from mcap.writer import CompressionType, Writer

        path = self.directory / file_name(self.directory, len(self._files))
        try:
            stream = open(path, "xb")  # noqa: SIM115  (closed in _finish_file / abandon)
        except OSError as exc:
            self._fail(exc, path)
        writer = Writer(
            stream,
            chunk_size=self._chunk_size,
            compression=CompressionType.ZSTD if self._compression else CompressionType.NONE,
        )
        _use_lean_chunks(writer)
        opened = _OpenFile(path=path, stream=stream, mcap=writer)
        self._file = opened
        self._files.append(FileRecord(path=path.name))

        def start() -> None:
            writer.start(profile=PROFILE, library=_library())
            for topic_id in range(len(self._topics)):
                self._register(opened, topic_id)
            # The header on disk at once: even a file killed before its first chunk is
            # recognisably MCAP.
            stream.flush()

        self._guard(start, path)
        opened.flushed_bytes = stream.tell()
        self._last_flush = time.monotonic()
        self._write_metadata()

    def _register(self, opened: _OpenFile, topic_id: int) -> None:
        spec = self._topics[topic_id]
        schema_id = opened.schemas.get(spec.type)
        if schema_id is None:
            if spec.definition is None:
                schema_id = opened.mcap.register_schema(spec.type, "", b"")
            else:
                schema_id = opened.mcap.register_schema(
                    spec.type, "ros2msg", spec.definition.encode()
                )
            opened.schemas[spec.type] = schema_id
        metadata = {"offered_qos_profiles": profiles_yaml(list(spec.offered_qos_profiles))}
        if spec.type_hash:
            metadata["topic_type_hash"] = spec.type_hash
        channel_id = opened.mcap.register_channel(spec.name, "cdr", schema_id, metadata)
        if channel_id != topic_id + 1:
            raise AssertionError(f"channel {channel_id} for topic {topic_id} of {opened.path}")
        opened.channels[topic_id] = channel_id

    def _finish_file(self) -> None:
        current = self._file
        assert current is not None
        self._files[-1] = self._file_record(current)
        serialized = self.metadata().to_yaml()

        def finish() -> None:
            current.mcap.flush()
            current.mcap.add_metadata(
                "rosbag2", {"serialized_metadata": serialized, "ROS_DISTRO": ROS_DISTRO}
            )
            current.mcap.finish()
            current.stream.flush()
            if self._fsync:
                os.fsync(current.stream.fileno())

        try:
            self._guard(finish, current.path)
        except BagWriteError:
            self.abandon()
            raise
        self._closed_bytes += current.stream.tell()
        current.stream.close()
        self._file = None

    @staticmethod
    def _file_record(opened: _OpenFile) -> FileRecord:
        first = opened.first_time or 0
        return FileRecord(
            path=opened.path.name,
            starting_time=first,
            duration=(opened.last_time - first) if opened.messages else 0,
            message_count=opened.messages,
        )

    def _write_metadata(self) -> None:
        self._metadata_dirty = False
        try:
            write_metadata(self.directory, self.metadata())
        except OSError as exc:
            self._fail(exc, self.directory / METADATA_FILE)

    def _guard(self, action: Any, path: Path) -> None:
        try:
            action()
        except OSError as exc:
            self._fail(exc, path)

    def _fail(self, exc: OSError, path: Path) -> Any:
        if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
            reason = "the disk is full" if exc.errno != errno.EFBIG else "the file size limit"
            message = f"stopped recording: {reason} writing {path} ({exc.strerror})"
        else:
            message = f"stopped recording: cannot write {path}: {exc}"
        raise BagWriteError(
            message,
            hint=f"what was written is kept; `msctl bag recover {self.directory}` completes it",
        ) from exc


def _use_lean_chunks(writer: Any) -> bool:
    """Give ``writer`` (an ``mcap.writer.Writer``) a chunk builder that appends each message
    record with one ``struct`` call; returns whether it could.

    Why: the library's chunk builder writes a message record in seven calls and two seeks,
    and its message index two calls per message; at 50,000 messages a second that was most
    of the recorder's writer thread (measured by bench/record.py with py-spy). The records,
    indexes and chunks written are byte for byte the library's own (a test compares whole
    files); everything else (schemas, channels, chunk records, summary, statistics) stays the
    library's. The builder is the writer's private attribute: if a future ``mcap`` renames
    it, the library's builder is kept and only speed is lost.
    """
    try:
        from mcap._chunk_builder import ChunkBuilder
    except ImportError:
        return False
    if not isinstance(getattr(writer, "_Writer__chunk_builder", None), ChunkBuilder):
        return False
    lean = _lean_chunk_builder_class(ChunkBuilder)()
    if not hasattr(lean.record_writer, "_buffer"):
        return False
    writer._Writer__chunk_builder = lean
    statistics = getattr(writer, "_Writer__statistics", None)
    finalize = getattr(writer, "_Writer__finalize_chunk", None)
    chunk_size = getattr(writer, "_Writer__chunk_size", None)
    if statistics is not None and finalize is not None and isinstance(chunk_size, int):
        writer.add_message = _lean_add_message(statistics, lean, finalize, chunk_size)
    return True


def _lean_add_message(
    statistics: Any, builder: Any, finalize: Callable[[], None], chunk_size: int
) -> Callable[[int, int, bytes, int, int], None]:
    """``Writer.add_message`` for a chunked writer with a lean builder: the same statistics,
    record and chunking, without making a ``Message`` and four calls per message (a third
    of what was left of the writer's time per message, py-spy on bench/record.py)."""
    counts = statistics.channel_message_counts
    append = builder.append
    record_writer = builder.record_writer

    def add_message(
        channel_id: int, log_time: int, data: bytes, publish_time: int, sequence: int = 0
    ) -> None:
        if statistics.message_count == 0 or log_time < statistics.message_start_time:
            statistics.message_start_time = log_time
        if log_time > statistics.message_end_time:
            statistics.message_end_time = log_time
        counts[channel_id] += 1
        statistics.message_count += 1
        append(channel_id, sequence, log_time, publish_time, data)
        if record_writer.count > chunk_size:
            finalize()

    return add_message


@functools.cache
def _lean_chunk_builder_class(base: type) -> type:
    import itertools
    import struct

    from mcap.opcode import Opcode
    from mcap.records import MessageIndex

    # Opcode, record length, channel, sequence, log time, publish time (MCAP's Message).
    head = struct.Struct("<BQHIQQ")
    opcode = int(Opcode.MESSAGE)

    class LeanMessageIndex(MessageIndex):
        """The library's message index, written in one ``struct`` call at the chunk's end."""

        def write(self, stream: Any) -> None:
            stream.start_record(Opcode.MESSAGE_INDEX)
            stream.write2(self.channel_id)
            stream.write4(len(self.records) * 16)
            stream.write(struct.pack(f"<{2 * len(self.records)}Q", *itertools.chain(*self.records)))
            stream.finish_record()

    class LeanChunkBuilder(base):  # type: ignore[misc,valid-type]
        """The library's chunk builder with a one-call message record."""

        def add_message(self, message: Any) -> None:
            self.append(
                message.channel_id,
                message.sequence,
                message.log_time,
                message.publish_time,
                message.data,
            )

        def append(
            self, channel: int, sequence: int, log_time: int, publish_time: int, data: bytes
        ) -> None:
            """:meth:`add_message` from the message's fields (no ``Message`` made)."""
            buffer = self.record_writer._buffer
            if self.num_messages == 0:
                self.message_start_time = self.message_end_time = log_time
            elif log_time < self.message_start_time:
                self.message_start_time = log_time
            elif log_time > self.message_end_time:
                self.message_end_time = log_time
            index = self.message_indices.get(channel)
            if index is None:
                index = self.message_indices[channel] = MessageIndex(channel_id=channel, records=[])
            index.records.append((log_time, buffer.tell()))
            self.num_messages += 1
            size = 22 + len(data)
            buffer.write(head.pack(opcode, size, channel, sequence, log_time, publish_time))
            buffer.write(data)

    return LeanChunkBuilder


def _library() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return f"msctl-{version('msctl')}; mcap-python-{version('mcap')}"
    except PackageNotFoundError:
        return "msctl"
