"""Interop with ``pyzeros``, an rmw_zenoh implementation we did not write, over real Zenoh.

Each direction is exercised on separate sessions joined through a loopback router: a pyzeros
publisher reaches our subscription and ours reaches a pyzeros subscription; a service call
works both ways; each side's graph shows the other's node, topic and service. pyzeros is
asyncio-based, so its part of every scenario runs in ``asyncio.run`` with deadlines, and every
pyzeros endpoint is closed inside the loop that created it.
"""

import asyncio
import contextlib
import time
from collections.abc import Callable, Coroutine, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest
import pyzeros
from conftest import quick_peer_settings, quick_router, wait_until
from pyzeros.builtin_msgs import Attachment as PzAttachment
from pyzeros.pub import publisher_keyexpr
from pyzeros.utils import rmw_zenoh_gid
from ros2_pyterfaces.cyclone import idl
from ros2_pyterfaces.cyclone.all_msgs import Header, JointState, String, Time
from ros2_pyterfaces.cyclone.service_msgs.msg import ServiceEventInfo

from components.comm import Node, ServiceTimeout
from components.comm.graph import Graph, snapshot
from components.comm.liveliness import Entity, EntityKind
from components.comm.session import SessionSettings
from components.comm.stats import drops
from components.comm.types import registry
from components.messages import msg

STRING = "std_msgs/msg/String"
JOINT_STATE = "sensor_msgs/msg/JointState"
ADD = "example_interfaces/srv/AddTwoInts"


# example_interfaces is not in ros2_pyterfaces; defined here the way its std_srvs are (this
# module has no postponed annotations: cyclonedds_idl resolves them eagerly).
@dataclass
class AddTwoInts_Request(idl.IdlStruct, typename="example_interfaces/srv/AddTwoInts_Request"):
    """Request half of example_interfaces/srv/AddTwoInts."""

    a: idl.types.int64 = 0
    b: idl.types.int64 = 0


@dataclass
class AddTwoInts_Response(idl.IdlStruct, typename="example_interfaces/srv/AddTwoInts_Response"):
    """Response half of example_interfaces/srv/AddTwoInts."""

    sum: idl.types.int64 = 0


@dataclass
class AddTwoInts_Event(idl.IdlStruct, typename="example_interfaces/srv/AddTwoInts_Event"):
    """Service event message (it takes part in the service's type hash)."""

    info: ServiceEventInfo = field(default_factory=ServiceEventInfo)
    request: idl.types.sequence[AddTwoInts_Request, 1] = field(default_factory=list)
    response: idl.types.sequence[AddTwoInts_Response, 1] = field(default_factory=list)


AddTwoInts = idl.make_idl_service(
    AddTwoInts_Request, AddTwoInts_Response, _event_type=AddTwoInts_Event
)


@pytest.fixture
def router_endpoint() -> Iterator[str]:
    """Overrides conftest's: the same real router, without the 0.5 s opening wait."""
    yield from quick_router()


@pytest.fixture
def session_settings(router_endpoint: str) -> SessionSettings:
    """Overrides conftest's: peers that open at once (deliveries are polled anyway)."""
    return quick_peer_settings(router_endpoint)


@pytest.fixture
def pz(open_sessions: Callable[[], Any]) -> Iterator[Any]:
    """A pyzeros node ``/pz/pz_talker`` on its own Zenoh session."""
    node = pyzeros.Session(node="pz_talker", zenoh_session=open_sessions(), namespace="/pz")
    yield node
    node.close()


@pytest.fixture
def ours(open_sessions: Callable[[], Any]) -> Iterator[Node]:
    """Our node ``/ours/probe`` on another session."""
    node = Node(open_sessions(), "probe", "/ours")
    yield node
    node.close()


def run(scenario: Coroutine[Any, Any, Any], timeout: float = 10.0) -> Any:
    """Run one asyncio scenario with a deadline."""
    return asyncio.run(asyncio.wait_for(scenario, timeout))


async def publish_until(publish: Callable[[], None], done: Callable[[], Any]) -> None:
    """Publish until ``done()`` (the first samples may precede route discovery)."""
    while not done():
        publish()
        await asyncio.sleep(0.03)


