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

import sys
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
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


# ------------------------------------------------------- the run documents supervisors write
#: A process standing in for a component worker: the run's supervisor starts and stops it like
#: one (its own process group), it only opens no session. Its last word marks it as msctl's
#: (what the state file's readers look for on a command line, as they find it on a worker's).
SLEEPER = [sys.executable, "-c", "import time; time.sleep(300)", "msctl-stand-in"]
#: The minimal assembly's one computer.
ROBOT = "hl-limb-01"


@pytest.fixture(scope="module")
def minimal_plan() -> tuple[Any, Any]:
    """The minimal assembly, resolved from msctl's data, and its computer's part of it as its
    agent runs it simulated, with a component whose kind no code builds (as ``plan_host``
    lists one)."""
    from dataclasses import replace

    from components.assembly import from_document
    from msctl.assembler import resolve
    from msctl.launcher.part import plan_part

    assembly = from_document(resolve("minimal").document)
    plan = plan_part(assembly, ROBOT, sim=True)
    return assembly, replace(plan, not_built=[("limb1/camera", "camera")])


@pytest.fixture
def run(
    minimal_plan: tuple[Any, Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> Iterator[Any]:
    """A real :class:`~msctl.launcher.run.Launch` of the minimal plan as an agent runs it
    (no control service of its own: asked through its dispatcher directly, and its document
    says ``agent``), each of its processes a real child, running."""
    from components.comm.session import SessionSettings
    from msctl.launcher.run import Launch

    monkeypatch.setenv("MSCTL_HOME", str(tmp_path / "home"))
    assembly, plan = minimal_plan
    launch = Launch(
        assembly,
        plan,
        settings=SessionSettings(mode="peer", connect=(), listen=(), multicast=False),
        serve_control=False,
    )
    try:
        for process in plan.processes:
            launch.supervisor.add(
                process.name, SLEEPER, components=[c.name for c in process.components]
            )
            launch.supervisor.start(process.name)
        wait_until(
            lambda: all(p.pid for p in launch.supervisor.processes.values()),
            30.0,
            "every process started",
        )
        yield launch
    finally:
        launch.shutdown()


def _asked_ps(answer: Any) -> str:
    """The payload a supervisor's dispatcher sends for ``ps`` (what travels)."""
    replies: list[Any] = []
    pending = SimpleNamespace(request=SimpleNamespace(verb="ps", args=""), reply=replies.append)
    answer(pending)
    assert len(replies) == 1 and replies[0].success, replies
    return replies[0].payload


def test_a_runs_ps_answer_is_its_run_document_and_its_state_file_reads_alike(run: Any) -> None:
    """What a run answers to ``ps`` decodes into the values it holds, nothing lost; its
    state file holds the same JSON for the readers that take it as a dict."""
    from components.supervision.contract import ps_document
    from msctl.launcher import state

    made = run.document()
    assert isinstance(made, protocol.RunDocument)
    payload = _asked_ps(run._answer)
    typed = protocol.run_document(payload)
    assert typed is not None
    assert msgspec.to_builtins(typed) == msgspec.json.decode(payload)  # nothing left out
    assert b'"rejoin"' not in payload.encode()  # a run has none: never on the wire
    moving = {"uptime": 0.0, "heartbeat_age": None}  # seconds that pass between two reads

    def still(document: protocol.RunDocument) -> protocol.RunDocument:
        return msgspec.structs.replace(
            document,
            processes=[msgspec.structs.replace(p, **moving) for p in document.processes],
            components=[msgspec.structs.replace(c, uptime=0.0) for c in document.components],
        )

    assert still(typed) == still(made)
    assert (typed.host, typed.template, typed.agent) == (ROBOT, "minimal", True)
    assert typed.state == "running" and typed.simulated and not typed.off_robot
    pids = {p.name: p.pid for p in typed.processes}
    assert pids == {n: p.pid for n, p in run.supervisor.processes.items()}
    planned = [(c.name, c.process) for c in run.components()]
    assert [(c.name, c.process) for c in typed.components] == planned
    assert all(c.pid == pids[c.process] and c.host == ROBOT for c in typed.components)
    assert typed.not_built == [protocol.NotBuilt("limb1/camera", "camera")]

    run.write_state()
    written = state.read_state()
    assert still(protocol.run_document(written)) == still(typed)
    assert "rejoin" not in written
    # Read by its fields, as `msctl ps`, `down` and the agent at its start read it.
    read = ps_document(written)
    assert (read["host"], read["template"], read["state"]) == (ROBOT, "minimal", "running")
    assert [(c["name"], c["pid"]) for c in read["components"]] == [
        (c.name, c.pid) for c in typed.components
    ]
    assert sorted(state.groups_left(written)) == sorted(pids)


def test_an_agents_ps_answer_carries_its_rejoin_only_while_it_has_one(
    run: Any, tmp_path: Path
) -> None:
    """An idle agent answers its idle document, without ``rejoin``; one that reports what it
    did at its start carries the report (over its run's document) until the next ``down``."""
    from msctl.launcher.agent import Agent

    agent = Agent(ROBOT, log=lambda _line: None)
    try:
        idle = _asked_ps(agent._answer)
        assert b'"rejoin"' not in idle.encode()
        typed = protocol.run_document(idle)
        assert typed is not None and msgspec.to_builtins(typed) == msgspec.json.decode(idle)
        assert (typed.host, typed.state, typed.agent, typed.template) == (ROBOT, "idle", True, None)
        assert typed.rejoin is msgspec.UNSET and typed.components == []

        agent.launch = run  # the part it brought back by itself at its start
        agent._report_rejoin("rejoined", f"{ROBOT} rebooted and rejoined")
        rejoined = protocol.run_document(_asked_ps(agent._answer))
        assert rejoined is not None and rejoined.agent and rejoined.template == "minimal"
        assert [c.name for c in rejoined.components] == [c.name for c in run.components()]
        assert rejoined.rejoin == agent.rejoin
        assert rejoined.rejoin.outcome == "rejoined"
        assert rejoined.rejoin.agent_started <= rejoined.rejoin.at

        # The same up again (its answer lost on a radio link): what runs, as an UpAnswer.
        asked = {"assembly": run.assembly.document, "sim": True}
        up, said = agent.handle("up", asked)
        assert said == "already running"
        part = protocol.up_answer(msgspec.json.encode(up))
        assert part == up
        assert (part.host, part.template, part.simulated) == (ROBOT, "minimal", True)
        assert part.processes == [p.name for p in run.plan.processes]
        assert part.components == [c.name for c in run.plan.components]
        assert part.not_built == [protocol.NotBuilt("limb1/camera", "camera")]

        payload, _ = agent.handle("down", {})  # what was asked now supersedes the rejoin
        assert sorted(payload.stopped) == sorted(p.name for p in run.plan.processes)
        after = _asked_ps(agent._answer)
        assert b'"rejoin"' not in after.encode()
        assert protocol.run_document(after).state == "idle"
    finally:
        agent._stop_run()
        agent.router.shutdown()


# ----------------------------------------------------------------- restart/stop/start answers
@pytest.mark.parametrize(
    ("made", "sent"),
    [  # what RunRequests answers (msctl/launcher/requests.py), and the JSON it always sent
        (
            protocol.ProcessAnswer("limb1", "restarting", ["limb1/a", "limb1/b"], ["limb1/b"]),
            b'{"process":"limb1","state":"restarting","components":["limb1/a","limb1/b"],'
            b'"siblings":["limb1/b"]}',
        ),
        (
            protocol.ProcessAnswer("router", "restarting", [], []),
            b'{"process":"router","state":"restarting","components":[],"siblings":[]}',
        ),
        (
            protocol.ProcessAnswer("limb1", "rebuilding", ["limb1/a"], [], only=True),
            b'{"process":"limb1","state":"rebuilding","components":["limb1/a"],'
            b'"siblings":[],"only":true}',
        ),
    ],
)
def test_a_process_answer_travels_as_it_always_did_and_reads_back_as_itself(
    made: protocol.ProcessAnswer, sent: bytes
) -> None:
    """The wire is unchanged (``only`` only when set); both the JSON and the parsed payload
    (what ``call_supervisor`` returns) read back as the struct."""
    assert msgspec.json.encode(made) == sent
    assert protocol.process_answer(sent) == made
    assert protocol.process_answer(msgspec.json.decode(sent)) == made
    assert bool(protocol.process_answer(sent).only) is (b'"only"' in sent)


def test_a_process_answer_from_an_older_or_newer_supervisor_reads() -> None:
    """Lists left out default to empty; a field added later is ignored."""
    acted = protocol.process_answer({"process": "p", "state": "stopped", "newer": [1]}, "stop")
    assert (acted.process, acted.state, acted.components, acted.siblings) == (
        "p",
        "stopped",
        [],
        [],
    )
    assert not acted.only


@pytest.mark.parametrize(
    "garbage",
    [b"x", b"[]", b"{}", b'{"process": 5, "state": "x"}', [], "null", {"state": "running"}],
)
def test_a_garbage_process_answer_is_a_typed_error_naming_who_sent_it(garbage: Any) -> None:
    from components.errors import LinkError

    with pytest.raises(protocol.AnswerError, match="the supervisor of hl-01 answered stop") as e:
        protocol.process_answer(garbage, "stop", "the supervisor of hl-01")
    assert isinstance(e.value, LinkError)


# ------------------------------------------------------------------------------ up answers
def test_an_up_answer_travels_as_the_dict_it_replaced_and_garbage_is_a_typed_error() -> None:
    """The agent's ``up`` answer as older agents sent it (a dict, its fields in this order)
    is the struct's JSON; one from an older or newer agent reads, garbage names its sender."""
    older = {
        "host": "hl-wheel-02",
        "template": "dragon",
        "simulated": True,
        "processes": ["wheel2"],
        "components": ["wheel2/joint_manager", "wheel2/health_monitor"],
        "not_built": [{"name": "wheel2/camera", "kind": "camera"}],
    }
    typed = protocol.up_answer(msgspec.json.encode(older))
    assert msgspec.json.encode(typed) == msgspec.json.encode(older)
    assert typed.not_built == [protocol.NotBuilt("wheel2/camera", "camera")]
    assert protocol.up_answer({"host": "h", "newer": 1}).components == []
    for garbage in (b"x", b"[]", b"{}", {"host": "h", "components": "wheel2"}):
        with pytest.raises(protocol.AnswerError, match="the agent of h answered up"):
            protocol.up_answer(garbage, "the agent of h")


# ---------------------------------------------------------------------- doctor and logs answers
def test_a_doctor_answer_travels_as_the_dicts_it_replaced_and_reads_back() -> None:
    """Real findings (this computer's version check), sent as the struct: the same JSON as
    the ``dataclasses.asdict`` payload older agents send (a dict per finding, its fields in
    order), and read back field for field."""
    from msctl.net import doctor

    found = doctor.version("hl-limb-01", None)
    assert found and any(f.status == doctor.WARN for f in found)
    typed = protocol.DoctorAnswer(
        "hl-limb-01",
        [protocol.DoctorFinding(f.host, f.check, f.status, f.detail, f.value) for f in found],
    )
    fields = ("host", "check", "status", "detail", "value")
    older = {
        "host": "hl-limb-01",
        "findings": [{name: getattr(f, name) for name in fields} for f in found],
    }
    assert msgspec.json.encode(typed) == msgspec.json.encode(older)
    told = protocol.doctor_answer(msgspec.json.decode(msgspec.json.encode(older)))
    assert [doctor.Finding(*msgspec.structs.astuple(f)) for f in told.findings] == found
    assert protocol.doctor_answer({"host": "h", "newer": 1}).findings == []


def test_a_logs_answer_reads_back_and_garbage_is_a_typed_error() -> None:
    sent = {"limb1": ["12:00:01 up", "12:00:02 homing"], "router": []}
    assert protocol.logs_answer(msgspec.json.encode(sent)) == sent
    assert protocol.logs_answer(sent) == sent
    for garbage in ([], {"limb1": "one line"}, {"limb1": [3]}, b"{", "null"):
        with pytest.raises(protocol.AnswerError, match="answered logs"):
            protocol.logs_answer(garbage, "the supervisor of hl-01")
    for garbage in ({}, {"host": 5}, {"host": "h", "findings": [{"host": "h"}]}, b"[]"):
        with pytest.raises(protocol.AnswerError, match="answered doctor"):
            protocol.doctor_answer(garbage)


# ------------------------------------------------------------------- bags and bag_read answers
def _shelf(root: Path) -> Path:
    """A shelf with one bag: a finished MCAP file, one being written, its metadata."""
    from msctl.recorder.shelf import MCAP_MAGIC

    bag = root / "limb1_data_archiver_2026_11_27-21_30_00"
    bag.mkdir(parents=True)
    (bag / "b_0.mcap").write_bytes(MCAP_MAGIC + b"chunks" + MCAP_MAGIC)
    (bag / "b_1.mcap").write_bytes(MCAP_MAGIC + b"still writing")
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    return bag


def test_the_shelfs_answers_travel_as_their_structs_and_read_back(tmp_path: Path) -> None:
    """What the agent's shelf handler sends (the shelf's own listing and read, as structs):
    the same JSON as the dicts, and read back by ``bag pull``'s reader."""
    import base64

    from msctl.recorder import shelf
    from msctl.recorder.pull_plan import remote_files

    bag = _shelf(tmp_path)
    listing = shelf.listing(tmp_path)
    typed = msgspec.convert(listing, protocol.BagsAnswer)
    assert msgspec.json.encode(typed) == msgspec.json.encode(listing)
    assert protocol.bags_answer(msgspec.json.encode(listing)) == typed
    (told,) = typed.bags
    assert told.recording and [f.complete for f in told.files] == [True, False, True]
    pulled = remote_files(msgspec.json.decode(msgspec.json.encode(typed)), "hl-limb-01")
    assert [f.name for f in pulled] == ["b_0.mcap", "b_1.mcap", "metadata.yaml"]

    read = shelf.read({"path": f"{bag.name}/b_0.mcap", "offset": 2, "size": 5}, "h", tmp_path)
    typed_read = msgspec.convert(read, protocol.BagReadAnswer)
    assert msgspec.json.encode(typed_read) == msgspec.json.encode(read)
    back = protocol.bag_read_answer(msgspec.json.encode(read))
    assert base64.b64decode(back.data) == (bag / "b_0.mcap").read_bytes()[2:7]


@pytest.mark.parametrize(
    "garbage",
    [[], {"bags": 3}, {"bags": [{"files": []}]}, {"bags": [{"name": "b", "files": [{}]}]}, b"x"],
)
def test_a_garbage_bags_answer_is_a_typed_error(garbage: Any) -> None:
    from msctl.recorder.pull_plan import PullError, remote_files

    with pytest.raises(protocol.AnswerError, match="answered bags"):
        protocol.bags_answer(garbage, "the agent of hl-01")
    with pytest.raises(PullError, match="hl-01's bag listing is refused"):
        remote_files(garbage, "hl-01")


def test_a_garbage_bag_read_answer_is_a_typed_error() -> None:
    for garbage in ({}, {"path": "b/x", "offset": "0", "file_size": 1}, [], b"{}"):
        with pytest.raises(protocol.AnswerError, match="answered bag_read"):
            protocol.bag_read_answer(garbage)
