"""``msctl topic``: list, echo, pub and hz, as ``ros2 topic`` does, over our data plane."""

from __future__ import annotations

import itertools
import json
import math
import queue
import signal
import statistics
import threading
import time
from typing import Any

import typer

from msctl.errors import InputError, MsctlError, OperationTimeout

app = typer.Typer(help="Topics: list, echo, publish, measure rate.", no_args_is_help=True)

JSON_OPT = typer.Option(False, "--json", help="Print JSON instead of tables/YAML.")


class _Stopper:
    """Ctrl-C / SIGTERM end a streaming command cleanly (sessions are closed on the way out)."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> threading.Event:
        for signum in (signal.SIGINT, signal.SIGTERM):
            self._previous[signum] = signal.signal(signum, lambda *_: self.event.set())
        return self.event

    def __exit__(self, *exc: object) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)


def checked_name(name: str, what: str = "topic") -> str:
    """``name`` qualified, or an InputError saying why ROS 2 would refuse it.

    Checked before any session opens: an illegal name is the operator's typo, answered at
    once in one line, never an internal error from deep in the data plane.

    Raises:
        InputError: Naming the name and what is wrong with it.
    """
    from components.comm.names import NameError_, qualify

    try:
        return qualify(name, "/")
    except NameError_ as exc:
        raise InputError(
            f"{what} {name!r} is not a legal ROS 2 {what} name: {exc}",
            hint="names are /-separated parts of letters, digits and '_', "
            "each not starting with a digit (e.g. /limb1/joint_read)",
        ) from None


def _count(value: int, flag: str) -> None:
    if value < 0:
        raise InputError(f"{flag} must be 0 (no limit) or a number of messages, not {value}")


@app.command("list")
def list_topics(
    show_types: bool = typer.Option(False, "--show-types", "-t", help="Show each topic's type."),
    verbose: bool = typer.Option(
        False, "--verbose", "-v", help="Show publisher/subscriber counts."
    ),
    json_output: bool = JSON_OPT,
) -> None:
    """List every topic on the network."""
    from msctl.listings import show_topics

    show_topics(show_types=show_types, verbose=verbose, json_output=json_output)


def _resolve_type(node: Any, topic: str, msg_type: str | None, timeout: float) -> str:
    """The type to use on ``topic``: the one given (checked against the graph), or the graph's.

    Raises:
        NotFoundError: A type msctl does not know (with the nearest known names), or no type
            given and no topic of that name (with the nearest topic names).
        InputError: A known type, but not the one the topic's publishers carry.
    """
    from msctl.plane import find_type

    if not msg_type:
        return _known(find_type(node, topic, "topic", timeout), node, topic)
    type_name = _known(msg_type, node, topic)
    _check_publishers(node, topic, type_name)
    return type_name


def _known(msg_type: str, node: Any, topic: str) -> str:
    """``msg_type`` normalized, if msctl knows it; else a NotFoundError naming what is near
    and, when the graph shows it, the type the topic really carries."""
    from components.comm.types import UnknownTypeError, normalize_type_name, registry
    from msctl.errors import NotFoundError, did_you_mean
    from msctl.plane import describe_types, topic_types

    try:
        type_name = normalize_type_name(msg_type)
    except UnknownTypeError as exc:
        raise InputError(str(exc)) from exc
    if registry().known(type_name):
        return type_name
    carried = topic_types(node, topic, publishers_only=True) if node is not None else {}
    where = f"; topic {topic} carries {describe_types(carried)}" if carried else ""
    raise NotFoundError(
        f"{type_name} is not a message type msctl knows{where}",
        hint=did_you_mean(type_name, registry().message_names())
        or "register its .msg definition (components.comm.types.registry().register_msg)",
    )


def _check_publishers(node: Any, topic: str, type_name: str) -> None:
    """Refuse to listen for a type the topic's publishers do not carry: say which they do."""
    from msctl.plane import topic_users

    published = topic_users(node, topic).publishers
    if published and type_name not in published:
        raise _other_type(topic, published, type_name)


def _other_type(topic: str, published: dict[str, set[str]], type_name: str) -> InputError:
    from msctl.plane import describe_types, qualify_topic

    return InputError(
        f"topic {qualify_topic(topic)} carries {describe_types(published)}, not {type_name}",
        hint="leave the type out to use the topic's own",
    )


