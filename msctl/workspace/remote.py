"""``msctl update --all`` and ``msctl build --all``: every robot computer's agent updates and
builds its own workspace (the paper's network-synchronised orchestrators).

Each ``msctl agent`` serves ``/msctl/<host>/workspace`` (``msctl_msgs/srv/AgentRequest``,
the agent's own request type) beside its ``/request``. A request is a verb and a JSON
object:

- ``update``: ``repos`` (``{"name", "text"}``, the .repos file's content), ``overlays`` (a
  list of the same), ``offline``, ``shallow``;
- ``build``: ``packages_up_to`` (package names), ``offline``;
- ``progress``: what the running (or last) job has done so far.

What is sent is checked as data: the files are parsed exactly as a local ``msctl update``
parses them (paths inside the workspace, git URLs without shell metacharacters or
``transport::`` forms, plain ref names), file and package names are plain names, and
nothing else is accepted: no command line, no path. The workspace directory (and the
wheelhouse of an offline build) are the agent's own settings (``MSCTL_WORKSPACE``,
``MSCTL_WHEELHOUSE``), never part of a request. The build commands that run are those of
the packages in that workspace.

An update or build runs on the agent's own worker thread, one at a time (a second request
meanwhile is refused, naming the first); the ground station asks for ``progress`` every
half second until every agent is done, and shows one combined view. Unreachable agents are
named: those of the resolved assembly's computers that serve nothing, and those that stop
answering mid-job (once the agent has been out of the graph for :data:`GONE_AFTER` seconds,
else after :data:`SILENT_AFTER` seconds without an answer), with how far they had got. A
moment out of the graph is not leaving it: a computer whose CPU is taken (five builds
starting at once) can miss its 1 s lease, and its tokens come back as its session
reconnects, the job still running.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

from msctl.errors import MsctlError, NetworkError
from msctl.workspace.service import SERVICE, Refused

#: Seconds an agent asked for progress must stay out of the graph to be named unreachable
#: (it left: its computer is down, its agent died, its radio link is gone).
GONE_AFTER = 5.0
#: Seconds without an answer after which an agent still in the graph is unreachable.
SILENT_AFTER = 15.0
# --------------------------------------------------------------------------- the ground station
#: :meth:`Unanswered.failed`'s verdicts: the agent left the graph, or stayed silent in it.
LEFT, SILENT = "left", "silent"


class Unanswered:
    """When an agent asked for its job's progress, that stopped answering, is unreachable.

    Once it has been out of the graph for :data:`GONE_AFTER` seconds (it left: its computer
    is down, its agent died, its radio link is gone), or without an answer for
    :data:`SILENT_AFTER` seconds while in it. Not at the first ask it missed out of the
    graph: a computer whose CPU is taken misses its 1 s lease, its tokens leave for a
    moment and come back as its session reconnects, its job still running.

    Args:
        namespaces: The agents asked (their host namespaces).
        now: The time their job started (seconds, a monotonic clock).
    """

    def __init__(self, namespaces: Iterable[str], now: float):
        self._answered = dict.fromkeys(namespaces, now)
        self._out: dict[str, float] = {}

    def answered(self, namespace: str, now: float) -> None:
        """The agent answered at ``now``."""
        self._answered[namespace] = now
        self._out.pop(namespace, None)

    def failed(self, namespace: str, now: float, in_graph: bool) -> str | None:
        """The agent did not answer at ``now``; ``in_graph``: the graph shows its service.

        Returns:
            :data:`LEFT` or :data:`SILENT` when it is unreachable now, else ``None`` (ask
            again).
        """
        if in_graph:
            self._out.pop(namespace, None)
        else:
            self._out.setdefault(namespace, now)
        if now - self._out.get(namespace, now) >= GONE_AFTER:
            return LEFT
        if now - self._answered.get(namespace, now) >= SILENT_AFTER:
            return SILENT
        return None


#: Stages after which an item is done, for the combined progress bar.
_DONE = {"cloned", "updated", "unchanged", "refused", "failed", "built", "up to date"}
_DONE |= {"blocked", "skipped"}


def workspace_services(node: Any, timeout: float = 1.0) -> dict[str, str]:
    """``{host namespace: service}`` of every agent serving workspace requests (the graph's
    answer within ``timeout`` seconds)."""
    from components.comm.graph import snapshot
    from components.comm.types import dds_type_name
    from components.supervision.contract import AGENT_SRV

    # Only the servers of AgentRequest (zid/node/entity/SS/enclave/namespace/node/service/
    # type/hash/qos), as fleet.supervisors asks: not every token of the fleet.
    servers = f"*/*/*/SS/*/*/*/*/{dds_type_name(AGENT_SRV)}/*/*"
    found = {}
    graph = snapshot(node.session, node.domain, timeout, tokens=servers)
    for name, info in graph.services().items():
        if name.startswith("/msctl/") and name.endswith(f"/{SERVICE}") and AGENT_SRV in info.types:
            found[name[: -len(SERVICE) - 1]] = name
    return found


def _expected_namespaces() -> dict[str, str]:
    """``{namespace: host}`` of the resolved assembly's computers (none if nothing is
    resolved): the agents that should answer."""
    from components.assembly import AssemblyError, load_assembly
    from components.supervision.contract import host_namespace

    try:
        assembly = load_assembly()
    except (AssemblyError, OSError):
        return {}
    return {host_namespace(h): h for h in assembly.hosts}


def update_all(
    repos: Path,
    overlays: Sequence[Path],
    offline: bool,
    shallow: bool,
    json_output: bool,
    timeout: float,
) -> None:
    """Ask every agent to update its workspace from these files (read and checked here
    first, then sent as they are)."""
    from msctl.workspace.repos import load

    load(repos, overlays)  # the same refusal here as on every robot, said once
    args = {
        "repos": {"name": repos.name, "text": repos.read_text(encoding="utf-8")},
        "overlays": [{"name": p.name, "text": p.read_text(encoding="utf-8")} for p in overlays],
        "offline": offline,
        "shallow": shallow,
    }
    _run_all("update", args, json_output, timeout)


def build_all(packages_up_to: list[str], offline: bool, json_output: bool, timeout: float) -> None:
    """Ask every agent to build its workspace."""
    _run_all("build", {"packages_up_to": packages_up_to, "offline": offline}, json_output, timeout)


def _call(node: Any, service: str, verb: str, args: dict[str, Any], timeout: float) -> Any:
    from components.supervision.contract import RequestError
    from components.supervision.wire import SupervisorClient

    client = SupervisorClient(node, service)
    try:
        return client.payload(verb, args, timeout)
    except RequestError as exc:
        raise Refused(str(exc)) from None
    finally:
        client.close()


class Problem(NamedTuple):
    """Why an agent's job is not done: said in its row of the summary."""

    text: str


