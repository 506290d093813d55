"""Honest partial results of the commands that ask several computers (issue 30, point 5).

Inner loop (real Zenoh sessions on a loopback router, no subprocess): the plan is read from
the lock ``msctl assemble`` writes; a request to several supervisors tells an answer from
"no supervisor on the graph", "no answer within the timeout" and a refusal; a computer that
runs the whole assembly off-robot stands for the plan's hosts.

End to end: a resolved Dragon on a ground station, and real ``msctl agent`` subprocesses for
only two of its five computers (ground1 and hl-limb-01, each with its own MSCTL_HOST and
MSCTL_HOME). The other three are unreachable: ``ps --all``, ``doctor --all`` and
``down --all`` name each and exit 1; plain ``ps`` names them on stderr and exits 0. A
supervisor that is on the graph and never answers is "no answer", and fails plain ``ps``
too.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import quick_peer_settings, wait_until
from test_agents import Agents, _base_env

from components.comm.node import Node
from components.comm.session import open_session
from components.comm.types import registry
from msctl.launcher import fleet
from msctl.launcher.control import AGENT_SRV, host_namespace

ROOT = Path(__file__).resolve().parents[1]
GROUND = "ground1"
RUNNING = (GROUND, "hl-limb-01")  # the computers whose agents run
DOWN = ("hl-limb-02", "hl-wheel-01", "hl-wheel-02")  # the plan's other computers


@pytest.fixture(scope="module")
def ground_home(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The ground station's MSCTL_HOME with the Dragon resolved (H-line limbs: five hosts),
    written as ``msctl assemble dragon`` writes it (no MJCF: nothing here simulates)."""
    from msctl.assembler import resolve
    from msctl.assembler.store import write_resolution

    home = tmp_path_factory.mktemp("ground")
    write_resolution(home / "assembly", resolve("dragon", {}), mjcf=False)
    return home


