"""The Core: a component's main logic, pure Python.

A Core does no I/O, opens no session and reads no clock. The executor calls its handlers
one at a time with ``now`` (monotonic seconds) and it answers by publishing through its
:class:`Outbox`. Tests drive a Core with plain calls and fake time and read what it sent
from a :class:`RecordingOutbox`.
"""

from __future__ import annotations

from typing import Any, Protocol


class Outbox(Protocol):
    """Where a Core's outputs go: the executor binds it to publishers."""

    def publish(self, topic: str, message: Any) -> None:
        """Send ``message`` on the core's output ``topic`` (relative name)."""


class RecordingOutbox:
    """An Outbox that keeps what was published, for tests and dry runs."""

    def __init__(self) -> None:
        self.sent: list[tuple[str, Any]] = []

    def publish(self, topic: str, message: Any) -> None:
        """Record one output."""
        self.sent.append((topic, message))

    def on(self, topic: str) -> list[Any]:
        """Everything published on ``topic`` so far, oldest first."""
        return [m for t, m in self.sent if t == topic]

    def take(self, topic: str | None = None) -> list[Any]:
        """Remove and return what was published (on ``topic``, or everything)."""
        if topic is None:
            taken = [m for _, m in self.sent]
            self.sent.clear()
            return taken
        taken = [m for t, m in self.sent if t == topic]
        self.sent = [(t, m) for t, m in self.sent if t != topic]
        return taken


class Core:
    """Base of every component's logic.

    Attributes:
        name: The component's name (used in logs and diagnostics).
        outbox: Where outputs go; a :class:`RecordingOutbox` until the executor binds one.
        wall_offset: Add to ``now`` to get wall-clock seconds for message stamps. The
            executor sets it; fake-time tests leave it at 0.
    """

    def __init__(self, name: str) -> None:
        self.name = name
        self.outbox: Outbox = RecordingOutbox()
        self.wall_offset = 0.0

    def bind(self, outbox: Outbox, wall_offset: float = 0.0) -> None:
        """Attach the core to its outputs (called by the executor before any handler)."""
        self.outbox = outbox
        self.wall_offset = wall_offset

    def publish(self, topic: str, message: Any) -> None:
        """Publish on one of the core's declared outputs."""
        self.outbox.publish(topic, message)

    def stamp(self, now: float) -> float:
        """Wall-clock seconds for a message stamp at monotonic time ``now``."""
        return now + self.wall_offset

    def start(self, now: float) -> None:
        """Called once before the first handler. Override to initialise outputs."""

    def stop(self, now: float) -> None:
        """Called once at shutdown, before sessions close. Override to leave things safe."""
