"""Reading an MCAP file record by record, whatever state a crash left it in.

The ``mcap`` library's readers need a summary (seeking reader) or stop with an exception at
the first truncated record (stream reader). A file whose writer was killed has no summary
and usually ends inside a chunk, so this scanner walks the records itself:

- every complete record is read; a chunk whose CRC does not match is skipped and counted;
- a truncated chunk at the end is read as far as it goes: uncompressed records, or what a
  streaming zstd/lz4 decoder gets out of the partial frame, up to the last whole message;
- a run of zero bytes or an impossible length (what a power loss can leave) ends the scan.

Everything it cannot read is reported (:class:`ScanReport`), never silently dropped.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import Any, BinaryIO

#: The 8 bytes an MCAP file starts and ends with.
MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEAD = struct.Struct("<BQ")
_MESSAGE_HEAD = struct.Struct("<HIQQ")
_CHUNK_HEAD = struct.Struct("<QQQI")

HEADER, FOOTER, SCHEMA, CHANNEL, MESSAGE, CHUNK = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
METADATA, DATA_END = 0x0C, 0x0F
_KNOWN_OPCODES = frozenset(range(0x01, 0x10))


@dataclass(frozen=True, slots=True)
class ScannedMessage:
    """One message read from a file."""

    channel_id: int
    sequence: int
    log_time: int
    publish_time: int
    data: bytes


@dataclass
class ScanReport:
    """What a scan found and what it could not read.

    Attributes:
        path: The file.
        size: Its size in bytes.
        complete: It ends with a footer and the magic (its writer finished it).
        profile: The MCAP header's profile (``ros2`` for rosbag2 files).
        library: The MCAP header's library (who wrote it).
        messages: Messages read.
        chunks: Complete chunks read.
        damaged_chunks: Complete chunks skipped (CRC mismatch or undecodable).
        truncated_chunk: Whether the data ended inside a chunk.
        salvaged: Messages read out of that truncated chunk.
        lost_bytes: Bytes at the end that could not be read as whole records.
        problems: One line per thing that went wrong, in the file's order.
    """

    path: Path
    size: int = 0
    complete: bool = False
    profile: str = ""
    library: str = ""
    messages: int = 0
    chunks: int = 0
    damaged_chunks: int = 0
    truncated_chunk: bool = False
    salvaged: int = 0
    lost_bytes: int = 0
    problems: list[str] = field(default_factory=list)

    @property
    def intact(self) -> bool:
        """Finished and nothing skipped."""
        return self.complete and not self.damaged_chunks and not self.lost_bytes


class NotMcapError(ValueError):
    """A file that does not start with the MCAP magic."""


def is_complete(path: Path) -> bool:
    """Whether an MCAP file ends with its footer and magic (cheap: reads 8 + 29 bytes)."""
    try:
        with open(path, "rb") as stream:
            stream.seek(0, 2)
            size = stream.tell()
            if size < 2 * len(MAGIC) + 9 + 20:
                return False
            stream.seek(size - len(MAGIC) - 29)
            tail = stream.read(29 + len(MAGIC))
    except OSError:
        return False
    return tail[-8:] == MAGIC and tail[0] == FOOTER


class FileScan:
    """Iterate the records of one MCAP file; the report fills in as it goes.

    Args:
        path: The file.

    Typical use::

        scan = FileScan(path)
        for record in scan.records():
            ...
        print(scan.report.lost_bytes)
    """

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.report = ScanReport(self.path)

    def records(self) -> Iterator[Any]:
        """Schemas and channels (``mcap.records``), :class:`ScannedMessage`, and metadata
        records (``mcap.records.Metadata``), in file order.

        Raises:
            NotMcapError: If the file is not MCAP at all.
            OSError: If it cannot be read.
        """
        report = self.report
        with open(self.path, "rb") as stream:
            stream.seek(0, 2)
            report.size = size = stream.tell()
            stream.seek(0)
            if stream.read(len(MAGIC)) != MAGIC:
                raise NotMcapError(f"{self.path} is not an MCAP file (no MCAP magic at its start)")
            report.complete = is_complete(self.path)
            position = len(MAGIC)
            while position < size:
                head = stream.read(_RECORD_HEAD.size)
                if len(head) < _RECORD_HEAD.size:
                    self._lose(size - position, "the file ends inside a record's header")
                    return
                opcode, length = _RECORD_HEAD.unpack(head)
                body_start = position + _RECORD_HEAD.size
                if opcode not in _KNOWN_OPCODES and (opcode == 0 or length == 0):
                    self._lose(size - position, f"unreadable bytes from offset {position}")
                    return
                if body_start + length > size:
                    if opcode == CHUNK:
                        yield from self._truncated_chunk(stream, size - body_start, position)
                    else:
                        self._lose(
                            size - position,
                            f"the file ends inside a record (opcode {opcode:#04x}) at "
                            f"offset {position}",
                        )
                    return
                if opcode == DATA_END:
                    return  # the summary follows; the data section is all read
                if opcode in (CHUNK, SCHEMA, CHANNEL, MESSAGE, METADATA, HEADER):
                    body = stream.read(length)
                    yield from self._record(opcode, body, position)
                else:
                    stream.seek(length, 1)
                position = body_start + length

    # ------------------------------------------------------------------------ records
    def _record(self, opcode: int, body: bytes, offset: int) -> Iterator[Any]:
        if opcode == CHUNK:
            yield from self._chunk(body, offset)
            return
        if opcode == HEADER:
            try:
                stream = _data_stream(body)
                self.report.profile = stream.read_prefixed_string()
                self.report.library = stream.read_prefixed_string()
            except Exception:
                self.report.problems.append(f"unreadable header at offset {offset}")
            return
        record = self._parse(opcode, body, offset)
        if record is not None:
            yield record

    def _parse(self, opcode: int, body: bytes, offset: int) -> Any:
        from mcap.records import Channel, Metadata, Schema

        try:
            if opcode == MESSAGE:
                channel_id, sequence, log_time, publish_time = _MESSAGE_HEAD.unpack_from(body)
                self.report.messages += 1
                return ScannedMessage(
                    channel_id, sequence, log_time, publish_time, body[_MESSAGE_HEAD.size :]
                )
            parser = {SCHEMA: Schema, CHANNEL: Channel, METADATA: Metadata}[opcode]
            return parser.read(_data_stream(body))
        except Exception as exc:
            self.report.problems.append(
                f"unreadable record (opcode {opcode:#04x}) at offset {offset}: {exc}"
            )
            return None

    def _chunk(self, body: bytes, offset: int) -> Iterator[Any]:
        try:
            compression, records, crc, uncompressed_size = _chunk_parts(body)
            data = _decompress(compression, records, uncompressed_size)
            if crc and zlib.crc32(data) != crc:
                raise ValueError("its CRC does not match its content")
        except Exception as exc:
            self.report.damaged_chunks += 1
            self.report.problems.append(f"skipped the chunk at offset {offset}: {exc}")
            return
        self.report.chunks += 1
        for record, _ in self._inner_with_end(data, offset):
            yield record

    def _truncated_chunk(self, stream: BinaryIO, available: int, offset: int) -> Iterator[Any]:
        self.report.truncated_chunk = True
        body = stream.read(available)
        salvaged_before = self.report.messages
        try:
            compression, records, _, _ = _chunk_parts(body, partial=True)
            data = _decompress_partial(compression, records)
        except Exception as exc:
            self._lose(available + _RECORD_HEAD.size, f"the last chunk is cut short ({exc})")
            return
        used = 0
        for record, end in self._inner_with_end(data, offset):
            used = end
            yield record
        self.report.salvaged = self.report.messages - salvaged_before
        lost = available + _RECORD_HEAD.size
        self._lose(
            lost,
            f"the last chunk (offset {offset}) is cut short; {self.report.salvaged} whole "
            f"message(s) read from it, {len(data) - used} byte(s) of it unreadable",
        )

    def _inner_with_end(self, data: bytes, offset: int) -> Iterator[tuple[Any, int]]:
        position = 0
        size = len(data)
        while position + _RECORD_HEAD.size <= size:
            opcode, length = _RECORD_HEAD.unpack_from(data, position)
            start = position + _RECORD_HEAD.size
            if start + length > size:
                return
            if opcode in (SCHEMA, CHANNEL, MESSAGE):
                record = self._parse(opcode, data[start : start + length], offset)
                if record is not None:
                    yield record, start + length
            position = start + length

    def _lose(self, count: int, why: str) -> None:
        self.report.lost_bytes += count
        self.report.problems.append(why)


def _data_stream(body: bytes) -> Any:
    from mcap.data_stream import ReadDataStream

    return ReadDataStream(BytesIO(body))


def _chunk_parts(body: bytes, partial: bool = False) -> tuple[str, bytes, int, int]:
    """(compression, records bytes, uncompressed CRC, uncompressed size) of a chunk body."""
    _, _, uncompressed_size, crc = _CHUNK_HEAD.unpack_from(body)
    position = _CHUNK_HEAD.size
    (name_length,) = struct.unpack_from("<I", body, position)
    position += 4
    if name_length > 16:
        raise ValueError(f"compression name of {name_length} bytes")
    compression = body[position : position + name_length].decode()
    position += name_length
    (records_length,) = struct.unpack_from("<Q", body, position)
    position += 8
    records = body[position : position + records_length]
    if not partial and len(records) != records_length:
        raise ValueError("its length fields disagree")
    return compression, records, crc, uncompressed_size


def _decompress(compression: str, data: bytes, size: int) -> bytes:
    if compression == "":
        return data
    if compression == "zstd":
        import zstandard

        return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    if compression == "lz4":
        import lz4.frame

        return lz4.frame.decompress(data)
    raise ValueError(f"unknown compression {compression!r}")


def _decompress_partial(compression: str, data: bytes) -> bytes:
    """As much as a streaming decoder gets out of the start of a compressed chunk."""
    if compression == "":
        return data
    if compression == "zstd":
        import zstandard

        return zstandard.ZstdDecompressor().decompressobj().decompress(data)
    if compression == "lz4":
        import lz4.frame

        return lz4.frame.LZ4FrameDecompressor().decompress(data)
    raise ValueError(f"unknown compression {compression!r}")
