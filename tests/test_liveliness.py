"""Liveliness token strings (build and parse), names (qualify, mangle) and QoS token fields.

Our tokens are compared with those ``pyzeros`` builds for the same identity, and parsed from
strings in the exact form rmw_zenoh (Jazzy) declares them.
"""

from __future__ import annotations

import pytest
from pyzeros import node as pz_node
from pyzeros import pub as pz_pub
from pyzeros import service_common as pz_service
from pyzeros import sub as pz_sub
from pyzeros.qos import QosProfile

from components.comm.liveliness import Entity, EntityKind, TokenError
from components.comm.names import (
    NameError_,
    check_node_name,
    key_name,
    mangle,
    normalize_namespace,
    qualify,
    unmangle,
)
from components.comm.qos import LATCHED, SENSOR, QoS
from components.comm.types import registry

ZID = "7f3b9a0c4d5e6f708192a3b4c5d6e7f8"
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
ADD_HASH = "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"

#: A publisher token as rmw_zenoh_cpp declares it for demo_nodes_cpp's talker (keep last 7).
RMW_TALKER = (
    f"@ros2_lv/0/{ZID}/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/"
    f"{STRING_HASH}/::,7:,:,:,,"
)


def _entity(kind: EntityKind, **changes: object) -> Entity:
    base: dict[str, object] = {
        "domain": 0,
        "zid": ZID,
        "node_id": 3,
        "entity_id": 3 if kind is EntityKind.NODE else 8,
        "kind": kind,
        "namespace": "/limb1",
        "node_name": "joint_manager",
    }
    if kind is not EntityKind.NODE:
        base.update(
            topic="/limb1/joint_read", type_name="std_msgs/msg/String", type_hash=STRING_HASH
        )
    base.update(changes)
    return Entity(**base)  # type: ignore[arg-type]


# --------------------------------------------------------------------------- tokens
def test_node_token_string() -> None:
    token = _entity(EntityKind.NODE).token()
    assert token == f"@ros2_lv/0/{ZID}/3/3/NN/%/%limb1/joint_manager"


def test_publisher_token_string() -> None:
    token = _entity(EntityKind.PUBLISHER, qos=QoS(depth=7).encode()).token()
    assert token == (
        f"@ros2_lv/0/{ZID}/3/8/MP/%/%limb1/joint_manager/%limb1%joint_read/"
        f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,7:,:,:,,"
    )


@pytest.mark.parametrize("kind", list(EntityKind))
def test_tokens_round_trip(kind: EntityKind) -> None:
    entity = _entity(kind, domain=12, enclave="/")
    if kind is not EntityKind.NODE:
        entity = _entity(kind, domain=12, qos=SENSOR.encode())
    assert Entity.parse(entity.token()) == entity


def test_parse_rmw_zenoh_talker_token() -> None:
    entity = Entity.parse(RMW_TALKER)
    assert entity.kind is EntityKind.PUBLISHER
    assert (entity.domain, entity.zid, entity.node_id, entity.entity_id) == (0, ZID, 0, 10)
    assert (entity.namespace, entity.node_name, entity.node_fqn) == ("/", "talker", "/talker")
    assert (entity.topic, entity.type_name, entity.type_hash) == (
        "/chatter",
        "std_msgs/msg/String",
        STRING_HASH,
    )
    assert QoS.decode(entity.qos or "") == QoS(depth=7)
    assert entity.token() == RMW_TALKER
    assert entity.node_key == (ZID, 0)


def test_parse_service_token() -> None:
    token = (
        f"@ros2_lv/0/{ZID}/1/4/SS/%/%demo/adder/%demo%add_two_ints/"
        f"example_interfaces::srv::dds_::AddTwoInts_/{ADD_HASH}/::,10:,:,:,,"
    )
    entity = Entity.parse(token)
    assert entity.kind is EntityKind.SERVICE
    assert entity.topic == "/demo/add_two_ints"
    assert entity.type_name == "example_interfaces/srv/AddTwoInts"
    assert entity.node_fqn == "/demo/adder"


