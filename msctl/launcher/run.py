"""One run of this computer's part of an assembly: router, processes, health, control.

The loop runs on one thread: it polls the supervisor, judges components healthy, rewrites the
state file and answers control requests (which the Zenoh thread only queues), so the
supervisor is never touched from two threads.
"""

from __future__ import annotations

import json
import os
import queue
import socket
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from components import kinds
from components.assembly import ResolvedAssembly
from components.comm.session import SessionConfigError, SessionSettings, open_session
from components.ros import rclpy_available
from components.supervision import protocol
from components.supervision.contract import AGENT_SRV, RequestError, host_namespace
from components.supervision.dispatch import OffLoop, Verbs
from components.supervision.protocol import request_of
from msctl.errors import MsctlError
from msctl.launcher import boot, forkserver, state
from msctl.launcher.plan import HostPlan, ProcessPlan
from msctl.launcher.supervisor import (
    LivenessPolicy,
    ManagedProcess,
    ProcessState,
    RestartPolicy,
    Supervisor,
)
from msctl.launcher.watch import HealthWatch

ROUTER_PROCESS = "router"

#: The component worker's exit codes after which a restart would fail the same way
#: (``components/executor/worker.py``): its process is FAILED at once, with the worker's last
#: line (``error: cannot build limb1/joint_manager: ...``) as the reason. Any other exit (a
#: crash, a signal) is restarted with backoff.
WORKER_FINAL_EXITS = {2: "bad arguments", 3: "a component cannot be built or configured"}

#: Seconds the loop rests between two turns when no request comes (one wakes it).
LOOP_PAUSE = 0.05

#: Seconds to wait for the fork server's imports before starting plain interpreters instead
#: (a heavily loaded machine takes several).
FORKSERVER_READY_WITHIN = 60.0


def _tcp_refused(endpoint: str, timeout: float) -> bool:
    """Whether nothing accepts TCP connections on a ``tcp/HOST:PORT`` endpoint (``False``
    when it cannot tell: another protocol, a name that does not resolve)."""
    protocol, _, address = endpoint.partition("/")
    host, _, port = address.rpartition(":")
    if protocol != "tcp" or not port.isdigit():
        return False
    host = host.strip("[]")
    if host in ("", "0.0.0.0", "::"):
        host = "localhost"
    try:
        with socket.create_connection((host, int(port)), timeout=timeout):
            return False
    except ConnectionRefusedError:
        return True
    except OSError:
        return False


def router_reachable(endpoint: str, timeout: float = 0.5) -> bool:
    """Whether a Zenoh router answers on ``endpoint``."""
    import zenoh

    # A closed port is known at once, while a Zenoh client keeps retrying it for the whole
    # timeout: without this, each "no router yet" cost 0.5 s of start-up.
    if _tcp_refused(endpoint, timeout):
        return False
    settings = SessionSettings(mode="client", connect=(endpoint,), listen=())
    config = settings.to_config()
    config.insert_json5("connect/timeout_ms", str(int(timeout * 1000)))
    try:
        session = zenoh.open(config)
    except Exception:
        return False
    session.close()
    return True


def listen_endpoint_for(connect_endpoint: str) -> str:
    """Where to listen so that ``connect_endpoint`` reaches us: loopback only for the
    default ``tcp/localhost:7447`` (a plain router open to every interface let anyone on
    the network command the robot); ``MSCTL_ROUTER_LISTEN`` adds endpoints on purpose."""
    if connect_endpoint.startswith("tcp/localhost:"):
        return "tcp/127.0.0.1:" + connect_endpoint.rsplit(":", 1)[1]
    return connect_endpoint


def doctor_payload(host: str, session: Any, settings: Any) -> dict[str, Any]:
    """``msctl doctor``'s findings for this computer, as a request's answer."""
    import dataclasses

    from msctl.net import doctor

    found = doctor.this_computer(host, session, settings.connect, settings.domain)
    return {"host": host, "findings": [dataclasses.asdict(f) for f in found]}


#: ``msctl router``'s exit codes after which a restart would fail the same way: 2 is its
#: :class:`~msctl.errors.InputError` (a port another process holds, an address that is not
#: this computer's, an identity missing). The router is FAILED at once, never restarted five
#: times in a minute.
ROUTER_FINAL_EXITS = {2: "its settings cannot work as they are"}


