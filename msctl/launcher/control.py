"""Requests to a supervisor over the data plane (``msctl_msgs/srv/AgentRequest``).

Every supervisor (a foreground ``msctl up`` or a robot's ``msctl agent``) serves
``/msctl/<host>/request``. A request is a verb and a JSON object of arguments; it can only
name things the supervisor already knows (processes, components of the assembly it runs or
was sent) — never a command line, a path or a shell fragment.
"""

from __future__ import annotations

import contextlib
import json
import re
from collections.abc import Callable
from typing import Any, NamedTuple

AGENT_SRV = "msctl_msgs/srv/AgentRequest"
VERBS = ("ps", "logs", "restart", "stop", "start", "down", "up", "doctor", "bags", "bag_read")
_ARG_KEYS: dict[str, set[str]] = {
    "ps": set(),
    "logs": {"component", "lines"},
    "restart": {"component", "only"},
    "stop": {"component"},
    "start": {"component"},
    "down": set(),
    "up": {"assembly", "sim", "speed"},
    "doctor": set(),
    # The bag shelf an agent serves (msctl.recorder.shelf checks the values).
    "bags": set(),
    "bag_read": {"path", "offset", "size"},
}
_HOST_CHARS = re.compile(r"[^A-Za-z0-9_]")
#: Bounds on a request's arguments, checked before they are parsed. The largest request is
#: an ``up`` carrying a resolved assembly document, as :func:`call_supervisor` sends it
#: (compact JSON), measured with the shipped templates: minimal 6.5 KB, dragon 18 KB,
#: dragon_x4 36 KB, two_dragons 40 KB (about 5 KB per module), 7 levels deep. 64 KiB holds
#: a dozen modules; past that, ``msctl up --all`` says so before sending (the bound is the
#: size of the request, not of the fleet: raise it here, with a new measurement, if a
#: bigger assembly needs it). Anything nesting deeper than 32 is an attack or a bug.
MAX_ARGS_BYTES = 64 * 1024
MAX_ARGS_DEPTH = 32
_JSON_STRING = re.compile(r'"(?:[^"\\]|\\.)*"')
_NESTING = str.maketrans({"[": "(", "{": "(", "]": ")", "}": ")"})


class RequestError(ValueError):
    """A request that is refused; the message says what is wrong."""


def host_namespace(host: str) -> str:
    """The ROS namespace of a host's supervisor (ROS names allow only letters, digits, _)."""
    mangled = _HOST_CHARS.sub("_", host)
    if not mangled or mangled[0].isdigit():
        mangled = "h_" + mangled
    return f"/msctl/{mangled}"


class Request(NamedTuple):
    """A validated request."""

    verb: str
    args: dict[str, Any]


def parse_request(verb: str, args_text: str) -> Request:
    """Validate a request's verb and arguments.

    Raises:
        RequestError: For an unknown verb, malformed JSON, unknown keys or bad values.
    """
    if not isinstance(verb, str) or verb not in VERBS:
        shown = verb[:40] if isinstance(verb, str) else type(verb).__name__
        raise RequestError(f"unknown verb {shown!r}; accepted: {', '.join(VERBS)}")
    if not isinstance(args_text, str):
        raise RequestError("arguments must be JSON text")
    size = args_size(args_text)
    if size > MAX_ARGS_BYTES:
        raise RequestError(f"arguments are {size} bytes; at most {MAX_ARGS_BYTES} are accepted")
    if _depth(args_text) > MAX_ARGS_DEPTH:
        raise RequestError(f"arguments nest deeper than {MAX_ARGS_DEPTH} levels")
    try:
        args = json.loads(args_text) if args_text.strip() else {}
    except ValueError as exc:
        raise RequestError(f"arguments are not JSON: {exc}") from None
    if not isinstance(args, dict):
        raise RequestError("arguments must be a JSON object")
    unknown = set(args) - _ARG_KEYS[verb]
    if unknown:
        raise RequestError(f"{verb} takes no argument {', '.join(sorted(unknown))}")
    for key in ("component",):
        if key in args and not (isinstance(args[key], str) and len(args[key]) < 128):
            raise RequestError(f"{key} must be a component or process name")
    if "only" in args and not isinstance(args["only"], bool):
        raise RequestError("only must be true or false")
    if "lines" in args and not (isinstance(args["lines"], int) and 0 < args["lines"] <= 10000):
        raise RequestError("lines must be a whole number from 1 to 10000")
    if "speed" in args and not (
        isinstance(args["speed"], int | float) and 0 < float(args["speed"]) <= 100
    ):
        raise RequestError("speed must be a number in (0, 100]")
    if "sim" in args and not isinstance(args["sim"], bool | type(None)):
        raise RequestError("sim must be true, false or null")
    if "assembly" in args and not isinstance(args["assembly"], dict):
        raise RequestError("assembly must be a resolved assembly document (a JSON object)")
    return Request(verb, args)


def args_size(text: str) -> int:
    """Bytes of ``text`` in UTF-8 (a character count first: a huge text is not encoded)."""
    if len(text) > MAX_ARGS_BYTES:
        return len(text)
    return len(text.encode("utf-8", "surrogatepass"))


def encode_args(args: dict[str, Any] | None) -> str:
    """A request's arguments as the compact JSON :func:`call_supervisor` sends."""
    return json.dumps(args or {}, separators=(",", ":"))