def _run_all(verb: str, args: dict[str, Any], json_output: bool, timeout: float) -> None:
    from msctl.plane import connected

    expected = _expected_namespaces()
    with connected(f"{verb}_all") as node:
        services = _discover(node, expected)
        problems = {
            namespace: f"unreachable: no agent serves {namespace}/{SERVICE}"
            for namespace in expected
            if namespace not in services
        }
        if not services and not expected:
            raise NetworkError(
                f"no agent serves /msctl/<host>/{SERVICE} on this network",
                hint="start `msctl agent` on each robot computer (or `msctl agent install`)",
            )
        replies = _start_jobs(node, services, verb, args)
        problems.update({ns: p.text for ns, p in replies.silent.items()})
        final, unfinished = _follow_jobs(node, services, verb, replies.answers, timeout)
        problems.update(unfinished)
    # Each agent said its host's name when it started: name it so, not by its namespace.
    started = replies.answers
    hosts = {**expected, **{ns: a["host"] for ns, a in started.items() if a.get("host")}}
    document = _summarise(verb, final, problems, hosts)
    _print_outcome(verb, document, json_output)
    bad = [h for h in document["hosts"] if not h["ok"]]
    if bad:
        raise MsctlError(
            f"{verb} did not succeed on {', '.join(h['host'] for h in bad)} (the other "
            "agents' workspaces were done)",
            hint="see the note of each; `msctl agent` logs on the robot say more",
            exit_code=1,
        )


