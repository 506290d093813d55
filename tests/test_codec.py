"""The generated CDR codecs (components/comm/codec/) against rosbags' own, type by type.

Every registered message type: random messages encode to rosbags' exact bytes and decode to
equal messages; mutated payloads decode to what rosbags decodes or raise where it raises. The
string-sequence memo (JointState's names) never hands out a stale or shared list; the shape
path (a payload laid out like the last one) reads what the full path would.
"""

from __future__ import annotations

import random
import struct
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from components.comm.codec import memory
from components.comm.types import TypeRegistry, registry
from components.messages import JOINT_STATE, msg

_INTS = {
    "int8": (-(2**7), 2**7 - 1),
    "byte": (-(2**7), 2**7 - 1),
    "uint8": (0, 2**8 - 1),
    "char": (0, 2**8 - 1),
    "octet": (0, 2**8 - 1),
    "int16": (-(2**15), 2**15 - 1),
    "uint16": (0, 2**16 - 1),
    "int32": (-(2**31), 2**31 - 1),
    "uint32": (0, 2**32 - 1),
    "int64": (-(2**63), 2**63 - 1),
    "uint64": (0, 2**64 - 1),
}
_DTYPES = {"byte": "i1", "char": "u1", "octet": "u1", "bool": "?", "float32": "<f4"}


@pytest.fixture(scope="module")
def reg() -> TypeRegistry:
    return registry()


def _random_value(reg: TypeRegistry, desc: Any, rng: random.Random) -> Any:
    node, detail = int(desc[0]), desc[1]
    if node == 1:  # a primitive
        base = detail[0]
        if base == "string":
            return "".join(rng.choice("ab/_\u00e9\u4e2d") for _ in range(rng.randint(0, 9)))
        if base == "bool":
            return rng.random() < 0.5
        if base in _INTS:
            return rng.randint(*_INTS[base])
        if base == "float32":
            return float(np.float32(rng.uniform(-1e3, 1e3)))
        return rng.uniform(-1e9, 1e9)
    if node == 2:  # a nested message
        return _random_message(reg, detail, rng)
    inner, bound = detail
    count = bound if node == 3 else rng.randint(0, bound or 4)
    if int(inner[0]) == 1 and inner[1][0] != "string":
        dtype = _DTYPES.get(inner[1][0], inner[1][0])
        return np.array([_random_value(reg, inner, rng) for _ in range(count)], dtype=dtype)
    return [_random_value(reg, inner, rng) for _ in range(count)]


def _random_message(reg: TypeRegistry, type_name: str, rng: random.Random) -> Any:
    values = [_random_value(reg, desc, rng) for _, desc in reg.fields(type_name)]
    return reg.msg_class(type_name)(*values)


def _same(a: Any, b: Any) -> bool:
    """Equal values of equal types (NaN equal to itself, arrays by dtype and bytes)."""
    if hasattr(a, "__dataclass_fields__"):
        return type(a) is type(b) and all(
            _same(getattr(a, f), getattr(b, f)) for f in a.__dataclass_fields__
        )
    if isinstance(a, np.ndarray):
        return isinstance(b, np.ndarray) and a.dtype == b.dtype and a.tobytes() == b.tobytes()
    if isinstance(a, list):
        return isinstance(b, list) and len(a) == len(b) and all(map(_same, a, b))
    return type(a) is type(b) and (a == b or (a != a and b != b))


def _revalue(reg: TypeRegistry, type_name: str, message: Any, rng: random.Random) -> Any:
    """A message of the same shape (strings, string lists, sequence lengths) as ``message``,
    with new numbers."""
    values = []
    for field, desc in reg.fields(type_name):
        value, node = getattr(message, field), int(desc[0])
        if node == 2:
            value = _revalue(reg, desc[1], value, rng)
        elif isinstance(value, np.ndarray):
            inner = desc[1][0]
            value = np.array([_random_value(reg, inner, rng) for _ in value], dtype=value.dtype)
        elif node == 1 and desc[1][0] != "string":
            value = _random_value(reg, desc, rng)
        values.append(value)
    return reg.msg_class(type_name)(*values)