class _OtherTypes:
    """Publishers of another type that show up on a topic after the command subscribed
    (the graph check before subscribing cannot see a publisher that starts later)."""

    def __init__(self, type_name: str) -> None:
        self.type_name = type_name
        self._found: dict[str, set[str]] = {}
        self._lock = threading.Lock()

    def __call__(self, entity: Any) -> None:
        """Note a publisher of another type (a Zenoh thread calls this)."""
        shown = entity.type_name or "an unnamed type"
        if entity.type_name == self.type_name:
            shown = f"another version of {entity.type_name} ({entity.type_hash})"
        with self._lock:
            self._found.setdefault(shown, set()).add(entity.node_fqn)

    def check(self, node: Any, topic: str) -> None:
        """Raise if only publishers of another type are there (none of ours, on the graph)."""
        from msctl.plane import topic_users

        with self._lock:
            found = {t: set(n) for t, n in self._found.items()}
        if not found:
            return
        published = topic_users(node, topic).publishers
        if self.type_name in published:
            with self._lock:
                self._found.clear()  # ours publish too: their messages come
            return
        for type_name, nodes in published.items():
            found.setdefault(type_name, set()).update(nodes)
        raise _other_type(topic, found, self.type_name)


def _no_message(node: Any, topic: str, type_name: str, timeout: float) -> MsctlError:
    """What ``--timeout`` says when nothing came: who publishes the topic, if anyone."""
    from components.comm.graph import snapshot
    from msctl.plane import describe_types, qualify_topic, topic_users, unknown_name_hint

    qualified = qualify_topic(topic)
    published = topic_users(node, topic).publishers
    if type_name in published:
        return OperationTimeout(
            f"no message on {qualified} within {timeout:g} s, though "
            f"{describe_types({type_name: published[type_name]})} publishes it",
            hint="it publishes only on change, or is stuck: see `msctl ps` and `msctl logs`",
        )
    if published:
        return _other_type(topic, published, type_name)
    topics = snapshot(node.session, node.domain, timeout=3.0).topics()
    with_publishers = [name for name, info in topics.items() if info.publishers]
    return OperationTimeout(
        f"no message on {qualified} within {timeout:g} s: nothing publishes it",
        hint=unknown_name_hint(qualified, with_publishers, "topic"),
    )


@app.command("echo")
def echo(
    topic: str = typer.Argument(..., help="Topic name, e.g. /limb1/joint_read."),
    msg_type: str = typer.Argument(None, help="Message type (default: found on the graph)."),
    once: bool = typer.Option(False, "--once", help="Print one message and exit."),
    count: int = typer.Option(0, "--times", "-n", help="Exit after this many messages."),
    timeout: float = typer.Option(
        0.0, "--timeout", help="Fail if no message arrives within this many seconds (0: wait)."
    ),
    latched: bool = typer.Option(False, "--latched", help="Also get the last latched sample."),
    json_output: bool = JSON_OPT,
) -> None:
    """Print the messages of a topic as they arrive (YAML, or one JSON document each)."""
    from components.comm.qos import LATCHED, QoS
    from msctl.console import out
    from msctl.plane import connected, to_plain, to_yaml

    checked_name(topic)
    _count(count, "--times")
    if not (timeout >= 0 and math.isfinite(timeout)):
        raise InputError(f"--timeout must be a number of seconds >= 0, not {timeout}")
    limit = 1 if once else count
    inbox: queue.SimpleQueue[Any] = queue.SimpleQueue()
    with connected("echo") as node, _Stopper() as stop:
        type_name = _resolve_type(node, topic, msg_type, timeout or 3.0)
        others = _OtherTypes(type_name)
        node.subscription(
            topic, type_name, inbox.put, LATCHED if latched else QoS(), on_other_type=others
        )
        printed = 0
        started = time.monotonic()
        while not stop.is_set():
            try:
                message = inbox.get(timeout=0.1)
            except queue.Empty:
                if printed == 0:
                    others.check(node, topic)
                    if timeout and time.monotonic() - started > timeout:
                        raise _no_message(node, topic, type_name, timeout) from None
                continue
            if json_output:
                out.file.write(json.dumps(to_plain(message)) + "\n")
                out.file.flush()
            else:
                out.print(to_yaml(message), highlight=False, markup=False)
                out.print("---", highlight=False, markup=False)
            printed += 1
            if limit and printed >= limit:
                break


