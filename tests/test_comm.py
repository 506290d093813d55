"""The data plane over real Zenoh sessions on loopback: topics, bad input, QoS, services, graph,
and session settings.

Every session joins the per-test router of ``conftest.py`` (random port, multicast off) and is
closed at teardown. Deliveries are polled with deadlines, never waited for with fixed sleeps.
"""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh
from conftest import free_port, quick_peer_settings, quick_router, wait_until

from components.comm import LATCHED, SENSOR, Node, QoS, ServiceError, ServiceTimeout
from components.comm.attachment import Attachment, encode_keyed
from components.comm.graph import NODE_TOKENS, Graph, snapshot
from components.comm.liveliness import EntityKind, ask_tokens, follow_tokens
from components.comm.services import service_key
from components.comm.session import (
    SessionConfigError,
    SessionOpenError,
    SessionSettings,
    open_session,
)
from components.comm.stats import DropStats, drops
from components.comm.topics import data_key
from components.comm.types import registry
from components.messages import msg

STRING = "std_msgs/msg/String"
ADD = "example_interfaces/srv/AddTwoInts"
_names = itertools.count()


def unique(prefix: str) -> str:
    """A topic name no other test uses (drop counters are per process, keyed by topic)."""
    return f"/{prefix}_{next(_names)}_{int(time.monotonic() * 1000) % 100000}"


def text(data: str) -> Any:
    return msg(STRING, data=data)


def send_until(send: Callable[[], None], done: Callable[[], Any], timeout: float = 5.0) -> Any:
    """Send repeatedly until ``done()``: the first sample may precede route discovery."""

    def attempt() -> Any:
        if not done():
            send()
            time.sleep(0.03)
        return done()

    return wait_until(attempt, timeout)


@pytest.fixture
def router_endpoint() -> Iterator[str]:
    """Overrides conftest's: the same real router, without the 0.5 s opening wait."""
    yield from quick_router()


@pytest.fixture
def session_settings(router_endpoint: str) -> SessionSettings:
    """Overrides conftest's: peers that open at once (deliveries are polled anyway)."""
    return quick_peer_settings(router_endpoint)


@pytest.fixture
def pair(open_sessions: Callable[[], Any]) -> tuple[Node, Node]:
    """Two nodes on two sessions (so every sample crosses the router)."""
    talker = Node(open_sessions(), "talker", "/test")
    listener = Node(open_sessions(), "listener", "/test")
    yield talker, listener
    talker.close()
    listener.close()


# --------------------------------------------------------------------------- topics
def test_publish_and_receive(pair: tuple[Node, Node]) -> None:
    talker, listener = pair
    got: list[Any] = []
    sub = listener.subscription("chatter", STRING, got.append)
    pub = talker.publisher("chatter", STRING)
    assert pub.topic == sub.topic == "/test/chatter"
    assert pub.key == (
        "0/test/chatter/std_msgs::msg::dds_::String_/"
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
    )
    send_until(lambda: pub.publish(text("hello")), lambda: got)
    assert got[-1].data == "hello"
    first = sub.last_attachment
    assert first is not None and first.gid == pub.gid
    pub.publish(text("again"))
    wait_until(lambda: got[-1].data == "again")
    assert sub.last_attachment is not None
    assert sub.last_attachment.sequence_number == first.sequence_number + 1
    assert abs(sub.last_attachment.source_timestamp - time.time_ns()) < 5e9
    assert sub.received == len(got)


def test_raw_subscription_gets_cdr_bytes(pair: tuple[Node, Node]) -> None:
    talker, listener = pair
    got: list[bytes] = []
    listener.subscription("raw", STRING, got.append, raw=True)
    pub = talker.publisher("raw", STRING)
    send_until(lambda: pub.publish(text("bytes")), lambda: got)
    assert got[-1] == registry().serialize(text("bytes"), STRING)


