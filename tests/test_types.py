"""Type registry: RIHS01 hash vectors (REP 2011), CDR round trips, type names, bad definitions.

Known hashes come from ROS 2 Jazzy; a project-defined type registered from ``.msg`` text is
checked against ``ros2_pyterfaces``, an implementation of the same rules we did not write.
"""

from dataclasses import dataclass, field

import numpy as np
import pytest
from ros2_pyterfaces.cyclone import idl
from ros2_pyterfaces.cyclone.all_msgs import Header, JointState, String

from components.comm.types import (
    TypeRegistry,
    UnknownTypeError,
    dds_type_name,
    normalize_type_name,
    registry,
)
from components.messages import msg

JOINT_STATE_HASH = "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e"
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
ADD_TWO_INTS_HASH = "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"

PROBE_MSG = """\
# A project type touching nested, bounded, fixed and unbounded fields.
std_msgs/Header header
float64 x
string<=8 label   # bounded string
int32[3] counts
uint8[] blob
float32[<=4] few
bool flag
"""

_t = idl.types


@dataclass
class _Probe(idl.IdlStruct, typename="msctl_test/msg/Probe"):
    """The same structure as PROBE_MSG, written with ros2_pyterfaces.

    (No postponed annotations in this module: cyclonedds_idl resolves them eagerly.)
    """

    header: Header = field(default_factory=Header)
    x: _t.float64 = 0.0
    label: _t.bounded_str[8] = ""
    counts: _t.array[_t.int32, 3] = field(default_factory=lambda: [0, 0, 0])
    blob: _t.sequence[_t.uint8] = field(default_factory=list)
    few: _t.sequence[_t.float32, 4] = field(default_factory=list)
    flag: bool = False


@pytest.fixture(scope="module")
def reg() -> TypeRegistry:
    """A private registry, so registrations here never leak into other tests."""
    return TypeRegistry()


@pytest.mark.parametrize(
    ("type_name", "expected"),
    [
        ("sensor_msgs/msg/JointState", JOINT_STATE_HASH),
        ("std_msgs/msg/String", STRING_HASH),
        ("example_interfaces/srv/AddTwoInts", ADD_TWO_INTS_HASH),
    ],
)
def test_known_hash_vectors(reg: TypeRegistry, type_name: str, expected: str) -> None:
    assert reg.type_hash(type_name) == expected


def test_hashes_agree_with_ros2_pyterfaces(reg: TypeRegistry) -> None:
    from ros2_pyterfaces.cyclone.all_srvs import SetBool, Trigger

    assert reg.type_hash("std_msgs/msg/String") == String.hash_rihs01()
    assert reg.type_hash("sensor_msgs/msg/JointState") == JointState.hash_rihs01()
    # Service hashes cover the event message, whose ServiceEventInfo has a char[16].
    assert reg.type_hash("std_srvs/srv/Trigger") == Trigger.hash_rihs01()
    assert reg.type_hash("std_srvs/srv/SetBool") == SetBool.hash_rihs01()


def test_project_type_from_msg_text(reg: TypeRegistry) -> None:
    reg.register_msg("msctl_test/msg/Probe", PROBE_MSG)
    assert reg.known("msctl_test/msg/Probe")
    assert reg.type_hash("msctl_test/msg/Probe") == _Probe.hash_rihs01()
    assert [name for name, _ in reg.fields("msctl_test/msg/Probe")] == [
        "header",
        "x",
        "label",
        "counts",
        "blob",
        "few",
        "flag",
    ]
    # Registering the same name again is a no-op, and the hash is stable.
    reg.register_msg("msctl_test/msg/Probe", PROBE_MSG)
    assert reg.type_hash("msctl_test/msg/Probe") == _Probe.hash_rihs01()


def test_project_service_from_srv_text(reg: TypeRegistry) -> None:
    reg.register_srv("msctl_test/srv/Scale", "float64 factor\n---\nbool ok\nstring why\n")
    parts = reg.service("msctl_test/srv/Scale")
    assert parts.request == "msctl_test/srv/Scale_Request"
    assert parts.response == "msctl_test/srv/Scale_Response"
    assert parts.event == "msctl_test/srv/Scale_Event"
    assert "msctl_test/srv/Scale" in reg.service_names()
    assert reg.type_hash("msctl_test/srv/Scale").startswith("RIHS01_")
    assert reg.type_hash("msctl_test/srv/Scale") != reg.type_hash(parts.request)


