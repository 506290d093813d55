"""The supervision protocol as types: a struct per request (a tagged union by verb) and per
answer.

On the wire a request is the verb and its arguments as a JSON object (see :mod:`.wire`); here
the verb is the tag of the request's struct, so ``{"verb": "logs", "lines": 20}`` is a
:class:`Logs`. An answer is ``success``, ``message`` and a JSON payload; a request that is
refused or fails is answered with an :class:`ErrorAnswer` as its payload, so a client can
tell a malformed request from a refusal and from a supervisor's failure without reading
the message.

Adding a verb is one struct here and one handler in each supervisor's table
(:class:`components.supervision.dispatch.Verbs`).
"""

from __future__ import annotations

import re
from typing import Annotated, Any, Literal, NamedTuple, Union

import msgspec

from components.supervision.contract import RequestError, args_object, encode_args

#: A component or process name, as a request may carry it.
Name = Annotated[str, msgspec.Meta(max_length=127)]
#: How many log lines ``logs`` returns, at most.
Lines = Annotated[int, msgspec.Meta(ge=1, le=10000)]
#: The simulation speed ``up`` asks for.
Speed = Annotated[float, msgspec.Meta(gt=0, le=100)]


class _Request(msgspec.Struct, frozen=True, forbid_unknown_fields=True, omit_defaults=True):
    """What every request is: a struct tagged by its verb, with no unknown field."""


class Ps(_Request, tag="ps", tag_field="verb"):
    """What runs on the supervisor's computer (its run document)."""


class Logs(_Request, tag="logs", tag_field="verb"):
    """The last lines of a process's output (every process's without ``component``)."""

    component: Name | None = None
    lines: Lines = 50


class Restart(_Request, tag="restart", tag_field="verb"):
    """Restart a component's process (``only``: rebuild the component alone in it)."""

    component: Name | None = None
    only: bool = False


class Stop(_Request, tag="stop", tag_field="verb"):
    """Stop a component's process."""

    component: Name | None = None


class Start(_Request, tag="start", tag_field="verb"):
    """Start a stopped component's process."""

    component: Name | None = None


class Down(_Request, tag="down", tag_field="verb"):
    """Stop everything the supervisor runs."""


class Up(_Request, tag="up", tag_field="verb"):
    """Start this computer's part of a resolved assembly (an agent's verb).

    Attributes:
        assembly: The resolved assembly document (its lock), checked by the agent.
        sim: Simulate the motors (``None``: as the assembly says).
        speed: Simulation speed.
    """

    assembly: dict[str, Any] | msgspec.UnsetType = msgspec.UNSET
    sim: bool | None = None
    speed: Speed = 1.0


class Doctor(_Request, tag="doctor", tag_field="verb"):
    """The supervisor's computer's preflight checks."""


class Bags(_Request, tag="bags", tag_field="verb"):
    """The bags on the agent's shelf."""


class BagRead(_Request, tag="bag_read", tag_field="verb"):
    """Bytes of a bag file on the shelf; the shelf checks the values (its own messages)."""

    path: Any = None
    offset: Any = None
    size: Any = None


#: Each request's struct by its verb: every struct above, in their order (a verb is added by
#: adding its struct, and its handler to each supervisor's table).
REQUESTS: dict[str, type[_Request]] = {
    cls.__struct_config__.tag: cls  # type: ignore[misc]
    for cls in _Request.__subclasses__()
}
#: Every request: a union tagged by verb.
Request = Union[tuple(REQUESTS.values())]  # type: ignore[valid-type]  # noqa: UP007
#: The verbs in the order they are told to a person.
VERBS = tuple(REQUESTS)
#: What a value that does not fit its field is told, by field.
_FIELD_RULES = {
    "component": "component must be a component or process name",
    "only": "only must be true or false",
    "lines": "lines must be a whole number from 1 to 10000",
    "speed": "speed must be a number in (0, 100]",
    "sim": "sim must be true, false or null",
    "assembly": "assembly must be a resolved assembly document (a JSON object)",
}


#: The field a validation error names (``... - at `$.lines```).
_FIELD = re.compile(r"`\$\.([A-Za-z_]+)")


