"""One way every supervisor answers a request: parse it into its struct, find its handler in
a table by verb, reply with the handler's payload or a typed error (:class:`ErrorAnswer`).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Mapping
from typing import Any

import msgspec

from components.supervision.contract import RequestError
from components.supervision.protocol import Checked, Request, error_payload, parse_request

#: A handler: a request's struct in, its answer's payload out (a struct, a dict, a list).
Handler = Callable[[Any], Any]


class Verbs:
    """A supervisor's table of what it does: each request's struct -> its handler.

    Args:
        who: What the supervisor is, for a verb it does not do ("an agent").
        handlers: The handler of each request struct it answers.
    """

    def __init__(self, who: str, handlers: Mapping[type, Handler]) -> None:
        self.who = who
        self._handlers = dict(handlers)

    def __contains__(self, request_type: type) -> bool:
        return request_type in self._handlers

    def run(self, request: Request) -> Any:
        """Carry out ``request`` with its handler; returns the handler's payload.

        Raises:
            RequestError: If no handler takes it, or the handler refused it.
        """
        handler = self._handlers.get(type(request))
        if handler is None:
            verb = type(request).__struct_config__.tag
            raise RequestError(f"{verb} is not something {self.who} does")
        return handler(request)


def reply(pending: Any, success: bool, message: str, payload: Any = None) -> None:
    """Answer a pending AgentRequest (``payload`` goes as JSON; a str is sent as it is)."""
    from components.messages import msg

    if payload is None:
        text = ""
    elif isinstance(payload, str):
        text = payload
    else:
        text = msgspec.json.encode(payload).decode()
    pending.reply(
        msg("msctl_msgs/srv/AgentRequest_Response", success=success, message=message, payload=text)
    )


def request_verb(pending: Any) -> str:
    """A pending request's verb, for messages about it (never raises)."""
    verb = getattr(getattr(pending, "request", None), "verb", None)
    return verb[:40] if isinstance(verb, str) and verb else "?"


#: What carrying out a request came to: ``(success, message, payload)`` (an unsuccessful
#: one's payload is its :class:`~components.supervision.protocol.ErrorAnswer`, as JSON).
Outcome = tuple[bool, str, Any]


def answer(
    pending: Any,
    handle: Callable[[Checked], tuple[str, Any]],
    note: Callable[[str], None],
    who: str,
    parse: Callable[[Any, Any], Checked] = parse_request,
) -> None:
    """Parse a pending request, carry it out with ``handle`` and reply; never raises.

    A supervisor answers on its one loop thread: an exception escaping here would stop the
    loop, and with it every process it supervises. So whatever ``handle`` (or the reply)
    raises is answered as an error (see :func:`outcome`).

    Args:
        pending: The pending AgentRequest.
        handle: Carries out a checked request; returns ``(message, payload)``.
        note: Where to say what went wrong (the supervisor's log or events).
        who: Names the supervisor in error replies (its host).
        parse: Reads ``(verb, args_text)`` into a checked request.
    """
    reply_all([pending], outcome(pending, handle, note, who, parse), note, who)


def outcome(
    pending: Any,
    handle: Callable[[Checked], tuple[str, Any]],
    note: Callable[[str], None],
    who: str,
    parse: Callable[[Any, Any], Checked] = parse_request,
) -> Outcome:
    """What carrying out a pending request comes to (never raises).

    An error is an :class:`~components.supervision.protocol.ErrorAnswer`: ``malformed`` if
    the request could not be read, ``refused`` if ``handle`` refused it (a
    :class:`RequestError`), ``failed`` for anything else (a bug: also said with ``note``).
    """
    verb = request_verb(pending)
    try:
        checked = parse(pending.request.verb, pending.request.args)
    except RequestError as exc:
        return _error("malformed", str(exc), verb)
    except Exception as exc:  # RecursionError, MemoryError: still a malformed request
        note(f"request {verb!r} could not be read: {_describe(exc)}")
        return _error("malformed", f"{who} could not read {verb}: {_describe(exc)}", verb)
    try:
        message, payload = handle(checked)
    except RequestError as exc:
        return _error("refused", str(exc), verb)
    except Exception as exc:  # a bug in a handler: an error reply, the loop goes on
        note(f"request {verb!r} failed: {_describe(exc)}")
        return _error("failed", f"{who} could not {verb}: {_describe(exc)}", verb)
    return True, message, payload


def reply_all(pendings: list[Any], done: Outcome, note: Callable[[str], None], who: str) -> None:
    """Send one outcome to each of ``pendings`` (never raises: a reply that cannot be sent
    is said with ``note``, and a plain error reply is tried instead)."""
    success, message, payload = done
    for pending in pendings:
        verb = request_verb(pending)
        try:
            reply(pending, success, message, payload)
        except Exception as exc:
            note(f"could not answer request {verb!r}: {_describe(exc)}")
            failed = f"{who} could not answer {verb}: {_describe(exc)}"
            with contextlib.suppress(Exception):
                reply(pending, False, failed, error_payload("failed", failed, verb))


def _error(kind: str, message: str, verb: str) -> Outcome:
    return False, message, error_payload(kind, message, verb)


def _describe(exc: BaseException) -> str:
    text = str(exc)
    return f"{type(exc).__name__}: {text[:300]}" if text else type(exc).__name__


#: Verbs that only read and take seconds: ``doctor`` verifies every certificate of the fleet
#: and lists the whole graph (1.4 s on an idle rehearsal, tens of seconds on a starved
#: machine). On the supervisor's loop they would stop its supervision for that long (no
#: heartbeat read, no restart), so :class:`OffLoop` answers them on a thread of their own.
OFF_LOOP = frozenset({"doctor"})


class OffLoop:
    """Answers the :data:`OFF_LOOP` verbs on one worker thread, the others on the loop.

    Requests of such a verb that arrive while one is being carried out wait for the next
    run, and one run answers every identical request (same verb and arguments) waiting when
    it began: a client asking again while a slow doctor runs adds one run, not a queue.

    Args:
        handle: Carries out a checked request; returns ``(message, payload)``. Called on the
            worker thread for the :data:`OFF_LOOP` verbs: they must only read.
        note: Where to say what went wrong.
        who: Names the supervisor in error replies (its host).
    """

    def __init__(
        self,
        handle: Callable[[Checked], tuple[str, Any]],
        note: Callable[[str], None],
        who: str,
    ) -> None:
        import threading

        self._handle = handle
        self._note = note
        self._who = who
        self._lock = threading.Lock()
        self._waiting: dict[tuple[str, Any], list[Any]] = {}
        self._working = False

    def __call__(self, pending: Any) -> None:
        """Answer ``pending``: now, or (an :data:`OFF_LOOP` verb) from the worker thread."""
        verb = request_verb(pending)
        if verb not in OFF_LOOP:
            answer(pending, self._handle, self._note, self._who)
            return
        import threading

        args = getattr(getattr(pending, "request", None), "args", None)
        same = (verb, args if isinstance(args, str) else id(pending))
        with self._lock:
            self._waiting.setdefault(same, []).append(pending)
            if self._working:
                return
            self._working = True
        threading.Thread(target=self._work, name="msctl-off-loop", daemon=True).start()

    def _work(self) -> None:
        while True:
            with self._lock:
                if not self._waiting:
                    self._working = False
                    return
                pendings = self._waiting.pop(next(iter(self._waiting)))
            done = outcome(pendings[0], self._handle, self._note, self._who)
            reply_all(pendings, done, self._note, self._who)
