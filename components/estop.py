"""The e-stop: every module's joint manager ``halt`` called at once (and ``recover``).

A halt goes to each module's ``<namespace>/halt`` (``std_srvs/srv/Trigger``): its joint manager
holds every joint and refuses commands until ``recover``. Every request is sent before any
answer is awaited, so the slowest module sets the time, not the sum; each answer is stamped
as it arrives. No claim is asked for or checked: a halt is never blocked by a claim.

Used by ``msctl estop`` / ``msctl recover``, and by any operator that stops what it drives
(the guardian; teleop's ``space``)::

    estop = Estop(node, {"limb1": "/limb1", "wheel1": "/wheel1"})  # clients declared once
    for answer in estop.halt():       # -> [Acknowledgement(module, ok, message, seconds)]
        ...
    estop.close()
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from components.messages import TRIGGER

#: Seconds to wait for each module's answer.
HALT_TIMEOUT = 2.0
#: Seconds between two sends of a request that reached no server.
RESEND_PAUSE = 0.05
#: Seconds with no answer before a request is sent again, the earlier copies still waiting.
REPEAT_EVERY = 0.25
#: Seconds between two looks at the answers (each answer is stamped when it came, on
#: Zenoh's thread: the look's period does not enter the acknowledgement time).
POLL = 0.005


@dataclass(frozen=True)
class Acknowledgement:
    """One module's answer to a halt or recover.

    Attributes:
        module: The module's slot.
        ok: It answered, with success.
        message: What it said, or why no answer came.
        seconds: From the request to its answer; ``None`` when none came.
    """

    module: str
    ok: bool
    message: str
    seconds: float | None

    def as_dict(self) -> dict[str, Any]:
        """A JSON-ready view."""
        return {
            "module": self.module,
            "ok": self.ok,
            "message": self.message,
            "seconds": self.seconds,
        }


class Estop:
    """Halt and recover clients for a set of modules, declared once and reused.

    The clients appear on the graph only once their first requests have left: a new token
    wakes every process watching the graph, and arriving with a halt, that delayed it
    (see :class:`~components.comm.services.ServiceClient`'s ``announce``).

    Args:
        node: The node the clients belong to (the caller keeps it open).
        modules: Slot -> the module's namespace (``/limb1``), or just slots (namespace
            ``/<slot>``, the assembly's rule).
    """

    def __init__(self, node: Any, modules: Mapping[str, str] | Iterable[str]) -> None:
        spaces = dict(modules) if isinstance(modules, Mapping) else {m: f"/{m}" for m in modules}
        self.modules: tuple[str, ...] = tuple(spaces)
        self._clients: dict[str, dict[str, Any]] = {"halt": {}, "recover": {}}
        for slot, namespace in spaces.items():
            for verb, clients in self._clients.items():
                clients[slot] = node.client(
                    f"{namespace.rstrip('/')}/{verb}", TRIGGER, announce=False
                )

    def halt(
        self, modules: Iterable[str] | None = None, timeout: float = HALT_TIMEOUT
    ) -> list[Acknowledgement]:
        """Halt ``modules`` (default: all of this e-stop's) at once; one answer each, in
        module order.

        Raises:
            KeyError: If a module is not one of this e-stop's (the message names them).
        """
        return self._trigger("halt", modules, timeout)

    def recover(
        self, modules: Iterable[str] | None = None, timeout: float = HALT_TIMEOUT
    ) -> list[Acknowledgement]:
        """Recover ``modules`` (default: all) from a halt, at once."""
        return self._trigger("recover", modules, timeout)

    def _trigger(
        self, verb: str, modules: Iterable[str] | None, timeout: float
    ) -> list[Acknowledgement]:
        from components.comm.services import ServiceError

        chosen = list(self.modules if modules is None else modules)
        unknown = [m for m in chosen if m not in self.modules]
        if unknown:
            raise KeyError(
                f"no module {', '.join(unknown)} here; modules: {', '.join(self.modules)}"
            )
        clients = self._clients[verb]
        request = clients[chosen[0]].request_type()() if chosen else None
        first = time.monotonic()
        deadline = first + timeout
        # Every request leaves before any answer is awaited: all modules at once.
        copies = {s: [clients[s].call_async(request, timeout, urgent=True)] for s in chosen}
        for slot in chosen:
            clients[slot].announce()
        answers: dict[str, Acknowledgement] = {}
        while len(answers) < len(chosen):
            now = time.monotonic()
            for slot in chosen:
                if slot in answers:
                    continue
                calls = copies[slot]
                answered = next((c for c in calls if c.answered is not None), None)
                if answered is not None:
                    try:
                        response = answered.result(0.0)
                        ok, message = bool(response.success), str(response.message)
                    except ServiceError as exc:  # an error reply, or not a response
                        ok, message = False, str(exc)
                    answers[slot] = Acknowledgement(slot, ok, message, answered.answered - first)
                    continue
                newest = calls[-1]
                ended = all(c.done.is_set() for c in calls)
                if now >= deadline or (ended and deadline - now <= RESEND_PAUSE):
                    why = newest.error() if newest.done.is_set() else None
                    answers[slot] = Acknowledgement(
                        slot, False, str(why or _silence(clients[slot], timeout)), None
                    )
                    continue
                # A copy that reached nobody (the router knew no server: a radio link's route
                # lapsed for a moment) goes again at once; one that is only unanswered goes
                # again every REPEAT_EVERY, the earlier ones still waiting (a link that closed
                # while it waited lost it for good). A halt taken twice is one halt.
                due = RESEND_PAUSE if newest.reached_nobody else REPEAT_EVERY
                if now - newest.started >= due:
                    left = max(deadline - now, RESEND_PAUSE)
                    calls.append(clients[slot].call_async(request, left, urgent=True))
            if len(answers) < len(chosen):
                time.sleep(POLL)
        return [answers[slot] for slot in chosen]

    def close(self) -> None:
        """Undeclare the clients (idempotent; the node stays open)."""
        for clients in self._clients.values():
            for client in clients.values():
                client.close()
            clients.clear()

    def __enter__(self) -> Estop:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _silence(client: Any, timeout: float) -> str:
    """Why a module whose copies all waited to the deadline gave no answer."""
    return (
        f"no server answered {client.service} ({client.srv_type}) within {timeout:g} s; "
        "check it is running (`msctl service list`)"
    )