def test_messages_of_the_last_shape_encode_and_decode_as_rosbags_does(reg: TypeRegistry) -> None:
    rng = random.Random(22)
    for type_name in reg.message_names():
        encode, decode = reg.serializer(type_name), reg.deserializer(type_name)
        first = _random_message(reg, type_name, rng)
        decode(encode(first))  # its shape remembered on both sides
        for _ in range(3):
            message = _revalue(reg, type_name, first, rng)
            expected = bytes(reg._store.serialize_cdr(message, type_name))
            assert encode(message) == expected, type_name
            assert _same(decode(expected), _rosbags_decode(reg, expected, type_name)), type_name


def test_the_encoder_leaves_the_shape_path_for_any_other_shape(reg: TypeRegistry) -> None:
    encode = reg.serializer(JOINT_STATE)
    message = _joint_state(["a", "b"])
    encode(message)
    others = {
        "frame": {"header.frame_id": "base"},
        "a name": {"name": ["a", "c"]},
        "a tuple of names": {"name": ("a", "b")},
        "a length": {"position": np.arange(3.0)},
        "a dtype": {"position": np.arange(2, dtype=np.float32)},
        "a list": {"position": [1.0, 2.5]},
    }
    for what, change in others.items():
        other = _joint_state(["a", "b"])
        for path, value in change.items():
            owner = other.header if path.startswith("header.") else other
            setattr(owner, path.rsplit(".", 1)[-1], value)
        encode(message)
        got = encode(other)
        other.position = np.asarray(other.position, dtype=np.float64)  # as rosbags takes it
        assert got == bytes(reg._store.serialize_cdr(other, JOINT_STATE)), what
    encode(message)
    flat = _joint_state(["a", "b"])
    flat.position = np.zeros((1, 2))  # the same bytes, two dimensions
    with pytest.raises(ValueError, match="dimensions"):
        encode(flat)


def _rosbags_decode(reg: TypeRegistry, data: bytes, type_name: str) -> Any:
    return reg._store.deserialize_cdr(data, type_name)


def test_every_type_encodes_to_rosbags_bytes_and_decodes_alike(reg: TypeRegistry) -> None:
    rng = random.Random(16)
    for type_name in reg.message_names():
        encode, decode = reg.serializer(type_name), reg.deserializer(type_name)
        for _ in range(3):
            message = _random_message(reg, type_name, rng)
            expected = bytes(reg._store.serialize_cdr(message, type_name))
            assert encode(message) == expected, type_name
            decoded = decode(expected)
            assert _same(decoded, _rosbags_decode(reg, expected, type_name)), type_name
            assert _same(decode(expected), decoded), type_name  # memoised paths alike


def test_mutated_payloads_decode_as_rosbags_does_or_raise_where_it_raises(
    reg: TypeRegistry,
) -> None:
    rng = random.Random(13)
    for type_name in reg.message_names():
        decode = reg.deserializer(type_name)
        good = reg.serializer(type_name)(_random_message(reg, type_name, rng))
        for _ in range(12):
            decode(good)  # the good payload's shape remembered: a mutation meets it
            data = bytearray(good)
            kind = rng.randrange(4)
            if kind == 0:
                del data[rng.randint(0, len(data)) :]
            elif kind == 1 and len(data) > 4:
                data[rng.randrange(4, len(data))] = rng.randrange(256)
            elif kind == 2:
                data += bytes(rng.randrange(256) for _ in range(rng.randint(1, 9)))
            elif len(data) > 8:  # a forged count or length
                at = rng.randrange(4, len(data) - 4)
                data[at : at + 4] = rng.choice([b"\xff\xff\xff\x7f", b"\0\0\0\x40", b"\5\0\0\0"])
            payload = bytes(data)
            try:
                expected = _rosbags_decode(reg, payload, type_name)
            except Exception:
                with pytest.raises(Exception):  # noqa: B017 - rosbags raises several kinds
                    decode(payload)
                continue
            assert _same(decode(payload), expected), (type_name, payload.hex())


