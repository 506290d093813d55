"""The supervision protocol (issue 33): a struct per request and answer, one table of verbs,
one client, typed errors.

Pure: every request struct travels as the verb and JSON the supervisors have always read,
and is read back as itself; a bad request is refused naming what is wrong. On the wire: a
supervisor's request service on a real Zenoh session (a loopback router), answered by
:func:`components.supervision.dispatch.answer` with a :class:`Verbs` table, asked with the one
client: garbage gets a typed error answer (malformed, refused, failed), and the server keeps
answering after each.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import msgspec
import pytest
from conftest import quick_peer_settings, quick_router, wait_until

from components.comm.node import Node
from components.comm.services import ServiceError
from components.comm.session import open_session
from components.supervision import protocol
from components.supervision.contract import AGENT_SRV, RequestError, host_namespace
from components.supervision.dispatch import Verbs, answer
from components.supervision.wire import SupervisorClient, call_supervisor

HOST = "proto-robot"


@pytest.mark.parametrize(
    "request_",
    [
        protocol.Ps(),
        protocol.Doctor(),
        protocol.Down(),
        protocol.Up(assembly={"template": "dragon"}, sim=True, speed=2.5),
        protocol.Logs(component="limb1/joint_manager", lines=20),
        protocol.Logs(),
        protocol.Restart(component="limb1/joint_manager", only=True),
        protocol.Stop(component="router"),
        protocol.Start(component="d1_limb1"),
        protocol.Bags(),
        protocol.BagRead(path="a/b_0.mcap", offset=0, size=1024),
    ],
)
def test_each_request_travels_as_verb_and_json_and_reads_back_as_itself(
    request_: protocol.Request,
) -> None:
    verb, args = protocol.wire_form(request_)
    assert verb in protocol.VERBS
    assert msgspec.json.decode(args, type=dict) is not None
    assert protocol.parse_request(verb, args).request == request_


def test_defaults_are_left_out_of_the_wire() -> None:
    assert protocol.wire_form(protocol.Restart(component="x")) == ("restart", '{"component":"x"}')
    assert protocol.wire_form(protocol.Ps()) == ("ps", "{}")


def test_every_verb_has_one_struct() -> None:
    assert set(protocol.REQUESTS) == set(protocol.VERBS)
    assert len(protocol.VERBS) == len(set(protocol.VERBS))


def test_a_table_refuses_a_verb_it_has_no_handler_for() -> None:
    verbs = Verbs("a test supervisor", {protocol.Ps: lambda _: {"host": HOST}})
    assert verbs.run(protocol.Ps()) == {"host": HOST}
    with pytest.raises(RequestError, match="up is not something a test supervisor does"):
        verbs.run(protocol.Up())


# --------------------------------------------------------------------------- on the wire
class Supervisor:
    """A supervisor's request service in this process, answered through a verb table."""

    def __init__(self, session: Any) -> None:
        self.notes: list[str] = []
        self.node = Node(session, "supervisor", host_namespace(HOST))
        self.verbs = Verbs(
            "a test supervisor",
            {
                protocol.Ps: lambda _: {"host": HOST, "components": []},
                protocol.Restart: self._restart,
                protocol.Stop: self._broken,
            },
        )
        self.node.service("request", AGENT_SRV, self._serve, deferred=True)

    def _serve(self, pending: Any) -> None:
        answer(pending, lambda c: ("ok", self.verbs.run(c.request)), self.notes.append, HOST)

    def _restart(self, request: protocol.Restart) -> protocol.ProcessAnswer:
        if request.component != "d1_limb1":
            raise RequestError(f"no component or process {request.component!r} on {HOST}")
        return protocol.ProcessAnswer("d1_limb1", "restarting", ["limb1/a", "limb1/b"], [])

    def _broken(self, _request: protocol.Stop) -> Any:
        raise RecursionError("maximum recursion depth exceeded")

    def close(self) -> None:
        self.node.close()


@pytest.fixture(scope="module")
def wire() -> Iterator[tuple[Supervisor, Node]]:
    """A router, a supervisor and an asking node, each with its own session."""
    for endpoint in quick_router():
        serving = open_session(quick_peer_settings(endpoint))
        asking = open_session(quick_peer_settings(endpoint))
        supervisor = Supervisor(serving)
        node = Node(asking, "asker", "/")
        try:
            _wait_for_supervisor(node)
            yield supervisor, node
        finally:
            node.close()
            supervisor.close()
            asking.close()
            serving.close()


def _wait_for_supervisor(node: Node) -> None:
    client = SupervisorClient(node, f"{host_namespace(HOST)}/request")

    def answers_ps() -> bool:
        try:
            return client.ask("ps", "{}", 2.0).success
        except ServiceError:
            return False

    try:
        wait_until(answers_ps, 30.0, "the supervisor on the graph")
    finally:
        client.close()


