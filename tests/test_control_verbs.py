"""The supervisor's control verbs from the CLI (``stop``, ``restart``, ``logs``, ``down``) where
they went wrong: a supervisor that died, a name nothing runs, no network, the router that
carries the requests, and what a stop takes with a process. Each on the real command in a
subprocess, a random loopback port, an ``MSCTL_HOME`` of its own (the stop on a detached
``msctl up minimal`` of the module's own, which it restarts)."""

from __future__ import annotations

import json
import os
import signal
from collections.abc import Iterator

import msgspec
import pytest
from conftest import wait_until
from home_rig import Home, home  # noqa: F401  (home: the fixture)
from running import Up

from msctl.launcher.state import process_group_alive

pytestmark = [pytest.mark.e2e, pytest.mark.timeout(600)]


def test_down_after_the_supervisor_died_kills_what_it_left_and_says_so(home: Home) -> None:  # noqa: F811
    # A supervisor SIGKILLed (OOM killer, power blip of a terminal): `ps` went on showing every
    # component "running" from the state file, and `down` said "nothing is running on this
    # computer" while it killed the groups left behind, leaving the state file "running".
    result = home.msctl("up", "minimal", "--detach", timeout=90.0)
    assert result.returncode == 0, result.stderr
    document = home.state()
    groups = {p["name"]: p["pgid"] for p in document["processes"] if p["pgid"]}
    os.kill(document["supervisor_pid"], signal.SIGKILL)
    wait_until(lambda: not process_group_alive(document["supervisor_pid"]), what="supervisor gone")

    ps = home.msctl("ps", "--json")
    assert ps.returncode == 0, ps.stderr
    listed = json.loads(ps.stdout)
    assert listed["components"]
    assert not [c["name"] for c in listed["components"] if c["state"] == "running"]
    assert any("msctl down" in note for note in listed["notes"]), listed["notes"]

    down = home.msctl("down", timeout=30.0)
    assert down.returncode == 0, down.stderr
    assert "nothing is running" not in down.stderr
    assert "killed" in down.stderr and "limb1" in down.stderr, down.stderr
    for name, pgid in groups.items():
        assert not process_group_alive(pgid), f"{name} (group {pgid}) left after down"
    assert home.state()["state"] == "stopped"
    after = json.loads(home.msctl("ps", "--json").stdout)
    assert not [c["name"] for c in after["components"] if c["state"] == "running"]


def test_unknown_component_is_not_found_exit_4(home: Home) -> None:  # noqa: F811
    # `msctl restart/stop/logs NAME` of a name nothing runs: exit 1 (restart, stop) or 3 (logs,
    # "cannot get the log ... from <host>", as if the network failed) instead of 4, not found.
    result = home.msctl("up", "minimal", "--detach", timeout=90.0)
    assert result.returncode == 0, result.stderr
    try:
        for verb in ("restart", "stop", "logs"):
            answer = home.msctl(verb, "limb9/joint_manager")
            assert answer.returncode == 4, (verb, answer.returncode, answer.stderr)
            assert "limb9/joint_manager" in answer.stderr and "msctl ps" in answer.stderr
            assert "limb1/joint_manager" in answer.stderr  # what does run
            assert answer.stdout == ""
        ok = home.msctl("restart", "limb1/joint_manager")
        assert ok.returncode == 0, ok.stderr
    finally:
        assert home.msctl("down", timeout=30.0).returncode == 0


def test_logs_of_a_component_with_no_network_names_the_component(home: Home) -> None:  # noqa: F811
    # Nothing ran here and no router: the one line named only the router, not what was asked.
    answer = home.msctl("logs", "limb1/joint_manager")
    assert answer.returncode == 3, answer.stderr
    assert "no log for 'limb1/joint_manager' on this computer" in answer.stderr
    assert "no Zenoh router reachable" in answer.stderr