def test_bad_input_is_counted_and_dropped_while_good_samples_arrive(
    pair: tuple[Node, Node],
) -> None:
    talker, listener = pair
    topic = unique("bad_input")
    got: list[str] = []
    sub = listener.subscription(topic, STRING, lambda m: got.append(m.data))
    pub = talker.publisher(topic, STRING)
    send_until(lambda: pub.publish(text("warm-up")), lambda: got)
    session = talker.session
    good_payload = registry().serialize(text("good"), STRING)
    good_attachment = Attachment(1, time.time_ns(), pub.gid).encode()
    base = dict(drops.snapshot().get(sub.topic, {}))

    session.put(pub.key, b"\x00\x01\x00\x00\xff\xff\xff\x7f", attachment=good_attachment)
    session.put(pub.key, b"garbage", attachment=good_attachment)
    session.put(pub.key, good_payload, attachment=b"\x01\x02\x03")
    session.put(pub.key, good_payload, attachment=b"\x00" * 33)  # gid length byte 0
    # A publisher of another type on the topic: counted once, from its token, naming its node.
    wrong = talker.publisher(topic, "std_msgs/msg/Int32")
    wrong.publish(registry().msg_class("std_msgs/msg/Int32")(data=5))
    pub.publish(text("still fine"))

    def counted(reason: str) -> int:
        return drops.count(sub.topic, reason) - base.get(reason, 0)

    wait_until(lambda: "still fine" in got)
    wait_until(
        lambda: (
            (counted("malformed"), counted("bad_attachment"), counted("wrong_type")) == (2, 2, 1)
        )
    )
    assert got == ["warm-up"] * (len(got) - 1) + ["still fine"]
    assert sub.received == len(got)


def test_callback_exception_is_counted_and_the_subscription_keeps_going(
    pair: tuple[Node, Node],
) -> None:
    talker, listener = pair
    topic = unique("flaky")
    seen: list[str] = []

    def handler(message: Any) -> None:
        seen.append(message.data)
        if message.data == "boom":
            raise RuntimeError("handler bug")

    sub = listener.subscription(topic, STRING, handler)
    pub = talker.publisher(topic, STRING)
    send_until(lambda: pub.publish(text("boom")), lambda: seen)
    pub.publish(text("after"))
    wait_until(lambda: "after" in seen)
    assert drops.count(sub.topic, "callback_error") == seen.count("boom")


def test_keyed_77_byte_attachment_is_accepted_over_zenoh(pair: tuple[Node, Node]) -> None:
    talker, listener = pair
    topic = unique("keyed")
    got: list[str] = []
    sub = listener.subscription(topic, STRING, lambda m: got.append(m.data))
    key = data_key(0, topic, STRING)
    payload = registry().serialize(text("old rmw_zenoh"), STRING)
    gid = bytes(range(16))
    keyed = encode_keyed(Attachment(77, 1_234_567_890, gid))
    assert len(keyed) == 77
    send_until(lambda: talker.session.put(key, payload, attachment=keyed), lambda: got)
    assert got[0] == "old rmw_zenoh"
    assert sub.last_attachment == Attachment(77, 1_234_567_890, gid)
    assert drops.count(sub.topic) == 0


def test_latched_topic_reaches_a_late_subscriber(pair: tuple[Node, Node]) -> None:
    talker, listener = pair
    topic = unique("latched")
    pub = talker.publisher(topic, STRING, LATCHED)
    for n in range(3):
        pub.publish(text(f"plan {n}"))
    got: list[str] = []
    listener.subscription(topic, STRING, lambda m: got.append(m.data), LATCHED)
    wait_until(lambda: got, timeout=5.0)
    assert got == ["plan 2"]  # depth 1: only the newest is kept for late joiners
    pub.publish(text("plan 3"))
    wait_until(lambda: got[-1] == "plan 3")


@pytest.mark.parametrize(
    ("qos", "reliability", "congestion", "token_qos"),
    [
        (QoS(), zenoh.Reliability.RELIABLE, zenoh.CongestionControl.BLOCK, "::,10:,:,:,,"),
        (SENSOR, zenoh.Reliability.BEST_EFFORT, zenoh.CongestionControl.DROP, "2::,5:,:,:,,"),
    ],
)
def test_reliable_and_best_effort_publishers(
    pair: tuple[Node, Node], qos: QoS, reliability: Any, congestion: Any, token_qos: str
) -> None:
    talker, listener = pair
    topic = unique("qos")
    got: list[str] = []
    listener.subscription(topic, STRING, lambda m: got.append(m.data), qos)
    pub = talker.publisher(topic, STRING, qos)
    assert pub._zpub.reliability == reliability
    assert pub._zpub.congestion_control == congestion
    assert pub.token_key.endswith("/" + token_qos)
    send_until(lambda: pub.publish(text("x")), lambda: got)
    for n in range(50):
        pub.publish(text(str(n)))
    wait_until(lambda: got[-1] == "49")  # loopback loses nothing, even best effort


