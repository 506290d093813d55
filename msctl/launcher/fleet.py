"""Finding and asking every supervisor on the network (this computer's and the agents'), and
saying which hosts that should have answered did not.

The hosts that should answer are those of this computer's resolved assembly (the lock that
``msctl assemble`` wrote into MSCTL_HOME: every robot computer of its modules and every ground
station), plus any other supervisor the graph shows. The lock is read here as plain JSON, not
through :mod:`components.assembly`'s schema: ``msctl ps`` reads it on every run and must not
pay for msgspec and the module specs (see :mod:`msctl.quick`). For the same reason the ``ps``
answers are read by their typed struct's field names
(:func:`components.supervision.contract.ps_document`), not decoded by msgspec.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any, NamedTuple

from components.paths import state_dir
from components.supervision.contract import AGENT_SRV, encode_args, host_namespace, ps_document
from msctl.launcher import state
from msctl.launcher.fanout import ask_each

#: Why a host did not answer (:attr:`Silence.why`): no supervisor of it on the graph (the
#: query ended at once: no server known), ...
NO_SUPERVISOR = "no supervisor"
#: ... one is there but its answer did not come within the timeout, ...
NO_ANSWER = "no answer"
#: ... it answered with an error instead, ...
REFUSED = "refused"
#: ... or there was no router to ask through at all.
NO_NETWORK = "no network"

#: What a plan host the graph does not show is told when it was not asked (plain ``ps``).
NOT_ASKED = "no supervisor on the graph (not asked: `msctl ps --all` asks it)"


class Silence(NamedTuple):
    """A host that should have answered and did not.

    A named tuple, not a dataclass: ``msctl ps`` imports no dataclasses (see
    :mod:`msctl.quick`).

    Attributes:
        host: The host, or its supervisor's namespace when no plan names it.
        why: :data:`NO_SUPERVISOR`, :data:`NO_ANSWER`, :data:`REFUSED` or :data:`NO_NETWORK`.
        detail: What was seen, for a person.
        asked: Whether a request was sent to it (plain ``ps`` names plan hosts it did not
            ask, and does not fail for them).
    """

    host: str
    why: str
    detail: str
    asked: bool = True


class Plan(NamedTuple):
    """The computers of this computer's resolved assembly.

    Attributes:
        template: The template it was resolved from (``dragon``).
        hosts: Each host (robot computers and ground stations, in the lock's order) and the
            components planned on it.
    """

    template: str
    hosts: dict[str, tuple[str, ...]]


class Asked(NamedTuple):
    """What a request to several supervisors brought back, by supervisor namespace."""

    answers: dict[str, Any]
    silent: dict[str, Silence]


class FleetState(NamedTuple):
    """What ``msctl ps`` shows: every run document, who did not answer, notes, the plan."""

    documents: list[dict[str, Any]]
    silent: list[Silence]
    notes: list[str]
    plan: Plan | None


def describe(silent: Iterable[Silence]) -> str:
    """``a, b (why); c (why)``: hosts that did not answer, grouped by what was seen, in order."""
    groups: dict[str, list[str]] = {}
    for silence in silent:
        groups.setdefault(silence.detail, []).append(silence.host)
    return "; ".join(f"{', '.join(hosts)} ({detail})" for detail, hosts in groups.items())


def plan_path() -> Path:
    """The resolved assembly's lock file (:func:`components.assembly.lock_path`)."""
    return state_dir() / "assembly" / "assembly.lock.json"


def read_plan() -> Plan | None:
    """This computer's resolved assembly's hosts, or ``None`` when none is resolved (or its
    lock cannot be read: the commands that ask the fleet then ask whoever answers)."""
    try:
        lock = json.loads(plan_path().read_text(encoding="utf-8"))
        roles = lock.get("host_plans") or {}
        # The lock's hosts are those with something to run; every module's computer is one
        # (its motor interface at least), named again in case a lock ever says otherwise.
        named = [*lock["hosts"], *(m["host"] for m in lock.get("modules", ()))]
        hosts = {
            host: tuple((roles.get(host) or {}).get("components", ()))
            or tuple(c["name"] for c in lock.get("components", ()) if c.get("host") == host)
            for host in dict.fromkeys(named)
        }
        return Plan(str(lock["template"]), hosts)
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None


def expected_hosts(plan: Plan | None, documents: Iterable[dict[str, Any]]) -> list[str]:
    """The plan's hosts that must answer, given the run documents at hand.

    Every one, unless one computer runs the whole assembly off-robot (``msctl up dragon`` on
    a laptop, MuJoCo for the motors): its document stands for every host of the plan, whose
    computers then take no part. An agent's run is never that, off-robot or not: a ground
    station's agent runs the station's own part (``msctl.launcher.part.plan_part``).
    """
    if plan is None:
        return []
    for document in documents:
        whole = document.get("off_robot") and not document.get("agent")
        if whole and document.get("template") == plan.template:
            return []
    return list(plan.hosts)


def supervisors(node: Any) -> dict[str, str]:
    """``{host namespace: service name}`` of every supervisor on the graph."""
    from components.comm.graph import snapshot
    from components.comm.types import dds_type_name

    # Only the servers of AgentRequest (zid/node/entity/SS/enclave/namespace/node/service/
    # type/hash/qos): not the whole graph's tokens, parsed to keep a few.
    servers = f"*/*/*/SS/*/*/*/*/{dds_type_name(AGENT_SRV)}/*/*"
    found = {}
    graph = snapshot(node.session, node.domain, timeout=3.0, tokens=servers)
    for name, info in graph.services().items():
        if name.startswith("/msctl/") and name.endswith("/request") and AGENT_SRV in info.types:
            found[name[: -len("/request")]] = name
    return found


#: Seconds a host whose router knows no server for it is asked again before it is called
#: gone (a busy agent that missed its lease is back within that), and the pause between.
NO_SERVER_GRACE = 2.0
NO_SERVER_PAUSE = 0.25
#: A request is sent again after a share of its bound with no answer (never sooner than
#: :data:`MIN_ATTEMPT` seconds), the earlier copies still waiting: a radio link that closes
#: while a query waits loses the query or its answer for good, and nothing resends it when
#: the link reopens. Only :data:`REPEATED`'s verbs.
ATTEMPTS = 3
MIN_ATTEMPT = 2.0
#: The verbs sent again that way: cheap to answer twice.
REPEATED = ("ps", "down")


def ask_hosts(
    node: Any,
    verb: str,
    hosts: Iterable[str] = (),
    args: dict[str, Any] | None = None,
    timeout: float = 3.0,
    found: dict[str, str] | None = None,
) -> Asked:
    """Send one request to every supervisor on the graph and to each of ``hosts``, all at once.

    A host of ``hosts`` the graph does not show is asked all the same: the graph's answer
    may have missed it, and a query for a server nobody serves ends as soon as the router
    says so (well under a second), so asking costs little and tells "no supervisor" from
    "no answer" (a query that waited the whole ``timeout``).

    Args:
        node: The asking node.
        verb: The request's verb (:data:`components.supervision.protocol.VERBS`).
        hosts: Hosts that must be asked even if the graph does not show their supervisor
            (the plan's, see :func:`read_plan`).
        args: The request's arguments.
        timeout: Seconds each supervisor may take to answer.
        found: The graph's supervisors (:func:`supervisors`) when the caller has them.

    Returns:
        The answers and the silences, each by namespace, in asking order (graph first).
    """
    from components.supervision.wire import SupervisorClient

    found = supervisors(node) if found is None else found
    named = {namespace: namespace for namespace in found}  # what a silence is called
    services = dict(found)
    for host in hosts:
        namespace = host_namespace(host)
        named[namespace] = host
        services.setdefault(namespace, f"{namespace}/request")
    clients = {ns: SupervisorClient(node, service) for ns, service in services.items()}
    request = encode_args(args)

    def ask(namespace: str) -> Any:
        return _ask_one(
            clients[namespace], verb, request, timeout, named[namespace], namespace in found
        )

    try:
        replies = ask_each(clients, ask, lambda result: isinstance(result, Silence))
    finally:
        for client in clients.values():
            client.close()
    return Asked(replies.answers, replies.silent)


def _ask_one(client: Any, verb: str, request: str, timeout: float, host: str, seen: bool) -> Any:
    """One host's answer to :func:`ask_hosts`' request, or the :class:`Silence` it kept.

    Args:
        client: The client of its supervisor.
        verb: The request's verb.
        request: Its arguments' JSON.
        timeout: Seconds it may take to answer.
        host: What a silence of it is called.
        seen: Whether the graph showed its supervisor.
    """
    from components.comm.services import ServiceError, ServiceTimeout

    started = time.monotonic()
    while True:
        asked_at = time.monotonic()
        budget = timeout - (asked_at - started)
        # A verb that is cheap and safe to repeat goes again; doctor runs every check
        # each time it is asked (a repeat would only queue more work at the agent).
        every = max(MIN_ATTEMPT, timeout / ATTEMPTS) if verb in REPEATED else budget
        try:
            response = client.ask_repeating(verb, request, budget, every)
            break
        except ServiceTimeout:
            # Timed by the clock, not by the error's wording: a query that ended well
            # before its bound ended because the router knows no server for that host.
            if time.monotonic() - asked_at >= 0.9 * budget:
                return Silence(host, NO_ANSWER, f"no answer within {timeout:g} s")
            # A busy agent's route lapses for a moment when it misses its lease: look
            # again for a while (within half the bound) before calling it gone. The
            # verbs asked this way (ps, doctor, down) are safe to repeat.
            elapsed = time.monotonic() - started + NO_SERVER_PAUSE
            if elapsed >= min(NO_SERVER_GRACE, timeout / 2):
                left = " (it left while asked)" if seen else ""
                return Silence(host, NO_SUPERVISOR, f"no supervisor on the graph{left}")
            time.sleep(NO_SERVER_PAUSE)
        except ServiceError as exc:  # an error reply, or one that is not a response
            return Silence(host, REFUSED, str(exc))
    if not response.success:
        return Silence(host, REFUSED, response.message)
    return json.loads(response.payload) if response.payload else {}


def ask_all(
    node: Any, verb: str, args: dict[str, Any] | None = None, timeout: float = 3.0
) -> dict[str, Any]:
    """Send one request to every supervisor on the graph, all at once; ``{namespace: payload
    or {"error": ...}}``, in the graph's order."""
    found = supervisors(node)
    asked = ask_hosts(node, verb, (), args, timeout, found)
    return {
        namespace: (
            asked.answers[namespace]
            if namespace in asked.answers
            else {"error": asked.silent[namespace].detail}
        )
        for namespace in found
    }


def hosts_to_ask(
    node: Any, plan: Plan | None, found: dict[str, str], timeout: float = 5.0
) -> list[str]:
    """The plan's hosts that must answer a fleet-wide request: :func:`expected_hosts`, the
    graph's supervisors asked what they run only when some host of the plan has none on the
    graph (to see whether one computer runs the whole assembly off-robot)."""
    hosts = expected_hosts(plan, ())
    if all(host_namespace(h) in found for h in hosts):
        return hosts
    documents = ask_hosts(node, "ps", (), None, timeout, found).answers.values()
    return expected_hosts(plan, documents)


def fleet_state(timeout: float = 3.0, every_host: bool = False) -> FleetState:
    """Every host's run document (network first, this computer's state file as fallback),
    the hosts that did not answer, and notes about the rest.

    Args:
        timeout: Seconds each supervisor may take to answer.
        every_host: Also ask each host of the plan the graph does not show (``ps --all``);
            without it, those are named as not asked.
    """
    plan = read_plan()
    documents: dict[str, dict[str, Any]] = {}
    silent: dict[str, Silence] = {}  # by host
    notes: list[str] = []
    local = ps_document(state.read_state())
    # Why the network could not be asked, if it could not.
    unreached = _ask_network(plan, every_host, timeout, documents, silent, notes)
    if local and local.get("host") not in documents:
        _add_local(local, documents, silent, notes)
    silent = _owed_silences(plan, documents, silent, unreached, every_host)
    return FleetState(list(documents.values()), list(silent.values()), notes, plan)


def _ask_network(
    plan: Plan | None,
    every_host: bool,
    timeout: float,
    documents: dict[str, dict[str, Any]],
    silent: dict[str, Silence],
    notes: list[str],
) -> str:
    """Ask every supervisor on the network for its run document, into ``documents`` (by
    host) and ``silent``; why the network could not be asked ("" when it could)."""
    from msctl.errors import NetworkError
    from msctl.plane import connected

    try:
        with connected("ps") as node:
            asked = ask_hosts(node, "ps", plan.hosts if plan and every_host else (), None, timeout)
        for answer in asked.answers.values():
            # Read by the typed answer's field names (RunDocument's, without msgspec).
            document = ps_document(answer)
            if document is not None:
                documents[document["host"]] = document
        # A silent supervisor of a plan host is named as the plan names the host.
        named = {host_namespace(h): h for h in (plan.hosts if plan else ())}
        for namespace, silence in asked.silent.items():
            host = named.get(namespace, silence.host)
            silent[host] = silence._replace(host=host)
    except NetworkError as exc:
        notes.append(f"network: {exc} (showing this computer's state file only)")
        return exc.message
    return ""


def _add_local(
    local: dict[str, Any],
    documents: dict[str, dict[str, Any]],
    silent: dict[str, Silence],
    notes: list[str],
) -> None:
    """This computer's state file stands for its supervisor, which the network did not
    bring: gone (its components judged by their process groups) or silent."""
    if not state.supervisor_alive(local) and local.get("state") != "stopped":
        local = _supervisor_gone(local)
        left = state.groups_left(local)
        if left:
            notes.append(
                f"the supervisor of {local.get('template')} on {local['host']} (pid "
                f"{local.get('supervisor_pid')}) is gone; processes left running: "
                f"{', '.join(left)} — stop them with `msctl down`"
            )
    elif local["host"] in silent:
        # Alive, yet its answer did not come: its state file (rewritten twice a second)
        # answers for it.
        notes.append(f"{local['host']}: {silent[local['host']].detail}; shown from its state file")
    silent.pop(local["host"], None)
    documents[local["host"]] = local


def _owed_silences(
    plan: Plan | None,
    documents: dict[str, dict[str, Any]],
    silent: dict[str, Silence],
    unreached: str,
    every_host: bool,
) -> dict[str, Silence]:
    """The silences that count, by host: a plan host with no supervisor is owed an answer
    only if no computer runs the whole assembly in its stead; one that has a supervisor and
    stayed silent always is."""
    owed = set(expected_hosts(plan, documents.values()))
    covered = set(plan.hosts) - owed if plan else set()
    silent = {
        host: s
        for host, s in silent.items()
        if not (host in covered and s.why in (NO_SUPERVISOR, NO_NETWORK))
    }
    for host in (h for h in (plan.hosts if plan else ()) if h in owed):
        if host not in documents and host not in silent:
            if unreached:
                silent[host] = Silence(host, NO_NETWORK, unreached, asked=every_host)
            else:
                silent[host] = Silence(host, NO_SUPERVISOR, NOT_ASKED, asked=False)
    return silent


def _supervisor_gone(document: dict[str, Any]) -> dict[str, Any]:
    """A state file whose supervisor died: its components are no longer watched, so none is
    "running"; each is "orphaned" while its process group lives, else "stopped"."""
    alive = set(state.groups_left(document))
    components = []
    for c in document.get("components", []):
        orphaned = c.get("process") in alive
        components.append(
            {
                **c,
                "state": "orphaned (supervisor gone)" if orphaned else "stopped",
                "pid": c.get("pid") if orphaned else None,
                "uptime": c.get("uptime", 0.0) if orphaned else 0.0,
            }
        )
    return {**document, "state": "stopped (supervisor gone)", "components": components}
