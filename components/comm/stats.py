"""Counting what the data plane drops, and saying so without flooding the log.

A malformed payload, an unknown type or a bad attachment must never crash a component: it
is dropped, counted per topic and reason, and logged at most once per interval per
(topic, reason) with the running count.
"""

from __future__ import annotations

import threading
import time
from collections import defaultdict
from typing import Any


class _Logger:
    """The ``msctl.comm`` logger, looked up on first use: importing ``logging`` (~10 ms) is
    paid by the processes that log, not by every short CLI command that imports the plane."""

    def __getattr__(self, name: str) -> Any:
        import logging

        return getattr(logging.getLogger("msctl.comm"), name)


#: Where the plane's warnings go (the ``msctl.comm`` logger).
log: Any = _Logger()

#: Seconds between two log lines about the same topic and reason.
LOG_INTERVAL = 5.0


class DropStats:
    """Thread-safe counters of dropped samples, per topic and reason."""

    def __init__(self, log_interval: float = LOG_INTERVAL) -> None:
        self._counts: dict[str, dict[str, int]] = defaultdict(lambda: defaultdict(int))
        self._last_log: dict[tuple[str, str], float] = {}
        self._lock = threading.Lock()
        self._interval = log_interval

    def drop(self, topic: str, reason: str, detail: str = "", quiet: bool = False) -> None:
        """Count one dropped sample and log it if this (topic, reason) has been quiet.

        Args:
            topic: Topic or service the sample came on.
            reason: Short reason (``malformed``, ``intruder``...).
            detail: Said in the log line.
            quiet: Count only: the caller says it in its own words (e.g. once per node).
        """
        now = time.monotonic()
        with self._lock:
            self._counts[topic][reason] += 1
            count = self._counts[topic][reason]
            if quiet:
                return
            last = self._last_log.get((topic, reason))
            due = last is None or now - last >= self._interval
            if due:
                self._last_log[(topic, reason)] = now
        if due:
            log.warning("dropped sample on %s: %s (%d so far) %s", topic, reason, count, detail)

    def count(self, topic: str, reason: str | None = None) -> int:
        """Drops on ``topic`` (for one reason, or all)."""
        with self._lock:
            per_reason = self._counts.get(topic, {})
            if reason is None:
                return sum(per_reason.values())
            return per_reason.get(reason, 0)

    def snapshot(self) -> dict[str, dict[str, int]]:
        """A copy of every counter: ``{topic: {reason: count}}``."""
        with self._lock:
            return {t: dict(r) for t, r in self._counts.items()}


#: The process-wide counters every subscription, server and client reports to.
drops = DropStats()
