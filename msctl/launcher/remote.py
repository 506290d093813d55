"""Acting on components wherever they run: find the host's supervisor, send it a request."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, NamedTuple, Union

from msctl.errors import InputError, MsctlError, NetworkError, NotFoundError
from msctl.launcher.control import RequestError

if TYPE_CHECKING:
    from components.supervision.protocol import ComponentRow, RunDocument, UpAnswer


def host_of(component: str, node: Any) -> str:
    """The host whose supervisor runs ``component`` (a component or a process).

    Asked of every supervisor on the graph at once. Where none that answered runs it, this
    computer's own supervisor (alive, its answer lost) or the host this computer's plan puts
    it on is named, so that the request then goes there and a silence is said as one; a
    name nobody runs and nobody plans is not found.

    Raises:
        NotFoundError: If no supervisor that answered runs it and no plan names its host.
        NetworkError: If the same, but some supervisors did not answer (it may run there).
    """
    from components.supervision.protocol import run_document
    from msctl.launcher import state
    from msctl.launcher.fleet import ask_all, read_plan

    answered: set[str] = set()
    known: list[str] = []
    silent: list[str] = []
    for namespace, answer in ask_all(node, "ps").items():
        document = run_document(answer)  # None: the host's error, or no ps answer
        if document is None:
            silent.append(namespace)
            continue
        for c in document.components:
            if component in (c.name, c.process):
                return document.host
        for p in document.processes:
            if component == p.name:
                return document.host
        answered.add(document.host)
        known += [c.name for c in document.components]
    local = state.read_state()
    # This computer's supervisor, when its answer did not arrive: let it say for itself.
    if local and state.supervisor_alive(local) and local.get("host") not in answered:
        return local["host"]
    plan = read_plan()
    planned = [h for h, names in (plan.hosts if plan else {}).items() if component in names]
    if planned and planned[0] not in answered:
        # Planned there and that host did not answer with its run: ask it, and say so.
        return planned[0]
    from msctl.errors import did_you_mean

    if silent:
        raise NetworkError(
            f"no supervisor that answered runs {component!r}, and "
            f"{', '.join(silent)} did not answer: it may run there",
            hint="check those computers' links and agents (`msctl ps --all`), then try again",
        )
    near = did_you_mean(component, known)
    raise NotFoundError(
        f"no running supervisor knows {component!r}"
        + (
            f" (components: {', '.join(known[:12])}{', ...' if len(known) > 12 else ''})"
            if known
            else ""
        ),
        hint=f"{near + ' ' if near else ''}see what runs where with `msctl ps`",
    )


def control_component(verb: str, component: str, only: bool = False) -> None:
    """Send ``verb`` (restart/stop/start) for ``component`` to the host that runs it.

    Says which components the verb takes with it (every one sharing the process). With
    ``only`` (restart), the component is rebuilt alone inside its process, and this waits
    until it runs again.
    """
    from components.comm.services import ServiceTimeout
    from components.supervision.protocol import process_answer
    from msctl.console import err
    from msctl.launcher.control import call_supervisor
    from msctl.plane import connected

    args: dict[str, Any] = {"component": component}
    if only:
        args["only"] = True
    with connected(verb) as node:
        host = host_of(component, node)
        try:
            answer = call_supervisor(node, host, verb, args)
        except ServiceTimeout as exc:
            raise NetworkError(f"the supervisor of {host} did not answer: {exc}") from exc
        except RequestError as exc:
            raise MsctlError(str(exc)) from exc
        acted = process_answer(answer, verb, f"the supervisor of {host}")
        if acted.only:
            _wait_rebuilt(node, host, component, acted.process)
            return
    siblings = acted.siblings
    taken = ""
    if component == acted.process and siblings:
        # A process named: every one of its components goes, and none is a sibling of it.
        taken = f", and with it every component it runs: {', '.join(siblings)}"
        if verb == "restart" and len(siblings) > 1:
            taken += "; `msctl restart --only COMPONENT` restarts one of them alone"
    elif siblings:
        taken = f", and with it {', '.join(siblings)} (they share the process)"
        if verb == "restart":
            taken += f"; `msctl restart --only {component}` restarts it alone"
    err.print(
        f"[green]{verb}[/] {component} on {host}: process {acted.process} is {acted.state}{taken}",
        highlight=False,
    )


def _wait_rebuilt(
    node: Any, host: str, component: str, process: str, timeout: float = 60.0
) -> None:
    """Until ``component``, rebuilt alone, runs again (its siblings never stopped)."""
    import time

    from components.supervision.protocol import run_document
    from msctl.console import err
    from msctl.errors import OperationTimeout
    from msctl.launcher.control import call_supervisor

    deadline = time.monotonic() + timeout
    with err.status(f"rebuilding {component} in process {process} on {host}..."):
        while True:
            document = run_document(call_supervisor(node, host, "ps", timeout=5.0))
            rows = document.components if document is not None else []
            row = next((r for r in rows if r.name == component), None)
            if row is not None and row.state == "running":
                break
            if row is not None and row.state in ("failed", "restarting"):
                raise MsctlError(
                    f"{component} could not be rebuilt alone; its process {process} is "
                    f"{row.state}: {row.last_error or 'see `msctl logs ' + component + '`'}"
                )
            if time.monotonic() > deadline:
                raise OperationTimeout(
                    f"{component} was not running again {timeout:g} s after its rebuild",
                    hint=f"see `msctl logs {component}`",
                )
            time.sleep(0.2)
    siblings = [r.name for r in rows if r.process == process and r.name != component]
    err.print(
        f"[green]restart[/] {component} on {host}: rebuilt alone in process {process} "
        f"(pid {row.pid} unchanged)"
        + (f"; {', '.join(siblings)} ran on untouched" if siblings else ""),
        highlight=False,
    )


#: Least seconds ``up --all`` keeps asking a host whose route has lapsed (on field Wi-Fi a
#: link flaps for a second or two) before naming it unreachable.
UP_GRACE = 3.0
#: A host not on the graph may be one whose link is being opened again: noticed dead after
#: its lease, then reopened (TLS and Zenoh's handshake, a few round trips). It is asked for
#: this many of the longer lease of its link and this computer's before it is named
#: unreachable (on ``degraded``, every link 256 kbit/s losing a fifth of its packets, robots
#: whose agents were off the graph for more than 3 s were named while their routes came back).
UP_GRACE_LEASES = 2.0
#: Seconds ``up --all`` waits for one answer before asking again: a radio link that closed
#: while the request or its answer was on it lost it for good (seen on the ``degraded``
#: profile: parts started, and ``up --all`` named their hosts unreachable). The agent takes
#: the same ``up`` again as one, answered as soon as the first is done.
UP_ATTEMPT = 10.0
#: Seconds ``up --all`` gives each host's ``ps`` while it waits for healthy: more than a round
#: trip over the slowest link rehearsed (Earth to the Moon: 2.56 s), where 2 s never came.
PS_BOUND = 8.0


class Unstarted(NamedTuple):
    """A host ``up --all`` did not start: ``unreachable`` or ``refused``, and why."""

    outcome: str
    why: str


def up_all(assembly: Any, sim: bool | None, speed: float, timeout: float) -> None:
    """Start every host's part through its agent, with one progress view for all of them.

    Every host is asked even when one does not answer; the unreachable ones and the ones
    that refused are named at the end, after the others have come up.

    Raises:
        NetworkError: If some host's agent did not answer (named).
        MsctlError: If some host's agent refused (named, with its reason).
        OperationTimeout: If a started host's components are not all healthy in ``timeout``.
    """
    import json
    import time

    from msctl.plane import connected

    document = json.loads(assembly.lock_path.read_text()) if assembly.lock_path else {}
    request = {"assembly": document, "sim": sim, "speed": speed}
    _refuse_oversized(assembly, request)
    hosts = list(dict.fromkeys(assembly.hosts))
    with connected("up_all") as node:
        # One budget for the whole start: the answers, then the wait for healthy (it was
        # two: a slow link took twice the --timeout the user gave).
        deadline = time.monotonic() + timeout
        graces = _graces(assembly, hosts, timeout)
        replies = _start_each(node, hosts, request, timeout, graces)
        status = _wait_healthy(node, replies.answers, deadline)
    _show_hosts(assembly.template, replies, status)
    _fail_unless_healthy(replies, status, timeout)


def _refuse_oversized(assembly: Any, request: dict[str, Any]) -> None:
    from msctl.launcher.control import MAX_ARGS_BYTES, args_size, encode_args

    size = args_size(encode_args(request))
    if size > MAX_ARGS_BYTES:
        # Every agent would refuse it: say why once, here, rather than once per host.
        raise InputError(
            f"the resolved {assembly.template} ({assembly.lock_path}) is {size} bytes as an "
            f"`up` request; agents accept at most {MAX_ARGS_BYTES}",
            hint="MAX_ARGS_BYTES in components/supervision/contract.py bounds it: raise it there",
        )


def _graces(assembly: Any, hosts: list[str], timeout: float) -> dict[str, float]:
    """Seconds to keep asking each host that is not on the graph: :data:`UP_GRACE_LEASES`
    of the longer lease of its link class and this computer's, at least :data:`UP_GRACE`,
    at most the whole start's ``timeout``."""
    from components.links import Network
    from components.supervision.contract import this_host

    network = Network.from_dict(getattr(assembly, "network", None))
    here = network.link_class(this_host()).lease_s
    return {
        host: min(
            timeout, max(UP_GRACE, UP_GRACE_LEASES * max(here, network.link_class(host).lease_s))
        )
        for host in hosts
    }


