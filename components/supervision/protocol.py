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
from collections.abc import Mapping
from typing import Annotated, Any, Literal, NamedTuple, Union

import msgspec

from components.errors import LinkError
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


class ProcessAnswer(msgspec.Struct, frozen=True):
    """What ``restart``, ``stop`` and ``start`` answer: the process acted on.

    Attributes:
        process: The process (every component it runs goes with it).
        state: Its state now.
        components: Every component it runs (``restart --only``: the one rebuilt).
        siblings: Those the verb took along with the one named.
        only: ``restart --only``: the component is being rebuilt alone. Unset (falsy) is
            left off the wire, as it always was; the lists are always sent, and default to
            empty for a supervisor that left them out.
    """

    process: str
    state: str
    components: list[str] = []
    siblings: list[str] = []
    only: bool | msgspec.UnsetType = msgspec.UNSET


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


class DoctorFinding(msgspec.Struct, frozen=True):
    """One line of a computer's preflight (``msctl doctor``'s ``Finding``, on the wire).

    Attributes:
        host: The computer checked.
        check: What was checked (``clock``, ``router``, ``bus limb1``...).
        status: ``OK``, ``WARN`` or ``ERROR``.
        detail: What was found, and for WARN/ERROR what to do.
        value: The measured value, when there is one (seconds, bytes, a hash).
    """

    host: str
    check: str
    status: str
    detail: str = ""
    value: Any = None


class DoctorAnswer(msgspec.Struct, frozen=True):
    """What ``doctor`` answers: the supervisor's computer's preflight findings."""

    host: str
    findings: list[DoctorFinding] = []


class ShelfFile(msgspec.Struct, frozen=True):
    """One file of a bag on an agent's shelf.

    Attributes:
        name: Its name in the bag's directory.
        size: Bytes.
        complete: Whether it is finished (an MCAP file ends with its magic).
        abandoned: Unfinished and no longer written (its recorder was killed).
        sha256: Its SHA-256 (hex) when complete or abandoned, else ``None``.
    """

    name: str
    size: int
    complete: bool
    abandoned: bool = False
    sha256: str | None = None


class ShelfBag(msgspec.Struct, frozen=True):
    """One bag on an agent's shelf: its directory's name, whether it is being recorded,
    its files."""

    name: str
    recording: bool = False
    files: list[ShelfFile] = []


class BagsAnswer(msgspec.Struct, frozen=True):
    """What ``bags`` answers: the shelf's directory and its bags, by name."""

    root: str = ""
    bags: list[ShelfBag] = []


class BagReadAnswer(msgspec.Struct, frozen=True):
    """What ``bag_read`` answers: bytes of a bag file.

    Attributes:
        path: ``<bag>/<file>``, as asked.
        offset: Where the bytes start, as asked.
        file_size: The file's size now.
        data: The bytes, base64 (fewer than asked at the end of the file, none past it).
    """

    path: str
    offset: int
    file_size: int
    data: str = ""


class ProcessRow(msgspec.Struct, frozen=True):
    """One process of a run document (what its supervisor knows of it).

    Attributes:
        name: The process.
        state: ``starting``, ``running``, ``restarting``, ``unresponsive``, ``failed``,
            ``stopped``.
        pid: Its pid (``None`` when it does not run), also its process group (``pgid``).
        uptime: Seconds since it started.
        restarts: How many times it was started again.
        last_error: Why it last ended or failed.
        heartbeat_age: Seconds since its last heartbeat (``None``: none, or none yet).
        log: Its log file.
        log_lines_lost: Lines its log could not keep (a full disk).
        components: The components it runs.
    """

    name: str
    state: str = ""
    pid: int | None = None
    pgid: int | None = None
    uptime: float = 0.0
    restarts: int = 0
    last_error: str | None = None
    heartbeat_age: float | None = None
    log: str = ""
    log_lines_lost: int = 0
    components: list[str] = []