class RouterStartError(MsctlError):
    """The embedded router cannot start; the message is its own one line (what, and the fix)."""

    exit_code = 2


def _env_endpoints(variable: str, environ: Mapping[str, str]) -> tuple[str, ...]:
    return tuple(e.strip() for e in environ.get(variable, "").split(",") if e.strip())


@dataclass(frozen=True)
class EmbeddedRouter:
    """The router ``msctl up`` and ``msctl agent`` start for this computer when none answers.

    Attributes:
        endpoint: Where this computer's sessions reach it (``MSCTL_ZENOH_CONNECT``'s first).
        host: This computer (the run's host: ``msctl up --host`` too).
        whole_assembly: It serves a run of the whole assembly (``msctl up`` off-robot): with
            ``secure``, its access control lets this computer's components write every
            module's inputs. ``None``: decided by whether the host is one of the assembly's.
        secure: Mutual TLS and access control from ``msctl net`` (``MSCTL_SECURE=1``).
        listen: ``MSCTL_ROUTER_LISTEN``: more endpoints to listen on (secure: TLS ones, in
            place of the generated TLS listener).
        connect: ``MSCTL_ROUTER_CONNECT``: routers to link to (secure: TLS ones, in place of
            the links the assembly gives).
    """

    endpoint: str
    host: str
    whole_assembly: bool | None = None
    secure: bool = False
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()

    @classmethod
    def from_env(
        cls,
        endpoint: str,
        host: str | None = None,
        whole_assembly: bool | None = None,
        environ: Mapping[str, str] | None = None,
    ) -> EmbeddedRouter:
        """The router for ``endpoint`` as the environment sets it up (see the attributes)."""
        from msctl.launcher.plan import this_host

        env = os.environ if environ is None else environ
        return cls(
            endpoint,
            host or this_host(),
            whole_assembly,
            env.get("MSCTL_SECURE") == "1",
            _env_endpoints("MSCTL_ROUTER_LISTEN", env),
            _env_endpoints("MSCTL_ROUTER_CONNECT", env),
        )

    def plain_listen(self) -> list[str]:
        """A plain router's listeners: loopback where ``endpoint`` reaches it, and each of
        ``MSCTL_ROUTER_LISTEN``. One of those that covers the loopback one (the same port on
        a wildcard address, ``tcp/0.0.0.0:7447``) replaces it: one process cannot bind both,
        and the wildcard takes loopback connections too."""
        from msctl.net.endpoints import covers

        local = listen_endpoint_for(self.endpoint)
        extra = list(dict.fromkeys(self.listen))
        if local in extra or any(covers(e, local) for e in extra):
            return extra
        return [local, *extra]

    def argv(self) -> list[str]:
        """``msctl router``'s arguments."""
        if self.secure:
            argv = ["router", "--secure", "--host", self.host]
            if self.whole_assembly is not None:
                argv.append("--whole-assembly" if self.whole_assembly else "--own-part")
        else:
            argv = ["router"]
            for endpoint in self.plain_listen():
                argv += ["--listen", endpoint]
        for endpoint in self.listen if self.secure else ():
            argv += ["--listen", endpoint]
        for endpoint in self.connect:
            argv += ["--connect", endpoint]
        return argv

    def not_applied(self) -> str:
        """What the operator asked of this router that a router already answering on
        ``endpoint`` (used as it is) does not do, as a warning line, or ``""``."""
        asked = [
            name
            for name, given in (
                ("MSCTL_SECURE", self.secure),
                ("MSCTL_ROUTER_LISTEN", self.listen),
                ("MSCTL_ROUTER_CONNECT", self.connect),
            )
            if given
        ]
        if not asked:
            return ""
        return (
            f"warning: a router already answers on {self.endpoint} and is used as it is: "
            f"{', '.join(asked)} apply only to a router msctl starts; stop that one first "
            "(`msctl down`, or the agent or router holding it) to have them"
        )

    def check(self) -> list[str]:
        """What would make the router fail at once, raised now; what to warn of, returned.

        Runs in the process that starts the router, so a setting that cannot work fails in
        well under a second with its one line (the endpoint or identity, and the fix), and
        a detached ``msctl up`` says it before it detaches. The secure config is generated
        here as the router will generate it (an identity is made for a computer running the
        whole assembly, once).

        Returns:
            Lines for the operator: a plain router open beyond this computer, an identity
            made.

        Raises:
            RouterStartError: Naming the endpoint, file or host at fault, and the fix.
        """
        from components.assembly import AssemblyError
        from msctl.commands.router import plain_exposure
        from msctl.net import config as netconfig
        from msctl.net import endpoints, pki

        notes: list[str] = []
        listen: list[tuple[str, str]]  # (endpoint, the setting it comes from)
        try:
            if self.secure:
                path, notes = netconfig.this_computer_router(
                    self.host,
                    self.whole_assembly,
                    listen=self.listen,
                    connect=self.connect or None,
                )
                document = json.loads(path.read_text())
                listen = [
                    (e, "MSCTL_ZENOH_CONNECT" if e.startswith("tcp/") else "MSCTL_NET_TLS_PORT")
                    for e in document["listen"]["endpoints"]
                ]
            else:
                for variable, given in (
                    ("MSCTL_ROUTER_LISTEN", self.listen),
                    ("MSCTL_ROUTER_CONNECT", self.connect),
                ):
                    for text in given:
                        try:
                            endpoints.parse(text)
                        except endpoints.EndpointError as exc:
                            raise endpoints.EndpointError(f"{variable}: {exc}") from None
                local = listen_endpoint_for(self.endpoint)
                listen = [
                    (e, "MSCTL_ZENOH_CONNECT" if e == local else "MSCTL_ROUTER_LISTEN")
                    for e in self.plain_listen()
                ]
                warning = plain_exposure(self.plain_listen(), self.connect)
                if warning:
                    notes.append(f"warning: {warning}")
            for text, setting in listen:
                endpoints.check_listen(text, setting)
        except endpoints.EndpointError as exc:
            raise RouterStartError(f"this computer's router: {exc}") from None
        except (AssemblyError, netconfig.NetConfigError, pki.PkiError) as exc:
            raise RouterStartError(f"this computer's secure router (--secure): {exc}") from None
        return notes