def _start_each(
    node: Any,
    hosts: list[str],
    request: dict[str, Any],
    timeout: float,
    graces: dict[str, float] | None = None,
) -> Any:
    """Ask every host's agent to start its part, all at once (:func:`fanout.ask_each`).

    An agent the router's graph does not show is first asked a cheap `ps`: with no agent
    anywhere the query ends as soon as the router says it knows no server (in well under a
    second), so its generous bound only waits for an agent that is there but slow (a loaded
    computer: 2 s was too short, and a host that was there was named unreachable). The `up`
    itself gets longer still: an agent starts its processes before it answers, and one told
    "unreachable" must not be starting.

    Returns:
        :class:`~msctl.launcher.fanout.Replies`: each started host's
        :class:`~components.supervision.protocol.UpAnswer`, and an :class:`Unstarted` for
        each other (one that answered something else is ``refused``, with what it was).
    """
    from components.comm.services import ServiceError
    from components.supervision.protocol import AnswerError, up_answer
    from msctl.console import err
    from msctl.launcher.control import call_supervisor, host_namespace
    from msctl.launcher.fanout import ask_each
    from msctl.launcher.fleet import supervisors

    present = set(supervisors(node))
    # An agent answers `up` once its processes are started: on a loaded computer that took
    # over 30 s (seen with four agents starting on one 2-core machine), so it gets as long
    # as the user gave the whole start, never less than 30 s.
    answer_bound = max(30.0, timeout)

    def ask(host: str) -> Any:
        try:
            if host_namespace(host) not in present:
                grace = (graces or {}).get(host, UP_GRACE)
                call_supervisor(
                    node,
                    host,
                    "ps",
                    timeout=max(10.0, grace),
                    grace=grace,
                    attempt=UP_ATTEMPT / 2,
                )
            # Its agent is there (on the graph, or it answered): a route that lapses now
            # is a radio link reopening, not an agent gone, so it is asked again for as
            # long as the answer may take (on a 256 kbit/s link losing a fifth of its
            # packets, a robot's route was gone longer than UP_GRACE).
            answered = call_supervisor(
                node, host, "up", request, answer_bound, grace=answer_bound, attempt=UP_ATTEMPT
            )
        except ServiceError as exc:  # a timeout says how long it waited, and for what
            return Unstarted("unreachable", str(exc))
        except RequestError as exc:
            return Unstarted("refused", str(exc))
        try:
            return up_answer(answered, f"the agent of {host}")
        except AnswerError as exc:  # not an agent of this msctl: its part is not waited for
            return Unstarted("refused", str(exc))

    for host in hosts:
        err.print(f"[dim]asking {host} to start its part...[/]", highlight=False)
    return ask_each(hosts, ask, lambda result: isinstance(result, Unstarted))


