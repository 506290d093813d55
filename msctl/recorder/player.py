"""``msctl bag play``: republish a bag onto the data plane with its original timing.

Messages go out through msctl's own publishers, so they carry the right keys, type hashes,
attachments and liveliness tokens, exactly as a live component's would. Bags made by ROS 2
play too: a type msctl does not know is registered from the bag's own ``ros2msg``
definition first.

What a topic is comes from the roles the component interfaces declare
(:mod:`components.roles`): commands, halts and control requests (``joint_set``, ``cmd_vel``,
...) move a robot, so onto a running assembly (something subscribes to them) they are refused
unless asked for; raw motor commands and motor feedback (``joint_commands``,
``joint_states``) may come only from the module's own components, so they are refused onto a
running assembly even then, unless remapped away. A remap must name a topic of the bag: a typo
would otherwise play the topic under its own, live name.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from components.recording.definitions import SEPARATOR, profiles_to_qos
from components.recording.errors import BagError
from msctl.recorder.bag import BagInfo, TopicDefinition, read_messages


def is_command_topic(topic: str) -> bool:
    """Whether ``topic`` drives, stops or speaks for a robot's motors, by its declared role
    (:func:`components.roles.role_of`)."""
    from components.roles import moves, role_of

    return moves(role_of(topic))


def parse_remaps(texts: Iterable[str]) -> dict[str, str]:
    """``OLD:=NEW`` pairs (names qualified against ``/``).

    Raises:
        BagError: Naming the remap that is malformed.
    """
    from components.comm.names import NameError_, qualify

    remaps = {}
    for text in texts:
        old, sep, new = text.partition(":=")
        if not sep or not old.strip() or not new.strip():
            raise BagError(f"--remap {text!r} is not OLD:=NEW (e.g. /chatter:=/chatter2)")
        try:
            remaps[qualify(old.strip(), "/")] = qualify(new.strip(), "/")
        except NameError_ as exc:
            raise BagError(f"--remap {text!r}: {exc}") from None
    return remaps


def register_definition(type_name: str, text: str) -> bool:
    """Register a type (and those it uses) from a ``ros2msg`` definition, if msctl lacks it.

    Returns whether the type is known afterwards.
    """
    from components.comm.types import UnknownTypeError, normalize_type_name, registry

    reg = registry()
    if reg.known(type_name):
        return True
    if not text.strip():
        return False
    sections: list[tuple[str, str]] = []
    name, lines = type_name, []
    for line in text.splitlines():
        if line.strip() == SEPARATOR:
            sections.append((name, "\n".join(lines) + "\n"))
            name, lines = "", []
        elif not name and line.startswith("MSG:"):
            name = line[4:].strip()
        else:
            lines.append(line)
    sections.append((name, "\n".join(lines) + "\n"))
    pending = []
    for section_name, body in sections:
        try:
            pending.append((normalize_type_name(section_name), body))
        except UnknownTypeError:
            return False
    # Dependencies first: retry what fails for an unknown nested type until nothing moves.
    while pending:
        left = []
        for section_name, body in pending:
            if reg.known(section_name):
                continue
            try:
                reg.register_msg(section_name, body)
            except ValueError:
                left.append((section_name, body))
        if len(left) == len(pending):
            return False
        pending = left
    return reg.known(type_name)


@dataclass
class PlayReport:
    """What a play did.

    Attributes:
        published: Messages sent.
        topics: Topic -> messages sent (by the name they were published on).
        skipped: Topic -> why it was not played.
        loops: Complete passes over the bag.
    """

    published: int = 0
    topics: dict[str, int] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)
    loops: int = 0


class Player:
    """Publishes a bag's messages with the original spacing (scaled by ``rate``).

    Args:
        node: The node to publish through (the caller closes it).
        info: The bag, from :func:`msctl.recorder.bag.inspect`.
        rate: Speed factor (2.0: twice as fast).
        topics: Only these topics (names as recorded); all when empty.
        start_offset: Seconds into the bag to start at.
        remap: Recorded name -> name to publish on.
        loop: Start over at the end, until stopped.
        allow_commands: Play commands, halts and control requests even when something
            subscribes to them (never raw motor commands or feedback: remap those).

    Raises:
        BagError: If an option is out of range or names a topic the bag lacks (a remap's
            source included).
    """

    def __init__(
        self,
        node: Any,
        info: BagInfo,
        *,
        rate: float = 1.0,
        topics: Iterable[str] = (),
        start_offset: float = 0.0,
        remap: Mapping[str, str] | None = None,
        loop: bool = False,
        allow_commands: bool = False,
    ) -> None:
        from components.comm.names import qualify

        if not rate > 0:
            raise BagError(f"--rate must be above 0, not {rate}")
        if start_offset < 0:
            raise BagError(f"--start-offset cannot be negative ({start_offset})")
        self.node = node
        self.info = info
        self.rate = rate
        self.start_offset = start_offset
        self.remap = dict(remap or {})
        self.loop = loop
        self.allow_commands = allow_commands
        recorded = {t.name for t in info.metadata.topics}
        wanted = [qualify(t, "/") for t in topics]
        missing = [t for t in wanted if t not in recorded]
        if missing:
            raise BagError(
                f"bag {info.path} has no topic {', '.join(missing)}; "
                f"it has: {', '.join(sorted(recorded)) or 'none'}"
            )
        unknown = [f"{old}:={new}" for old, new in self.remap.items() if old not in recorded]
        if unknown:
            raise BagError(
                f"--remap {', '.join(unknown)}: bag {info.path} has no topic "
                f"{', '.join(old for old in self.remap if old not in recorded)}; "
                f"it has: {', '.join(sorted(recorded)) or 'none'}",
                hint="name a recorded topic on the left of :=",
            )
        self.topics = set(wanted) or recorded
        self.report = PlayReport()
        self._publishers: dict[str, Any] = {}

    def check_commands(self, subscribed: Callable[[str], bool]) -> None:
        """Refuse, by their declared roles, topics a running assembly listens to that a
        recording must not speak on: commands, halts and control requests (unless
        ``allow_commands``), raw motor commands and feedback (always).

        Args:
            subscribed: Whether a topic (as it would be published) has subscribers.

        Raises:
            BagError: Naming the topics, their roles, and the way to play them anyway.
        """
        from components.roles import RULES, declared_names, moves, role_of

        names = declared_names()
        own_only, commands = [], []
        for topic in sorted(self.remap.get(t, t) for t in self.topics):
            role = role_of(topic, names)
            if not moves(role) or not subscribed(topic):
                continue
            assert role is not None
            if RULES[role].own_senders:
                own_only.append(f"{topic} ({role.value}: only {RULES[role].who} publishes it)")
            elif not self.allow_commands:
                commands.append(f"{topic} ({role.value})")
        if own_only:
            raise BagError(
                f"refusing to play {'; '.join(own_only)} onto a running assembly",
                hint="leave them out with --topics, or remap them (--remap SRC:=/replay/...)",
            )
        if commands:
            raise BagError(
                f"refusing to play command topic(s) {', '.join(commands)} onto a running "
                "assembly (they would move or stop the robot)",
                hint="leave them out with --topics, remap them, or give --allow-commands",
            )

    def play(
        self,
        stop: threading.Event,
        progress: Callable[[PlayReport, float], None] | None = None,
    ) -> PlayReport:
        """Publish until the bag ends (or, with ``loop``, until ``stop`` is set).

        Args:
            stop: Set it to end the play early.
            progress: Called now and then with the report and the seconds of bag played.
        """
        while not stop.is_set():
            self._one_pass(stop, progress)
            if stop.is_set() or not self.loop:
                break
            self.report.loops += 1
        self.close()
        return self.report

    def close(self) -> None:
        """Undeclare the publishers (idempotent)."""
        for publisher in self._publishers.values():
            publisher.close()
        self._publishers.clear()

    def _one_pass(
        self, stop: threading.Event, progress: Callable[[PlayReport, float], None] | None
    ) -> None:
        start = self.info.metadata.starting_time + int(self.start_offset * 1e9)
        first: int | None = None
        wall_start = 0.0
        last_progress = 0.0
        for message in read_messages(self.info, sorted(self.topics), self._prepare):
            if message.log_time < start:
                continue
            publisher = self._publishers.get(message.topic)
            if publisher is None:
                continue
            if first is None:
                first, wall_start = message.log_time, time.monotonic()
            due = wall_start + (message.log_time - first) / 1e9 / self.rate
            delay = due - time.monotonic()
            if delay > 0 and stop.wait(delay):
                return
            if stop.is_set():
                return
            publisher.publish_raw(message.data)
            self.report.published += 1
            name = publisher.topic
            self.report.topics[name] = self.report.topics.get(name, 0) + 1
            now = time.monotonic()
            if progress is not None and now - last_progress > 0.1:
                last_progress = now
                progress(self.report, (message.log_time - first) / 1e9)

    def _prepare(self, topic: TopicDefinition) -> None:
        """Make the publisher of a topic, before its first message."""
        if topic.name in self._publishers or topic.name in self.report.skipped:
            return
        if not topic.type:
            self.report.skipped[topic.name] = (
                "the bag names no type for it (its channel has no schema): nothing to publish it as"
            )
            return
        if topic.encoding not in ("ros2msg", "") and not _known(topic.type):
            self.report.skipped[topic.name] = (
                f"its type {topic.type} is defined as {topic.encoding}, which msctl cannot read"
            )
            return
        if not register_definition(topic.type, topic.definition):
            self.report.skipped[topic.name] = (
                f"msctl has no definition of {topic.type} and the bag holds none"
            )
            return
        qos = profiles_to_qos(topic.offered_qos_profiles)
        from components.data_archiver.core import subscription_qos

        offered = subscription_qos(qos)
        self._publishers[topic.name] = self.node.publisher(
            self.remap.get(topic.name, topic.name), topic.type, offered
        )


def _known(type_name: str) -> bool:
    from components.comm.types import registry

    return registry().known(type_name)