@app.command("pub")
def pub(
    topic: str = typer.Argument(..., help="Topic name."),
    msg_type: str = typer.Argument(..., help="Message type, e.g. std_msgs/msg/String."),
    values: str = typer.Argument(None, help='Field values as YAML, e.g. "{data: hello}".'),
    once: bool = typer.Option(False, "--once", "-1", help="Publish one message and exit."),
    rate: float = typer.Option(1.0, "--rate", "-r", help="Messages per second."),
    times: int = typer.Option(0, "--times", "-t", help="Publish this many messages then exit."),
    wait_matching: float = typer.Option(
        None,
        "--wait-matching",
        help="Seconds to wait for a matching subscriber before the first message "
        "[default: 1; 0 with --fire-and-forget].",
    ),
    latched: bool = typer.Option(False, "--latched", help="Transient-local (latched) QoS."),
    force: bool = typer.Option(
        False, "--force", help="Publish even if the topic carries another type."
    ),
    fire_and_forget: bool = typer.Option(
        False,
        "--fire-and-forget",
        help="Publishing to nobody is fine: do not wait for a subscriber, and exit 0 whether "
        "or not one matched (the count is still said).",
    ),
) -> None:
    """Publish a message, once, N times, or at a rate until Ctrl-C; then say how many were
    delivered.

    A message counts as delivered when Zenoh showed a subscriber matching it as it was
    published (its matching status; the QoS is reliable, so the network resends it until
    that subscriber has it, unless the link itself breaks). Exit status 1 when any message
    was published with no subscriber matching ("no subscriber matched: none delivered", or
    how many of them were), unless --fire-and-forget.
    """
    from components.comm.names import qualify
    from components.comm.qos import LATCHED, QoS
    from msctl.console import err
    from msctl.plane import build_message, connected, parse_values

    checked_name(topic)
    _count(times, "--times")
    if rate <= 0 or not math.isfinite(rate):
        raise InputError(f"--rate must be a positive number of messages per second, not {rate}")
    if wait_matching is not None and not (wait_matching >= 0 and math.isfinite(wait_matching)):
        raise InputError(f"--wait-matching must be a number of seconds >= 0, not {wait_matching}")
    if wait_matching is None:
        wait_matching = 0.0 if fire_and_forget else 1.0
    # Input first, network after: a typo in VALUES fails at once.
    type_name = _known(msg_type, None, topic)
    message = build_message(type_name, parse_values(values))
    total = 1 if once else times
    qualified = qualify(topic, "/")
    sent = delivered = 0
    with connected("pub") as node, _Stopper() as stop:
        if not force:
            _refuse_another_type(node, topic, type_name)
        publisher = node.publisher(topic, type_name, LATCHED if latched else QoS())
        # Zenoh's matching status, read from a plain publisher on the same key that never
        # publishes: a latched topic's publisher (an advanced one) does not expose it, and
        # this one is no entity on the graph.
        probe = node.session.declare_publisher(publisher.key)
        try:
            deadline = time.monotonic() + wait_matching
            while not stop.is_set() and not _matching(probe) and time.monotonic() < deadline:
                stop.wait(0.01)
            period = 1.0 / rate
            next_time = time.monotonic()
            while not stop.is_set():
                matched = _matching(probe)
                publisher.publish(message)
                sent += 1
                delivered += matched
                err.print(f"publishing #{sent} on {qualified}", highlight=False)
                if total and sent >= total:
                    break
                next_time += period
                stop.wait(max(0.0, next_time - time.monotonic()))
            if latched and total:
                stop.wait(0.5)  # a latched sample must outlive this process a moment to be fetched
        finally:
            probe.undeclare()
    _report_delivery(qualified, sent, delivered, fire_and_forget)


def _matching(probe: Any) -> bool:
    """Whether Zenoh knows a subscriber matching ``probe``'s key now."""
    return bool(probe.matching_status.matching)


def _messages(count: int) -> str:
    return f"{count} message" + ("" if count == 1 else "s")