def _start_jobs(node: Any, services: dict[str, str], verb: str, args: dict[str, Any]) -> Any:
    """Ask every agent to start its job, all at once; the answers, and a :class:`Problem`
    for each agent that refused or did not answer (:func:`fanout.ask_each`)."""
    from components.comm.services import ServiceError
    from msctl.console import err
    from msctl.launcher.fanout import ask_each

    def ask(namespace: str) -> Any:
        try:
            return _call(node, services[namespace], verb, args, 10.0)
        except Refused as exc:
            return Problem(f"refused: {exc}")
        except ServiceError as exc:
            return Problem(f"unreachable: {exc}")

    namespaces = sorted(services)
    for namespace in namespaces:
        err.print(f"[dim]asking {namespace} to {verb}...[/]", highlight=False)
    return ask_each(namespaces, ask, lambda result: isinstance(result, Problem))


def _follow_jobs(
    node: Any,
    services: dict[str, str],
    verb: str,
    started: dict[str, dict[str, Any]],
    timeout: float,
) -> tuple[dict[str, dict[str, Any]], dict[str, str]]:
    """Ask every started agent for its job's progress, all at once, every half second, and
    show it (:func:`fanout.rounds`) until each is done, gone or the time is up.

    Returns:
        The final progress of each agent whose job ended, and the problem of each other.
    """
    from components.comm.services import ServiceError
    from msctl.launcher.fanout import progress, rounds

    with progress("{task.completed}/{task.total}", "{task.fields[stage]}", bar_width=20) as view:
        rows = {
            ns: view.add_task(answer.get("host", ns), total=None, stage="starting")
            for ns, answer in started.items()
        }
        follow = _JobFollower(node, verb, started, view, rows)

        def look(namespace: str) -> Any:
            try:
                return _call(node, services[namespace], "progress", {}, 3.0)
            except (Refused, ServiceError) as exc:
                return exc

        def settle(results: dict[str, Any]) -> set[str]:
            return {ns for ns, result in results.items() if follow.settled(ns, result)}

        waiting = rounds(started, look, settle, time.monotonic() + timeout, 0.5)
    final, problems = follow.final, follow.problems
    for namespace in waiting:
        problems[namespace] = f"still running after {timeout:g} s (see its agent's log)"
    return final, problems


class _JobFollower:
    """What each progress answer (or failure to answer) means for an agent's job."""

    def __init__(
        self,
        node: Any,
        verb: str,
        started: dict[str, dict[str, Any]],
        view: Any,
        rows: dict[str, Any],
    ) -> None:
        self.node = node
        self.verb = verb
        self.started = started
        self.view = view
        self.rows = rows
        self.watch = Unanswered(started, time.monotonic())
        self.last_seen: dict[str, str] = {}
        self.final: dict[str, dict[str, Any]] = {}
        self.problems: dict[str, str] = {}

    def settled(self, namespace: str, result: Any) -> bool:
        """Show ``result`` (a progress answer, or the error of asking); whether the agent's
        job is settled now (done, or the agent named unreachable or restarted)."""
        if isinstance(result, Exception):
            return self._unanswered(namespace, result)
        self.watch.answered(namespace, time.monotonic())
        job = result.get("job") or {}
        asked = (self.started[namespace].get("job") or {}).get("id")
        if job.get("id") != asked:
            self.problems[namespace] = (
                f"its agent restarted during the {self.verb} (job {asked} is gone); ask again"
            )
            self.view.update(self.rows[namespace], stage="[red]restarted[/]")
            return True
        items = job.get("items", {})
        done = sum(stage in _DONE for stage in items.values())
        busy = [n for n, s in items.items() if s not in _DONE and s != "waiting"]
        self.last_seen[namespace] = f"{done}/{len(items)} done" + (
            f", {', '.join(busy[:3])}" if busy else ""
        )
        self.view.update(
            self.rows[namespace],
            total=len(items) or None,
            completed=done,
            stage=", ".join(busy[:3]) if job.get("state") == "running" else "done",
        )
        if job.get("state") == "done":
            self.final[namespace] = result
            return True
        return False

    def _unanswered(self, namespace: str, exc: Exception) -> bool:
        # A robot whose agent died or whose radio link dropped mid-job is named within
        # seconds, not after the whole --timeout: once its agent has stayed out of the
        # graph, else once it stayed silent. A generous wait for the graph's answer: on a
        # loaded link an answer cut short would read as the agent gone.
        now = time.monotonic()
        seen = namespace in workspace_services(self.node, timeout=5.0)
        verdict = self.watch.failed(namespace, now, seen)
        if verdict is None:
            self.view.update(self.rows[namespace], stage=f"[yellow]{exc}[/]")
            return False
        why = "its agent left the network" if verdict == LEFT else str(exc)
        last = self.last_seen.get(namespace)
        self.problems[namespace] = f"unreachable during the {self.verb}: {why}" + (
            f" (last seen: {last})" if last else ""
        )
        self.view.update(self.rows[namespace], stage="[red]unreachable[/]")
        return True