#: A host's last ``ps`` while ``up --all`` waits: its typed answer, or why there was none.
Looked = Union["RunDocument", str]


def _components(looked: Looked | None) -> list[ComponentRow]:
    return [] if looked is None or isinstance(looked, str) else looked.components


def _healthy(looked: Looked) -> bool:
    # A host whose part is only kinds not built yet runs nothing, and is done at once.
    return not isinstance(looked, str) and all(c.state == "running" for c in looked.components)


def _not_running(status: dict[str, Looked]) -> list[str]:
    return [
        f"{host}: {c.name}"
        for host, d in status.items()
        for c in _components(d)
        if c.state != "running"
    ]


def _wait_healthy(node: Any, started: dict[str, UpAnswer], deadline: float) -> dict[str, Looked]:
    """Ask every started host what runs (all at once, :func:`fanout.rounds`) until every
    component is healthy or the deadline passes; each host's last ``ps`` (or its error)."""
    from components.comm.services import ServiceError
    from components.supervision.protocol import run_document
    from msctl.launcher.control import call_supervisor
    from msctl.launcher.fanout import progress, rounds

    status: dict[str, Looked] = {}
    total = sum(len(answer.components) for answer in started.values())

    def look(host: str) -> Looked:
        # Each given a round trip to the Moon and back.
        try:
            answer = call_supervisor(node, host, "ps", timeout=PS_BOUND, attempt=2.0)
        except (ServiceError, RequestError) as exc:
            return str(exc)
        return run_document(answer) or f"{host} answered ps with no run document"

    with progress("{task.completed}/{task.total} healthy") as view:
        task = view.add_task("starting", total=total)

        def settle(results: dict[str, Looked]) -> Any:
            status.update(results)
            waiting = _not_running(status)
            running = sum(c.state == "running" for d in status.values() for c in _components(d))
            described = "waiting for " + ", ".join(waiting[:3]) if waiting else "healthy"
            view.update(task, completed=running, description=described)
            return results if all(_healthy(d) for d in status.values()) else ()

        rounds(started, look, settle, deadline, 0.2)
    return status