def test_close_is_idempotent_and_stops_delivery(pair: tuple[Node, Node]) -> None:
    talker, listener = pair
    topic = unique("closing")
    got: list[str] = []
    sub = listener.subscription(topic, STRING, lambda m: got.append(m.data))
    pub = talker.publisher(topic, STRING)
    send_until(lambda: pub.publish(text("one")), lambda: got)
    sub.close()
    sub.close()
    count = len(got)
    for _ in range(5):
        pub.publish(text("after close"))
    # The publisher is still fine; nothing reaches the closed subscription.
    # (The topic may be missing from one snapshot altogether: no token of it answered yet.)
    wait_until(
        lambda: getattr(snapshot(listener.session).topics().get(sub.topic), "subscribers", 0) == 0
    )
    assert len(got) == count
    listener.close()
    with pytest.raises(RuntimeError, match="closed"):
        listener.publisher(topic, STRING)


# --------------------------------------------------------------------------- services
def test_service_round_trip_and_errors(pair: tuple[Node, Node]) -> None:
    caller, server_node = pair
    parts = registry().service(ADD)

    def add(request: Any) -> Any:
        if request.a < 0:
            raise ValueError("negative a")
        return msg(parts.response, sum=request.a + request.b)

    server = server_node.service("add_two_ints", ADD, add)
    client = caller.client("add_two_ints", ADD)
    assert server.key == client.key == service_key(0, "/test/add_two_ints", ADD)
    assert server.key.endswith(
        "/example_interfaces::srv::dds_::AddTwoInts_/"
        "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"
    )
    request_type = client.request_type()

    def answered() -> Any:
        try:
            return client.call(request_type(a=2, b=40), timeout=0.5)
        except ServiceTimeout:
            return None

    assert wait_until(answered).sum == 42
    with pytest.raises(ServiceError, match="negative a"):
        client.call(request_type(a=-1, b=0), timeout=2)
    assert client.call(request_type(a=1, b=2**40), timeout=2).sum == 2**40 + 1


def test_deferred_service_answers_later(pair: tuple[Node, Node]) -> None:
    caller, server_node = pair
    parts = registry().service(ADD)

    def later(pending: Any) -> None:
        threading.Timer(
            0.05, pending.reply, args=(msg(parts.response, sum=pending.request.a * 10),)
        ).start()

    server_node.service("/deferred_add", ADD, later, deferred=True)
    client = caller.client("/deferred_add", ADD)

    def answered() -> Any:
        try:
            return client.call(client.request_type()(a=7, b=0), timeout=0.5)
        except ServiceTimeout:
            return None

    assert wait_until(answered).sum == 70


def test_a_queue_only_server_is_called_on_zenohs_thread_and_urgent_calls_are_answered(
    pair: tuple[Node, Node],
) -> None:
    caller, server_node = pair
    threads: dict[str, threading.Thread] = {}
    answer = msg("std_srvs/srv/Trigger_Response", success=True, message="held")

    def queued(pending: Any) -> None:
        threads.setdefault("queue_only", threading.current_thread())
        threading.Thread(target=pending.reply, args=(answer,)).start()  # answered elsewhere

    def own_thread(pending: Any) -> None:
        threads.setdefault("own", threading.current_thread())
        pending.reply(answer)

    trigger = "std_srvs/srv/Trigger"
    server_node.service("/q/halt", trigger, queued, deferred=True, queue_only=True, urgent=True)
    server_node.service("/q/slow", trigger, own_thread, deferred=True)
    halt = caller.client("/q/halt", trigger)
    slow = caller.client("/q/slow", trigger)

    def answered(client: Any) -> Any:
        call = client.call_async(client.request_type()(), timeout=0.5, urgent=True)
        try:
            return call.result()
        except ServiceError:
            return None

    assert wait_until(lambda: answered(halt), 30.0).message == "held"
    assert wait_until(lambda: answered(slow), 30.0).message == "held"
    # Zenoh's network thread is not one Python started; a handler that may block gets a
    # Python thread of its own.
    assert isinstance(threads["queue_only"], threading._DummyThread)
    assert not isinstance(threads["own"], threading._DummyThread)


