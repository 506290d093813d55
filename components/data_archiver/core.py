"""The data archiver's logic: which topics to record, with what QoS, what was lost, and how
the recording is doing. Pure Python: no Zenoh, no files, no clocks (time is passed in).

The recorder (:mod:`components.recording.recorder`) does the I/O and asks this module every
decision; ``msctl record`` and the ``data_archiver`` component share it.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from components.comm.qos import QoS
from components.config import require
from components.executor.core import Core
from components.messages import Level, diagnostic_array, diagnostic_status

#: Topics a recording of "everything" leaves out unless named: the graph's own machinery.
HIDDEN_PREFIXES = ("/_",)


@dataclass(frozen=True)
class TopicSelection:
    """Which topics a recording takes.

    Attributes:
        topics: Topic names taken whatever the other settings say (fully qualified).
        all_topics: Take every topic (``--all``).
        regex: Take topics whose name matches (``re.search``) this.
        exclude: Leave out topics whose name matches this (never one named in ``topics``).
    """

    topics: tuple[str, ...] = ()
    all_topics: bool = False
    regex: str = ""
    exclude: str = ""

    def __post_init__(self) -> None:
        for option, text in (("--regex", self.regex), ("--exclude", self.exclude)):
            if text:
                try:
                    re.compile(text)
                except re.error as exc:
                    raise ValueError(
                        f"{option} {text!r} is not a regular expression: {exc}"
                    ) from None
        if not (self.topics or self.all_topics or self.regex):
            raise ValueError("nothing to record: name topics, or give --all or --regex")

    @property
    def wildcard(self) -> bool:
        """Whether topics not named in advance can be taken (so every key is listened to)."""
        return self.all_topics or bool(self.regex)

    def matches(self, topic: str) -> bool:
        """Whether ``topic`` (fully qualified) is recorded."""
        if topic in self.topics:
            return True
        if self.exclude and re.search(self.exclude, topic):
            return False
        if self.all_topics:
            return not topic.startswith(HIDDEN_PREFIXES)
        return bool(self.regex) and re.search(self.regex, topic) is not None

    @classmethod
    def from_text(cls, topics: str = "", regex: str = "", exclude: str = "") -> TopicSelection:
        """From station data: ``topics`` is space- or comma-separated names, or ``*`` for all.

        Raises:
            ValueError: If a name or pattern is invalid, or nothing would be recorded.
        """
        from components.comm.names import qualify

        names = [n for n in re.split(r"[\s,]+", topics.strip()) if n]
        everything = "*" in names
        qualified = tuple(qualify(n, "/") for n in names if n != "*")
        return cls(topics=qualified, all_topics=everything, regex=regex, exclude=exclude)


def subscription_qos(offered: Iterable[QoS]) -> QoS:
    """The QoS to subscribe with, from what the topic's publishers offer (rosbag2's rule).

    Reliable only when every publisher offers reliable (a reliable subscription matches no
    best-effort publisher); transient local only when every publisher offers it (so each
    one's latched samples are fetched and none is incompatible); the deepest history asked.
    """
    profiles = list(offered)
    if not profiles:
        return QoS()
    reliable = all(q.reliability == "reliable" for q in profiles)
    latched = all(q.durability == "transient_local" for q in profiles)
    depth = (
        max(q.depth for q in profiles if q.history == "keep_last")
        if any(q.history == "keep_last" for q in profiles)
        else 10
    )
    return QoS(
        reliability="reliable" if reliable else "best_effort",
        durability="transient_local" if latched else "volatile",
        depth=max(depth, 1),
    )


@dataclass
class SequenceTracker:
    """Messages lost before they reached the recorder, from the senders' sequence numbers.

    Each publisher (GID) numbers its samples 1, 2, 3...; a jump is that many samples lost on
    the way (a best-effort link, a full queue upstream). A restart (a smaller number) starts
    a new count.

    Attributes:
        lost: Samples missing, per topic id.
        thinned: Topic ids thinned on their way on purpose (a router downsampling a radio
            link): their jumps are no losses, and are not counted.
    """

    lost: dict[int, int] = field(default_factory=dict)
    thinned: set[int] = field(default_factory=set)
    _last: dict[tuple[int, bytes], int] = field(default_factory=dict)

    def observe(self, topic_id: int, gid: bytes, sequence: int) -> int:
        """Record one sample's number; returns how many were missing just before it."""
        return self.count(topic_id, gid, sequence) or 0

    def count(self, topic_id: int, gid: bytes, sequence: int) -> int | None:
        """Record one sample's number; returns how many were missing just before it, or
        ``None`` when that cannot be known (the publisher's first sample, or a restart)."""
        key = (topic_id, gid)
        last = self._last.get(key)
        self._last[key] = sequence
        if last is None or sequence <= last:
            return None
        gap = sequence - last - 1
        if gap:
            if topic_id in self.thinned:
                return None  # sampled on the way: what was lost cannot be told
            self.lost[topic_id] = self.lost.get(topic_id, 0) + gap
        return gap

    @property
    def total(self) -> int:
        """Samples missing over all topics."""
        return sum(self.lost.values())


@dataclass(frozen=True)
class RecorderStatus:
    """A snapshot of a recording, as the recorder reports it.

    Attributes:
        directory: The bag directory.
        current_file: The file being written ("" once closed).
        files: Data files so far.
        topics: Topics recorded so far.
        messages: Messages written.
        bytes: Bytes written.
        dropped: Messages dropped by the recorder (its queue was full).
        lost: Messages missing upstream (sequence gaps).
        unknown_types: Types recorded without a definition (msctl has none).
        duration: Seconds from the first to the last message's receive time.
        paused: Whether recording is paused.
        error: Why the recording stopped by itself ("" while fine).
        gaps: Interruptions of a topic so far (see ``components.data_archiver.gaps``).
        silent: Topics that were flowing and are not arriving now (a link down).
    """

    directory: str = ""
    current_file: str = ""
    files: int = 0
    topics: int = 0
    messages: int = 0
    bytes: int = 0
    dropped: int = 0
    lost: int = 0
    unknown_types: tuple[str, ...] = ()
    duration: float = 0.0
    paused: bool = False
    error: str = ""
    gaps: int = 0
    silent: tuple[str, ...] = ()


@dataclass
class ArchiverConfig:
    """A data archiver's parameters, from the station's data.

    Attributes:
        topics: Topic names to record, space- or comma-separated; ``*`` for every topic.
        regex: Also record topics matching this regular expression.
        exclude: Leave out topics matching this regular expression.
        directory: Where bags are made (one ``<node>_<date-time>`` bag per start); relative
            paths are under the launcher's home.
        max_bag_size: Split files at this many bytes (0: never).
        max_bag_duration: Split files at this many seconds (0: never).
        compression: ``zstd`` or ``none`` (chunk compression inside the MCAP files).
    """

    topics: str = "*"
    regex: str = ""
    exclude: str = ""
    directory: str = "bags"
    max_bag_size: int = 0
    max_bag_duration: float = 0.0
    compression: str = "zstd"

    def __post_init__(self) -> None:
        require(self, non_negative=("max_bag_size", "max_bag_duration"))
        if self.compression not in ("zstd", "none"):
            raise ValueError(
                f"ArchiverConfig.compression must be 'zstd' or 'none', not {self.compression!r}"
            )
        if not self.directory.strip():
            raise ValueError("ArchiverConfig.directory cannot be empty")
        self.selection()

    def selection(self) -> TopicSelection:
        """The topics this configuration records."""
        return TopicSelection.from_text(self.topics, self.regex, self.exclude)


class ArchiverCore:
    """Turns recorder status snapshots into the archiver's diagnostic status.

    Args:
        name: The archiver's name on diagnostics (its node's fully qualified name).
    """

    def __init__(self, name: str) -> None:
        self.name = name
        self._previous: tuple[float, int, int] | None = None
        self._rate = 0.0
        self._byte_rate = 0.0

    def report(self, status: RecorderStatus, now: float) -> tuple[Level, str, dict[str, str]]:
        """The level, one-line message and key/values for ``status`` at time ``now`` (s)."""
        if self._previous is not None:
            then, messages, size = self._previous
            elapsed = now - then
            if elapsed > 0:
                self._rate = (status.messages - messages) / elapsed
                self._byte_rate = (status.bytes - size) / elapsed
        self._previous = (now, status.messages, status.bytes)
        values = {
            "directory": status.directory,
            "current_file": status.current_file,
            "files": str(status.files),
            "topics": str(status.topics),
            "messages": str(status.messages),
            "bytes": str(status.bytes),
            "rate_hz": f"{self._rate:.1f}",
            "bytes_per_s": f"{self._byte_rate:.0f}",
            "dropped": str(status.dropped),
            "lost_upstream": str(status.lost),
            "unknown_types": ", ".join(status.unknown_types),
            "paused": "true" if status.paused else "false",
            "gaps": str(status.gaps),
            "not_receiving": ", ".join(status.silent),
        }
        if status.error:
            return Level.ERROR, f"not recording: {status.error}", values
        # The one line `msctl health` shows: where, how much, how fast, what was lost.
        figures = (
            f"{status.messages} msgs, {status.bytes / 1e6:.1f} MB, {self._rate:.0f} msg/s, "
            f"{status.dropped} dropped, {status.lost} lost upstream, "
            f"file {status.current_file or '-'}"
        )
        if status.dropped:
            return (
                Level.WARN,
                f"recording, but messages were dropped (the disk is too slow): {figures}",
                values,
            )
        if status.paused:
            return Level.OK, f"paused: {figures}", values
        if status.silent:
            # Still recording what arrives; it resumes by itself when the link is back.
            return (
                Level.WARN,
                f"not receiving {', '.join(status.silent)} (a link down?); recording the rest: "
                f"{figures}",
                values,
            )
        return Level.OK, f"recording {status.topics} topic(s): {figures}", values


def bag_name(node: str, stamp: str) -> str:
    """The bag directory a data archiver makes at a start: ``<node>_<stamp>``."""
    return f"{node.strip('/').replace('/', '_')}_{stamp}"


def params_of(config: ArchiverConfig) -> Mapping[str, Any]:
    """The recorder's options for a configuration."""
    return {
        "compression": None if config.compression == "none" else config.compression,
        "max_bytes": config.max_bag_size,
        "max_duration": config.max_bag_duration,
    }


class DataArchiverCore(Core):
    """The data archiver component's logic: report the recording on diagnostics.

    The recording itself runs beside the executor (it is I/O: a Zenoh subscriber and a
    writer thread); its builder hands this core a ``status`` function reading it.

    Args:
        name: The component's name.
        status: Returns the recording's current :class:`RecorderStatus`.
        hardware_id: The station's host, named in the diagnostic.
    """

    def __init__(
        self, name: str, status: Callable[[], RecorderStatus], hardware_id: str = ""
    ) -> None:
        super().__init__(name)
        self._status = status
        self._report = ArchiverCore(name)
        self._hardware_id = hardware_id

    def tick(self, now: float) -> None:
        """Publish the recording's status (every second)."""
        level, message, values = self._report.report(self._status(), now)
        status = diagnostic_status(self.name, level, message, self._hardware_id, values)
        self.outbox.publish("diagnostics", diagnostic_array([status], now + self.wall_offset))