def _show_hosts(template: str, replies: Any, status: dict[str, Looked]) -> None:
    """The table of every host: what it runs and how much is healthy, or why it did not."""
    from rich.markup import escape
    from rich.table import Table

    from msctl.console import err

    table = Table(title=f"{template}: every host", title_justify="left")
    for column in ("host", "components", "healthy", "note"):
        table.add_column(column)
    for host, answer in replies.answers.items():
        looked = status.get(host)
        components = _components(looked)
        note = looked if isinstance(looked, str) else ""
        if not components and not note:
            kinds = sorted({n.kind for n in answer.not_built})
            note = "nothing to run" + (
                f" (not implemented yet: {', '.join(kinds)})" if kinds else ""
            )
        healthy_count = sum(c.state == "running" for c in components)
        table.add_row(host, str(len(components)), str(healthy_count), note)
    for outcome in ("unreachable", "refused"):
        for host, silence in replies.silent.items():
            if silence.outcome == outcome:
                shown = (
                    f"unreachable: {escape(silence.why)}"
                    if outcome == "unreachable"
                    else escape(silence.why)
                )
                table.add_row(host, "-", "-", f"[red]{shown}[/]")
    err.print(table)


def _fail_unless_healthy(replies: Any, status: dict[str, Looked], timeout: float) -> None:
    """Raise for the hosts that did not start, else for the components not healthy."""
    from msctl.errors import OperationTimeout

    unreachable = [h for h, s in replies.silent.items() if s.outcome == "unreachable"]
    refused = [s.why for s in replies.silent.values() if s.outcome == "refused"]
    also = f"; refused: {'; '.join(refused)}" if refused else ""
    # Exactly which hosts did start: an operator decides from it whether to `down --all`.
    started = replies.answers
    outcome = f"started: {', '.join(started)}" if started else "no host was started"
    if unreachable:
        # Each host's own reason in the line too: a log or a script keeps only the last line
        # (a soak's up --all said two ground stations did not answer, and nothing of why).
        whys = "; ".join(f"{h}: {replies.silent[h].why}" for h in unreachable)
        raise NetworkError(
            f"no agent answered for {', '.join(unreachable)}{also} ({outcome}); {whys}",
            hint="start `msctl agent` there (or `msctl agent install`), check its network",
        )
    if refused:
        raise MsctlError("; ".join(refused) + f" ({outcome})")
    late = _not_running(status) + [f"{h}: {d}" for h, d in status.items() if isinstance(d, str)]
    if late:
        raise OperationTimeout(
            f"not healthy after {timeout:g} s: {', '.join(late[:6])}",
            hint="see `msctl ps` and `msctl logs <component>`",
        )