@pytest.mark.parametrize(
    "bad",
    [
        "",
        "@ros2_lv/0/zid/1/1/NN/%/%",  # too short
        "@other/0/zid/1/1/NN/%/%/node",
        "@ros2_lv/x/zid/1/1/NN/%/%/node",  # domain not a number
        "@ros2_lv/0/zid/one/1/NN/%/%/node",
        "@ros2_lv/0/zid/1/1/XX/%/%/node",  # unknown kind
        "@ros2_lv/0/zid/1/1/NN/%/%/node/extra",
        RMW_TALKER.rsplit("/", 1)[0],  # publisher token without its QoS
        RMW_TALKER.replace("std_msgs::msg::dds_::String_", "String"),
    ],
)
def test_malformed_tokens_are_refused(bad: str) -> None:
    with pytest.raises(TokenError):
        Entity.parse(bad)


def test_endpoint_token_needs_topic_type_and_hash() -> None:
    entity = _entity(EntityKind.PUBLISHER, type_hash=None)
    with pytest.raises(TokenError, match="publisher"):
        entity.token()


# --------------------------------------------------------------------------- vs pyzeros
_IDENTITY = {"session": object(), "domain_id": 0, "_zenoh_id": ZID, "_node_id": 3}


def test_node_token_matches_pyzeros() -> None:
    theirs = pz_node.token_keyexpr(
        "joint_manager", namespace="/limb1", _enclave="%", _entity_id=3, **_IDENTITY
    )
    assert _entity(EntityKind.NODE).token() == theirs
    assert Entity.parse(theirs) == _entity(EntityKind.NODE)


@pytest.mark.parametrize(
    ("ours", "theirs"),
    [
        (QoS(), QosProfile()),
        (QoS(depth=7), QosProfile(depth=7)),
        (SENSOR, QosProfile.sensor_data()),
        (LATCHED, QosProfile(durability="transient_local", depth=1)),
        (QoS(history="keep_all"), QosProfile(history="keep_all")),
    ],
)
@pytest.mark.parametrize(
    ("kind", "build"),
    [(EntityKind.PUBLISHER, pz_pub.token_keyexpr), (EntityKind.SUBSCRIPTION, pz_sub.token_keyexpr)],
)
def test_topic_tokens_match_pyzeros(
    ours: QoS, theirs: QosProfile, kind: EntityKind, build: object
) -> None:
    expected = build(  # type: ignore[operator]
        "joint_read",
        "std_msgs::msg::dds_::String_",
        STRING_HASH,
        qos_profile=theirs,
        node_name="joint_manager",
        namespace="/limb1",
        _enclave="%",
        _entity_id=8,
        **_IDENTITY,
    )
    assert _entity(kind, qos=ours.encode()).token() == expected


def test_service_tokens_match_pyzeros() -> None:
    for kind in (EntityKind.SERVICE, EntityKind.CLIENT):
        expected = pz_service.token_keyexpr(
            kind.value,
            name="/limb1/add_two_ints",
            dds_type="example_interfaces::srv::dds_::AddTwoInts_",
            hash=ADD_HASH,
            qos_profile=QosProfile.services(),
            node_name="joint_manager",
            namespace="/limb1",
            _enclave="%",
            _entity_id=8,
            **_IDENTITY,
        )
        ours = _entity(
            kind,
            topic="/limb1/add_two_ints",
            type_name="example_interfaces/srv/AddTwoInts",
            type_hash=registry().type_hash("example_interfaces/srv/AddTwoInts"),
            qos=QoS(depth=10).encode(),
        )
        assert ours.token() == expected