def test_an_unannounced_client_calls_at_once_and_shows_on_the_graph_when_announced(
    pair: tuple[Node, Node], open_sessions: Callable[[], Any]
) -> None:
    caller, server_node = pair
    trigger = "std_srvs/srv/Trigger"
    server_node.service("/quiet/halt", trigger, lambda r: msg("std_srvs/srv/Trigger_Response"))
    with Graph(open_sessions()) as graph:
        assert graph.wait_for(lambda g: "/quiet/halt" in g.services(), 30.0)
        client = caller.client("/quiet/halt", trigger, announce=False)

        def answered() -> Any:
            try:
                return client.call(client.request_type()(), timeout=0.5)
            except ServiceTimeout:
                return None

        assert wait_until(answered, 30.0) is not None
        assert graph.services()["/quiet/halt"].clients == 0
        client.announce()
        client.announce()  # idempotent
        assert graph.wait_for(lambda g: g.services()["/quiet/halt"].clients == 1, 30.0)
        client.close()
        assert graph.wait_for(lambda g: g.services()["/quiet/halt"].clients == 0, 30.0)
        client.announce()  # closed: nothing is declared again
        # A marker declared after it on the same session arrives after anything it declared.
        caller.client("/quiet/marker", trigger)
        assert graph.wait_for(lambda g: "/quiet/marker" in g.services(), 30.0)
        assert graph.services()["/quiet/halt"].clients == 0


@pytest.mark.timeout(120)  # a call that never ends fails here, however loaded the machine
def test_service_without_server_times_out(pair: tuple[Node, Node]) -> None:
    caller, _ = pair
    client = caller.client("/nobody_home", "std_srvs/srv/Trigger")
    with pytest.raises(ServiceTimeout, match="/nobody_home"):
        client.call(msg("std_srvs/srv/Trigger_Request"), timeout=0.3)


def test_service_refuses_requests_with_bad_attachments(pair: tuple[Node, Node]) -> None:
    caller, server_node = pair
    server = server_node.service(
        unique("guarded"), "std_srvs/srv/Trigger", lambda r: msg("std_srvs/srv/Trigger_Response")
    )
    payload = registry().serialize(
        msg("std_srvs/srv/Trigger_Request"), "std_srvs/srv/Trigger_Request"
    )

    def error_for(attachment: bytes | None) -> str:
        def ask() -> str | None:
            for reply in caller.session.get(
                server.key,
                payload=payload,
                attachment=attachment,
                target=zenoh.QueryTarget.ALL_COMPLETE,
                timeout=0.5,
            ):
                if reply.err is not None:
                    return reply.err.payload.to_bytes().decode()
            return None

        return wait_until(ask)

    assert "without attachment" in error_for(None)
    assert "bad attachment" in error_for(b"\x01\x02")
    assert drops.count(server.service, "bad_attachment") >= 2


# --------------------------------------------------------------------------- graph
def test_graph_snapshot_and_live_view(open_sessions: Callable[[], Any]) -> None:
    observer = open_sessions()
    changes: list[tuple[EntityKind, bool]] = []
    with Graph(observer, on_change=lambda e, alive: changes.append((e.kind, alive))) as graph:
        node = Node(open_sessions(), "probe", "/limb1")
        node.publisher("joint_read", "sensor_msgs/msg/JointState", SENSOR)
        node.subscription("joint_set", "sensor_msgs/msg/JointState", lambda m: None)
        node.service("halt", "std_srvs/srv/Trigger", lambda r: None)
        node.client("/other/halt", "std_srvs/srv/Trigger")
        assert graph.wait_for(
            lambda g: "/limb1/halt" in g.services() and "/other/halt" in g.services(), 5.0
        )
        assert graph.wait_for(lambda g: "/limb1/joint_set" in g.topics(), 5.0)
        # A query right after the tokens appear can miss them (routes settle a moment later).
        shot = wait_until(lambda: (s := snapshot(observer)) and len(s.entities()) >= 5 and s)
        for view in (graph, shot):
            assert "/limb1/probe" in view.node_names()
            topics = view.topics()
            assert topics["/limb1/joint_read"].types == {"sensor_msgs/msg/JointState"}
            assert topics["/limb1/joint_read"].publishers == 1
            assert topics["/limb1/joint_read"].publisher_nodes == {"/limb1/probe"}
            assert topics["/limb1/joint_set"].subscribers == 1
            services = view.services()
            assert (services["/limb1/halt"].servers, services["/limb1/halt"].clients) == (1, 0)
            assert services["/limb1/halt"].server_nodes == {"/limb1/probe"}
            assert (services["/other/halt"].servers, services["/other/halt"].clients) == (0, 1)
        info = next(n for n in shot.nodes() if n.fqn == "/limb1/probe")
        assert (info.namespace, info.name, info.zid) == ("/limb1", "probe", node.zid)
        node.close()
        assert graph.wait_for(lambda g: "/limb1/probe" not in g.node_names(), 5.0)
        assert graph.wait_for(lambda g: "/limb1/joint_read" not in g.topics(), 5.0)
    assert (EntityKind.NODE, True) in changes
    assert (EntityKind.NODE, False) in changes
    assert (EntityKind.SERVICE, True) in changes


