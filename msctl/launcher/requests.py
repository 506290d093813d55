"""What a foreground run answers: the verbs of its request service, each a handler in one
table (:class:`components.supervision.dispatch.Verbs`), mixed into
:class:`~msctl.launcher.run.Launch`, whose loop calls :meth:`RunRequests._answer`."""

from __future__ import annotations

import json
import os
import time
from typing import Any

import msgspec

from components import kinds
from components.supervision import protocol
from components.supervision.contract import RequestError
from components.supervision.dispatch import OffLoop, Verbs
from components.supervision.protocol import Checked, request_of
from msctl.launcher.router import ROUTER_PROCESS
from msctl.launcher.supervisor import ProcessState


def doctor_payload(host: str, session: Any, settings: Any) -> protocol.DoctorAnswer:
    """``msctl doctor``'s findings for this computer, as a request's answer."""
    from msctl.net import doctor

    found = doctor.this_computer(host, session, settings.connect, settings.domain)
    return protocol.DoctorAnswer(
        host,
        [protocol.DoctorFinding(f.host, f.check, f.status, f.detail, f.value) for f in found],
    )


class RunRequests:
    """The request handlers of :class:`~msctl.launcher.run.Launch` (a mixin: it uses the
    run's supervisor, plan, events and health watch)."""

    supervisor: Any
    plan: Any
    assembly: Any
    settings: Any
    session: Any
    watch: Any
    events: list[str]
    _answerer: OffLoop | None
    _rebuilding: dict[str, int]
    _router_restart_at: float | None

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


class AgentRequests:
    """The request handlers of :class:`~msctl.launcher.agent.Agent` (a mixin: it uses the
    agent's host, session, log and run); each returns ``(payload, message)``."""

    host: str
    session: Any
    settings: Any
    launch: Any
    _answerer: OffLoop | None

    def _answer(self, pending: Any) -> None:
        """Answer one request (a slow read-only one from a thread of its own: the loop goes
        on supervising); whatever it raises is an error reply, never the agent's end."""
        if self._answerer is None:
            self._answerer = OffLoop(self._handled, self.log, self.host)
        self._answerer(pending)

    def _handled(self, checked: Checked) -> tuple[str, Any]:
        try:
            payload, message = self._verbs.run(checked.request)
        except RequestError as exc:
            self.log(f"refused {checked.verb!r}: {exc}")
            raise
        return message, payload

    def handle(self, verb: str, args: dict[str, Any]) -> tuple[Any, str]:
        """Carry out a request given as its verb and arguments; returns ``(payload, message)``.

        Raises:
            RequestError: If the request is malformed, or cannot be carried out in the
                agent's state.
        """
        return self._verbs.run(request_of(verb, args))

    @property
    def _verbs(self) -> Verbs:
        """What an agent does, by request; each handler returns ``(payload, message)``."""
        return Verbs(
            "an agent",
            {
                protocol.Doctor: self._doctor,
                protocol.Ps: lambda _: (self.document(), "ok"),
                protocol.Up: self._up,
                protocol.Down: lambda _: self._down(),
                # This computer's own bags, idle or not (`msctl bag pull`).
                protocol.Bags: self._shelf,
                protocol.BagRead: self._shelf,
                protocol.Logs: self._forward,
                protocol.Restart: self._forward,
                protocol.Stop: self._forward,
                protocol.Start: self._forward,
            },
        )

    def _doctor(self, _request: protocol.Doctor) -> tuple[Any, str]:
        return doctor_payload(self.host, self.session, self.settings), "ok"

    def _shelf(self, request: protocol.Bags | protocol.BagRead) -> tuple[Any, str]:
        from msctl.recorder import shelf

        verb, args = protocol.wire_form(request)
        payload, message = shelf.serve(verb, json.loads(args), self.host)
        # Sent as its struct (the same JSON: the shelf's dicts have the structs' fields, in
        # their order), so what leaves is what a reader decodes.
        answer = protocol.BagsAnswer if verb == "bags" else protocol.BagReadAnswer
        return msgspec.convert(payload, answer), message

    def _forward(self, request: protocol.Request) -> tuple[Any, str]:
        """A verb on what runs, carried out by the run."""
        if self.launch is None:
            raise RequestError(
                f"nothing runs on {self.host} (its agent is idle); start with `msctl up --all`"
            )
        verb, args = protocol.wire_form(request)
        if verb != "logs":
            self.log(f"{verb} {getattr(request, 'component', None)}")
        return self.launch._do(verb, json.loads(args)), "ok"
