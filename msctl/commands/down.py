"""``msctl down``: stop everything (this computer's run, and with --all every host's)."""

from __future__ import annotations

import contextlib
import os
import signal
import time
from typing import Any

import typer

from components.errors import ComponentError
from msctl.errors import MsctlError
from msctl.launcher import state

COMMAND_SETTINGS = {"help": "Stop every component (verified gone); --all for every host."}


def command(
    all_hosts: bool = typer.Option(
        False,
        "--all",
        help="Also stop every agent's run: every supervisor on the graph and every host of the "
        "resolved assembly's plan; exit 1 naming each that did not stop (no supervisor on the "
        "graph, no answer, refused).",
    ),
    timeout: float = typer.Option(15.0, "--timeout", help="Seconds to wait for everything to end."),
) -> None:
    """Stop the run on this computer (and every host with --all), then check nothing is left."""
    from rich.markup import escape

    from msctl.console import err

    document = state.read_state()
    local_runs = bool(document) and state.supervisor_alive(document)
    elsewhere: ComponentError | None = None
    if all_hosts:
        try:
            _down_every_host(local_runs, document)
        except ComponentError as exc:  # msctl's, or the runtime's (bad session settings)
            # This computer's run is stopped all the same; what did not stop is said last.
            elsewhere = exc
    try:
        _down_here(document, local_runs, all_hosts, timeout)
    except ComponentError:
        if elsewhere is not None:
            err.print(f"[bold red]error:[/] {escape(str(elsewhere))}", highlight=False)
        raise
    if elsewhere is not None:
        raise elsewhere


def _down_here(
    document: dict[str, Any] | None, local_runs: bool, all_hosts: bool, timeout: float
) -> None:
    """Stop this computer's run (through its agent when it has one) and check nothing of it
    is left; a dead supervisor's leftovers are killed.

    Raises:
        MsctlError: If processes are still alive after it.
    """
    from msctl.console import err

    if not local_runs:
        # A supervisor that died (SIGKILL, OOM) leaves its process groups behind: kill them,
        # say so, and make the state file stop claiming they run.
        left = state.groups_left(document) if document else []
        _kill_leftovers((document or {}).get("processes", []))
        if document and document.get("state") != "stopped":
            _mark_stopped(document)
        if left:
            deadline = time.monotonic() + 5.0  # SIGKILLed, but a big process takes a moment
            while state.groups_left(document) and time.monotonic() < deadline:
                time.sleep(0.05)
            still = state.groups_left(document)
            if still:
                raise MsctlError(f"processes still alive after down: {', '.join(still)}")
            err.print(
                f"[green]down[/]: the supervisor of {document.get('template')} on "
                f"{document.get('host')} was gone; killed what it left: {', '.join(left)}",
                highlight=False,
            )
        elif not all_hosts:
            err.print("nothing is running on this computer")
        return
    if document.get("agent"):
        _down_through_agent(document)
        return
    pid = document["supervisor_pid"]
    os.kill(pid, signal.SIGTERM)
    deadline = time.monotonic() + timeout
    # Until the supervisor itself has exited, not only marked its state stopped: "down"
    # promises nothing is left.
    while time.monotonic() < deadline and state.pid_alive(pid):
        time.sleep(0.05)
    if state.pid_alive(pid):
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    _kill_leftovers(document.get("processes", []))
    still = state.groups_left(document)
    if still:
        raise MsctlError(f"processes still alive after down: {', '.join(still)}")
    err.print(
        f"[green]down[/]: {document.get('template')} stopped on {document.get('host')}, "
        "nothing left"
    )