def test_a_graph_of_nodes_only_takes_no_endpoint_token(open_sessions: Callable[[], Any]) -> None:
    observer = open_sessions()
    kinds: list[EntityKind] = []
    with Graph(observer, on_change=lambda e, _alive: kinds.append(e.kind), tokens=NODE_TOKENS):
        node = Node(open_sessions(), "probe", "/limb1")
        node.publisher("joint_read", "sensor_msgs/msg/JointState", SENSOR)
        node.service("halt", "std_srvs/srv/Trigger", lambda r: None)
        with Graph(observer) as whole:
            # Once a graph of everything has the endpoints, the nodes-only one had its chance.
            assert whole.wait_for(lambda g: "/limb1/halt" in g.services(), 30.0)
        wait_until(lambda: EntityKind.NODE in kinds, 30.0, "the node token")
        node.close()
    assert set(kinds) == {EntityKind.NODE}


def test_graph_ignores_foreign_tokens(open_sessions: Callable[[], Any]) -> None:
    session = open_sessions()
    token = session.liveliness().declare_token("@ros2_lv/0/zid/1/1/XX/%/%/strange")
    node = Node(session, "normal")
    try:
        before = drops.count("@ros2_lv", "bad_token")
        shot = wait_until(lambda: (s := snapshot(session)) and "/normal" in s.node_names() and s)
        assert [n.fqn for n in shot.nodes()] == ["/normal"]
        assert drops.count("@ros2_lv", "bad_token") > before
    finally:
        node.close()
        token.undeclare()


def test_a_graph_query_answered_past_256_by_the_sessions_own_tokens_returns_them_all(
    open_sessions: Callable[[], Any],
) -> None:
    # A session answers a liveliness query from what it knows inside ``get`` itself; read
    # through Zenoh's default channel (256 answers), the 257th blocked that call for good,
    # as a peer of two_dragons (625 tokens) did.
    session = open_sessions()
    nodes = [Node(session, f"many_{i}", domain=5) for i in range(400)]
    expected = {f"/many_{i}" for i in range(400)}
    result: list[Any] = []

    def ask() -> None:
        result.append(
            wait_until(lambda: snapshot(session, domain=5).node_names() == expected, 30.0)
        )

    try:
        asking = threading.Thread(target=ask, daemon=True)
        asking.start()
        asking.join(60.0)
        assert not asking.is_alive(), "the graph query never ended"
        assert result == [True]
        assert len(ask_tokens(session, "@ros2_lv/5/**", 5.0)) == 400
    finally:
        for node in nodes:
            node.close()


def test_a_peers_graph_questions_get_the_whole_answer_every_time(
    open_sessions: Callable[[], Any],
) -> None:
    # Asked of a peer itself, Zenoh 1.10 answered with 0 to 100 of these 100 tokens from one
    # query to the next (its own tokens!); through a client of the router, all of them.
    session = open_sessions()
    other = open_sessions()
    nodes = [Node(other, f"known_{i}", domain=6) for i in range(100)]
    try:
        # A query ends once answered: the generous bound costs a quick machine nothing.
        wait_until(lambda: len(ask_tokens(session, "@ros2_lv/6/**", 5.0)) == 100, 30.0)
        answers = [len(ask_tokens(s, "@ros2_lv/6/**", 5.0)) for s in (session, other) * 10]
        assert answers == [100] * 20
    finally:
        for node in nodes:
            node.close()


def test_a_client_asks_through_itself_until_it_follows_tokens(router_endpoint: str) -> None:
    from components.comm.session import graph_questions

    client = open_session(SessionSettings(mode="client", connect=(router_endpoint,)))
    try:
        with graph_questions(client) as asked:
            assert asked is client
        follower = follow_tokens(client, "@ros2_lv/7/**", lambda _sample: None)
        try:
            with graph_questions(client) as asked:
                assert asked is not client and str(asked.zid()) != str(client.zid())
            assert asked.is_closed()
        finally:
            follower.undeclare()
    finally:
        client.close()