def _print_outcome(verb: str, document: dict[str, Any], json_output: bool) -> None:
    """Every host's outcome: one JSON document, or a table."""
    from rich.markup import escape
    from rich.table import Table

    from msctl.console import out, print_json

    if json_output:
        print_json(document)
        return
    table = Table(title=f"{verb} on every agent", title_justify="left")
    for column in ("host", "result", "done", "not done", "note"):
        table.add_column(column, overflow="fold")
    for host in document["hosts"]:
        colour = "green" if host["ok"] else "red"
        table.add_row(
            escape(host["host"]),
            f"[{colour}]{'ok' if host['ok'] else 'failed'}[/]",
            str(len(host["done"])),
            escape(", ".join(host["not_done"])),
            escape(host["note"]),
        )
    out.print(table)


def _discover(node: Any, expected: dict[str, str], settle: float = 3.0) -> dict[str, str]:
    """The agents' services, waiting a moment for the graph to show the expected ones."""
    deadline = time.monotonic() + settle
    services = workspace_services(node)
    while time.monotonic() < deadline and not (services and set(expected) <= set(services)):
        time.sleep(0.1)
        services = workspace_services(node)
    return services


def _summarise(
    verb: str,
    final: dict[str, dict[str, Any]],
    problems: dict[str, str],
    names: dict[str, str],
) -> dict[str, Any]:
    """One document of every host's outcome (``names``: host of each namespace known)."""
    hosts = [_host_outcome(verb, namespace, state) for namespace, state in sorted(final.items())]
    for namespace, problem in sorted(problems.items()):
        host = names.get(namespace, namespace.rsplit("/", 1)[-1])
        hosts.append(
            {
                "host": host,
                "workspace": None,
                "ok": False,
                "done": [],
                "not_done": [],
                "note": problem,
                "result": None,
            }
        )
    return {"verb": verb, "ok": all(h["ok"] for h in hosts), "hosts": hosts}


def _host_outcome(verb: str, namespace: str, state: dict[str, Any]) -> dict[str, Any]:
    """One host's outcome from its agent's last job state."""
    job = state.get("job") or {}
    result = job.get("result")
    done, not_done = _done_and_not(verb, result)
    return {
        "host": state.get("host", namespace),
        "workspace": state.get("workspace"),
        "ok": bool(job.get("ok")),
        "done": done,
        "not_done": not_done,
        "note": _failure_note(verb, job, result),
        "result": result,
    }


def _done_and_not(verb: str, result: Any) -> tuple[list[str], list[str]]:
    """The repositories (``update``) or packages (``build``) a job did and did not do."""
    done: list[str] = []
    not_done: list[str] = []
    if verb == "update" and isinstance(result, list):
        for outcome in result:
            (done if outcome.get("ok") else not_done).append(outcome["path"])
    elif verb == "build" and isinstance(result, dict):
        for package in result.get("packages", []):
            ok = package.get("status") in ("built", "up to date", "skipped")
            (done if ok else not_done).append(package["name"])
    return done, not_done


def _failure_note(verb: str, job: dict[str, Any], result: Any) -> str:
    """Why a job failed: its error, else what each failed repository or package said."""
    note = job.get("error", "")
    if not note and verb == "update" and isinstance(result, list):
        note = "; ".join(f"{o['path']}: {o['reason']}" for o in result if not o.get("ok"))
    if not note and verb == "build" and isinstance(result, dict):
        note = "; ".join(
            f"{p['name']}: {p['step']}: {p['message'].splitlines()[0]}"
            for p in result.get("packages", [])
            if p.get("status") in ("failed", "blocked") and p.get("message")
        )
    return note