def _joint_state(names: list[str]) -> Any:
    return msg(
        JOINT_STATE,
        name=names,
        position=np.arange(len(names), dtype=float),
        velocity=np.zeros(0),
        effort=np.zeros(0),
    )


def test_decoded_names_are_fresh_lists_and_follow_the_payload(reg: TypeRegistry) -> None:
    encode, decode = reg.serializer(JOINT_STATE), reg.deserializer(JOINT_STATE)
    first = decode(encode(_joint_state(["a", "b"])))
    first.name.append("mine")  # the caller's list: never what the next decode hands out
    again = decode(encode(_joint_state(["a", "b"])))
    assert again.name == ["a", "b"] and again.name is not first.name
    assert decode(encode(_joint_state(["a", "c"]))).name == ["a", "c"]


def test_the_names_memo_takes_the_count_into_account(reg: TypeRegistry) -> None:
    encode, decode = reg.serializer(JOINT_STATE), reg.deserializer(JOINT_STATE)
    payload = encode(_joint_state(["a", "b"]))
    decode(payload)  # remembered: 2 names
    # The same bytes after a count of 1: the second name is now read as the next field.
    count_at = payload.index(b"\x02\x00\x00\x00\x02\x00\x00\x00a\x00")
    forged = payload[:count_at] + b"\x01" + payload[count_at + 1 :]
    try:
        expected = _rosbags_decode(reg, forged, JOINT_STATE)
    except Exception:
        with pytest.raises(Exception):  # noqa: B017
            decode(forged)
    else:
        assert _same(decode(forged), expected)


def test_encoded_names_follow_a_list_changed_in_place(reg: TypeRegistry) -> None:
    encode = reg.serializer(JOINT_STATE)
    message = _joint_state(["a", "b"])
    encode(message)
    message.name[1] = "changed"
    assert encode(message) == bytes(reg._store.serialize_cdr(message, JOINT_STATE))
    message.name = ("a", "tuple")  # any sequence of strings, as rosbags takes it
    assert encode(message) == bytes(reg._store.serialize_cdr(message, JOINT_STATE))


def test_big_endian_payloads_decode_through_rosbags(reg: TypeRegistry) -> None:
    message = _joint_state(["a", "b"])
    big = bytes(reg._store.serialize_cdr(message, JOINT_STATE, little_endian=False))
    assert big[1] == 0
    assert _same(reg.deserializer(JOINT_STATE)(big), _rosbags_decode(reg, big, JOINT_STATE))


def test_bad_headers_and_shapes_are_refused(reg: TypeRegistry) -> None:
    decode, encode = reg.deserializer(JOINT_STATE), reg.serializer(JOINT_STATE)
    good = encode(_joint_state(["a"]))
    for bad in (b"", b"\x00\x01", b"\x01\x01" + good[2:], b"\x00\x02" + good[2:]):
        with pytest.raises(ValueError, match="encapsulation"):
            decode(bad)
    with pytest.raises(ValueError, match="trailing"):
        decode(good + bytes(8))
    message = _joint_state(["a"])
    message.position = np.zeros((1, 1))
    with pytest.raises(ValueError, match="dimensions"):
        encode(message)


def test_the_shape_path_reads_new_values_and_leaves_on_any_other_byte(reg: TypeRegistry) -> None:
    encode, decode = reg.serializer(JOINT_STATE), reg.deserializer(JOINT_STATE)
    first = _joint_state(["a", "b"])
    first.header.frame_id = "base"
    decode(encode(first))
    again = _joint_state(["a", "b"])  # the same layout, other values
    again.header.frame_id = "base"
    again.header.stamp.sec, again.position = 7, np.array([3.5, -1.0])
    decoded = decode(encode(again))
    assert decoded.header.stamp.sec == 7 and list(decoded.position) == [3.5, -1.0]
    assert decoded.header.frame_id == "base" and decoded.name == ["a", "b"]
    decoded.name.append("mine")  # the caller's list: never the memo's
    assert decode(encode(again)).name == ["a", "b"]
    # The same length, one shape byte other: a name, the frame, a count.
    for names, frame in ((["a", "c"], "base"), (["b", "b"], "base"), (["a", "b"], "bass")):
        other = _joint_state(names)
        other.header.frame_id = frame
        payload = encode(other)
        assert len(payload) == len(encode(again))
        decode(encode(again))
        assert _same(decode(payload), _rosbags_decode(reg, payload, JOINT_STATE))
    payload = encode(again)
    decode(payload)
    at = payload.index(struct.pack("<I4xd", 2, 3.5))  # position's count
    forged = payload[:at] + b"\x03" + payload[at + 1 :]
    with pytest.raises((ValueError, struct.error)):
        decode(forged)


