"""What the ``msctl health`` screen reads and acts through.

The screen is written against :class:`HealthSource`; :class:`~msctl.health.live.LiveHealth`
is the real one (Zenoh, supervisors). :class:`BoardSource` serves a board fed by hand, with
a fixed clock and canned answers, for snapshot tests and demonstrations: the library's own
test double, so the screen is testable without a running assembly.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Protocol

from components.data_monitor.alarms import Alarm
from components.data_monitor.board import HealthBoard
from components.data_monitor.measures import RateStats
from components.data_monitor.model import BoardSnapshot


@dataclass(frozen=True)
class TopicRow:
    """A topic on the graph, with its measured rate.

    Attributes:
        name: Fully qualified topic name.
        types: Message types seen on it.
        publishers: Publishers on the graph.
        subscribers: Subscriptions on the graph.
        stats: Its rate, when measured.
    """

    name: str
    types: tuple[str, ...]
    publishers: int
    subscribers: int
    stats: RateStats | None = None


class ActionError(Exception):
    """An action (restart, stop, halt, recover, log tail) that could not be carried out;
    the message says which and why."""


class HealthSource(Protocol):
    """Everything the screen needs: snapshots, alarms, topics, joints and actions."""

    history_source: str | None

    @property
    def version(self) -> int:
        """Changes with every input."""

    def evaluate(self, now: float | None = None) -> BoardSnapshot:
        """The board now."""

    def take_alarms(self) -> list[Alarm]:
        """Alarms since the last call."""

    def alarms(self) -> list[Alarm]:
        """Every alarm kept, oldest first."""

    def router_connected(self) -> bool:
        """Whether a router is reachable."""

    def data_monitors(self) -> list[str]:
        """Data monitors' alarm services on the graph."""

    def fetch_history(self, timeout: float = 2.0) -> int:
        """Merge a data monitor's history; how many alarms were new."""

    def topics(self) -> list[TopicRow]:
        """Every topic on the graph, with rates for the watched ones."""

    def watch_topics(self, names: Iterable[str]) -> None:
        """Measure the rates of exactly these topics from now on."""

    def watch_joints(self, module: str | None) -> None:
        """Keep recent joint positions of ``module`` (``None``: of none)."""

    def joint_history(self, joint: str) -> list[float | None]:
        """Recent positions of ``joint``, oldest first."""

    def control(self, verb: str, component: str, host: str) -> str:
        """``restart`` or ``stop`` a component through its supervisor; what it says."""

    def trigger(self, service: str) -> str:
        """Call a ``std_srvs/Trigger`` service (a module's ``halt``/``recover``)."""

    def log_tail(self, component: str, host: str, lines: int = 40) -> list[str]:
        """The last lines of a component's log, from its supervisor."""


@dataclass
class BoardSource:
    """A :class:`HealthSource` over a board fed by hand (tests, snapshots).

    Attributes:
        board: The board.
        now: The fixed monotonic time snapshots are taken at.
        topic_rows: What :meth:`topics` returns.
        history: Joint -> positions for sparklines.
        logs: Component -> log lines.
        calls: Every action asked for, as ``(verb, target)``.
    """

    board: HealthBoard
    now: float = 0.0
    topic_rows: list[TopicRow] = field(default_factory=list)
    history: dict[str, list[float | None]] = field(default_factory=dict)
    logs: dict[str, list[str]] = field(default_factory=dict)
    calls: list[tuple[str, str]] = field(default_factory=list)
    history_source: str | None = None

    @property
    def version(self) -> int:
        """The board's version."""
        return self.board.version

    def evaluate(self, now: float | None = None) -> BoardSnapshot:
        """The board at the fixed time."""
        return self.board.evaluate(self.now if now is None else now)

    def take_alarms(self) -> list[Alarm]:
        """The board's new alarms."""
        return self.board.take_alarms()

    def alarms(self) -> list[Alarm]:
        """The board's alarms."""
        return list(self.board.alarms)

    def router_connected(self) -> bool:
        """Always connected."""
        return True

    def data_monitors(self) -> list[str]:
        """None."""
        return []

    def fetch_history(self, timeout: float = 2.0) -> int:
        """Nothing to fetch."""
        return 0

    def topics(self) -> list[TopicRow]:
        """The canned topics."""
        return list(self.topic_rows)

    def watch_topics(self, names: Iterable[str]) -> None:
        """Noted."""
        self.calls.append(("watch_topics", ",".join(sorted(names))))

    def watch_joints(self, module: str | None) -> None:
        """Noted."""
        self.calls.append(("watch_joints", module or ""))

    def joint_history(self, joint: str) -> list[float | None]:
        """The canned positions."""
        return list(self.history.get(joint, []))

    def control(self, verb: str, component: str, host: str) -> str:
        """Noted; answers as a supervisor would."""
        self.calls.append((verb, component))
        return f"{verb} {component} on {host}: done"

    def trigger(self, service: str) -> str:
        """Noted."""
        self.calls.append(("trigger", service))
        return f"{service}: ok"

    def log_tail(self, component: str, host: str, lines: int = 40) -> list[str]:
        """The canned lines."""
        self.calls.append(("logs", component))
        return self.logs.get(component, [])[-lines:]