#: Hosts whose links never leave the computer: plain TCP to them is not exposed.
_LOOPBACK = ("127.", "localhost", "[::1]")

#: What to do about plain links, in every refusal.
_SECURE_THE_FLEET = (
    "run `msctl net init`, copy MSCTL_HOME/net (all but ca/ca.key) to every computer, start "
    "the agents with MSCTL_SECURE=1 and set MSCTL_IDENTITY to your operator name; or pass "
    "--insecure on a network you trust"
)


def refuse_plain_links() -> None:
    """Refuse to send agents requests over a link that leaves the computer unencrypted.

    Anyone on the network could send the same requests over such a link (``up``, ``down``,
    ``stop``). Loopback links are fine: they never leave the computer. Two places are
    looked at: this command's own endpoints, and the links of the routers it reaches (their
    admin space, ``@/<zid>/router``): a command on loopback to a router that links to the
    robots over plain TCP sends its requests across the network all the same.

    Raises:
        InputError: Naming the endpoint or link, how to secure the fleet, and ``--insecure``.
    """
    from components.comm.session import SessionSettings

    settings = SessionSettings.from_env()
    for endpoint in settings.connect:
        protocol, _, address = endpoint.partition("/")
        if protocol != "tls" and not address.startswith(_LOOPBACK):
            raise InputError(
                f"msctl up --all would command the agents over {endpoint}, which is not TLS: "
                "anyone on that network could do the same",
                hint=_SECURE_THE_FLEET,
            )
    _refuse_plain_router_links(settings)


def _refuse_plain_router_links(settings: Any) -> None:
    """The routers' side of :func:`refuse_plain_links`.

    A router that does not describe itself (its admin space off, as in a router that is not
    msctl's; a secure router's access control denies the question) cannot be judged: over
    plain TCP, that is said, and the command goes on as before.
    """
    from rich.markup import escape

    from components.comm.session import SessionConfigError, SessionSettings, open_session
    from msctl.console import err
    from msctl.net.endpoints import plain_links, router_documents

    try:
        session = open_session(SessionSettings.joining())
    except SessionConfigError:
        return  # no router: `up --all` says so itself, naming the endpoint
    try:
        documents = router_documents(session)
    finally:
        session.close()
    if documents is None:
        if not all(e.startswith("tls/") for e in settings.connect):
            where = escape(", ".join(settings.connect))
            err.print(
                f"[yellow]warning:[/] the router at {where} does not say "
                "what it links to (its admin space is off): if it links to other computers over "
                "plain TCP, the agents' requests cross that network unencrypted",
                highlight=False,
            )
        return
    found = plain_links(documents)
    if found:
        also = f" (and {len(found) - 1} more)" if len(found) > 1 else ""
        raise InputError(
            f"msctl up --all would command the agents through a router link that is not TLS: "
            f"{found[0]}{also}; anyone on that network could do the same",
            hint=_SECURE_THE_FLEET,
        )
