"""The rmw_zenoh sample attachment (33-byte current form, 77-byte keyed form) and GIDs.

Byte layouts are checked field by field, and against ``pyzeros``, which we did not write.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest
import xxhash
from pyzeros.builtin_msgs import Attachment as PzAttachment
from pyzeros.utils import rmw_zenoh_gid

from components.comm.attachment import (
    CURRENT_SIZE,
    Attachment,
    AttachmentError,
    encode_keyed,
    gid_of,
)

GID = bytes(range(0xA0, 0xB0))
TOKEN = (
    "@ros2_lv/0/7f3b9a0c4d5e6f708192a3b4c5d6e7f8/0/3/MP/%/%/talker/%chatter/"
    "std_msgs::msg::dds_::String_/"
    "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,7:,:,:,,"
)


def test_current_form_layout() -> None:
    data = Attachment(sequence_number=5, source_timestamp=1_700_000_000_123_456_789, gid=GID)
    raw = data.encode()
    assert CURRENT_SIZE == 33
    assert len(raw) == 33
    assert raw[:8] == (5).to_bytes(8, "little")
    assert raw[8:16] == (1_700_000_000_123_456_789).to_bytes(8, "little")
    assert raw[16] == 0x10
    assert raw[17:] == GID
    assert Attachment.decode(raw) == data


def test_current_form_matches_pyzeros() -> None:
    theirs = PzAttachment(
        sequence_number=np.int64(42),
        source_timestamp=np.int64(-7),
        source_gid=np.frombuffer(GID, dtype=np.uint8),
    ).serialize()[4:]
    ours = Attachment(42, -7, GID).encode()
    assert ours == bytes(theirs)
    assert Attachment.decode(bytes(theirs)) == Attachment(42, -7, GID)


def test_keyed_form_is_77_bytes_and_decodes() -> None:
    data = Attachment(sequence_number=2**40 + 3, source_timestamp=123_456_789, gid=GID)
    raw = encode_keyed(data)
    assert len(raw) == 77
    assert raw.startswith(b"\x0fsequence_number")
    assert b"\x10source_timestamp" in raw
    assert raw.endswith(b"\x0asource_gid\x10" + GID)
    assert Attachment.decode(raw) == data


def test_keyed_form_in_another_key_order_decodes() -> None:
    def key(name: str) -> bytes:
        return bytes([len(name)]) + name.encode()

    raw = (
        key("source_gid")
        + b"\x10"
        + GID
        + key("source_timestamp")
        + struct.pack("<q", 99)
        + key("sequence_number")
        + struct.pack("<q", 7)
    )
    assert Attachment.decode(raw) == Attachment(7, 99, GID)


KEYED = encode_keyed(Attachment(1, 2, GID))


@pytest.mark.parametrize(
    ("raw", "why"),
    [
        (b"", "empty"),
        (b"\x00" * 32, "one byte short of the current form"),
        (b"\x00" * 34, "one byte too long"),
        (struct.pack("<qqB16s", 1, 2, 8, GID), "gid length byte is not 16"),
        (KEYED[:-1], "keyed form truncated in the gid"),
        (KEYED[:40], "keyed form truncated mid-key"),
        (KEYED + b"\x00", "trailing byte"),
        (KEYED.replace(b"sequence_number", b"sequence_numbeX"), "unknown key"),
        (KEYED.replace(b"\x0asource_gid\x10", b"\x0asource_gid\x0f")[:-1], "15-byte gid"),
        (b"\xff" * 77, "garbage"),
        (bytes([0x0F]) + b"\xff" * 15 + b"\x00" * 61, "key is not ascii"),
    ],
)
def test_malformed_attachments_raise(raw: bytes, why: str) -> None:
    with pytest.raises(AttachmentError):
        Attachment.decode(raw)


def test_keyed_form_missing_a_key_raises() -> None:
    raw = encode_keyed(Attachment(1, 2, GID))
    without_stamp = raw.replace(b"\x10source_timestamp" + struct.pack("<q", 2), b"")
    with pytest.raises(AttachmentError, match="malformed"):
        Attachment.decode(without_stamp)


def test_gid_is_xxh3_128_of_the_token_low_half_first() -> None:
    gid = gid_of(TOKEN)
    digest = xxhash.xxh3_128(TOKEN.encode()).intdigest()
    assert len(gid) == 16
    assert gid[:8] == (digest & (2**64 - 1)).to_bytes(8, "little")
    assert gid[8:] == (digest >> 64).to_bytes(8, "little")


@pytest.mark.parametrize(
    "token",
    [
        TOKEN,
        TOKEN.replace("MP", "MS"),
        "@ros2_lv/0/aa/1/1/NN/%/%limb1/joint_manager",
        "@ros2_lv/7/aa/1/9/SS/%/%/srv_node/%add_two_ints/"
        "example_interfaces::srv::dds_::AddTwoInts_/RIHS01_e118/::,10:,:,:,,",
        "ünïcode/token",
    ],
)
def test_gid_matches_pyzeros(token: str) -> None:
    assert gid_of(token) == rmw_zenoh_gid(token)


def test_distinct_tokens_give_distinct_gids() -> None:
    assert gid_of(TOKEN) != gid_of(TOKEN.replace("/3/MP/", "/4/MP/"))
