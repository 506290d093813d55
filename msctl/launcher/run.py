"""One run of this computer's part of an assembly: router, processes, health, control.

The loop runs on one thread: it polls the supervisor, judges components healthy, rewrites the
state file and answers control requests (which the Zenoh thread only queues), so the
supervisor is never touched from two threads.
"""

from __future__ import annotations

import os
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from components import kinds
from components.assembly import ResolvedAssembly
from components.comm.session import SessionConfigError, SessionSettings, open_session
from components.ros import rclpy_available
from components.supervision.contract import AGENT_SRV, host_namespace
from components.supervision.dispatch import OffLoop
from components.supervision.protocol import ComponentRow, NotBuilt, RunDocument
from msctl.launcher import boot, forkserver, state
from msctl.launcher.plan import HostPlan, ProcessPlan
from msctl.launcher.requests import RunRequests
from msctl.launcher.router import (
    ROUTER_PROCESS,
    EmbeddedRouter,
    router_reachable,
    start_router,
    wait_for_router,
)
from msctl.launcher.supervisor import (
    LivenessPolicy,
    ManagedProcess,
    ProcessState,
    RestartPolicy,
    Supervisor,
)
from msctl.launcher.watch import HealthWatch

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
class Launch(RunRequests):
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

    def document(self) -> RunDocument:
        """What ``ps`` answers and the state file holds."""
        processes = self.supervisor.snapshot()
        by_process = {p.name: p for p in processes}
        return RunDocument(
            host=self.plan.host,
            template=self.assembly.template,
            simulated=self.plan.simulated,
            off_robot=self.plan.off_robot,
            # Whether its router runs the generated config (what crosses the radio is then
            # filtered: a recorder here reads it, msctl.recorder.recorder.radio_thinned).
            secure=os.environ.get("MSCTL_SECURE") == "1",
            supervisor_pid=os.getpid(),
            # An agent's run is stopped by asking the agent, never by signalling it.
            agent=not self.serve_control,
            router=self.endpoint,
            started_router=self.started_router,
            started=self._started,
            state="stopped" if self._stop else "running",
            processes=processes,
            components=[
                ComponentRow(
                    name=c.name,
                    kind=c.kind,
                    host=self.plan.host,
                    process=c.process,
                    state=c.state,
                    pid=by_process[c.process].pid,
                    uptime=by_process[c.process].uptime,
                    restarts=by_process[c.process].restarts,
                    last_error=by_process[c.process].last_error,
                )
                for c in self.components()
            ],
            not_built=[NotBuilt(n, k) for n, k in self.plan.not_built],
            # What is wrong with the supervisor's own files (a full disk): `ps` warns of it.
            faults=self.supervisor.faults() + ([self._state_fault] if self._state_fault else []),
        )

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
