"""The agent of one robot computer (``msctl agent``): runs that computer's part on request.

An agent serves the same control service as a foreground ``msctl up``
(``/msctl/<host>/request``, ``msctl_msgs/srv/AgentRequest``), so ``msctl ps``, ``logs``,
``restart``, ``stop``, ``down --all`` and ``up --all`` from any computer of the network work
against it unchanged. Its node, ``/msctl/<host>/supervisor``, is on the graph from the moment
it starts: that is how it announces itself.

It is idle until an ``up`` carrying a resolved assembly document arrives. What it will run is
decided by data only, twice over:

1. the document must read as a resolved assembly, every name in it must be a plain name
   (:data:`~msctl.launcher.plan.SAFE_NAME`, no ``..``), and this computer must have a part in it;
2. this computer resolves the same template with the same units from its own data, and the
   result must equal the document (apart from ``sources``, the data files' local paths).

So a request can name an assembly this computer already knows how to build, and nothing else:
no command line, path or shell fragment reaches a process, and the URDF and MuJoCo model the
components read are generated here. The resolution is written atomically under
``$MSCTL_HOME/agent/assembly``, planned with :func:`plan_part` and run by a
:class:`~msctl.launcher.run.Launch` that does not serve control itself: the agent forwards
``ps / logs / restart / stop / start`` to it and handles ``up`` and ``down``. ``down`` stops
the run (every process group gone before the answer) and the agent stays, idle.

What ``up --all`` asked is kept on disk (:mod:`msctl.launcher.desired`, in the agent's
directory): written when an ``up`` is accepted, removed when a ``down`` is asked. An agent
that starts and finds it (the computer rebooted, lost power, or its agent was restarted)
brings the same part back up by itself, once its router is up and only if this computer's
data still resolves the same assembly, and says what it did in its ``ps`` document
(``rejoin``), which the ground's data monitor shows as an item and an alarm of the modules
on this computer. A desired state it cannot act on (cut, edited, another computer's, an
assembly this computer's data no longer resolves alike) is refused the same way, never
started, never a crash.

Everything runs on the agent's one loop thread (the Zenoh thread only queues requests), like
:class:`~msctl.launcher.run.Launch`, so the supervisor is never touched from two threads.
"""

from __future__ import annotations

import json
import os
import queue
import sys
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import msgspec

from components import kinds
from components.assembly import (
    LOCK_NAME,
    ResolvedAssembly,
    load_assembly,
    state_dir,
)
from components.comm.session import SessionSettings, open_session
from components.supervision import protocol
from components.supervision.contract import AGENT_SRV, RequestError, host_namespace
from components.supervision.dispatch import OffLoop
from msctl.errors import MsctlError
from msctl.launcher import desired as desired_state
from msctl.launcher import state
from msctl.launcher.desired import _Kept, _previous_run, _process_start, _why_back
from msctl.launcher.part import _check_name, _same_resolution, check_assembly, plan_part
from msctl.launcher.plan import HostPlan, this_host
from msctl.launcher.requests import AgentRequests
from msctl.launcher.router import (
    EmbeddedRouter,
    RouterStartError,
    router_reachable,
    start_router,
    wait_for_router,
)
from msctl.launcher.run import Launch
from msctl.launcher.state import RunLock
from msctl.launcher.supervisor import Supervisor

#: Seconds the loop rests between two turns when no request comes (one wakes it).
LOOP_PAUSE = 0.05


def agent_dir() -> Path:
    """``$MSCTL_HOME/agent``: the agent's resolution and its router's log."""
    return state_dir() / "agent"


def desired_state_path() -> Path:
    """Where the agent keeps what ``up --all`` asked of this computer (see :mod:`desired`)."""
    return agent_dir() / desired_state.FILE_NAME


def agent_assembly_dir() -> Path:
    """Where the agent writes the resolution it was sent (lock, URDF, MJCF)."""
    return agent_dir() / "assembly"