def router_argv(connect_endpoint: str) -> list[str]:
    """``msctl router``'s arguments for the embedded router, as the environment sets it up
    (see :class:`EmbeddedRouter`)."""
    return EmbeddedRouter.from_env(connect_endpoint).argv()


def start_router(
    supervisor: Supervisor,
    endpoint: str | EmbeddedRouter,
    say: Callable[[str], None] | None = None,
) -> ManagedProcess:
    """Start an embedded router (``msctl router``) as a supervised process.

    Its settings are checked first (:meth:`EmbeddedRouter.check`): one that cannot work
    raises here, and one that fails the router anyway later makes it FAILED at once
    (:data:`ROUTER_FINAL_EXITS`), not restarted.

    Args:
        supervisor: Who supervises it.
        endpoint: The router, or where this computer's sessions reach it (its settings then
            come from the environment).
        say: Where the check's warnings go (a plain router open beyond this computer).

    Raises:
        RouterStartError: A setting that cannot work (named, with the fix).
    """
    router = endpoint if isinstance(endpoint, EmbeddedRouter) else EmbeddedRouter.from_env(endpoint)
    for line in router.check():
        if say is not None:
            say(line)
    process = supervisor.add(
        ROUTER_PROCESS,
        boot.argv("msctl", *router.argv()),
        final_exits=ROUTER_FINAL_EXITS,
    )
    # Stopped while it still starts, it ends quietly (msctl.launcher.boot).
    with boot.held_sigint():
        supervisor.start(process.name)
    return process


def router_error_line(router: ManagedProcess) -> str:
    """The router's own last error line, whole (``last_error`` keeps only its tail)."""
    for line in reversed(list(router.log.tail)):
        text = line.strip()
        if text.startswith("error:"):
            return text.removeprefix("error:").strip()
    return router.last_error or "no answer"