@pytest.mark.parametrize(
    ("verb", "args", "kind", "why"),
    [
        ("reboot", "{}", "malformed", "unknown verb 'reboot'"),
        ("", "", "malformed", "unknown verb"),
        ("ps", "\x01garbage{{{", "malformed", "not JSON"),
        ("ps", "[1, 2", "malformed", "not JSON"),
        ("ps", "[" * 5000 + "]" * 5000, "malformed", "nest deeper than 32"),
        ("logs", '{"lines": 1e999}', "malformed", "lines must be"),
        ("restart", '{"component": "x", "cmd": "rm -rf /"}', "malformed", "no argument cmd"),
        ("restart", '{"component": "nobody"}', "refused", "no component or process 'nobody'"),
        ("up", "{}", "refused", "up is not something a test supervisor does"),
        ("stop", '{"component": "d1_limb1"}', "failed", "RecursionError"),
    ],
)
def test_a_bad_request_gets_a_typed_error_and_the_server_stays_up(
    wire: tuple[Supervisor, Node], verb: str, args: str, kind: str, why: str
) -> None:
    supervisor, node = wire
    client = SupervisorClient(node, f"{host_namespace(HOST)}/request")
    try:
        response = client.ask(verb, args, 10.0)
        assert not response.success and why in response.message
        error = protocol.error_of(response.payload)
        assert error is not None and error.kind == kind and error.message == response.message
        assert error.verb == (verb[:40] or "?")
        # Still there: the next request is answered.
        assert client.ask("ps", "{}", 10.0).success
    finally:
        client.close()
    if kind == "failed":
        assert any("RecursionError" in note for note in supervisor.notes)


def test_bytes_that_are_no_request_are_refused_by_the_transport_and_the_server_stays_up(
    wire: tuple[Supervisor, Node],
) -> None:
    _supervisor, node = wire
    client = SupervisorClient(node, f"{host_namespace(HOST)}/request")
    try:
        with pytest.raises(ServiceError):
            client.call_raw(b"\x00\x01\x00\x00\xff\xff\xff\xff", 10.0)
        assert client.ask("ps", "{}", 10.0).success
    finally:
        client.close()


def test_the_client_returns_the_typed_answer_and_names_the_host_in_a_refusal(
    wire: tuple[Supervisor, Node],
) -> None:
    _supervisor, node = wire
    payload = call_supervisor(node, HOST, "restart", {"component": "d1_limb1"}, 10.0)
    answer_ = msgspec.convert(payload, protocol.ProcessAnswer)
    assert answer_.process == "d1_limb1" and answer_.components == ["limb1/a", "limb1/b"]
    assert "only" not in payload  # left out unless it is a rebuild alone
    with pytest.raises(RequestError, match=f"{HOST} refused restart: no component"):
        call_supervisor(node, HOST, "restart", {"component": "ghost"}, 10.0)


# ---------------------------------------------------------------------------- ps answers
@pytest.mark.parametrize(
    ("names", "struct"),
    [
        ("RUN_FIELDS", protocol.RunDocument),
        ("COMPONENT_FIELDS", protocol.ComponentRow),
        ("PROCESS_FIELDS", protocol.ProcessRow),
    ],
)
def test_the_quick_paths_field_names_are_the_typed_answers_fields(names: str, struct: Any) -> None:
    """``msctl ps`` reads answers by these names without msgspec: they are the structs'."""
    from components.supervision import contract

    assert getattr(contract, names) == struct.__struct_fields__


IDLE_AGENT = {  # what an agent with no run answers (an older agent: no rejoin, no faults)
    "host": "hl-limb-01",
    "agent": True,
    "template": None,
    "state": "idle",
    "supervisor_pid": 4242,
    "router": "tcp/127.0.0.1:7447",
    "processes": [],
    "components": [],
    "not_built": [],
}


def test_a_ps_answer_reads_the_same_typed_and_by_field_names() -> None:
    """Both readings keep exactly what was sent; a newer supervisor's extra field is left out
    by both, and what is not a ps answer is none."""
    from components.supervision.contract import ps_document

    row = {
        "name": "limb1/joint_manager",
        "kind": "joint_manager",
        "host": "hl-limb-01",
        "process": "limb1",
        "state": "running",
        "pid": 77,
        "uptime": 3.5,
        "restarts": 1,
        "last_error": "",
    }
    sent = {**IDLE_AGENT, "state": "running", "template": "dragon", "components": [row]}
    typed = protocol.run_document(msgspec.json.encode({**sent, "newer": 1}))
    assert typed is not None and typed.components[0].pid == 77
    assert {k: v for k, v in msgspec.to_builtins(typed).items() if k in sent} == sent
    assert ps_document({**sent, "newer": 1}) == sent
    assert protocol.run_document(msgspec.json.encode(IDLE_AGENT)).components == []
    for not_one in (b"[]", b"{}", b'{"host": 5}', b'{"host": "a", "components": [7]}', b"x"):
        assert protocol.run_document(not_one) is None, not_one
    assert ps_document([]) is None and ps_document({"host": 5}) is None