def _report_delivery(topic: str, sent: int, delivered: int, fire_and_forget: bool) -> None:
    """Say how many of the ``sent`` messages a subscriber matched; fail unless all were.

    Raises:
        MsctlError: Exit status 1 when some (or every) message was published with no
            subscriber matching, unless ``fire_and_forget``.
    """
    from msctl.console import err

    if sent == 0:
        err.print(
            f"published nothing on {topic} (stopped before the first message)", highlight=False
        )
        return
    if delivered == sent:
        every = "it" if sent == 1 else f"all {sent}"
        err.print(
            f"published {_messages(sent)} on {topic}: {every} delivered to a matching subscriber",
            highlight=False,
        )
        return
    if delivered == 0:
        said = f"published {_messages(sent)} on {topic}, no subscriber matched: none delivered"
        hint = (
            f"start its subscriber first (e.g. `msctl topic echo {topic}`) or wait longer for "
            "it (--wait-matching SECONDS); --fire-and-forget if nobody needs to hear it"
        )
    else:
        said = (
            f"published {_messages(sent)} on {topic}: {delivered} delivered to a matching "
            f"subscriber, {sent - delivered} published with none matching"
        )
        hint = (
            "a subscriber came late or left meanwhile (`msctl topic list -v` counts them); "
            "--fire-and-forget if that is fine"
        )
    if fire_and_forget:
        err.print(f"{said} (--fire-and-forget)", highlight=False)
        return
    raise MsctlError(said, hint=hint)


def _refuse_another_type(node: Any, topic: str, type_name: str) -> None:
    """Refuse to publish a type the topic's publishers (or, with none, its subscribers) do
    not use: their readers would never get it, or would get it as the wrong thing."""
    from msctl.plane import describe_types, qualify_topic, topic_users

    users = topic_users(node, topic)
    hint = "give the topic's type, or --force to publish anyway"
    qualified = qualify_topic(topic)
    if users.publishers and type_name not in users.publishers:
        raise InputError(
            f"topic {qualified} is published as {describe_types(users.publishers)}, "
            f"not {type_name}",
            hint=hint,
        )
    if not users.publishers and users.subscribers and type_name not in users.subscribers:
        raise InputError(
            f"topic {qualified} has no publisher, and its subscribers take "
            f"{describe_types(users.subscribers)}, not {type_name}",
            hint=hint,
        )


@app.command("hz")
def hz(
    topic: str = typer.Argument(..., help="Topic name."),
    msg_type: str = typer.Argument(None, help="Message type (default: found on the graph)."),
    window: int = typer.Option(10000, "--window", "-w", help="Samples in the statistics window."),
    duration: float = typer.Option(0.0, "--for", help="Stop after this many seconds (0: Ctrl-C)."),
    json_output: bool = JSON_OPT,
) -> None:
    """Print the rate of a topic every second (average, min, max, std dev of the period)."""
    from msctl.console import out, print_json
    from msctl.plane import connected

    checked_name(topic)
    if window < 2:
        raise InputError(f"--window {window}: a rate needs at least 2 samples in the window")
    if not (duration >= 0 and math.isfinite(duration)):
        raise InputError(f"--for must be a number of seconds >= 0, not {duration}")
    stamps: list[float] = []
    lock = threading.Lock()

    def on_sample(_: bytes) -> None:
        now = time.monotonic()
        with lock:
            stamps.append(now)
            if len(stamps) > window + 1:
                del stamps[: len(stamps) - window - 1]

    reports: list[dict[str, Any]] = []
    with connected("hz") as node, _Stopper() as stop:
        type_name = _resolve_type(node, topic, msg_type, 3.0)
        others = _OtherTypes(type_name)
        node.subscription(topic, type_name, on_sample, raw=True, on_other_type=others)
        ends = None if not duration else time.monotonic() + duration
        while not stop.is_set() and (ends is None or time.monotonic() < ends):
            stop.wait(1.0 if ends is None else max(0.0, min(1.0, ends - time.monotonic())))
            with lock:
                periods = [b - a for a, b in itertools.pairwise(stamps)]
            if not periods:
                with lock:
                    heard = bool(stamps)
                if not heard:
                    others.check(node, topic)
                if not json_output:
                    out.print(f"no new messages on {topic}", highlight=False)
                continue
            mean = statistics.fmean(periods)
            report = {
                "topic": topic,
                "rate": 1.0 / mean if mean > 0 else math.inf,
                "min": min(periods),
                "max": max(periods),
                "std_dev": statistics.pstdev(periods),
                "window": len(periods),
            }
            reports.append(report)
            if not json_output:
                out.print(
                    f"average rate: {report['rate']:.3f}\n"
                    f"\tmin: {report['min']:.3f}s max: {report['max']:.3f}s "
                    f"std dev: {report['std_dev']:.5f}s window: {report['window']}",
                    highlight=False,
                )
    if json_output:
        print_json(reports[-1] if reports else {"topic": topic, "rate": 0.0, "window": 0})
