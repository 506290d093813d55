"""What every ``msctl`` command that touches the network shares: connecting, finding types,
and turning messages into and out of the YAML/dict form the ``ros2`` CLI uses."""

from __future__ import annotations

import os
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from typing import Any, NamedTuple

from msctl.errors import InputError, NetworkError, NotFoundError


@contextmanager
def connected(
    role: str = "cli", require_router: bool = True, open_timeout: float | None = None
) -> Iterator[Any]:
    """Open a session and a node for a CLI command; close both on exit.

    Args:
        role: Part of the node name (``msctl_<role>_<pid>``), so the graph shows who pokes it.
        require_router: Fail with a clear message when no router or peer is reachable.
        open_timeout: Seconds the router may take to answer the session's handshake (a
            command with a deadline of its own passes it; Zenoh's default is 10 s, which
            a frozen router, accepting TCP but answering nothing, takes in full).

    Raises:
        SessionConfigError: If the session settings (environment) are unusable (a
            ConfigError: exit 2).
        NetworkError: If nothing is reachable and ``require_router`` is set.
    """
    from components.comm.node import Node
    from components.comm.session import SessionOpenError, SessionSettings, open_session

    try:
        # A short-lived command is a client of the router: its queries (graph, services)
        # are answered by the router at once and whole (see SessionSettings.joining).
        settings = SessionSettings.joining()
        if open_timeout is not None:
            bound = {"transport/unicast/open_timeout": max(100, round(open_timeout * 1000))}
            settings = settings._replace(extra={**settings.extra, **bound})
        session = open_session(settings)
    except SessionOpenError as exc:
        # The settings were fine; nothing answered at the endpoints (a client needs a router).
        silent = [e for e in settings.connect if _accepts_tcp(e)]
        if silent:
            raise NetworkError(
                f"the Zenoh router at {', '.join(silent)} accepts connections but did not "
                "answer the session's handshake"
                + (f" within {open_timeout:g} s" if open_timeout is not None else ""),
                hint="it is frozen or overloaded (a stopped process, a full machine): "
                "check it with `msctl ps` or `top` where it runs, or restart it",
            ) from exc
        raise NetworkError(
            f"no Zenoh router reachable at {', '.join(settings.connect)}",
            hint="start one with `msctl router` (or `msctl up`), or point MSCTL_ZENOH_CONNECT "
            "at it",
        ) from exc
    # A SessionConfigError (bad settings) goes on as it is: a ConfigError, exit 2, its
    # message the same (msctl.cli.main maps it, as every runtime error).
    node = None
    try:
        if require_router:
            wait = 1.5 if open_timeout is None else min(1.5, open_timeout)
            _wait_for_network(session, settings, wait)
        node = Node(session, f"msctl_{role}_{os.getpid()}", "/", domain=settings.domain)
        yield node
    finally:
        if node is not None:
            node.close()
        session.close()


def _accepts_tcp(endpoint: str, timeout: float = 0.3) -> bool:
    """Whether a ``tcp/HOST:PORT`` endpoint accepts a TCP connection (a process listens,
    whether or not it answers): tells a frozen router from no router."""
    import socket

    if not endpoint.startswith("tcp/"):
        return False
    host, _, port = endpoint[4:].split("#", 1)[0].rpartition(":")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout):
            return True
    except (OSError, ValueError):
        return False


def _wait_for_network(session: Any, settings: Any, timeout: float = 1.5) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        info = session.info
        if list(info.routers_zid()) or list(info.peers_zid()):
            return
        time.sleep(0.02)
    raise NetworkError(
        f"no Zenoh router reachable at {', '.join(settings.connect)}",
        hint="start one with `msctl router` (or `msctl up`), or point MSCTL_ZENOH_CONNECT at it",
    )


def find_type(node: Any, name: str, kind: str, timeout: float = 2.0) -> str:
    """The type of a topic (``kind="topic"``) or service seen on the graph.

    Raises:
        NotFoundError: If nothing with that name appears within ``timeout`` (naming the
            nearest names the graph shows).
        InputError: If the graph shows several types for it.
    """
    from components.comm.graph import snapshot
    from components.comm.names import qualify

    qualified = qualify(name, "/")
    deadline = time.monotonic() + timeout
    while True:
        graph = snapshot(node.session, node.domain, timeout=2.0)
        table = graph.topics() if kind == "topic" else graph.services()
        if kind != "topic":
            # A service with clients only has nothing to answer: not one to suggest.
            table = {k: v for k, v in table.items() if v.servers or k == qualified}
        info = table.get(qualified)
        if info is not None and info.types:
            if len(info.types) > 1:
                raise InputError(
                    f"{kind} {qualified} carries several types ({', '.join(sorted(info.types))})",
                    hint="name the one you want explicitly",
                )
            return next(iter(info.types))
        if time.monotonic() > deadline:
            raise NotFoundError(
                f"no {kind} named {qualified} on the network",
                hint=unknown_name_hint(qualified, table, kind),
            )
        time.sleep(0.1)