def test_the_embedded_router_is_restarted_not_stopped_through_the_control_service(
    home: Home,  # noqa: F811
) -> None:
    # `msctl stop router` stopped the router that carries every request: the reply was lost
    # (exit 3) and nothing could reach the supervisor again, not even `msctl restart router`.
    # `msctl restart router` did restart it, but its reply was lost the same way (exit 3).
    result = home.msctl("up", "minimal", "--detach", timeout=90.0)
    assert result.returncode == 0, result.stderr
    try:
        first = {p["name"]: p["pid"] for p in home.state()["processes"]}["router"]
        stop = home.msctl("stop", "router")
        assert stop.returncode == 1, stop.stderr
        assert "msctl restart router" in stop.stderr and "msctl down" in stop.stderr
        restart = home.msctl("restart", "router")
        assert restart.returncode == 0, restart.stderr
        assert "router" in restart.stderr
        wait_until(
            lambda: (
                {p["name"]: p["pid"] for p in home.state()["processes"]}["router"]
                not in (None, first)
            ),
            timeout=10.0,
            what="a new router process",
        )
        wait_until(
            lambda: home.msctl("restart", "limb1/joint_manager").returncode == 0,
            timeout=20.0,
            what="requests reach the supervisor again",
        )
    finally:
        assert home.msctl("down", timeout=30.0).returncode == 0


@pytest.fixture(scope="module")
def minimal(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Up]:
    up = Up(tmp_path_factory.mktemp("control_verbs"), "minimal")
    try:
        yield up
    finally:
        up.down()


def _rows(up: Up) -> dict[str, dict]:
    result = up.msctl("ps", "--json")
    assert result.returncode == 0, result.stderr
    return {row["name"]: row for row in json.loads(result.stdout)["components"]}


def _all_running(up: Up) -> dict[str, dict] | None:
    rows = _rows(up)
    return rows if all(r["state"] == "running" for r in rows.values()) else None


def _said(result) -> str:
    assert result.returncode == 0, result.stderr
    return " ".join(result.stderr.split())


# Issue 18, point 9: what an action does to a running assembly, said exactly.
def test_stop_names_the_components_it_takes_with_the_process(minimal: Up) -> None:
    before = wait_until(lambda: _all_running(minimal), 90.0, "all running", interval=0.5)
    others = sorted(n for n, r in before.items() if r["process"] == "limb1")
    others.remove("limb1/health_monitor")
    said = _said(minimal.msctl("stop", "limb1/health_monitor"))
    assert "process limb1 is stopped" in said, said
    assert all(name in said for name in others) and "share the process" in said, said
    rows = _rows(minimal)
    assert {rows[n]["state"] for n in [*others, "limb1/health_monitor"]} == {"stopped"}
    # A process named: its components are the process's own, no "--only limb1" (refused).
    said = _said(minimal.msctl("restart", "limb1"))
    assert "process limb1 is starting, and with it every component it runs" in said, said
    assert all(name in said for name in [*others, "limb1/health_monitor"]), said
    assert "--only limb1" not in said and "share the process" not in said, said
    assert "`msctl restart --only COMPONENT` restarts one of them alone" in said, said
    wait_until(lambda: _all_running(minimal), 90.0, "all running again", interval=0.5)


def test_a_real_supervisors_ps_answer_is_its_typed_document(minimal: Up) -> None:
    """Every field a running supervisor sends in its ``ps`` answer is a field of
    :class:`~components.supervision.protocol.RunDocument` and its rows: decoded typed, or read
    by the field names as ``msctl ps`` does, nothing of it is lost."""
    from components.comm.node import Node
    from components.comm.session import open_session
    from components.supervision.contract import ps_document
    from components.supervision.protocol import run_document
    from components.supervision.wire import call_supervisor

    wait_until(lambda: _all_running(minimal), 90.0, "all running", interval=0.5)
    with open_session(minimal.settings()) as session, Node(session, "ps_reader") as node:
        sent = call_supervisor(node, "test-laptop", "ps", timeout=10.0)
    assert sent["components"] and sent["processes"]
    typed = run_document(json.dumps(sent))
    assert typed is not None
    assert json.loads(json.dumps(ps_document(sent))) == sent
    assert {k: v for k, v in msgspec.to_builtins(typed).items() if k in sent} == sent