def wait_for_router(
    supervisor: Supervisor,
    router: ManagedProcess,
    endpoint: str,
    timeout: float = 30.0,  # a loaded machine starts a (secure) router in 10+ s
    stopping: Callable[[], bool] | None = None,
) -> bool:
    """Wait until the embedded router answers on ``endpoint``; mark it running.

    Args:
        supervisor: The supervisor that started it.
        router: Its process.
        endpoint: Where it listens.
        timeout: Seconds to wait for it.
        stopping: Polled while waiting: once it says so, stop waiting (a Ctrl-C during
            start-up must not wait for a router that is about to be stopped anyway).

    Returns:
        Whether it answers (``False``: ``stopping`` said to stop first).

    Raises:
        RuntimeError: If it failed or did not answer within ``timeout`` (with its last error).
    """
    deadline = time.monotonic() + timeout
    while not router_reachable(endpoint):
        if stopping is not None and stopping():
            return False
        with boot.held_sigint():  # it may restart the router
            supervisor.poll()
        if router.state is ProcessState.FAILED and router.restarts == 0:
            # It said why in one line, and a restart would say it again.
            raise RouterStartError(f"the embedded router cannot start: {router_error_line(router)}")
        if router.state is ProcessState.FAILED or time.monotonic() > deadline:
            raise RuntimeError(
                f"the embedded router could not listen on {endpoint}: "
                f"{router.last_error or 'no answer'}"
            )
        time.sleep(0.02)
    supervisor.mark_running(ROUTER_PROCESS)
    return True


@dataclass
class ComponentView:
    """A component as ``ps`` shows it."""

    name: str
    kind: str
    process: str
    state: str
    node_seen: bool
    output_seen: bool