def unknown_name_hint(name: str, known: Iterable[str], kind: str) -> str:
    """What an error about an unknown topic or service name says to do: the nearest names
    the graph shows, or a few of them, and the listing command."""
    from msctl.errors import did_you_mean

    names = sorted(known)
    listing = f"`msctl {kind} list` shows them all"
    near = did_you_mean(name, names)
    if near:
        return f"{near} ({listing})"
    if not names:
        return f"the graph shows no {kind} at all: is anything running (`msctl ps`)?"
    more = ", ..." if len(names) > 8 else ""
    return f"the graph shows {', '.join(names[:8])}{more}; {listing}"


class TopicUsers(NamedTuple):
    """Who uses a topic, by type, from one graph snapshot.

    Attributes:
        publishers: Each type published on the topic -> the nodes publishing it.
        subscribers: Each type subscribed to -> the nodes subscribing.
    """

    publishers: dict[str, set[str]]
    subscribers: dict[str, set[str]]


def topic_users(node: Any, name: str, timeout: float = 3.0) -> TopicUsers:
    """The publishers and subscribers of topic ``name`` by type (one graph snapshot).

    Args:
        node: The CLI's node (its own entities are left out).
        name: Topic name.
        timeout: Seconds the graph's answers may take at most. The query ends as soon as
            the router has answered (milliseconds); a short bound cut the answer of a busy
            router short, and a publisher that was there went unseen.
    """
    from components.comm.graph import snapshot
    from components.comm.liveliness import EntityKind

    qualified = qualify_topic(name)
    publishers: dict[str, set[str]] = {}
    subscribers: dict[str, set[str]] = {}
    for entity in snapshot(node.session, node.domain, timeout=timeout).entities():
        if entity.topic != qualified or not entity.type_name or entity.node_fqn == node.fqn:
            continue
        if entity.kind is EntityKind.PUBLISHER:
            publishers.setdefault(entity.type_name, set()).add(entity.node_fqn)
        elif entity.kind is EntityKind.SUBSCRIPTION:
            subscribers.setdefault(entity.type_name, set()).add(entity.node_fqn)
    return TopicUsers(publishers, subscribers)


def topic_types(
    node: Any, name: str, publishers_only: bool = False, timeout: float = 3.0
) -> dict[str, set[str]]:
    """Each type seen on topic ``name`` -> the nodes using it with that type.

    One graph snapshot; empty when nobody is on the topic.

    Args:
        node: The CLI's node.
        name: Topic name.
        publishers_only: Only publishers (what a subscriber would receive).
        timeout: Seconds to wait for the graph's answers.
    """
    users = topic_users(node, name, timeout)
    found = {t: set(nodes) for t, nodes in users.publishers.items()}
    if not publishers_only:
        for type_name, nodes in users.subscribers.items():
            found.setdefault(type_name, set()).update(nodes)
    return found


def qualify_topic(name: str) -> str:
    """A topic name as the graph shows it (``joint_read`` -> ``/joint_read``)."""
    from components.comm.names import qualify

    return qualify(name, "/")


def describe_types(types: dict[str, set[str]]) -> str:
    """``sensor_msgs/msg/JointState (/limb1/joint_manager, ...)`` for an error message."""
    return "; ".join(
        f"{t} ({', '.join(sorted(nodes)[:3])}{', ...' if len(nodes) > 3 else ''})"
        for t, nodes in sorted(types.items())
    )


def parse_values(text: str | None) -> dict[str, Any]:
    """Parse VALUES as ``ros2 topic pub`` takes them: a YAML mapping (``"{data: hi}"``).

    Raises:
        InputError: If the text is not a YAML mapping.
    """
    import yaml

    if text is None or not text.strip():
        return {}
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        # PyYAML's own text spans several lines with a caret drawing; keep the one-line rule.
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        mark = getattr(exc, "problem_mark", None)
        where = ""
        if mark is not None:
            line = f"line {mark.line + 1}, " if mark.line else ""
            where = f" at {line}column {mark.column + 1}"
        raise InputError(f"VALUES is not valid YAML: {problem}{where}: {text!r}") from exc
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise InputError(
            f'VALUES must be a mapping like "{{data: hello}}", not {type(value).__name__}'
        )
    return value