# --------------------------------------------------------------------------- topics
def test_pyzeros_publisher_reaches_our_subscription(pz: Any, ours: Node) -> None:
    got: list[Any] = []
    sub = ours.subscription("/pz/chatter", STRING, got.append)

    async def scenario() -> Any:
        pub = pyzeros.Pub(String, "chatter", session=pz)  # relative: /pz/chatter
        try:
            assert pub.publisher_keyexpr == sub.key
            await publish_until(lambda: pub.publish(String(data="hello from pyzeros")), lambda: got)
            return bytes(pub.gid)
        finally:
            pub.close()

    gid = run(scenario())
    assert got[0].data == "hello from pyzeros"
    assert sub.last_attachment is not None and sub.last_attachment.gid == gid
    assert drops.count(sub.topic) == 0


def test_pyzeros_joint_state_decodes_field_by_field(pz: Any, ours: Node) -> None:
    got: list[Any] = []
    sub = ours.subscription("/pz/joint_read", JOINT_STATE, got.append)
    sample = JointState(
        header=Header(stamp=Time(sec=17, nanosec=250), frame_id="limb1"),
        name=["j1", "j2", "j3"],
        position=[0.5, -0.25, 3.0],
        velocity=[],
        effort=[1.0, 2.0, 3.0],
    )

    async def scenario() -> None:
        pub = pyzeros.Pub(JointState, "joint_read", session=pz)
        try:
            await publish_until(lambda: pub.publish(sample), lambda: got)
        finally:
            pub.close()

    run(scenario())
    state = got[0]
    assert state.name == ["j1", "j2", "j3"]
    assert state.position.tolist() == [0.5, -0.25, 3.0]
    assert state.velocity.tolist() == []
    assert state.effort.tolist() == [1.0, 2.0, 3.0]
    assert (state.header.stamp.sec, state.header.stamp.nanosec) == (17, 250)
    assert state.header.frame_id == "limb1"
    assert drops.count(sub.topic) == 0


def test_our_publisher_reaches_a_pyzeros_subscription(pz: Any, ours: Node) -> None:
    pub = ours.publisher("/pz/listen", STRING)

    async def scenario() -> tuple[Any, list[Any]]:
        sub = pyzeros.Sub(String, "listen", session=pz)
        raw: list[Any] = []
        raw_sub = pyzeros.sub.RawSub(String, "listen", raw.append, session=pz)
        try:
            assert raw_sub.subscriber_keyexpr == pub.key
            waiter = asyncio.ensure_future(sub.wait_for_value())
            await publish_until(
                lambda: pub.publish(msg(STRING, data="hello from msctl")), waiter.done
            )
            await publish_until(lambda: pub.publish(msg(STRING, data="more")), lambda: raw)
            return waiter.result(), raw
        finally:
            raw_sub.close()
            sub.close()

    received, raw = run(scenario())
    assert received.data == "hello from msctl"
    attachment = PzAttachment.deserialize(b"\x00\x01\x00\x00" + raw[0].attachment.to_bytes())
    assert bytes(attachment.source_gid) == pub.gid == rmw_zenoh_gid(pub.token_key)
    assert int(attachment.gid_length) == 16
    assert int(attachment.sequence_number) >= 1
    assert abs(int(attachment.source_timestamp) - time.time_ns()) < 10e9


def test_data_keys_agree_with_pyzeros(ours: Node) -> None:
    reg = registry()
    for topic in ("joint_read", "/abs/topic", "deep/er"):
        pub = ours.publisher(topic, JOINT_STATE)
        expected = publisher_keyexpr(
            topic,
            "sensor_msgs::msg::dds_::JointState_",
            reg.type_hash(JOINT_STATE),
            namespace="/ours",
            domain_id=0,
        )
        assert pub.key == expected


# --------------------------------------------------------------------------- services
def test_our_client_calls_a_pyzeros_server(pz: Any, ours: Node) -> None:
    client = ours.client("/pz/add_two_ints", ADD)
    request_type = client.request_type()

    def call() -> Any:
        def answered() -> Any:
            try:
                return client.call(request_type(a=19, b=23), timeout=0.5)
            except ServiceTimeout:
                return None

        return wait_until(answered, timeout=8.0)

    async def scenario() -> Any:
        server = pyzeros.Server(AddTwoInts, "add_two_ints", session=pz)
        assert server.service_keyexpr == client.key

        async def serve() -> None:
            async for responder in server.listen_reliable():
                responder.response.sum = responder.request.a + responder.request.b
                responder.send()

        task = asyncio.create_task(serve())
        try:
            return await asyncio.to_thread(call)
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
            server.close()

    assert run(scenario()).sum == 42


