"""Requests to a supervisor over the data plane (``msctl_msgs/srv/AgentRequest``).

Every supervisor (a foreground ``msctl up`` or a robot's ``msctl agent``) serves
``/msctl/<host>/request``. A request is a verb and a JSON object of arguments; it can only
name things the supervisor already knows (processes, components of the assembly it runs or
was sent) — never a command line, a path or a shell fragment.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from typing import Any

AGENT_SRV = "msctl_msgs/srv/AgentRequest"
VERBS = ("ps", "logs", "restart", "stop", "start", "down", "up")
_ARG_KEYS: dict[str, set[str]] = {
    "ps": set(),
    "logs": {"component", "lines"},
    "restart": {"component"},
    "stop": {"component"},
    "start": {"component"},
    "down": set(),
    "up": {"assembly", "sim", "speed"},
}
_HOST_CHARS = re.compile(r"[^A-Za-z0-9_]")
#: Bounds on a request's arguments: an assembly document is tens of kilobytes and a few
#: levels deep; anything far past that is an attack or a bug, refused before it is parsed.
MAX_ARGS_BYTES = 4 * 1024 * 1024
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


@dataclass(frozen=True)
class Request:
    """A validated request."""

    verb: str
    args: dict[str, Any]


def parse_request(verb: str, args_text: str) -> Request:
    """Validate a request's verb and arguments.

    Raises:
        RequestError: For an unknown verb, malformed JSON, unknown keys or bad values.
    """
    if verb not in VERBS:
        raise RequestError(f"unknown verb {verb!r}; accepted: {', '.join(VERBS)}")
    if len(args_text) > MAX_ARGS_BYTES:
        raise RequestError(
            f"arguments are {len(args_text)} bytes; at most {MAX_ARGS_BYTES} are accepted"
        )
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


def call_supervisor(
    node: Any, host: str, verb: str, args: dict[str, Any] | None = None, timeout: float = 5.0
) -> dict[str, Any]:
    """Send a request to ``host``'s supervisor and return its decoded payload.

    Raises:
        ServiceTimeout: If nobody answers for that host.
        RequestError: If the supervisor refused the request.
    """
    from components.comm.types import registry

    client = node.client(f"{host_namespace(host)}/request", AGENT_SRV)
    try:
        request_cls = registry().msg_class(client.parts.request)
        response = client.call(request_cls(verb=verb, args=json.dumps(args or {})), timeout=timeout)
    finally:
        client.close()
    if not response.success:
        raise RequestError(f"{host} refused {verb}: {response.message}")
    return json.loads(response.payload) if response.payload else {}