def _depth(text: str) -> int:
    """How deep JSON ``text`` nests (strings skipped), without recursing into it."""
    brackets = "".join(ch for ch in _JSON_STRING.sub("", text).translate(_NESTING) if ch in "()")
    depth = deepest = 0
    for ch in brackets:
        depth += 1 if ch == "(" else -1
        deepest = max(deepest, depth)
    return deepest


def reply(pending: Any, success: bool, message: str, payload: Any = None) -> None:
    """Answer a pending AgentRequest (``payload`` goes as JSON)."""
    from components.messages import msg

    pending.reply(
        msg(
            "msctl_msgs/srv/AgentRequest_Response",
            success=success,
            message=message,
            payload=json.dumps(payload) if payload is not None else "",
        )
    )


def request_verb(pending: Any) -> str:
    """A pending request's verb, for messages about it (never raises)."""
    verb = getattr(getattr(pending, "request", None), "verb", None)
    return verb[:40] if isinstance(verb, str) and verb else "?"


def answer(
    pending: Any,
    handle: Callable[[str, dict[str, Any]], tuple[bool, str, Any]],
    note: Callable[[str], None],
    who: str,
) -> None:
    """Parse a pending request, carry it out with ``handle`` and reply; never raises.

    A supervisor answers on its one loop thread: an exception escaping here would stop the
    loop, and with it every process it supervises. So whatever ``handle`` (or the reply)
    raises is answered as an error and said with ``note``.

    Args:
        pending: The pending AgentRequest.
        handle: Carries out ``(verb, args)``; returns ``(success, message, payload)``.
        note: Where to say what went wrong (the supervisor's log or events).
        who: Names the supervisor in error replies (its host).
    """
    _reply_all([pending], _outcome(pending, handle, note, who), note, who)


def _outcome(
    pending: Any,
    handle: Callable[[str, dict[str, Any]], tuple[bool, str, Any]],
    note: Callable[[str], None],
    who: str,
) -> tuple[bool, str, Any]:
    """``(success, message, payload)`` of carrying out a pending request (never raises)."""
    verb = request_verb(pending)
    try:
        request = parse_request(pending.request.verb, pending.request.args)
        return handle(request.verb, request.args)
    except RequestError as exc:
        return False, str(exc), None
    except Exception as exc:  # RecursionError, MemoryError, a bug: an error reply
        note(f"request {verb!r} failed: {_describe(exc)}")
        return False, f"{who} could not {verb}: {_describe(exc)}", None


def _reply_all(
    pendings: list[Any], outcome: tuple[bool, str, Any], note: Callable[[str], None], who: str
) -> None:
    """Send one outcome to each of ``pendings`` (never raises)."""
    success, message, payload = outcome
    for pending in pendings:
        verb = request_verb(pending)
        try:
            reply(pending, success, message, payload)
        except Exception as exc:
            note(f"could not answer request {verb!r}: {_describe(exc)}")
            with contextlib.suppress(Exception):
                reply(pending, False, f"{who} could not answer {verb}: {_describe(exc)}")


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
        handle: Carries out ``(verb, args)``; returns ``(success, message, payload)``. Called
            on the worker thread for the :data:`OFF_LOOP` verbs: they must only read.
        note: Where to say what went wrong.
        who: Names the supervisor in error replies (its host).
    """

    def __init__(
        self,
        handle: Callable[[str, dict[str, Any]], tuple[bool, str, Any]],
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
            outcome = _outcome(pendings[0], self._handle, self._note, self._who)
            _reply_all(pendings, outcome, self._note, self._who)


def _describe(exc: BaseException) -> str:
    text = str(exc)
    return f"{type(exc).__name__}: {text[:300]}" if text else type(exc).__name__


def call_supervisor(
    node: Any,
    host: str,
    verb: str,
    args: dict[str, Any] | None = None,
    timeout: float = 5.0,
    grace: float = 0.0,
    attempt: float | None = None,
) -> dict[str, Any]:
    """Send a request to ``host``'s supervisor and return its decoded payload.

    Args:
        node: The asking node.
        host: The supervisor's computer.
        verb: The request's verb.
        args: Its arguments.
        timeout: Seconds to wait for the answer.
        grace: Seconds to keep sending it again while its query ends early with no answer
            (the router knows no server for it: a radio link's route that lapsed for a
            moment is not an agent gone). Only for a verb that is safe to repeat: a query
            that ended early may still have reached its server (a link that dropped while
            it waited), and an agent takes the same ``up`` twice as one.
        attempt: Seconds with no answer before the request is sent again (the earlier
            copies still waiting), until ``timeout``; ``None`` sends it once. A radio link
            that closes while a query waits loses the query or its answer for good (nothing
            resends it when the link reopens): only a verb that is safe to repeat.

    Raises:
        ServiceTimeout: If nobody answers for that host.
        RequestError: If the supervisor refused the request.
    """
    import time

    from components.comm.services import NoServer
    from components.comm.types import registry

    client = node.client(f"{host_namespace(host)}/request", AGENT_SRV)
    started = time.monotonic()
    try:
        request = registry().msg_class(client.parts.request)(verb=verb, args=encode_args(args))
        while True:
            left = max(timeout - (time.monotonic() - started), 0.1)
            try:
                response = client.call_repeating(request, left, attempt or left)
                break
            except NoServer:
                if time.monotonic() - started + 0.25 >= min(grace, timeout):
                    raise
                time.sleep(0.25)
    finally:
        client.close()
    if not response.success:
        raise RequestError(f"{host} refused {verb}: {response.message}")
    return json.loads(response.payload) if response.payload else {}