def test_pyzeros_client_calls_our_server(pz: Any, ours: Node) -> None:
    parts = registry().service(ADD)
    seen: list[tuple[int, int]] = []

    def add(request: Any) -> Any:
        seen.append((request.a, request.b))
        return msg(parts.response, sum=request.a + request.b)

    ours.service("add_two_ints", ADD, add)  # /ours/add_two_ints

    async def scenario() -> list[Any]:
        client = pyzeros.Client(AddTwoInts, "/ours/add_two_ints", session=pz)
        try:
            await asyncio.wait_for(client.wait_for_service(), 5.0)
            return [
                await asyncio.wait_for(client.call_async(AddTwoInts_Request(a=a, b=b)), 5.0)
                for a, b in ((2, 3), (-7, 2**40))
            ]
        finally:
            client.close()

    responses = run(scenario())
    assert [r.sum for r in responses] == [5, 2**40 - 7]
    assert seen == [(2, 3), (-7, 2**40)]


# --------------------------------------------------------------------------- graph
def test_each_side_sees_the_other_on_the_graph(pz: Any, ours: Node) -> None:
    ours.publisher("/shared/status", STRING)
    ours.service("/ours/halt", "std_srvs/srv/Trigger", lambda r: None)

    async def scenario() -> tuple[Any, list[str]]:
        pub = pyzeros.Pub(String, "chatter", session=pz)
        server = pyzeros.Server(AddTwoInts, "add_two_ints", session=pz)
        try:
            their_tokens = [pz.token_keyexpr, pub.token_keyexpr, server.token_keyexpr]

            # Ours: the live Graph and the one-shot snapshot list pyzeros' node, topic, service.
            def ours_sees_theirs() -> Any:
                shot = snapshot(ours.session, timeout=0.5)
                return (
                    "/pz/pz_talker" in shot.node_names()
                    and "/pz/chatter" in shot.topics()
                    and "/pz/add_two_ints" in shot.services()
                    and shot
                )

            shot = await asyncio.to_thread(wait_until, ours_sees_theirs, 8.0)
            with Graph(ours.session) as graph:
                assert await asyncio.to_thread(
                    graph.wait_for, lambda g: "/pz/chatter" in g.topics(), 5.0
                )

            # Theirs: the liveliness tokens pyzeros' session sees include ours.
            def theirs_sees_ours() -> list[str]:
                keys = [
                    str(r.ok.key_expr)
                    for r in pz.session.liveliness().get("@ros2_lv/0/**", timeout=0.5)
                    if r.ok is not None
                ]
                wanted = ("%ours/probe", "%shared%status", "%ours%halt")
                return keys if all(any(w in k for k in keys) for w in wanted) else []

            keys = await asyncio.to_thread(wait_until, theirs_sees_ours, 8.0)
            return shot, keys, their_tokens
        finally:
            server.close()
            pub.close()

    shot, keys, their_tokens = run(scenario())
    topic = shot.topics()["/pz/chatter"]
    assert topic.types == {STRING} and topic.publishers == 1
    assert topic.publisher_nodes == {"/pz/pz_talker"}
    service = shot.services()["/pz/add_two_ints"]
    assert service.types == {ADD} and service.servers == 1
    # Our parser reads pyzeros' tokens exactly: parse then build gives the same strings.
    for token in their_tokens:
        assert Entity.parse(token).token() == token
    node_entity = Entity.parse(their_tokens[0])
    assert (node_entity.kind, node_entity.node_fqn) == (EntityKind.NODE, "/pz/pz_talker")
    # And pyzeros' session holds our tokens verbatim.
    assert ours.identity.token() in keys
    assert any(
        k.endswith(
            "/MP/%/%ours/probe/%shared%status/std_msgs::msg::dds_::String_/"
            + registry().type_hash(STRING)
            + "/::,10:,:,:,,"
        )
        for k in keys
    )


def test_gids_match_pyzeros_for_real_tokens(ours: Node) -> None:
    pub = ours.publisher("gid_check", STRING)
    sub = ours.subscription("gid_check", STRING, lambda m: None)
    client = ours.client("gid_service", "std_srvs/srv/Trigger")
    assert pub.gid == rmw_zenoh_gid(pub.token_key)
    assert client.gid == rmw_zenoh_gid(client.token_key)
    assert len({pub.gid, client.gid, rmw_zenoh_gid(sub.token_key)}) == 3
    assert np.frombuffer(pub.gid, dtype=np.uint8).shape == (16,)