@pytest.fixture
def in_ground_home(ground_home: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """This process reads the ground station's MSCTL_HOME (its plan)."""
    monkeypatch.setenv("MSCTL_HOME", str(ground_home))
    return ground_home


@pytest.fixture(scope="module")
def node(endpoint: str) -> Iterator[Node]:
    """A node of this process on the test router."""
    session = open_session(quick_peer_settings(endpoint))
    asking = Node(session, "fleet_test", "/")
    try:
        yield asking
    finally:
        asking.close()
        session.close()


class StandIn:
    """A supervisor's request service for ``host`` in this process: it answers ``ps`` with
    ``document``, refuses with ``refusal``, or never answers when ``silent``; the answers to
    its first ``lose`` requests are lost (a radio link that closed while they were on it)."""

    def __init__(
        self,
        node: Node,
        host: str,
        document: dict[str, Any] | None = None,
        refusal: str = "",
        silent: bool = False,
        lose: int = 0,
    ) -> None:
        self.node = Node(node.session, "supervisor", host_namespace(host))
        self.pending: list[Any] = []  # requests a silent one keeps, never answered
        self.asked: list[str] = []  # the verbs of the requests that reached it
        response = registry().msg_class(registry().service(AGENT_SRV).response)

        def serve(pending: Any) -> None:
            self.asked.append(pending.request.verb)
            if silent or len(self.asked) <= lose:
                self.pending.append(pending)  # its answer lost on the way back
                return
            payload = json.dumps(document or {"host": host, "components": []})
            pending.reply(response(success=not refusal, message=refusal, payload=payload))

        self.node.service("request", AGENT_SRV, serve, deferred=True)

    def answer_pending(self, document: dict[str, Any]) -> None:
        """Answer the first request it kept (a server that was only slow)."""
        response = registry().msg_class(registry().service(AGENT_SRV).response)
        self.pending[0].reply(response(success=True, message="", payload=json.dumps(document)))

    def close(self) -> None:
        self.node.close()


@pytest.fixture
def stand_in(node: Node) -> Iterator[Callable[..., StandIn]]:
    """Make stand-in supervisors (waited for on the graph); all are closed at teardown."""
    made: list[StandIn] = []

    def make(host: str, **kwargs: Any) -> StandIn:
        made.append(StandIn(node, host, **kwargs))
        wait_until(lambda: host_namespace(host) in fleet.supervisors(node), 20.0, host)
        return made[-1]

    try:
        yield make
    finally:
        for one in made:
            one.close()


# --------------------------------------------------------------------------- the plan
def test_the_plan_is_the_locks_hosts_read_without_the_schema(in_ground_home: Path) -> None:
    from components.assembly import load_assembly, lock_path

    assert fleet.plan_path() == lock_path()
    assembly = load_assembly()
    plan = fleet.read_plan()
    assert plan is not None and plan.template == "dragon"
    assert list(plan.hosts) == list(assembly.hosts) == [*RUNNING[1:], *DOWN, GROUND]
    for host, components in plan.hosts.items():
        assert set(components) == {c.name for c in assembly.components if c.host == host}
    assert "gc1/data_monitor" in plan.hosts[GROUND]


def test_no_plan_when_nothing_is_resolved_or_the_lock_is_unreadable(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("MSCTL_HOME", str(tmp_path))
    assert fleet.read_plan() is None
    fleet.plan_path().parent.mkdir(parents=True)
    fleet.plan_path().write_text('{"template": "dragon"')
    assert fleet.read_plan() is None


def test_an_off_robot_run_of_the_same_assembly_stands_for_every_host() -> None:
    plan = fleet.Plan("dragon", {"hl-limb-01": ("limb1/joint_manager",), GROUND: ()})
    assert fleet.expected_hosts(plan, []) == ["hl-limb-01", GROUND]
    assert fleet.expected_hosts(None, []) == []
    laptop = {"host": "laptop", "template": "dragon", "off_robot": True}
    assert fleet.expected_hosts(plan, [laptop]) == []
    # Another assembly simulated somewhere says nothing about this one's computers.
    assert fleet.expected_hosts(plan, [{**laptop, "template": "minimal"}]) == list(plan.hosts)
    assert fleet.expected_hosts(plan, [{**laptop, "off_robot": False}]) == list(plan.hosts)
    # A ground station's agent runs off-robot, but only the station's own part.
    station = {"host": GROUND, "template": "dragon", "off_robot": True, "agent": True}
    assert fleet.expected_hosts(plan, [station]) == list(plan.hosts)


# --------------------------------------------------------------------------- asking
def test_a_host_back_within_the_grace_is_answered_not_gone(node: Node) -> None:
    # A busy agent that missed its lease is out of the router's routes for a moment: the
    # host is asked again within the grace, and its answer counts.
    import threading

    made: list[StandIn] = []
    # The stand-in's types made first: made cold in the timer, they took 3.6 s (a loaded machine).
    registry().msg_class(registry().service(AGENT_SRV).response)
    timer = threading.Timer(0.4, lambda: made.append(StandIn(node, "late")))
    timer.start()
    try:
        asked = fleet.ask_hosts(node, "ps", ["late"], timeout=6.0, found={})
    finally:
        timer.join()
        for one in made:
            one.close()
    assert asked.answers == {host_namespace("late"): {"host": "late", "components": []}}, asked
    assert not asked.silent


def test_a_supervisor_call_with_a_grace_reaches_a_host_whose_route_came_back(
    node: Node,
) -> None:
    # `up --all` asks with a grace: a host whose route lapsed (no server known for a moment)
    # is asked again; without one, it is named at once.
    import threading

    from components.comm.services import ServiceTimeout
    from msctl.launcher.control import call_supervisor

    with pytest.raises(ServiceTimeout, match="no server of"):
        call_supervisor(node, "later", "ps", timeout=5.0)
    made: list[StandIn] = []
    timer = threading.Timer(0.4, lambda: made.append(StandIn(node, "later")))
    timer.start()
    try:
        answer = call_supervisor(node, "later", "ps", timeout=6.0, grace=3.0)
    finally:
        timer.join()
        for one in made:
            one.close()
    assert answer == {"host": "later", "components": []}


def test_a_request_whose_answer_was_lost_is_sent_again_and_answered(
    node: Node, stand_in: Callable[..., StandIn]
) -> None:
    # A radio link that closes while a query waits loses it for good: the verbs that are
    # safe to repeat are sent again, so the host is answered, not named unreachable.
    from components.comm.services import ServiceTimeout
    from msctl.launcher.control import call_supervisor

    lossy = stand_in("lossy", lose=2)
    answer = call_supervisor(node, "lossy", "up", timeout=30.0, attempt=0.5)
    assert answer == {"host": "lossy", "components": []}
    assert lossy.asked == ["up", "up", "up"]
    # Sent once, an answer lost is a host that never answered, however long it is waited for.
    once = stand_in("once", lose=1)
    with pytest.raises(ServiceTimeout, match="no server answered"):
        call_supervisor(node, "once", "ps", timeout=1.0)
    assert once.asked == ["ps"]
    # The fleet's own requests (ps --all, doctor --all, down --all) are sent again too.
    asked = fleet.ask_hosts(node, "ps", ["lossy2"], timeout=9.0, found={})
    assert asked.silent  # no such host yet
    stand_in("lossy2", lose=1)
    asked = fleet.ask_hosts(node, "ps", ["lossy2"], timeout=9.0, found={})
    assert asked.answers == {host_namespace("lossy2"): {"host": "lossy2", "components": []}}


def test_a_slow_answer_to_an_earlier_copy_still_counts(
    node: Node, stand_in: Callable[..., StandIn]
) -> None:
    # A server slower than the repeat (an agent answers its requests in order, and its `up`
    # starts processes first): the first copy's answer is taken when it comes.
    slow = stand_in("slow", silent=True)
    import threading

    timer = threading.Timer(1.5, lambda: slow.answer_pending({"host": "slow", "late": True}))
    timer.start()
    try:
        from msctl.launcher.control import call_supervisor

        answer = call_supervisor(node, "slow", "up", timeout=20.0, attempt=0.4)
    finally:
        timer.join()
    assert answer == {"host": "slow", "late": True}
    assert len(slow.asked) >= 3


def test_each_silence_says_why(node: Node, stand_in: Callable[..., StandIn]) -> None:
    stand_in("answers")
    stand_in("refuses", refusal="refused for the test")
    quiet = stand_in("quiet", silent=True)
    asked = fleet.ask_hosts(node, "ps", ["answers", "absent"], timeout=1.0)
    assert asked.answers == {host_namespace("answers"): {"host": "answers", "components": []}}
    silent = {s.host: s for s in asked.silent.values()}
    # The graph's supervisors are named by namespace, the plan's hosts by name.
    assert set(silent) == {"absent", host_namespace("refuses"), host_namespace("quiet")}
    assert silent["absent"].why == fleet.NO_SUPERVISOR and silent["absent"].asked
    assert silent["absent"].detail == "no supervisor on the graph"
    assert silent[host_namespace("refuses")].why == fleet.REFUSED
    assert silent[host_namespace("refuses")].detail == "refused for the test"
    assert silent[host_namespace("quiet")] == fleet.Silence(
        host_namespace("quiet"), fleet.NO_ANSWER, "no answer within 1 s"
    )
    assert len(quiet.pending) == 1  # it was asked; it just never answered
    # ask_all keeps its shape: every graph supervisor, an error for each that did not answer.
    every = fleet.ask_all(node, "ps", timeout=1.0)
    assert every[host_namespace("answers")] == {"host": "answers", "components": []}
    assert every[host_namespace("quiet")] == {"error": "no answer within 1 s"}


def test_a_host_with_no_supervisor_is_known_at_once_not_after_the_timeout(node: Node) -> None:
    started = time.monotonic()
    asked = fleet.ask_hosts(node, "ps", ["nowhere-1", "nowhere-2"], timeout=10.0)
    assert time.monotonic() - started < 5.0
    assert [s.why for s in asked.silent.values()] == [fleet.NO_SUPERVISOR] * 2
    assert not asked.answers


# --------------------------------------------------------------------------- end to end
@pytest.fixture(scope="module")
def agents(
    tmp_path_factory: pytest.TempPathFactory,
    net_env: dict[str, str],
    ground_home: Path,
    node: Node,
) -> Iterator[Agents]:
    """Agents on two of the Dragon's five computers, answering before the tests start."""
    del ground_home  # resolved first: the agents run nothing anyway
    fleet_rig = Agents(tmp_path_factory.mktemp("agents"), {**_base_env(), **net_env})
    try:
        for host in RUNNING:
            fleet_rig.start(host)
        wanted = {host_namespace(h) for h in RUNNING}
        wait_until(lambda: wanted <= set(fleet.supervisors(node)), 90.0, "the two agents")
        yield fleet_rig
    finally:
        fleet_rig.close()


def msctl(home: Path, env: dict[str, str], *args: str) -> subprocess.CompletedProcess:
    """Run ``msctl`` as the ground station."""
    return subprocess.run(
        [sys.executable, "-m", "msctl", *args],
        env={**_base_env(), **env, "MSCTL_HOME": str(home), "MSCTL_HOST": GROUND},
        capture_output=True,
        text=True,
        timeout=90,
        cwd=ROOT,
    )


def error_line(stderr: str) -> str:
    """The one ``error:`` line, after whatever else was said."""
    (line,) = [x for x in stderr.splitlines() if x.startswith("error:")]
    return line


@pytest.mark.e2e
def test_ps_all_lists_the_unreachable_hosts_and_exits_1(
    agents: Agents, ground_home: Path, net_env: dict[str, str]
) -> None:
    result = msctl(ground_home, net_env, "ps", "--all", "--json")
    assert result.returncode == 1, result.stderr + agents.logs()
    document = json.loads(result.stdout)  # exactly one document
    assert set(document["hosts"]) == set(RUNNING)
    assert document["unreachable"] == [
        {"host": h, "why": "no supervisor", "detail": "no supervisor on the graph", "asked": True}
        for h in DOWN
    ]
    line = error_line(result.stderr)
    assert f"3 host(s) did not answer: {', '.join(DOWN)} (no supervisor on the graph)" in line
    assert "msctl agent" in line and "msctl doctor --all" in line
    table = msctl(ground_home, net_env, "ps", "--all")
    assert table.returncode == 1, table.stderr
    rows = {line.split()[2]: line.split() for line in table.stdout.splitlines()[1:]}
    assert set(rows) == set(DOWN)  # the agents run nothing: only the unreachable are rows
    assert all(row[3] == "unreachable" for row in rows.values())
    assert table.stdout.splitlines()[1].endswith("no supervisor on the graph")
    assert f"answered, running nothing: {', '.join(RUNNING)}" in table.stderr


@pytest.mark.e2e
def test_ps_all_with_no_plan_asks_the_graph_and_says_so(
    agents: Agents, tmp_path: Path, net_env: dict[str, str]
) -> None:
    result = msctl(tmp_path, net_env, "ps", "--all", "--json")
    assert result.returncode == 0, result.stderr + agents.logs()
    assert set(json.loads(result.stdout)["hosts"]) == set(RUNNING)
    assert "no resolved assembly here" in result.stderr
    assert "asked only the supervisors on the graph" in result.stderr


@pytest.mark.e2e
def test_plain_ps_names_the_missing_hosts_and_exits_0(
    agents: Agents, ground_home: Path, net_env: dict[str, str]
) -> None:
    result = msctl(ground_home, net_env, "ps", "--json")
    assert result.returncode == 0, result.stderr + agents.logs()
    document = json.loads(result.stdout)
    assert set(document["hosts"]) == set(RUNNING)
    assert [(u["host"], u["asked"]) for u in document["unreachable"]] == [(h, False) for h in DOWN]
    assert f"not asked (not on the graph): {', '.join(DOWN)}, host(s) of dragon's plan" in (
        result.stderr
    )
    assert "msctl ps --all" in result.stderr and "error" not in result.stderr


@pytest.mark.e2e
def test_a_supervisor_that_does_not_answer_fails_ps_and_ps_all(
    agents: Agents,
    ground_home: Path,
    net_env: dict[str, str],
    stand_in: Callable[..., StandIn],
) -> None:
    stand_in("hl-wheel-01", silent=True)
    for args in (("ps", "--all", "--json"), ("ps", "--json")):
        result = msctl(ground_home, net_env, *args, "--timeout", "1")
        assert result.returncode == 1, result.stderr + agents.logs()
        why = {u["host"]: u["why"] for u in json.loads(result.stdout)["unreachable"]}
        assert why["hl-wheel-01"] == "no answer", why
        assert "hl-wheel-01 (no answer within 1 s)" in error_line(result.stderr)
        assert "longer --timeout" in error_line(result.stderr)


@pytest.mark.e2e
def test_a_computer_running_the_whole_assembly_off_robot_stands_for_the_plan(
    agents: Agents,
    ground_home: Path,
    net_env: dict[str, str],
    stand_in: Callable[..., StandIn],
) -> None:
    stand_in(
        "sim-laptop",
        document={"host": "sim-laptop", "template": "dragon", "off_robot": True, "components": []},
    )
    result = msctl(ground_home, net_env, "ps", "--all", "--json")
    assert result.returncode == 0, result.stderr + agents.logs()
    document = json.loads(result.stdout)
    assert set(document["hosts"]) == {*RUNNING, "sim-laptop"}
    assert document["unreachable"] == []


@pytest.mark.e2e
def test_doctor_all_names_every_host_that_did_not_answer(
    agents: Agents, ground_home: Path, net_env: dict[str, str]
) -> None:
    result = msctl(ground_home, net_env, "doctor", "--all", "--json", "--clock-timeout", "0.5")
    assert result.returncode == 1, result.stderr + agents.logs()
    findings = json.loads(result.stdout)["findings"]
    reachable = {f["host"]: f for f in findings if f["check"] == "reachable"}
    assert set(reachable) == set(DOWN), reachable
    for finding in reachable.values():
        assert finding["status"] == "ERROR"
        assert finding["detail"].startswith("no supervisor on the graph: start `msctl agent`")
    # The agents that run answered with their own findings.
    assert "hl-limb-01" in {f["host"] for f in findings if f["check"] != "reachable"}


@pytest.mark.e2e
def test_down_all_names_every_host_that_did_not_stop(
    agents: Agents, ground_home: Path, net_env: dict[str, str]
) -> None:
    result = msctl(ground_home, net_env, "down", "--all")
    assert result.returncode == 1, result.stderr + agents.logs()
    line = " ".join(error_line(result.stderr).split())
    said = f"3 host(s) did not stop: {', '.join(DOWN)} (no supervisor on the graph)"
    assert said in line, line
    assert f"none was stopped; idle: {', '.join(RUNNING)}" in line, line
    assert "msctl agent" in line
    for host in DOWN:  # and one line each as they are found
        assert f"{host}: no supervisor on the graph\n" in result.stderr
    # The agents that answered are still there, idle.
    assert all(p.poll() is None for p in agents.procs.values()), agents.logs()


def test_down_all_stops_this_computers_run_even_when_a_host_did_not_stop(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The hosts that did not stop are said last, after this computer's run is stopped."""
    from msctl.commands import down
    from msctl.errors import MsctlError

    done: list[str] = []
    document = {"host": "ground1", "supervisor_pid": 1, "processes": []}
    monkeypatch.setattr(down.state, "read_state", lambda: document)
    monkeypatch.setattr(down.state, "supervisor_alive", lambda d: True)

    def elsewhere(local_runs: bool, local: Any) -> None:
        done.append("elsewhere")
        raise MsctlError("1 host(s) did not stop: hl-wheel-02 (no supervisor on the graph)")

    monkeypatch.setattr(down, "_down_every_host", elsewhere)
    monkeypatch.setattr(down, "_down_here", lambda *args: done.append("here"))
    with pytest.raises(MsctlError, match="hl-wheel-02"):
        down.command(all_hosts=True, timeout=1.0)
    assert done == ["elsewhere", "here"]