@dataclass
class Launch:
    """Runs a host plan until stopped.

    Args:
        assembly: The resolved assembly.
        plan: This host's processes.
        settings: Session settings components will use (from the environment).
        speed: Simulation speed factor.
        policy: Restart policy.
        liveness: When a worker that stopped beating is unresponsive, then killed.
        serve_control: Serve ``/msctl/<host>/request`` itself; an agent, which serves it for
            its whole life and forwards requests to :meth:`_do`, turns this off.
    """

    assembly: ResolvedAssembly
    plan: HostPlan
    settings: SessionSettings = field(default_factory=SessionSettings.from_env)
    speed: float = 1.0
    policy: RestartPolicy = field(default_factory=RestartPolicy)
    liveness: LivenessPolicy = field(default_factory=LivenessPolicy)
    events: list[str] = field(default_factory=list)
    started_router: bool = False
    serve_control: bool = True
    #: Forks the component workers (msctl.launcher.forkserver), on Zenoh only: one started
    #: by the caller (``msctl up`` starts it before resolving, see
    #: :func:`msctl.launcher.forkserver.for_run`),
    #: else one started by :meth:`start`. Closed by :meth:`shutdown`.
    forkserver: forkserver.ForkServer | None = None

    def __post_init__(self) -> None:
        self.supervisor = Supervisor(
            state.log_dir(),
            self.policy,
            liveness=self.liveness,
            run=f"msctl up {self.assembly.template} on {self.plan.host}",
        )
        self.endpoint = self.settings.connect[0] if self.settings.connect else ""
        self.session: Any = None
        self.watch: HealthWatch | None = None
        #: The health watch's client of the router (see :meth:`start`), when there is one.
        self._watch_session: Any = None
        self._node: Any = None
        self._requests: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._answerer: OffLoop | None = None
        #: Set when a request arrives, so the loop answers it at once rather than after its
        #: pause (up to 50 ms more on every `msctl ps`).
        self._request_came = threading.Event()
        self._stop = False
        self._started = time.time()
        self._last_state_write = 0.0
        self._router_restart_at: float | None = None
        self._state_fault = ""  # the state file's write error, while writing fails
        # Components rebuilt alone and not seen again yet: the process log's line count when
        # the order went (their worker says "rebuilt <name>" in it once done).
        self._rebuilding: dict[str, int] = {}

    # ------------------------------------------------------------------ start
    def start(self) -> None:
        """Reach or start the router, and start every process of the plan.

        Before any component starts, the launcher opens its own sessions: its peer session
        (the control service; it opens at once, and links to a router it has just started
        once that listens; the health watch follows the graph there), then, once the
        router answers, a client of it, on which the watch takes the components' outputs.
        It sees every component's first output that way: a new peer
        sends its samples to the router as soon as its session is open, where a direct
        link to another peer comes later (measured: a subscriber on a peer got the first
        sample of 3 new peers in 20, a client of the router all 20). The watch opened on
        the peer session after the workers started missed most first outputs, and each
        missed one was waited for again (a health monitor's, once a second).

        The component workers are forked from a fork server (:mod:`msctl.launcher.forkserver`)
        started first (by ``msctl up``, before it resolves): it imports what they need once,
        while the router starts.

        A :meth:`request_stop` meanwhile (a Ctrl-C) ends it early: what was started is
        stopped by :meth:`shutdown`, and nothing waits for what would only be closed again.
        """
        router = None
        if self._stop:
            return
        self._start_forkserver()
        reached = bool(self.endpoint) and router_reachable(self.endpoint)
        if reached and self.serve_control:
            # An agent's run uses the agent's router, which was started as asked.
            note = EmbeddedRouter.from_env(self.endpoint, self.plan.host).not_applied()
            if note:
                self.events.append(note)
        if self.endpoint and not reached:
            # An agent's run (no control of its own) has the agent's router, which serves the
            # host's own part: a router started here for it must too. A run of its own
            # off-robot runs the whole assembly, and its router's access control says so.
            embedded = EmbeddedRouter.from_env(
                self.endpoint,
                self.plan.host,
                whole_assembly=self.plan.off_robot and self.serve_control,
            )
            router = start_router(self.supervisor, embedded, say=self.events.append)
            self.started_router = True
        # No scouting delay: Zenoh's default (0.5 s) waits in open for peers the launcher
        # does not need before its router.
        extra = {**self.settings.extra, "scouting/delay": 0}
        self.session = open_session(self.settings._replace(mode="peer", extra=extra))
        if self._stop:
            return  # serving requests would first import the node machinery, for nothing
        if self.serve_control:
            self._serve_control()
        if router is not None and not wait_for_router(
            self.supervisor, router, self.endpoint, stopping=lambda: self._stop
        ):
            return
        if self._stop:
            return
        self._watch()
        if self._stop:
            return
        self._start_processes()
        self.write_state()

    def _watch(self) -> None:
        """Start judging the components' health: the graph on the launcher's session, the
        outputs through a client of the router when there is one (see :meth:`start`)."""
        if os.environ.get("MSCTL_TRANSPORT") == "rclpy" and rclpy_available():
            # Components are rclpy nodes: judged from the ROS graph (their workers say it
            # when rclpy is missing).
            from components.ros.health_watch import RclpyHealthWatch

            self.watch = RclpyHealthWatch(self.plan.components, self.settings.domain)
            return
        outputs = None
        if self.settings.connect:
            try:
                outputs = self._watch_session = open_session(
                    self.settings._replace(mode="client", listen=())
                )
            except SessionConfigError as exc:
                # A router that answered a moment ago and no longer does (not ours): the
                # outputs on the peer session, as the rest, rather than no launch at all.
                self.events.append(f"health watch: outputs on the peer session ({exc})")
        self.watch = HealthWatch(
            self.session, self.plan.components, self.settings.domain, outputs_session=outputs
        )

    def _start_forkserver(self) -> None:
        """Start the fork server, which imports while the router and the session start.

        Not for the rclpy transport (each worker initialises its own rclpy context), nor with
        ``MSCTL_FORKSERVER=0``: workers are then started as new interpreters, as they are
        whenever the server does not work.
        """
        if not self.plan.processes:
            if self.forkserver is not None:
                self.forkserver.close()
                self.forkserver = None
            return
        if self.forkserver is None:
            room = max(len("\0".join(self._worker_argv(p))) for p in self.plan.processes)
            try:
                self.forkserver = forkserver.for_run(self.assembly.lock_path, room)
            except OSError as exc:
                self.events.append(
                    f"fork server: cannot start ({exc}); workers start as themselves"
                )
                return
            if self.forkserver is None:
                return
        # Every kind's modules imported before the first worker is forked: imported between
        # two forks instead, each import ran on a machine already loaded by the workers
        # forked before it, and held up every fork after it.
        first = self.plan.processes[0].name
        self.forkserver.preloads[first] = forkserver.preload_for(
            c.kind for p in self.plan.processes for c in p.components
        )

    def _forkserver_ready(self) -> forkserver.ForkServer | None:
        """The fork server once it has imported (``None``: workers start as themselves)."""
        server = self.forkserver
        if server is None:
            return None
        if not server.wait_ready(FORKSERVER_READY_WITHIN, stopping=lambda: self._stop):
            if not self._stop:
                self.events.append(
                    f"fork server: {server.failure}; workers start as new interpreters"
                )
            return None
        return server

    def _worker_argv(self, process: ProcessPlan) -> list[str]:
        """The command line of a worker process of the plan."""
        argv = boot.argv("components.executor.worker", "--lock", str(self.assembly.lock_path))
        for component in process.components:
            argv += ["--component", component.name]
        if any(kinds.get(c.kind).stands_in_for for c in process.components):
            argv += ["--speed", repr(self.speed)]
        return argv

    def _start_processes(self) -> None:
        server = self._forkserver_ready()
        for process in self.plan.processes:
            self.supervisor.add(
                process.name,
                self._worker_argv(process),
                components=[c.name for c in process.components],
                final_exits=WORKER_FINAL_EXITS,
                heartbeat=True,
                forkserver=server,
            )
            # A Ctrl-C on a run still starting ends a worker quietly, even one that has
            # not reached its first line yet (msctl.launcher.boot).
            with boot.held_sigint():
                self.supervisor.start(process.name)

    def _serve_control(self) -> None:
        from components.comm.node import Node

        self._node = Node(
            self.session, "supervisor", host_namespace(self.plan.host), self.settings.domain
        )
        self._node.service("request", AGENT_SRV, self._on_request, deferred=True)

    # ------------------------------------------------------------------ loop
    def step(self) -> None:
        """One turn of the loop: processes, health, requests, state file."""
        # What it restarts starts like the first ones (see _start_processes).
        with boot.held_sigint():
            self._step()

    def _step(self) -> None:
        events = self.supervisor.poll()
        for event in events:
            self.events.append(event)
            name = event.split(":", 1)[0]
            process = self.supervisor.processes.get(name)
            if process is not None and self.watch is not None:
                self.watch.forget(process.components)
        if self.watch is not None:
            status = self.watch.status()
            for process in self.supervisor.processes.values():
                if (
                    process.state is ProcessState.STARTING
                    and process.components
                    and all(all(status[c]) for c in process.components)
                ):
                    self.supervisor.mark_running(process.name)
        if self._router_restart_at is not None and time.monotonic() >= self._router_restart_at:
            self._router_restart_at = None
            self.supervisor.restart(ROUTER_PROCESS)
        router = self.supervisor.processes.get(ROUTER_PROCESS)
        if (
            router is not None
            and router.state is ProcessState.STARTING
            and self.session is not None
            and list(self.session.info.routers_zid())
        ):
            # A restarted router is healthy once our own session is linked to it again.
            self.supervisor.mark_running(ROUTER_PROCESS)
        while True:
            try:
                pending = self._requests.get_nowait()
            except queue.Empty:
                break
            self._answer(pending)
        if time.monotonic() - self._last_state_write > 0.5:
            self.write_state()

    def all_healthy(self) -> bool:
        """Every process RUNNING (its components seen and publishing)."""
        return all(p.state is ProcessState.RUNNING for p in self.supervisor.processes.values())

    def failed(self) -> list[ManagedProcess]:
        """Processes that gave up: crashed too often, or exited saying a restart cannot help."""
        return [p for p in self.supervisor.processes.values() if p.state is ProcessState.FAILED]

    def run(self, duration: float | None, on_step: Callable[[Launch], None] | None = None) -> None:
        """Loop until :meth:`request_stop`, a ``down`` request, or ``duration``."""
        deadline = None if duration is None else time.monotonic() + duration
        while not self._stop and (deadline is None or time.monotonic() < deadline):
            self.step()
            if on_step is not None:
                on_step(self)
            if self._request_came.wait(LOOP_PAUSE):
                self._request_came.clear()  # what came is in the queue for the next step

    def _on_request(self, pending: Any) -> None:
        """Queue a request for the loop (a Zenoh thread calls this) and wake the loop."""
        self._requests.put(pending)
        self._request_came.set()

    def request_stop(self) -> None:
        """Ask :meth:`run` to return (signal-safe)."""
        self._stop = True

    # ------------------------------------------------------------------ control
    def _answer(self, pending: Any) -> None:
        """Answer one request (a slow read-only one from a thread of its own: the loop goes
        on supervising); whatever it raises is an error reply, never the loop's end."""
        if self._answerer is None:
            self._answerer = OffLoop(
                lambda checked: ("ok", self._do(checked.verb, checked.args)),
                lambda line: self.events.append(f"supervisor: {line}"),
                self.plan.host,
            )
        self._answerer(pending)

    def _do(self, verb: str, args: dict[str, Any]) -> Any:
        """Carry out a checked request (its verb and arguments) with its handler."""
        return self._verbs.run(request_of(verb, args))

    @property
    def _verbs(self) -> Verbs:
        """What a foreground run does, by request."""
        return Verbs(
            f"the supervisor of {self.plan.host}",
            {
                protocol.Ps: lambda _: self.document(),
                protocol.Doctor: lambda _: doctor_payload(
                    self.plan.host, self.session, self.settings
                ),
                protocol.Down: self._down,
                protocol.Up: self._up,
                protocol.Logs: self._logs,
                protocol.Restart: self._control,
                protocol.Stop: self._control,
                protocol.Start: self._control,
            },
        )

    def _process_of(self, name: str) -> str:
        if name in self.supervisor.processes:
            return name
        for process in self.supervisor.processes.values():
            if name in process.components:
                return process.name
        known = sorted({*self.supervisor.processes, *(c.name for c in self.plan.components)})
        raise RequestError(
            f"no component or process {name!r} on {self.plan.host}; known: " + ", ".join(known)
        )

    def _down(self, _request: protocol.Down) -> protocol.DownAnswer:
        self.request_stop()
        return protocol.DownAnswer(self.plan.host)

    def _up(self, _request: protocol.Up) -> Any:
        raise RequestError(f"{self.plan.host} already runs {self.assembly.template}")

    def _logs(self, request: protocol.Logs) -> protocol.LogsAnswer:
        processes = self.supervisor.processes
        if request.component is None:
            return {p: list(processes[p].log.recent) for p in processes}
        process = self._process_of(request.component)
        return {process: list(processes[process].log.recent)[-request.lines :]}

    def _control(self, request: protocol.Restart | protocol.Stop | protocol.Start) -> Any:
        """``restart``, ``stop`` or ``start`` of a component's process."""
        verb = type(request).__struct_config__.tag
        name = request.component
        if name is None:
            raise RequestError(f"{verb} needs a component")
        process = self._process_of(name)
        if process == ROUTER_PROCESS:
            return self._control_router(verb, process)
        members = self.supervisor.processes[process].components
        if isinstance(request, protocol.Restart) and request.only and len(members) > 1:
            return self._rebuild_alone(process, name)
        act = {"restart": self.supervisor.restart, "stop": self.supervisor.stop}
        act.get(verb, self.supervisor.start)(process)
        if self.watch is not None:
            self.watch.forget(members)
        for member in members:
            self._rebuilding.pop(member, None)
        self.events.append(f"{process}: {verb} requested")
        return protocol.ProcessAnswer(
            process,
            self.supervisor.processes[process].state.value,
            # What the verb takes with it: every component sharing the process.
            components=list(members),
            siblings=[c for c in members if c != name],
        )

    def _control_router(self, verb: str, process: str) -> Any:
        if verb == "stop":
            # Every request and reply goes through it: stopped alone, nothing could reach
            # this supervisor again, not even to start it.
            raise RequestError(
                f"the embedded router carries every topic and request of {self.plan.host}; "
                "restart it with `msctl restart router`, or stop everything with `msctl down`"
            )
        if verb == "restart":
            # After the reply has left through it, or the caller hears nothing.
            self._router_restart_at = time.monotonic() + 0.3
            self.events.append(f"{process}: restart requested")
            return protocol.ProcessAnswer(process, ProcessState.RESTARTING.value, [], [])
        self.supervisor.start(process)
        self.events.append(f"{process}: {verb} requested")
        return protocol.ProcessAnswer(
            process, self.supervisor.processes[process].state.value, [], []
        )

    def _rebuild_alone(self, process: str, name: str) -> dict[str, Any]:
        """``restart --only``: one component rebuilt in its process, the others untouched."""
        if name == process:
            raise RequestError(
                f"--only restarts one component, and {name} is a process "
                f"(of {', '.join(self.supervisor.processes[process].components)})"
            )
        kind = next((c.kind for c in self.plan.components if c.name == name), "")
        why = kinds.get(kind).not_rebuilt_alone if kind else ""
        if not why and os.environ.get("MSCTL_TRANSPORT", "zenoh") != "zenoh":
            why = "the rclpy executor cannot rebuild one node of a running process"
        if not why:
            try:
                self.supervisor.rebuild(process, name)
            except ValueError as exc:
                why = str(exc)
        if why:
            raise RequestError(
                f"cannot restart {name} alone: {why}; `msctl restart {name}` restarts its "
                f"process {process} whole"
            )
        self._rebuilding[name] = self.supervisor.processes[process].log.lines
        if self.watch is not None:
            self.watch.forget([name])
        self.events.append(f"{name}: rebuild requested (alone in {process})")
        return protocol.ProcessAnswer(process, "rebuilding", [name], [], only=True)

    # ------------------------------------------------------------------ state
    def components(self) -> list[ComponentView]:
        """Every component with its state."""
        status = self.watch.status() if self.watch is not None else {}
        views = []
        for process in self.supervisor.processes.values():
            for name in process.components:
                node_seen, output_seen = status.get(name, (False, False))
                component_state = process.state.value
                if process.state is ProcessState.STARTING and node_seen and output_seen:
                    component_state = ProcessState.RUNNING.value
                if name in self._rebuilding:
                    # Rebuilt alone: starting until its worker says it is rebuilt, and it is
                    # seen and publishing again.
                    done = any(
                        line.endswith(f"rebuilt {name}")
                        for line in process.log.since(self._rebuilding[name])
                    )
                    if done and node_seen and output_seen:
                        del self._rebuilding[name]
                    elif process.state is ProcessState.RUNNING:
                        component_state = ProcessState.STARTING.value
                kind = next((c.kind for c in self.plan.components if c.name == name), "")
                views.append(
                    ComponentView(name, kind, process.name, component_state, node_seen, output_seen)
                )
        return views

    def document(self) -> dict[str, Any]:
        """What ``ps`` and the state file hold."""
        processes = self.supervisor.snapshot()
        by_process = {p["name"]: p for p in processes}
        return {
            "host": self.plan.host,
            "template": self.assembly.template,
            "simulated": self.plan.simulated,
            "off_robot": self.plan.off_robot,
            # Whether its router runs the generated config (what crosses the radio is then
            # filtered: a recorder here reads it, msctl.recorder.recorder.radio_thinned).
            "secure": os.environ.get("MSCTL_SECURE") == "1",
            "supervisor_pid": os.getpid(),
            # An agent's run is stopped by asking the agent, never by signalling it.
            "agent": not self.serve_control,
            "router": self.endpoint,
            "started_router": self.started_router,
            "started": self._started,
            "state": "stopped" if self._stop else "running",
            "processes": processes,
            "components": [
                {
                    "name": c.name,
                    "kind": c.kind,
                    "host": self.plan.host,
                    "process": c.process,
                    "state": c.state,
                    "pid": by_process[c.process]["pid"],
                    "uptime": by_process[c.process]["uptime"],
                    "restarts": by_process[c.process]["restarts"],
                    "last_error": by_process[c.process]["last_error"],
                }
                for c in self.components()
            ],
            "not_built": [{"name": n, "kind": k} for n, k in self.plan.not_built],
            # What is wrong with the supervisor's own files (a full disk): `ps` warns of it.
            "faults": self.supervisor.faults() + ([self._state_fault] if self._state_fault else []),
        }

    def write_state(self) -> None:
        """Rewrite the state file; a failure (full disk) is reported once, never fatal: the
        supervisor keeps supervising, and ``msctl ps`` asks it over the network."""
        self._last_state_write = time.monotonic()
        try:
            state.write_state(self.document())
        except OSError as exc:
            fault = f"cannot write the state file {state.state_path()}: {exc.strerror or exc}"
            if fault != self._state_fault:
                self.events.append(f"supervisor: {fault}; still supervising")
            self._state_fault = fault
            return
        if self._state_fault:
            self.events.append("supervisor: the state file is written again")
        self._state_fault = ""

    # ------------------------------------------------------------------ stop
    def shutdown(self) -> None:
        """Stop every process (router last), close the session, mark the state stopped."""
        self._stop = True
        router = self.supervisor.processes.pop(ROUTER_PROCESS, None)
        if self.watch is not None:
            self.watch.close()
        if self._watch_session is not None:
            self._watch_session.close()
            self._watch_session = None
        if self._node is not None:
            self._node.close()
        self.supervisor.shutdown()
        if self.forkserver is not None:
            self.forkserver.close()  # after its children, whose exits it reported
        if router is not None:
            self.supervisor.processes[ROUTER_PROCESS] = router
            self.supervisor.shutdown()
        if self.session is not None:
            self.session.close()
            self.session = None
        self.write_state()