def _down_every_host(local_runs: bool, local: dict[str, Any] | None) -> None:
    """Ask every agent and supervisor to stop its run, and every host of the resolved
    assembly's plan even if the graph does not show it.

    Raises:
        MsctlError: Naming every host that did not stop (a plan host with no supervisor on
            the graph, one that did not answer, one that refused) and those that did.
        NetworkError: If no router answers while a supervisor runs here, or while the plan
            names hosts that may still run (unless the last run here was the whole assembly).
    """
    from msctl.console import err
    from msctl.errors import NetworkError
    from msctl.launcher.control import host_namespace
    from msctl.launcher.fleet import (
        ask_hosts,
        describe,
        expected_hosts,
        hosts_to_ask,
        read_plan,
        supervisors,
    )
    from msctl.plane import connected

    plan = read_plan()
    try:
        with connected("down") as node:
            found = supervisors(node)
            planned = hosts_to_ask(node, plan, found)
            # An agent answers once its processes are gone: up to the shutdown policy's 3 s
            # of grace each, more on a loaded computer. All are asked at once, and the bound
            # costs nothing when they answer sooner.
            asked = ask_hosts(node, "down", planned, None, 20.0, found)
            owed = {host_namespace(h) for h in planned}
            there = _still_there(node, [n for n in asked.silent if n in found and n not in owed])
    except NetworkError as exc:
        if local_runs:
            raise  # a supervisor runs here, yet its router is gone: worth saying loudly
        # With no router, nothing the operator could reach through it runs here; but the
        # plan's computers have routers of their own and may run on. Unless this computer's
        # last run was the whole assembly off-robot (their stand-in), they are not known
        # to have stopped.
        hosts = expected_hosts(plan, [local] if local else [])
        if hosts:
            raise NetworkError(
                f"could not ask {', '.join(hosts)} ({plan.template}'s plan) to stop: "
                f"{exc.message}; nothing was stopped there",
                hint="start this computer's router (`msctl router`, or its `msctl agent`) or "
                "point MSCTL_ZENOH_CONNECT at one, then run `msctl down --all` again",
            ) from exc
        # Agents and supervisors serve through a router; with none, none can run anything
        # the operator could reach: the goal of `down` is met.
        err.print(f"nothing is running ({exc.message}, and no supervisor runs here)")
        return
    stopped = []
    idle = []  # agents that ran nothing: nothing of theirs was stopped
    for namespace, answer in asked.answers.items():
        host = answer.get("host") or namespace
        if answer.get("stopped") == [] and not answer.get("template"):
            idle.append(host)
        else:
            # An agent answers once its run is gone; a supervisor, as it begins to stop.
            what = f"stopped {answer['template']}" if answer.get("template") else "stopping"
            err.print(f"{namespace}: {what}", highlight=False)
            stopped.append(host)
    failed = []
    for namespace, silence in asked.silent.items():
        if namespace in owed or namespace in there:
            err.print(f"{silence.host}: {silence.detail}", highlight=False)
            failed.append(silence)
        else:
            err.print(f"{namespace}: left the network before it could be asked", highlight=False)
    if failed:
        done = f"stopped: {', '.join(stopped)}" if stopped else "none was stopped"
        if idle:
            done += f"; idle: {', '.join(sorted(idle))}"
        raise MsctlError(
            f"{len(failed)} host(s) did not stop: {describe(failed)}; {done}",
            hint=_identity_hint()
            or "check that `msctl agent` runs there and its router links to this one "
            "(`msctl doctor --all`), then run `msctl down --all` again; `msctl ps --all` "
            "shows what still runs",
        )
    if not asked.answers and not local_runs:
        if hint := _identity_hint():
            # A fleet's access control hides supervisors from who may not stop them: an
            # empty answer proves nothing runs only to an operator.
            raise MsctlError("no agent or supervisor answered, so nothing was stopped", hint=hint)
        err.print("nothing is running: no agent or supervisor answered")
    elif idle and len(idle) == len(asked.answers) and not local_runs:
        err.print(
            f"nothing is running: the agents of {', '.join(sorted(idle))} run nothing",
            highlight=False,
        )
    elif idle:
        err.print(f"idle, nothing to stop: {', '.join(sorted(idle))}", highlight=False)


def _still_there(node: Any, namespaces: list[str], settle: float = 2.0) -> set[str]:
    """Which of ``namespaces`` are still on the graph after ``settle`` s at most.

    A supervisor that could not be asked but left the network meanwhile (its agent stopped;
    its token outlives it by a moment) is gone, not refusing.
    """
    from msctl.launcher.fleet import supervisors

    deadline = time.monotonic() + settle
    there = set(namespaces)
    while there:
        there &= set(supervisors(node))
        if not there or time.monotonic() > deadline:
            break
        time.sleep(0.1)
    return there


def _identity_hint() -> str | None:
    """Why a secured fleet may not answer this identity (None: no identity, or an operator)."""
    identity = os.environ.get("MSCTL_IDENTITY")
    if not identity:
        return None
    from msctl.net import pki

    identities = pki.net_dir() / "identities"
    if (identities / f"{pki.OPERATOR_PREFIX}{identity}".replace(":", "-")).is_dir():
        return None
    return (
        f"MSCTL_IDENTITY={identity} is not an operator of this fleet, and a secured fleet "
        "answers only operators' requests (ground stations' too, on robot routers): set "
        "MSCTL_IDENTITY to an operator (`msctl net add-operator NAME`)"
    )


def _down_through_agent(document: dict) -> None:
    """This computer's run belongs to its agent: ask it (it stays up, idle, for the next run)."""
    from components.comm.services import ServiceTimeout
    from msctl.console import err
    from msctl.errors import NetworkError
    from msctl.launcher.control import RequestError, call_supervisor
    from msctl.plane import connected

    host = document["host"]
    with connected("down") as node:
        try:
            call_supervisor(node, host, "down", timeout=20.0)
        except (ServiceTimeout, RequestError) as exc:
            raise NetworkError(f"the agent of {host} did not stop its run: {exc}") from exc
    still = state.groups_left(document)
    if still:
        raise MsctlError(f"processes still alive after down: {', '.join(still)}")
    err.print(
        f"[green]down[/]: the agent of {host} stopped {document.get('template')}; it stays up"
    )


def _mark_stopped(document: dict) -> None:
    """Rewrite a dead supervisor's state file as stopped (no pids, nothing running)."""
    stopped = {"state": "stopped", "pid": None, "pgid": None}
    state.write_state(
        {
            **document,
            "state": "stopped",
            "processes": [{**p, **stopped} for p in document.get("processes", [])],
            "components": [
                {**c, "state": "stopped", "pid": None} for c in document.get("components", [])
            ],
        }
    )


def _kill_leftovers(processes: list[dict]) -> None:
    for process in processes:
        pgid = process.get("pgid")
        if pgid and state.group_alive(pgid):
            try:
                os.killpg(pgid, signal.SIGKILL)
            except ProcessLookupError:
                pass
