"""``msctl down``: stop everything (this computer's run, and with --all every host's)."""

from __future__ import annotations

import contextlib
import os
import signal
import time
from typing import Any

import typer

from msctl.errors import MsctlError
from msctl.launcher import state

COMMAND_SETTINGS = {"help": "Stop every component (verified gone); --all for every host."}


def command(
    all_hosts: bool = typer.Option(False, "--all", help="Also stop every agent's run."),
    timeout: float = typer.Option(15.0, "--timeout", help="Seconds to wait for everything to end."),
) -> None:
    """Stop the run on this computer (and every host with --all), then check nothing is left."""
    from msctl.console import err

    document = state.read_state()
    local_runs = bool(document) and state.supervisor_alive(document)
    if all_hosts:
        _down_every_host(local_runs)
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


def _down_every_host(local_runs: bool) -> None:
    """Ask every agent to stop its run; no router and nothing here means nothing runs."""
    from msctl.console import err
    from msctl.errors import NetworkError
    from msctl.launcher.fleet import ask_all
    from msctl.plane import connected

    try:
        with connected("down") as node:
            # An agent answers once its processes are gone: up to the shutdown policy's 3 s
            # of grace each, more on a loaded computer. All are asked at once, and the bound
            # costs nothing when they answer sooner.
            answers = ask_all(node, "down", timeout=20.0)
            there = _still_there(node, [n for n, a in answers.items() if "error" in a])
    except NetworkError as exc:
        if local_runs:
            raise  # a supervisor runs here, yet its router is gone: worth saying loudly
        # Agents and supervisors serve through a router; with none, none can run anything
        # the operator could reach: the goal of `down` is met.
        err.print(f"nothing is running ({exc.message}, and no supervisor runs here)")
        return
    failed = []
    idle = []  # agents that ran nothing: nothing of theirs was stopped
    for namespace, answer in answers.items():
        if "error" not in answer and answer.get("stopped") == [] and not answer.get("template"):
            idle.append(answer.get("host") or namespace)
        elif "error" not in answer:
            # An agent answers once its run is gone; a supervisor, as it begins to stop.
            what = f"stopped {answer['template']}" if answer.get("template") else "stopping"
            err.print(f"{namespace}: {what}", highlight=False)
        elif namespace in there:
            err.print(f"{namespace}: {answer['error']}", highlight=False)
            failed.append(namespace)
        else:
            err.print(f"{namespace}: left the network before it could be asked", highlight=False)
    failed.sort()
    if failed:
        raise MsctlError(
            f"{', '.join(failed)} did not stop: {answers[failed[0]]['error']}",
            hint=_identity_hint() or "see them with `msctl ps`; run `msctl down --all` again",
        )
    if not answers and not local_runs:
        if hint := _identity_hint():
            # A fleet's access control hides supervisors from who may not stop them: an
            # empty answer proves nothing runs only to an operator.
            raise MsctlError("no agent or supervisor answered, so nothing was stopped", hint=hint)
        err.print("nothing is running: no agent or supervisor answered")
    elif idle and len(idle) == len(answers) and not local_runs:
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