# --------------------------------------------------------------------------- QoS
@pytest.mark.parametrize(
    ("qos", "text"),
    [
        (QoS(), "::,10:,:,:,,"),
        (QoS(depth=42), "::,:,:,:,,"),
        (SENSOR, "2::,5:,:,:,,"),
        (LATCHED, ":1:,1:,:,:,,"),
        (QoS(history="keep_all"), "::2,:,:,:,,"),
        (QoS("best_effort", "transient_local", "keep_last", 3), "2:1:,3:,:,:,,"),
    ],
)
def test_qos_encode_and_decode(qos: QoS, text: str) -> None:
    assert qos.encode() == text
    assert QoS.decode(text) == (
        qos if qos.history == "keep_last" else QoS(history="keep_all", depth=42)
    )


@pytest.mark.parametrize(
    "profile",
    [
        QosProfile(),
        QosProfile.sensor_data(),
        QosProfile.services(),
        QosProfile(depth=42),
        QosProfile(reliability="best_effort", durability="transient_local", depth=1),
        QosProfile(deadline=(1, 500), lifespan=2.0, liveliness="manual_by_topic"),
    ],
)
def test_qos_decodes_pyzeros_encoding(profile: QosProfile) -> None:
    qos = QoS.decode(profile.encode())
    assert qos.reliability == ("best_effort" if profile.reliability == 2 else "reliable")
    assert qos.durability == ("transient_local" if profile.durability == 1 else "volatile")
    assert qos.depth == profile.depth
    if profile.deadline == QosProfile().deadline:
        # What msctl honours (no deadline, lifespan, liveliness) re-encodes identically.
        assert qos.encode() == profile.encode()


@pytest.mark.parametrize("bad", ["", "::,10:,:,", "a:b:c:d:e:f:g", "::,ten:,:,:,,"])
def test_malformed_qos_is_refused(bad: str) -> None:
    with pytest.raises(ValueError):
        QoS.decode(bad)


def test_invalid_qos_values_are_refused() -> None:
    with pytest.raises(ValueError, match="reliability"):
        QoS(reliability="sometimes")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="durability"):
        QoS(durability="forever")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="history"):
        QoS(history="keep_some")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="depth"):
        QoS(depth=0)
    assert LATCHED.latched and not SENSOR.latched


# --------------------------------------------------------------------------- names
@pytest.mark.parametrize(
    ("name", "namespace", "node", "expected"),
    [
        ("joint_set", "/limb1", None, "/limb1/joint_set"),
        ("joint_set", "limb1", None, "/limb1/joint_set"),
        ("joint_set", "/", None, "/joint_set"),
        ("joint_set", "", None, "/joint_set"),
        ("/clock", "/limb1", None, "/clock"),
        ("/clock/", "/limb1", None, "/clock"),
        ("a/b", "/ns/deep/", None, "/ns/deep/a/b"),
        ("~/status", "/limb1", "joint_manager", "/limb1/joint_manager/status"),
        ("~", "/", "probe", "/probe"),
    ],
)
def test_qualify(name: str, namespace: str, node: str | None, expected: str) -> None:
    assert qualify(name, namespace, node) == expected


@pytest.mark.parametrize(
    ("name", "namespace", "node", "fragment"),
    [
        ("", "/", None, "empty"),
        ("/", "/", None, "empty"),
        ("1joint", "/", None, "1joint"),
        ("joint-set", "/", None, "joint-set"),
        ("ok", "/bad ns", None, "bad ns"),
        ("~/status", "/", None, "private"),
        ("a//b", "/", None, "//"),
        ("ok", "/ns//deep", None, "//"),
    ],
)
def test_qualify_refuses_bad_names(
    name: str, namespace: str, node: str | None, fragment: str
) -> None:
    with pytest.raises(NameError_, match=fragment):
        qualify(name, namespace, node)


def test_mangle_namespace_and_keys() -> None:
    assert mangle("/limb1/joint_read") == "%limb1%joint_read"
    assert unmangle(mangle("/a/b/c")) == "/a/b/c"
    assert normalize_namespace("%") == "/"
    assert normalize_namespace("limb1/") == "/limb1"
    assert key_name("/limb1/joint_read") == "limb1/joint_read"
    assert check_node_name("joint_manager") == "joint_manager"
    with pytest.raises(NameError_, match="node name"):
        check_node_name("joint manager")