def test_a_session_asking_itself_hears_each_of_its_own_tokens_once(router_endpoint: str) -> None:
    # Its own tables and the router both answer with its tokens: Zenoh delivered each twice.
    client = open_session(SessionSettings(mode="client", connect=(router_endpoint,)))
    node = Node(client, "self_asker", domain=8)
    publisher = node.publisher("/mine", "std_msgs/msg/String")
    try:
        wait_until(lambda: len(ask_tokens(client, "@ros2_lv/8/**", 5.0)) == 2, 30.0)
        keys = ask_tokens(client, "@ros2_lv/8/**", 5.0)
        assert len(keys) == len(set(keys)) == 2
    finally:
        publisher.close()
        node.close()
        client.close()


def test_a_client_that_follows_publisher_tokens_gets_the_whole_graph_every_time(
    router_endpoint: str,
) -> None:
    # Asked of such a client itself, Zenoh 1.10 ended the query before resending the
    # publisher tokens it had already sent for the subscriber: 100 of 159 tokens (no
    # publisher) in 3 of 20 loaded `msctl topic echo` error paths.
    settings = SessionSettings(mode="client", connect=(router_endpoint,))
    others = open_session(settings)
    nodes = [Node(others, f"known_{i}", domain=7) for i in range(20)]
    publishers = [n.publisher(f"/t{i}", "std_msgs/msg/String") for i, n in enumerate(nodes)]
    asker = open_session(settings)
    node = Node(asker, "asker", domain=7)

    def answer() -> set[str]:
        return set(ask_tokens(asker, "@ros2_lv/7/**", 5.0))

    try:
        node.subscription("/t0", "std_msgs/msg/String", lambda _m: None)  # follows MP tokens
        # The nodes and publishers; the asker's node and subscription.
        wait_until(lambda: len(answer()) == 20 + 20 + 1 + 1, 30.0)
        everything = answer()
        misses = [len(everything - answer()) for _ in range(30)]
        assert misses == [0] * 30
    finally:
        node.close()
        asker.close()
        for publisher in publishers:
            publisher.close()
        for other in nodes:
            other.close()
        others.close()


def test_a_closed_peer_is_forgotten_by_the_graph_questions(
    session_settings: SessionSettings,
) -> None:
    from components.comm import session as session_module

    first = open_session(session_settings)
    first_zid = str(first.zid())
    assert first_zid in session_module._QUESTION_ROUTES
    first.close()
    second = open_session(session_settings)  # a later peer prunes what closed since
    try:
        assert first_zid not in session_module._QUESTION_ROUTES
        assert str(second.zid()) in session_module._QUESTION_ROUTES
    finally:
        second.close()


def test_a_joining_or_launched_process_is_a_client_of_the_router_unless_told_otherwise() -> None:
    env = {"MSCTL_ZENOH_CONNECT": "tcp/127.0.0.1:7999", "MSCTL_ZENOH_LISTEN": "tcp/0.0.0.0:0"}
    joining = SessionSettings.joining(env)
    assert (joining.mode, joining.connect, joining.listen) == (
        "client",
        ("tcp/127.0.0.1:7999",),
        (),
    )
    # So is a component the launcher started; a process opening a session of its own with
    # the defaults is a peer; MSCTL_ZENOH_MODE wins for all.
    launched = SessionSettings.launched(env)
    assert (launched.mode, launched.connect, launched.listen) == joining[:3]
    assert SessionSettings.from_env(env).mode == "peer"
    for settings in (SessionSettings.joining, SessionSettings.launched):
        peer = settings({**env, "MSCTL_ZENOH_MODE": "peer"})
        assert (peer.mode, peer.listen) == ("peer", ("tcp/0.0.0.0:0",))


def test_domains_are_separate(open_sessions: Callable[[], Any]) -> None:
    session = open_sessions()
    node = Node(session, "in_seven", domain=7)
    pub = node.publisher("/chatter", STRING)
    try:
        assert pub.key.startswith("7/chatter/")
        wait_until(lambda: "/in_seven" in snapshot(session, domain=7).node_names())
        assert "/in_seven" not in snapshot(session, domain=0, timeout=0.3).node_names()
    finally:
        node.close()