def test_a_prepared_type_has_its_codecs_and_hash_made(reg: TypeRegistry) -> None:
    reg.register_srv("msctl_test/srv/Prepared", "int32 a\n---\nint32 b\n")
    reg.prepare("msctl_test/srv/Prepared")
    for part in ("msctl_test/srv/Prepared_Request", "msctl_test/srv/Prepared_Response"):
        assert part in reg._encoders and part in reg._decoders  # made now, not on first use
    assert "msctl_test/srv/Prepared" in reg._hashes
    reg.prepare("msctl_msgs/msg/JointInfo")
    assert "msctl_msgs/msg/JointInfo" in reg._encoders
    with pytest.raises(UnknownTypeError):
        reg.prepare("msctl_test/msg/Nothing")


def test_bundled_types_are_registered() -> None:
    reg = registry()
    for name in (
        "example_interfaces/srv/AddTwoInts",
        "std_srvs/srv/Trigger",
        "std_srvs/srv/SetBool",
        "std_srvs/srv/Empty",
        "msctl_msgs/msg/JointInfo",
    ):
        assert reg.known(name), name
    assert len(reg.type_hash("msctl_msgs/msg/JointInfo")) == len("RIHS01_") + 64


def test_cdr_bytes_match_ros2_pyterfaces(reg: TypeRegistry) -> None:
    reg.register_msg("msctl_test/msg/Probe", PROBE_MSG)
    ours = reg.msg_class("msctl_test/msg/Probe")(
        header=msg("std_msgs/msg/Header"),
        x=1.5,
        label="abc",
        counts=np.array([1, 2, 3], dtype=np.int32),
        blob=np.array([9, 8], dtype=np.uint8),
        few=np.array([0.5], dtype=np.float32),
        flag=True,
    )
    theirs = _Probe(x=1.5, label="abc", counts=[1, 2, 3], blob=[9, 8], few=[0.5], flag=True)
    data = reg.serialize(ours, "msctl_test/msg/Probe")
    assert data[:4] == b"\x00\x01\x00\x00"  # CDR little-endian encapsulation header
    assert data == bytes(theirs.serialize())
    back = _Probe.deserialize(data)
    assert (back.x, back.label, list(back.counts), list(back.blob), back.flag) == (
        1.5,
        "abc",
        [1, 2, 3],
        [9, 8],
        True,
    )


def test_joint_state_round_trip_and_cross_decode() -> None:
    reg = registry()
    state = msg(
        "sensor_msgs/msg/JointState",
        header=msg(
            "std_msgs/msg/Header",
            stamp=msg("builtin_interfaces/msg/Time", sec=12, nanosec=345),
            frame_id="base_link",
        ),
        name=["limb1_j1", "limb1_j2"],
        position=np.array([0.25, -1.5]),
        velocity=np.array([0.0, 2.0]),
        effort=np.array([], dtype=np.float64),
    )
    data = reg.serialize(state, "sensor_msgs/msg/JointState")
    back = reg.deserialize(data, "sensor_msgs/msg/JointState")
    assert back.name == ["limb1_j1", "limb1_j2"]
    assert back.position.tolist() == [0.25, -1.5]
    assert back.velocity.tolist() == [0.0, 2.0]
    assert back.effort.tolist() == []
    assert (back.header.stamp.sec, back.header.stamp.nanosec) == (12, 345)
    assert back.header.frame_id == "base_link"
    other = JointState.deserialize(data)
    assert list(other.name) == ["limb1_j1", "limb1_j2"]
    assert list(other.position) == [0.25, -1.5]
    assert other.header.frame_id == "base_link"
    # And the other way round: their bytes decode with our codec.
    theirs = bytes(String(data="héllo").serialize())
    assert reg.deserialize(theirs, "std_msgs/msg/String").data == "héllo"
    assert reg.serialize(msg("std_msgs/msg/String", data="héllo"), "std_msgs/msg/String") == theirs


def test_service_request_response_round_trip() -> None:
    reg = registry()
    parts = reg.service("example_interfaces/srv/AddTwoInts")
    request = msg(parts.request, a=-3, b=2**40)
    back = reg.deserialize(reg.serialize(request, parts.request), parts.request)
    assert (back.a, back.b) == (-3, 2**40)
    response = msg(parts.response, sum=7)
    assert reg.deserializer(parts.response)(reg.serializer(parts.response)(response)).sum == 7


@pytest.mark.parametrize(
    ("given", "canonical"),
    [
        ("sensor_msgs/msg/JointState", "sensor_msgs/msg/JointState"),
        ("sensor_msgs/JointState", "sensor_msgs/msg/JointState"),
        ("/std_msgs/msg/String/", "std_msgs/msg/String"),
        ("sensor_msgs::msg::dds_::JointState_", "sensor_msgs/msg/JointState"),
        ("std_srvs::srv::dds_::Trigger_", "std_srvs/srv/Trigger"),
        ("std_srvs/srv/Trigger", "std_srvs/srv/Trigger"),
    ],
)
def test_normalize_type_name(given: str, canonical: str) -> None:
    assert normalize_type_name(given) == canonical