# --------------------------------------------------------------------------- the agent
class Agent(AgentRequests):
    """One computer's agent: idle, or running one assembly's part.

    Args:
        host: This computer's identity (default :func:`~msctl.launcher.plan.this_host`).
        settings: Session settings (default: from the environment); components use them too.
        log: Where to say what the agent does (one line per call).
    """

    def __init__(
        self,
        host: str | None = None,
        settings: SessionSettings | None = None,
        log: Callable[[str], None] | None = None,
    ) -> None:
        self.host = host or this_host()
        _check_name(self.host, "this computer's name (MSCTL_HOST)")
        self.settings = settings or SessionSettings.from_env()
        self.endpoint = self.settings.connect[0] if self.settings.connect else ""
        self.launch: Launch | None = None
        self._lock: RunLock | None = None
        self.router = Supervisor(agent_dir() / "logs")
        self._log = log or (lambda line: print(line, file=sys.stderr, flush=True))
        self._requests: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._answerer: OffLoop | None = None
        #: Set when a request arrives, so the loop answers it at once rather than after its
        #: pause (up to 50 ms more on every `msctl ps`).
        self._request_came = threading.Event()
        self._stop = False
        self._printed_events = 0
        self.session: Any = None
        self.node: Any = None
        #: When this agent's process started (Unix seconds): a rejoin is timed from it.
        self.started_at = _process_start()
        #: What the agent did at its start with a desired state it found; shown in ``ps``
        #: until the next ``up`` or ``down``. ``None``: it found none.
        self.rejoin: protocol.Rejoin | None = None

    def log(self, line: str) -> None:
        """One line about what the agent does, prefixed with its host."""
        self._log(f"msctl agent {self.host}: {line}")

    # ------------------------------------------------------------------ life
    def start(self) -> None:
        """Reach (or start) the router, then serve ``/msctl/<host>/request``.

        Raises:
            RuntimeError: If no router is reachable and none could be started.
        """
        from components.comm.node import Node

        if self.endpoint and not router_reachable(self.endpoint):
            self._start_router()
        elif self.endpoint:
            note = EmbeddedRouter.from_env(self.endpoint, self.host).not_applied()
            if note:
                self.log(note)
        self._refuse_a_second_supervisor()
        self.session = open_session(self.settings._replace(mode="peer"))
        self.node = Node(
            self.session, "supervisor", host_namespace(self.host), self.settings.domain
        )
        self.node.service("request", AGENT_SRV, self._on_request, deferred=True)
        self.log(
            f"serving {self.node.fqn.rsplit('/', 1)[0]}/request via {self.endpoint or 'peers'}; "
            "idle until `msctl up --all`"
        )

    def _refuse_a_second_supervisor(self) -> None:
        """Stop here if this host's service is already served (another agent, or a foreground
        `msctl up`, with the same MSCTL_HOST): both would answer every request.

        Asked as a client of the router, which answers graph queries from everything it knows
        at once, where a peer that has just joined would first have to learn the routes.

        Raises:
            MsctlError: Naming the service and what to check.
        """
        from components.comm.node import Node
        from msctl.launcher.fleet import supervisors

        if not self.endpoint:
            return  # peers only, no router to ask
        service = f"{host_namespace(self.host)}/request"
        session = open_session(self.settings._replace(mode="client", listen=()))
        try:
            with Node(session, f"msctl_agent_{os.getpid()}", "/", self.settings.domain) as node:
                taken = service in supervisors(node).values()
        finally:
            session.close()
        if taken:
            raise MsctlError(
                f"{service} is already served on this network: another agent (or `msctl up`) "
                f"runs as {self.host}",
                hint="give each computer its own MSCTL_HOST, or stop the other one",
            )

    def _start_router(self) -> None:
        """Start this computer's router, the field's router of this computer.

        A robot computer or a ground station is where the field's router runs: the agent
        brings one up, as `msctl up` would, so the other computers reach this one over the
        radio (``MSCTL_ROUTER_LISTEN``, ``MSCTL_ROUTER_CONNECT``, or ``MSCTL_SECURE=1``'s
        generated links). It serves this computer's own part of any assembly, never the
        whole of one (``up --all`` sends each agent its part).

        Raises:
            RouterStartError: A setting that cannot work, at once, in one line.
            RuntimeError: It did not answer in time.
        """
        embedded = EmbeddedRouter.from_env(self.endpoint, self.host, whole_assembly=False)
        router = start_router(self.router, embedded, say=self.log)
        try:
            wait_for_router(self.router, router, self.endpoint)
        except RouterStartError:
            raise
        except RuntimeError as exc:
            raise RuntimeError(f"no router at {self.endpoint}, and the agent's own: {exc}") from exc
        linked = f", linked to {', '.join(embedded.connect)}" if embedded.connect else ""
        if embedded.secure:
            self.log(f"started its secure router (mutual TLS, access control){linked}")
        else:
            self.log(f"started a router listening on {', '.join(embedded.plain_listen())}{linked}")

    def step(self) -> None:
        """One turn: answer queued requests, then let the run (if any) watch its processes."""
        while True:
            try:
                pending = self._requests.get_nowait()
            except queue.Empty:
                break
            self._answer(pending)
        for event in self.router.poll():
            self.log(f"router: {event}")
        if self.launch is not None:
            self.launch.step()
            for event in self.launch.events[self._printed_events :]:
                self.log(event)
            self._printed_events = len(self.launch.events)

    def run(self) -> None:
        """Bring back what ``up --all`` asked before this start (:meth:`rejoin_part`: every
        service of the agent is served by then), then loop until :meth:`request_stop`."""
        if not self._stop:
            self.rejoin_part()
        while not self._stop:
            self.step()
            if self._request_came.wait(LOOP_PAUSE):
                self._request_came.clear()  # what came is in the queue for the next step

    def _on_request(self, pending: Any) -> None:
        """Queue a request for the loop (a Zenoh thread calls this) and wake the loop."""
        self._requests.put(pending)
        self._request_came.set()

    def request_stop(self) -> None:
        """Ask :meth:`run` to return (signal-safe)."""
        self._stop = True

    def shutdown(self) -> None:
        """Stop the run (every process group gone), stop serving, close the session."""
        self._stop = True
        self._stop_run()
        if self.node is not None:
            self.node.close()
            self.node = None
        if self.session is not None:
            self.session.close()
            self.session = None
        self.router.shutdown()
        self.log("stopped")

    def document(self) -> protocol.RunDocument:
        """What ``ps`` returns: the run's document, or an idle host with no components; with
        ``rejoin`` when the agent found a desired state at its start (see :meth:`rejoin_part`),
        left out otherwise."""
        if self.launch is not None:
            run = self.launch.document()
        else:
            run = protocol.RunDocument(
                host=self.host,
                state="idle",
                supervisor_pid=os.getpid(),
                router=self.endpoint,
            )
        rejoin = self.rejoin if self.rejoin is not None else msgspec.UNSET
        return msgspec.structs.replace(run, agent=True, rejoin=rejoin)

    def _up(self, request: protocol.Up) -> tuple[Any, str]:
        args = json.loads(protocol.wire_form(request)[1])
        if self.launch is not None:
            if self._runs_already(args):
                # The same up again (its answer lost on a flapping link, or `up --all` run
                # again after a partial failure): what runs is what was asked, nothing moves.
                self.log(f"up {self.launch.assembly.template}: already running, as asked")
                return self._up_payload(self.launch.assembly, self.launch.plan), "already running"
            running = [c.name for c in self.launch.plan.components]
            raise RequestError(
                f"{self.host} already runs {self.launch.assembly.template} ({len(running)} "
                f"components: {', '.join(running[:4])}{', ...' if len(running) > 4 else ''}); "
                "stop it first with `msctl down --all`"
            )
        if "assembly" not in args:
            raise RequestError("up needs the resolved assembly (argument 'assembly')")
        sim = args.get("sim")
        speed = float(args.get("speed", 1.0))
        payload, message = self._start_part(args["assembly"], sim, speed)
        self.rejoin = None  # what was asked now supersedes what the agent did at its start
        kept = self._keep_desired(args["assembly"], sim, speed, payload.template)
        return payload, message if kept else f"{message} ({kept.reason})"

    def _start_part(
        self, document: Mapping[str, Any], sim: bool | None, speed: float
    ) -> tuple[protocol.UpAnswer, str]:
        """Check, resolve and start this computer's part of ``document``.

        Raises:
            RequestError: If it is refused or could not start (nothing of it is left running).
        """
        assembly, plan = self._prepare(document, sim)
        not_built = sorted({k for _, k in plan.not_built})
        if not plan.processes:
            note = f"nothing to start on {self.host}" + (
                f" (kinds not implemented yet: {', '.join(not_built)})" if not_built else ""
            )
            self.log(f"up {assembly.template}: {note}")
            return self._up_payload(assembly, plan), note
        self.log(
            f"up {assembly.template} ({'simulation' if plan.simulated else 'hardware'}): "
            f"{len(plan.components)} components in {len(plan.processes)} processes"
            + (f"; not started (not implemented yet): {', '.join(not_built)}" if not_built else "")
        )
        # One supervisor per MSCTL_HOME: not beside a `msctl up` of this computer's own.
        try:
            self._lock = RunLock.acquire(
                template=assembly.template, host=self.host, by="msctl agent"
            )
        except MsctlError as exc:
            raise RequestError(f"{self.host} cannot start {assembly.template}: {exc}") from None
        launch = Launch(assembly, plan, settings=self.settings, speed=speed, serve_control=False)
        try:
            launch.start()
        except Exception as exc:
            launch.shutdown()
            self._release_lock()
            raise RequestError(f"{self.host} could not start {assembly.template}: {exc}") from exc
        self.launch = launch
        self._printed_events = 0
        return self._up_payload(assembly, plan), "starting"

    def _runs_already(self, args: dict[str, Any]) -> bool:
        """Whether ``up`` asks for exactly what runs: the same resolution, simulated alike."""
        assert self.launch is not None
        document = args.get("assembly")
        if not isinstance(document, Mapping):
            return False
        try:
            sent = check_assembly(document, self.host)
        except RequestError:
            return False
        if _same_resolution(document, self.launch.assembly.document):
            return False
        return plan_part(sent, self.host, args.get("sim")).simulated == self.launch.plan.simulated

    def _up_payload(self, assembly: ResolvedAssembly, plan: HostPlan) -> protocol.UpAnswer:
        return protocol.UpAnswer(
            host=self.host,
            template=assembly.template,
            simulated=plan.simulated,
            processes=[p.name for p in plan.processes],
            components=[c.name for c in plan.components],
            not_built=[protocol.NotBuilt(n, k) for n, k in plan.not_built],
        )

    def _prepare(self, document: Mapping[str, Any], sim: bool | None) -> tuple[Any, HostPlan]:
        """Check the document, resolve it from this computer's data, write it, plan it."""
        from msctl.assembler import resolve
        from msctl.assembler.store import write_resolution

        sent = check_assembly(document, self.host)
        try:
            resolution = resolve(sent.template, dict(sent.units))
        except MsctlError as exc:
            raise RequestError(
                f"{self.host} cannot resolve {sent.template} with units "
                f"{', '.join(f'{s}={u}' for s, u in sent.units.items())} from its own data: {exc}"
            ) from None
        differ = _same_resolution(document, resolution.document)
        if differ:
            raise RequestError(
                f"the {sent.template} assembly sent differs from {self.host}'s own resolution "
                f"of the same units in {', '.join(differ)}: bring the two computers' msctl data "
                "(templates, modules, calibration) to the same version, then `msctl assemble` "
                "and `msctl up --all` again"
            )
        plan = plan_part(sent, self.host, sim)
        # The MJCF costs ~0.5 s of MuJoCo: only where the simulated world runs.
        stand_ins = {k.component_name for k in kinds.simulators()}
        simulates = any(c.name in stand_ins for c in plan.components)
        target = write_resolution(agent_assembly_dir(), resolution, mjcf=simulates)
        return load_assembly(target / LOCK_NAME), plan

    def _keep_desired(
        self, document: Mapping[str, Any], sim: Any, speed: float, template: str
    ) -> _Kept:
        """Write what ``up`` asked to disk, for the agent's next start (a reboot)."""
        path = desired_state_path()
        wanted = desired_state.DesiredState(
            host=self.host,
            template=template,
            assembly=document,
            sim=None if sim is None else bool(sim),
            speed=speed,
            asked_at=time.time(),
        )
        try:
            desired_state.write(path, wanted)
        except OSError as exc:
            # The part runs as asked; only its return after a reboot is lost: say so.
            reason = (
                f"not kept on disk ({path}: {exc.strerror or exc}): a reboot will not bring it back"
            )
            self.log(f"up {template}: {reason}")
            return _Kept(False, reason)
        return _Kept(True)

    def _forget_desired(self) -> str:
        """Remove the desired state (a ``down`` was asked): a reboot brings nothing back.

        Returns:
            ``""``, or why it could not be removed (said in the answer and the log).
        """
        self.rejoin = None
        path = desired_state_path()
        try:
            desired_state.remove(path)
        except OSError as exc:
            reason = (
                f"could not remove {path} ({exc.strerror or exc}): the agent would bring the "
                "part back at its next start; remove the file by hand"
            )
            self.log(f"down: {reason}")
            return reason
        return ""

    def rejoin_part(self) -> None:
        """At the agent's start: bring back what ``up --all`` asked before it (kept on disk).

        Nothing happens without a desired state. With one, this computer's part is started
        as the original ``up`` started it (same document, simulation flag and speed), after
        the same checks (its own data must still resolve the same assembly). What happened
        is kept in :attr:`rejoin` (so in ``ps``, so at the ground's data monitor) and
        logged; a refusal starts nothing, and nothing here raises.
        """
        path = desired_state_path()
        try:
            wanted = desired_state.read(path, self.host)
        except desired_state.DesiredStateError as exc:
            self._report_rejoin("refused", f"{self.host} started and found {exc}")
            return
        if wanted is None:
            return
        asked = time.strftime("%H:%M:%S", time.localtime(wanted.asked_at))
        previous, this_boot = _previous_run()
        cause = _why_back(previous, this_boot)
        self.log(
            f"{cause}; bringing back its part of {wanted.template} as `msctl up --all` asked at "
            f"{asked} (kept in {path})"
        )
        left = state.groups_left(previous) if previous is not None and this_boot else []
        if left:
            self._report_rejoin(
                "refused",
                f"{self.host} {cause} but did not bring back {wanted.template}: processes of its "
                f"previous run still run with no supervisor ({', '.join(left)}); stop them with "
                f"`msctl down` on {self.host}, then `msctl up --all`",
            )
            return
        try:
            self._start_part(wanted.assembly, wanted.sim, wanted.speed)
        except RequestError as exc:
            self._report_rejoin(
                "refused", f"{self.host} {cause} but did not bring back {wanted.template}: {exc}"
            )
            return
        except Exception as exc:  # whatever a desired state leads to: a refusal, never a crash
            self._report_rejoin(
                "refused",
                f"{self.host} {cause} but did not bring back {wanted.template}: "
                f"{type(exc).__name__}: {exc}",
            )
            return
        self._report_rejoin(
            "rejoined",
            f"{self.host} {cause} and rejoined: its agent brought back its part of "
            f"{wanted.template} by itself (`up --all` of {asked})",
        )

    def _report_rejoin(self, outcome: str, message: str) -> None:
        self.rejoin = protocol.Rejoin(
            outcome=outcome, at=time.time(), agent_started=self.started_at, message=message
        )
        self.log(message)

    def _down(self) -> tuple[Any, str]:
        forgot = self._forget_desired()
        if self.launch is None:
            message = f"nothing was running on {self.host}"
            message += f" ({forgot})" if forgot else ""
            return protocol.DownAnswer(self.host, stopped=[]), message
        template = self.launch.assembly.template
        stopped = self._stop_run()
        self.log(f"down {template}: stopped {', '.join(stopped) or 'nothing'}; idle")
        answer = f"stopped ({forgot})" if forgot else "stopped"
        return protocol.DownAnswer(self.host, template, stopped), answer

    def _stop_run(self) -> list[str]:
        """Stop the run and wait until its processes are gone; returns their names."""
        if self.launch is None:
            return []
        launch, self.launch = self.launch, None
        names = list(launch.supervisor.processes)
        try:
            launch.shutdown()
        finally:
            self._release_lock()
        return names

    def _release_lock(self) -> None:
        if self._lock is not None:
            self._lock.release()
            self._lock = None