def build_message(type_name: str, values: dict[str, Any], path: str = "") -> Any:
    """A message of ``type_name`` with ``values`` filled in, others at their defaults.

    Raises:
        InputError: Naming the field that does not exist or holds the wrong kind of value.
    """
    from rosbags.typesys.base import Nodetype

    from components.comm.types import registry
    from components.messages import msg

    fields = dict(registry().fields(type_name))
    built: dict[str, Any] = {}
    for key, value in values.items():
        where = f"{path}{key}"
        if key not in fields:
            # An empty ROS message is generated with one placeholder member: not a field.
            real = [f for f in fields if f != "structure_needs_at_least_one_member"]
            listing = f"its fields are: {', '.join(real)}" if real else "it takes no fields"
            raise InputError(f"{type_name} has no field {where!r}; {listing}")
        built[key] = _convert(fields[key], value, where, Nodetype)
    return msg(type_name, **built)


def _convert(desc: Any, value: Any, where: str, nodetype: Any) -> Any:
    node, detail = desc
    try:
        if node == nodetype.BASE:
            base = detail[0]
            if base in ("string", "wstring"):
                return str(value)
            if base == "bool":
                if not isinstance(value, bool):  # bool("false") is True: never guess
                    raise InputError(f"field {where!r} is a bool; give true or false")
                return value
            if base in ("float32", "float64"):
                return float(value)
            number = int(value)
            if isinstance(value, float) and number != value:
                raise InputError(f"field {where!r} is a {base}; give a whole number")
            low, high = _INT_RANGES.get(base, (-(2**63), 2**64 - 1))
            if not low <= number <= high:
                raise InputError(f"field {where!r} is a {base}, from {low} to {high}")
            return number
        if node == nodetype.NAME:
            if not isinstance(value, dict):
                raise InputError(f"field {where!r} is a {detail}; give a mapping")
            return build_message(detail, value, f"{where}.")
        inner, size = detail
        if not isinstance(value, list):
            raise InputError(f"field {where!r} is a sequence; give a list like [1, 2]")
        if node == nodetype.ARRAY and len(value) != size:
            raise InputError(f"field {where!r} holds exactly {size} values, not {len(value)}")
        items = [_convert(inner, v, f"{where}[{i}]", nodetype) for i, v in enumerate(value)]
        if inner[0] == nodetype.BASE and inner[1][0] not in ("string", "wstring", "bool"):
            import numpy as np

            from components.messages import _NUMPY_TYPES

            return np.array(items, dtype=_NUMPY_TYPES.get(inner[1][0], np.float64))
        return items
    except InputError:
        raise  # already names the innermost field
    except (TypeError, ValueError) as exc:
        raise InputError(f"field {where!r}: cannot use {value!r} ({exc})") from exc


#: Integer field ranges (char, byte and octet are unsigned 8-bit in ROS 2).
_INT_RANGES = {
    **{f"int{b}": (-(2 ** (b - 1)), 2 ** (b - 1) - 1) for b in (8, 16, 32, 64)},
    **{f"uint{b}": (0, 2**b - 1) for b in (8, 16, 32, 64)},
    **dict.fromkeys(("char", "byte", "octet"), (0, 255)),
}


def to_plain(message: Any) -> Any:
    """A message as plain dicts, lists and numbers (for YAML and JSON output)."""
    import numpy as np  # here: the commands that only connect never load numpy (~0.15 s)

    if hasattr(message, "__msgtype__"):
        return {
            name: to_plain(getattr(message, name))
            for name in message.__dataclass_fields__
            if name != "__msgtype__" and not name.isupper()
        }
    if isinstance(message, np.ndarray):
        return message.tolist()
    if isinstance(message, list | tuple):
        return [to_plain(v) for v in message]
    if isinstance(message, np.generic):
        return message.item()
    return message


def to_yaml(message: Any) -> str:
    """A message as YAML, the way ``ros2 topic echo`` shows it."""
    import yaml

    return yaml.safe_dump(to_plain(message), sort_keys=False, default_flow_style=False).rstrip()