def test_dds_type_names() -> None:
    assert dds_type_name("sensor_msgs/msg/JointState") == "sensor_msgs::msg::dds_::JointState_"
    assert dds_type_name("std_srvs/srv/Trigger") == "std_srvs::srv::dds_::Trigger_"
    assert dds_type_name("std_msgs/String") == "std_msgs::msg::dds_::String_"


@pytest.mark.parametrize("bad", ["JointState", "a/b/c/d", "pkg/nope/Name", "pkg::msg::Name"])
def test_malformed_type_names_are_refused(bad: str) -> None:
    with pytest.raises(UnknownTypeError):
        normalize_type_name(bad)


def test_unknown_and_misused_types(reg: TypeRegistry) -> None:
    with pytest.raises(UnknownTypeError, match="sensor_msgs/msg/JointStat"):
        reg.msg_class("sensor_msgs/msg/JointStat")
    with pytest.raises(UnknownTypeError, match="service type"):
        reg.serializer("std_srvs/srv/Trigger")
    with pytest.raises(UnknownTypeError, match="no_such/srv/Thing"):
        reg.service("no_such/srv/Thing")
    assert not reg.known("not a type")


def test_bad_definitions_are_refused(reg: TypeRegistry) -> None:
    with pytest.raises(ValueError, match="msctl_test/msg/Broken"):
        reg.register_msg("msctl_test/msg/Broken", "int32 1bad\n")
    with pytest.raises(ValueError, match="'---'"):
        reg.register_srv("msctl_test/srv/NoSplit", "int32 a\n")
    with pytest.raises(ValueError, match="not a service name"):
        reg.register_srv("msctl_test/msg/Wrong", "int32 a\n---\n")
    assert not reg.known("msctl_test/msg/Broken")
    with pytest.raises(
        ValueError, match=r"unknown type geometry_msgs/msg/Pointt \(field 'where'\)"
    ):
        reg.register_msg("msctl_test/msg/Typo", "geometry_msgs/Pointt where\n")
    with pytest.raises(ValueError, match="msctl_test/msg/Missing"):
        reg.register_msg("msctl_test/msg/Typo2", "Missing[3] items\n")
    assert not reg.known("msctl_test/msg/Typo")
    assert not reg.known("msctl_test/msg/Typo2")


def test_empty_message_gets_the_rosidl_placeholder(reg: TypeRegistry) -> None:
    from ros2_pyterfaces.cyclone.all_srvs import Empty

    reg.register_msg("msctl_test/msg/Nothing", "# only a comment\n")
    assert [n for n, _ in reg.fields("msctl_test/msg/Nothing")] == [
        "structure_needs_at_least_one_member"
    ]
    assert reg.type_hash("std_srvs/srv/Empty") == Empty.hash_rihs01()


def test_the_shipped_jazzy_snapshot_is_the_installed_rosbags_store() -> None:
    """The definitions read from the snapshot are rosbags' own, for the rosbags installed;
    after an upgrade of rosbags this fails until `write_snapshot()` is run again (the
    registry meanwhile reads rosbags directly: slower, never wrong)."""
    import json
    from importlib.metadata import version

    from rosbags.typesys import Stores, get_typestore

    from components.comm.types import JAZZY_SNAPSHOT, jazzy_definitions

    written = json.loads(JAZZY_SNAPSHOT.read_text(encoding="utf-8"))["rosbags"]
    assert written == version("rosbags"), "run components.comm.types.write_snapshot()"
    assert jazzy_definitions() == dict(get_typestore(Stores.ROS2_JAZZY).fielddefs)


def test_a_type_is_made_with_what_it_uses_when_first_encoded() -> None:
    from components.comm.types import TypeRegistry

    types = TypeRegistry()
    assert types.known("sensor_msgs/msg/JointState")
    assert "sensor_msgs/msg/JointState" not in types._store.fielddefs  # data only so far
    encode = types.serializer("sensor_msgs/msg/JointState")
    made = set(types._store.fielddefs)
    assert {"sensor_msgs/msg/JointState", "std_msgs/msg/Header"} <= made
    assert "builtin_interfaces/msg/Time" in made and "geometry_msgs/msg/Twist" not in made
    message = types.msg_class("sensor_msgs/msg/JointState")(
        header=types.msg_class("std_msgs/msg/Header")(
            stamp=types.msg_class("builtin_interfaces/msg/Time")(sec=1, nanosec=2),
            frame_id="base",
        ),
        name=["j1"],
        position=np.array([0.5]),
        velocity=np.array([], dtype=float),
        effort=np.array([], dtype=float),
    )
    back = types.deserializer("sensor_msgs/msg/JointState")(encode(message))
    assert list(back.name) == ["j1"] and back.position[0] == 0.5