class ComponentRow(msgspec.Struct, frozen=True):
    """One component of a run document: a row of ``msctl ps``.

    Attributes:
        name: The component (``limb1/joint_manager``).
        kind: Its kind.
        host: The host it runs on.
        process: The process it runs in.
        state: Its state (its process's, ``starting`` until its node is seen publishing).
        pid, uptime, restarts, last_error: Its process's (:class:`ProcessRow`).
    """

    name: str
    kind: str = ""
    host: str = ""
    process: str = ""
    state: str = ""
    pid: int | None = None
    uptime: float = 0.0
    restarts: int = 0
    last_error: str | None = None


class NotBuilt(msgspec.Struct, frozen=True):
    """A planned component no code builds here (its kind has no builder)."""

    name: str
    kind: str = ""


class Rejoin(msgspec.Struct, frozen=True):
    """What an agent did at its start with the run it was asked for before (``rejoined`` or
    ``refused``), at ``at`` (Unix seconds), and why.

    Attributes:
        outcome: ``rejoined`` or ``refused``.
        at: When it did (Unix seconds, the agent's clock).
        agent_started: When the agent's process started (Unix seconds): what ``at`` is
            timed from.
        message: What it did, for a person.
    """

    outcome: str = ""
    at: float | None = None
    agent_started: float | None = None
    message: str = ""


class RunDocument(msgspec.Struct, frozen=True):
    """What ``ps`` answers (and a supervisor's state file holds): its host's run.

    Read by ``msctl ps`` (by its field names, :data:`~.contract.RUN_FIELDS`), ``up --all``,
    the health screen and the data monitor. Fields a newer supervisor adds are ignored and
    those an older one lacks take their defaults, so an older agent still answers.

    Attributes:
        host: The supervisor's host.
        state: ``running``, ``stopped`` or (an agent with no run) ``idle``.
        template: The assembly's template (``None``: an idle agent).
        agent: Whether an agent runs it (stopped by asking, never by a signal).
        supervisor_pid: The supervisor's pid.
        router: The router it connects to.
        simulated, off_robot: Whether the motors are simulated; whether one computer runs
            the whole assembly.
        secure: Whether its router runs the generated (filtered) config.
        started_router: Whether it started that router.
        started: When the run started (Unix seconds).
        processes, components, not_built: Its processes, its components, the planned
            components no code builds here.
        faults: What is wrong with the supervisor's own files (a full disk).
        rejoin: An agent's rejoin report, until the next ``up`` or ``down``; unset (and
            left off the wire) when there is none.
    """

    host: str
    state: str = ""
    template: str | None = None
    agent: bool = False
    supervisor_pid: int | None = None
    router: str = ""
    simulated: bool = False
    off_robot: bool = False
    secure: bool = False
    started_router: bool = False
    started: float | None = None
    processes: list[ProcessRow] = []
    components: list[ComponentRow] = []
    not_built: list[NotBuilt] = []
    faults: list[str] = []
    rejoin: Rejoin | msgspec.UnsetType = msgspec.UNSET


class UpAnswer(msgspec.Struct, frozen=True):
    """What an agent answers to ``up``: the part of the assembly it starts (or already runs).

    Attributes:
        host: The agent's host.
        template: The assembly's template.
        simulated: Whether its motors are simulated.
        processes: The processes it starts.
        components: The components they run (``up --all`` waits for each to be healthy).
        not_built: Its planned components no code builds here.
    """

    host: str
    template: str = ""
    simulated: bool = False
    processes: list[str] = []
    components: list[str] = []
    not_built: list[NotBuilt] = []


def run_document(answer: bytes | str | Mapping[str, Any] | RunDocument) -> RunDocument | None:
    """A ``ps`` answer as a :class:`RunDocument`: its JSON payload, the payload already
    parsed, or the struct itself; ``None`` if it is not one (data from the network)."""
    if isinstance(answer, RunDocument):
        return answer
    try:
        if isinstance(answer, (bytes, str)):
            return msgspec.json.decode(answer, type=RunDocument)
        return msgspec.convert(answer, RunDocument)
    except (msgspec.DecodeError, msgspec.ValidationError):
        return None


