"""The supervisors' request service: its name, its type and the bounds on a request.

Every supervisor serves ``/msctl/<host>/request`` (``msctl_msgs/srv/AgentRequest``): a
request is a verb and a JSON object of arguments; it can only name things the supervisor
already knows (processes, components of the assembly it runs or was sent), never a command
line, a path or a shell fragment. This module is light on purpose (no msgspec: it loads
``inspect``): ``msctl ps`` imports it on every run (see :mod:`msctl.quick`).
"""

from __future__ import annotations

import json
import re
from typing import Any

AGENT_SRV = "msctl_msgs/srv/AgentRequest"
_HOST_CHARS = re.compile(r"[^A-Za-z0-9_]")
#: Bounds on a request's arguments, checked before they are parsed. The largest request is
#: an ``up`` carrying a resolved assembly document, as the CLI sends it (compact JSON),
#: measured with the shipped templates: minimal 6.5 KB, dragon 18 KB, dragon_x4 36 KB,
#: two_dragons 40 KB (about 5 KB per module), 7 levels deep. 64 KiB holds a dozen modules;
#: past that, ``msctl up --all`` says so before sending (the bound is the size of the
#: request, not of the fleet: raise it here, with a new measurement, if a bigger assembly
#: needs it). Anything nesting deeper than 32 is an attack or a bug.
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


def args_size(text: str) -> int:
    """Bytes of ``text`` in UTF-8 (a character count first: a huge text is not encoded)."""
    if len(text) > MAX_ARGS_BYTES:
        return len(text)
    return len(text.encode("utf-8", "surrogatepass"))


def encode_args(args: dict[str, Any] | None) -> str:
    """A request's arguments as the compact JSON the client sends."""
    return json.dumps(args or {}, separators=(",", ":"))


def args_object(args_text: Any) -> dict[str, Any]:
    """A request's arguments read from their JSON text, bounded before they are parsed.

    Raises:
        RequestError: For text over :data:`MAX_ARGS_BYTES`, nesting deeper than
            :data:`MAX_ARGS_DEPTH`, malformed JSON, or JSON that is not an object.
    """
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
    return args


def _depth(text: str) -> int:
    """How deep JSON ``text`` nests (strings skipped), without recursing into it."""
    brackets = "".join(ch for ch in _JSON_STRING.sub("", text).translate(_NESTING) if ch in "()")
    depth = deepest = 0
    for ch in brackets:
        depth += 1 if ch == "(" else -1
        deepest = max(deepest, depth)
    return deepest


def this_host() -> str:
    """This computer's identity: ``MSCTL_HOST`` or the hostname."""
    import os
    import socket

    return os.environ.get("MSCTL_HOST") or socket.gethostname()


# --------------------------------------------------------------------------- ps answers
# The field names of a ``ps`` answer (a run document), for the readers that must not load
# msgspec (``msctl ps``'s quick path, :mod:`msctl.launcher.fleet`). The answer's types are
# :class:`components.supervision.protocol.RunDocument` and its rows; a test checks these
# names are exactly those structs' fields, so this is no second schema, only their names.
#: :class:`~components.supervision.protocol.RunDocument`'s fields.
RUN_FIELDS = (
    "host",
    "state",
    "template",
    "agent",
    "supervisor_pid",
    "router",
    "simulated",
    "off_robot",
    "secure",
    "started_router",
    "started",
    "processes",
    "components",
    "not_built",
    "faults",
    "rejoin",
)
#: :class:`~components.supervision.protocol.ComponentRow`'s fields.
COMPONENT_FIELDS = (
    "name",
    "kind",
    "host",
    "process",
    "state",
    "pid",
    "uptime",
    "restarts",
    "last_error",
)
#: :class:`~components.supervision.protocol.ProcessRow`'s fields.
PROCESS_FIELDS = (
    "name",
    "state",
    "pid",
    "pgid",
    "uptime",
    "restarts",
    "last_error",
    "heartbeat_age",
    "log",
    "log_lines_lost",
    "components",
)


def ps_document(answer: Any) -> dict[str, Any] | None:
    """A ``ps`` answer (JSON already parsed) read by the field names above, or ``None`` if it
    is not one (no object, or no host).

    What a newer supervisor adds is left out, what an older one lacks is absent (a row's
    missing field is ``None``), so what is printed is the fields of the typed answer.
    """
    if not isinstance(answer, dict) or not isinstance(answer.get("host"), str):
        return None
    document = {name: answer[name] for name in RUN_FIELDS if name in answer}
    for key, names in (("components", COMPONENT_FIELDS), ("processes", PROCESS_FIELDS)):
        rows = answer.get(key)
        if isinstance(rows, list):
            document[key] = [
                {name: row.get(name) for name in names} for row in rows if isinstance(row, dict)
            ]
    return document