class Checked(NamedTuple):
    """A validated request: its verb, its arguments as sent, and its struct."""

    verb: str
    args: dict[str, Any]
    request: Request


def parse_request(verb: Any, args_text: Any) -> Checked:
    """Validate a request's verb and arguments (as they came off the wire).

    Raises:
        RequestError: For an unknown verb, arguments too big, too deep or not JSON, unknown
            keys or bad values; the message says which.
    """
    if not isinstance(verb, str) or verb not in REQUESTS:
        shown = verb[:40] if isinstance(verb, str) else type(verb).__name__
        raise RequestError(f"unknown verb {shown!r}; accepted: {', '.join(VERBS)}")
    args = args_object(args_text)
    return Checked(verb, args, request_of(verb, args))


def request_of(verb: str, args: dict[str, Any]) -> Request:
    """The struct of a request given as a verb and its arguments.

    Raises:
        RequestError: For an unknown verb, unknown keys or bad values.
    """
    cls = REQUESTS.get(verb)
    if cls is None:
        raise RequestError(f"unknown verb {verb[:40]!r}; accepted: {', '.join(VERBS)}")
    unknown = set(args) - set(cls.__struct_fields__)
    if unknown:
        raise RequestError(f"{verb} takes no argument {', '.join(sorted(map(str, unknown)))}")
    try:
        return msgspec.convert({**args, "verb": verb}, Request)
    except msgspec.ValidationError as exc:
        where = _FIELD.search(str(exc))
        rule = _FIELD_RULES.get(where.group(1)) if where else None
        raise RequestError(rule or f"{verb}: {exc}") from None


def wire_form(request: Request) -> tuple[str, str]:
    """A request as it travels: its verb and its arguments' JSON (defaults left out)."""
    fields = msgspec.to_builtins(request)
    verb = fields.pop("verb")
    return verb, encode_args(fields)


# --------------------------------------------------------------------------- answers
class ErrorAnswer(msgspec.Struct, frozen=True, tag="error", tag_field="answer"):
    """The payload of every unsuccessful answer.

    Attributes:
        kind: ``malformed`` (the request could not be read: unknown verb, bad JSON, bad
            values), ``refused`` (read, but not something this supervisor does now) or
            ``failed`` (the supervisor broke while carrying it out: a bug, said in its log).
        message: What went wrong, for a person (also the answer's ``message``).
        verb: The request's verb as it came (``?`` when it had none).
    """

    kind: Literal["malformed", "refused", "failed"]
    message: str
    verb: str = "?"


class ProcessAnswer(msgspec.Struct, frozen=True, omit_defaults=True):
    """What ``restart``, ``stop`` and ``start`` answer: the process acted on.

    Attributes:
        process: The process (every component it runs goes with it).
        state: Its state now.
        components: Every component it runs (``restart --only``: the one rebuilt).
        siblings: Those the verb took along with the one named.
        only: ``restart --only``: the component is being rebuilt alone.
    """

    process: str
    state: str
    components: list[str]
    siblings: list[str]
    only: bool = False


class DownAnswer(msgspec.Struct, frozen=True, omit_defaults=True):
    """What ``down`` answers.

    Attributes:
        host: The host that is stopping.
        template: What it ran (an agent says).
        stopped: The processes stopped (an agent says; empty when it was idle).
    """

    host: str
    template: str | None = None
    stopped: list[str] | None = None


#: ``logs``: each process and its last lines.
LogsAnswer = dict[str, list[str]]


def error_payload(kind: str, message: str, verb: str) -> str:
    """An :class:`ErrorAnswer` as the JSON payload of an unsuccessful answer."""
    return msgspec.json.encode(ErrorAnswer(kind, message, verb)).decode()  # type: ignore[arg-type]


def error_of(payload: str) -> ErrorAnswer | None:
    """The :class:`ErrorAnswer` in an unsuccessful answer's payload, if it holds one."""
    try:
        return msgspec.json.decode(payload, type=ErrorAnswer)
    except (msgspec.DecodeError, msgspec.ValidationError):
        return None