def test_each_stream_remembers_its_own_shape(reg: TypeRegistry) -> None:
    encoders = [reg.serializer(JOINT_STATE, stream=True) for _ in range(2)]
    decoders = [reg.deserializer(JOINT_STATE, stream=True) for _ in range(2)]
    messages = [_joint_state(["a", "b"]), _joint_state(["limb2_a", "limb2_b", "limb2_c"])]
    for _ in range(2):  # interleaved, as two limbs' states arrive
        for encode, decode, message in zip(encoders, decoders, messages, strict=True):
            payload = encode(message)
            assert payload == bytes(reg._store.serialize_cdr(message, JOINT_STATE))
            assert _same(decode(payload), _rosbags_decode(reg, payload, JOINT_STATE))
    # Each remembers the layout of its own stream, not the other's, nor the shared codec's.
    for encode, decode, message, other in zip(
        encoders, decoders, messages, messages[::-1], strict=True
    ):
        memo = memory(decode)
        assert memo[0][0] == len(encode(message)) != len(reg.serializer(JOINT_STATE)(other))
        memo = memory(encode)
        assert message.name in memo[0] and other.name not in memo[0]
    assert reg.deserializer(JOINT_STATE) not in decoders


def test_a_large_payload_is_not_remembered(reg: TypeRegistry) -> None:
    from components.comm.codec import REMEMBER_AT_MOST

    encode = reg.serializer("std_msgs/msg/String", stream=True)
    decode = reg.deserializer("std_msgs/msg/String", stream=True)
    for size in (REMEMBER_AT_MOST, 10):  # a long string is all shape: never kept
        message = msg("std_msgs/msg/String", data="x" * size)
        assert decode(encode(message)).data == message.data
        for codec in (encode, decode):
            memo = memory(codec)
            assert (memo[0][0] in (None, False)) == (size == REMEMBER_AT_MOST)


_LAYOUTS = st.sampled_from(
    [(("a", "b"), "", 2), (("a", "b"), "base", 2), (("a", "c"), "", 2), (("a", "b", "c"), "", 3)]
)
_FLOATS = st.floats(allow_nan=False, width=64)


@given(
    st.lists(
        st.tuples(_LAYOUTS, st.lists(_FLOATS, min_size=3, max_size=3), st.integers(0, 2**31 - 1)),
        min_size=1,
        max_size=12,
    )
)
@settings(max_examples=80, deadline=None)
def test_one_stream_of_changing_layouts_and_values_stays_exact(stream: list[Any]) -> None:
    """Through one stream's codecs, messages whose layout comes and goes (the shape path
    remembering and forgetting in any order) encode to rosbags' bytes and decode alike."""
    reg = registry()
    encode = reg.serializer(JOINT_STATE, stream=True)
    decode = reg.deserializer(JOINT_STATE, stream=True)
    for (names, frame, count), values, sec in stream:
        message = _joint_state(list(names))
        message.header.frame_id, message.header.stamp.sec = frame, sec
        message.position = np.array(values[:count] + [0.5] * (count - len(values)))
        expected = bytes(reg._store.serialize_cdr(message, JOINT_STATE))
        assert encode(message) == expected
        assert _same(decode(expected), _rosbags_decode(reg, expected, JOINT_STATE))