# --------------------------------------------------------------------------- sessions
def test_settings_from_environment(tmp_path: Path) -> None:
    config = tmp_path / "zenoh.json5"
    config.write_text("{ scouting: { delay: 50 } }")
    settings = SessionSettings.from_env(
        {
            "MSCTL_ZENOH_CONFIG": str(config),
            "MSCTL_ZENOH_MODE": "client",
            "MSCTL_ZENOH_CONNECT": " tcp/10.0.0.2:7447 , tcp/10.0.0.3:7447,",
            "MSCTL_ZENOH_LISTEN": "tcp/127.0.0.1:0",
            "MSCTL_ZENOH_MULTICAST": "on",
            "MSCTL_ZENOH_LEASE_MS": "2500",
            "ROS_DOMAIN_ID": "12",
        }
    )
    assert settings == SessionSettings(
        mode="client",
        connect=("tcp/10.0.0.2:7447", "tcp/10.0.0.3:7447"),
        listen=("tcp/127.0.0.1:0",),
        multicast=True,
        lease_ms=2500,
        domain=12,
        config_file=config,
    )
    zconfig = settings.to_config()
    assert '"client"' in zconfig.get_json("mode")
    assert "2500" in zconfig.get_json("transport/link/tx/lease")
    assert "50" in zconfig.get_json("scouting/delay")


def test_defaults_and_overrides() -> None:
    settings = SessionSettings.from_env({})
    assert settings == SessionSettings()
    assert settings.connect == ("tcp/localhost:7447",)
    assert settings.multicast is False
    assert SessionSettings.from_env({"ROS_DOMAIN_ID": "3"}, domain=5, mode=None).domain == 5
    assert SessionSettings.from_env({"MSCTL_ZENOH_MULTICAST": "0"}).multicast is False


@pytest.mark.parametrize(
    ("variable", "value"),
    [
        ("MSCTL_ZENOH_MODE", "server"),
        ("MSCTL_ZENOH_CONNECT", " , "),
        ("MSCTL_ZENOH_CONNECT", "localhost:7447"),
        ("MSCTL_ZENOH_LISTEN", "127.0.0.1:0"),
        ("MSCTL_ZENOH_MULTICAST", "maybe"),
        ("MSCTL_ZENOH_LEASE_MS", "fast"),
        ("MSCTL_ZENOH_LEASE_MS", "10"),
        ("ROS_DOMAIN_ID", "-1"),
        ("ROS_DOMAIN_ID", "zero"),
        ("MSCTL_ZENOH_CONFIG", "/nonexistent/zenoh.json5"),
    ],
)
def test_bad_environment_names_the_variable(variable: str, value: str) -> None:
    with pytest.raises(SessionConfigError, match=variable):
        SessionSettings.from_env({variable: value})


def test_unreadable_config_file_is_reported(tmp_path: Path) -> None:
    config = tmp_path / "broken.json5"
    config.write_text("{ this is not json5")
    settings = SessionSettings.from_env({"MSCTL_ZENOH_CONFIG": str(config)})
    with pytest.raises(SessionConfigError, match=r"broken\.json5"):
        settings.to_config()


def test_session_from_environment_joins_the_router(
    zenoh_env: dict[str, str], router_endpoint: str
) -> None:
    settings = SessionSettings.from_env(zenoh_env)
    assert settings.connect == (router_endpoint,)
    with open_session(settings) as session:
        wait_until(lambda: list(session.info.routers_zid()))


def test_client_without_router_fails_to_open() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    settings = SessionSettings(mode="client", connect=(endpoint,), listen=())
    with pytest.raises(SessionOpenError, match=endpoint.split("/")[1]):
        open_session(settings)


def test_drop_stats_count_and_rate_limit_logs(caplog: pytest.LogCaptureFixture) -> None:
    stats = DropStats(log_interval=60.0)
    with caplog.at_level("WARNING", logger="msctl.comm"):
        for _ in range(5):
            stats.drop("/t", "malformed")
        stats.drop("/t", "bad_attachment")
    assert stats.count("/t") == 6
    assert stats.count("/t", "malformed") == 5
    assert stats.count("/other") == 0
    assert stats.snapshot() == {"/t": {"malformed": 5, "bad_attachment": 1}}
    assert len(caplog.records) == 2  # once per (topic, reason) per interval