class AnswerError(LinkError):
    """An answer that is not what its verb answers: a garbled payload, or a peer that is
    not a supervisor of this protocol. A :class:`~components.errors.LinkError` (the peer
    could not be understood), so the CLI says it in one line with its network exit code.

    Attributes:
        detail: What in the payload did not fit (msgspec's words: the field's JSON path).
    """

    detail: str = ""


def decode_answer(answer: Any, kind: Any, verb: str, source: str = "a supervisor") -> Any:
    """A successful answer's payload as the struct (or typed container) of its verb.

    Args:
        answer: The JSON payload (bytes or str), the payload already parsed, or the struct.
        kind: What ``verb`` answers (:class:`ProcessAnswer`, :data:`LogsAnswer`, ...).
        verb: The request's verb, for the message.
        source: Who answered, for the message (``the supervisor of robot1``).

    Raises:
        AnswerError: If the payload is not one (data from the network: never a crash).
    """
    if isinstance(kind, type) and isinstance(answer, kind):
        return answer
    try:
        if isinstance(answer, (bytes, str)):
            return msgspec.json.decode(answer, type=kind)
        return msgspec.convert(answer, kind)
    except (msgspec.DecodeError, msgspec.ValidationError) as exc:
        error = AnswerError(
            f"{source} answered {verb} with something that is not a {verb} answer ({exc})",
            hint="see that both computers run the same msctl (`msctl doctor --all`)",
        )
        error.detail = str(exc)
        raise error from None


def process_answer(
    answer: Any, verb: str = "restart", source: str = "a supervisor"
) -> ProcessAnswer:
    """A ``restart``/``stop``/``start`` answer as a :class:`ProcessAnswer`.

    Raises:
        AnswerError: If it is not one.
    """
    return decode_answer(answer, ProcessAnswer, verb, source)


def up_answer(answer: Any, source: str = "an agent") -> UpAnswer:
    """An ``up`` answer as an :class:`UpAnswer`.

    Raises:
        AnswerError: If it is not one.
    """
    return decode_answer(answer, UpAnswer, "up", source)


def doctor_answer(answer: Any, source: str = "a supervisor") -> DoctorAnswer:
    """A ``doctor`` answer as a :class:`DoctorAnswer`.

    Raises:
        AnswerError: If it is not one.
    """
    return decode_answer(answer, DoctorAnswer, "doctor", source)


def logs_answer(answer: Any, source: str = "a supervisor") -> LogsAnswer:
    """A ``logs`` answer: each process's last lines.

    Raises:
        AnswerError: If it is not one.
    """
    return decode_answer(answer, LogsAnswer, "logs", source)


def bags_answer(answer: Any, source: str = "an agent") -> BagsAnswer:
    """A ``bags`` answer as a :class:`BagsAnswer` (names not yet checked as plain).

    Raises:
        AnswerError: If it is not one.
    """
    return decode_answer(answer, BagsAnswer, "bags", source)


def bag_read_answer(answer: Any, source: str = "an agent") -> BagReadAnswer:
    """A ``bag_read`` answer as a :class:`BagReadAnswer` (its data not yet decoded).

    Raises:
        AnswerError: If it is not one.
    """
    return decode_answer(answer, BagReadAnswer, "bag_read", source)


def error_payload(kind: str, message: str, verb: str) -> str:
    """An :class:`ErrorAnswer` as the JSON payload of an unsuccessful answer."""
    return msgspec.json.encode(ErrorAnswer(kind, message, verb)).decode()  # type: ignore[arg-type]


def error_of(payload: str) -> ErrorAnswer | None:
    """The :class:`ErrorAnswer` in an unsuccessful answer's payload, if it holds one."""
    try:
        return msgspec.json.decode(payload, type=ErrorAnswer)
    except (msgspec.DecodeError, msgspec.ValidationError):
        return None
