"""The attachment rmw_zenoh puts on every sample, query and reply.

Current form (33 bytes, rmw_zenoh >= 0.2.4 on Jazzy): CDR little-endian without header of
``int64 sequence_number, int64 source_timestamp_ns, uint8 gid_length (=16), uint8[16] gid``.

Older form (77 bytes): zenoh's serialized key/value list
``"sequence_number" -> int64, "source_timestamp" -> int64, "source_gid" -> 16 bytes``,
each key and the gid prefixed by a LEB128 length. Accepted on receive, never sent.
"""

from __future__ import annotations

import struct
from typing import NamedTuple

import xxhash

#: The 33-byte form: seq, timestamp, GID length (16), GID.
CURRENT_FORMAT = struct.Struct("<qqB16s")
_CURRENT = CURRENT_FORMAT
CURRENT_SIZE = _CURRENT.size  # 33
_INT64 = struct.Struct("<q")


class AttachmentError(ValueError):
    """Attachment bytes that are neither the current nor the older keyed form."""


class Attachment(NamedTuple):
    """Per-sample metadata: publisher sequence number, source time and publisher GID."""

    sequence_number: int
    source_timestamp: int
    gid: bytes

    def encode(self) -> bytes:
        """The 33-byte current form."""
        return _CURRENT.pack(self.sequence_number, self.source_timestamp, 16, self.gid)

    @classmethod
    def decode(cls, data: bytes) -> Attachment:
        """Parse either form.

        Raises:
            AttachmentError: If the bytes are malformed.
        """
        if len(data) == CURRENT_SIZE:
            seq, stamp, gid_len, gid = _CURRENT.unpack(data)
            if gid_len != 16:
                raise AttachmentError(f"GID length byte is {gid_len}, expected 16")
            return cls(seq, stamp, gid)
        return cls._decode_keyed(data)

    @classmethod
    def _decode_keyed(cls, data: bytes) -> Attachment:
        values: dict[str, object] = {}
        pos = 0
        try:
            while pos < len(data):
                length, pos = _leb128(data, pos)
                key = data[pos : pos + length].decode("ascii")
                pos += length
                if key in ("sequence_number", "source_timestamp"):
                    values[key] = _INT64.unpack_from(data, pos)[0]
                    pos += 8
                elif key == "source_gid":
                    glen, pos = _leb128(data, pos)
                    values[key] = bytes(data[pos : pos + glen])
                    pos += glen
                else:
                    raise AttachmentError(f"unknown attachment key {key!r}")
        except (struct.error, UnicodeDecodeError, IndexError) as exc:
            raise AttachmentError(f"malformed attachment ({len(data)} bytes): {exc}") from exc
        if pos != len(data) or set(values) != {"sequence_number", "source_timestamp", "source_gid"}:
            raise AttachmentError(f"malformed attachment ({len(data)} bytes)")
        gid = values["source_gid"]
        assert isinstance(gid, bytes)
        if len(gid) != 16:
            raise AttachmentError(f"GID is {len(gid)} bytes, expected 16")
        return cls(int(values["sequence_number"]), int(values["source_timestamp"]), gid)  # type: ignore[arg-type]


def encode_keyed(attachment: Attachment) -> bytes:
    """The older 77-byte keyed form (for tests of the receive path)."""

    def field(key: str) -> bytes:
        return bytes([len(key)]) + key.encode()

    return (
        field("sequence_number")
        + _INT64.pack(attachment.sequence_number)
        + field("source_timestamp")
        + _INT64.pack(attachment.source_timestamp)
        + field("source_gid")
        + bytes([16])
        + attachment.gid
    )


def _leb128(data: bytes, pos: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        byte = data[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return value, pos
        shift += 7
        if shift > 63:
            raise AttachmentError("LEB128 length too long")


def gid_of(token_key: str) -> bytes:
    """The GID rmw_zenoh gives an entity: XXH3-128 of its liveliness token, low 64 bits first.

    rmw_zenoh memcpy's the two 64-bit halves in host order; every platform msctl runs on is
    little-endian, so the layout is fixed here.
    """
    digest = xxhash.xxh3_128(token_key.encode()).intdigest()
    return (digest & 0xFFFFFFFFFFFFFFFF).to_bytes(8, "little") + (digest >> 64).to_bytes(
        8, "little"
    )
