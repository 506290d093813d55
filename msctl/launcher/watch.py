"""Judging components healthy from the data plane: their node's liveliness token is seen and
their first output has arrived."""

from __future__ import annotations

import threading
from collections.abc import Iterable
from typing import Any

from components.comm.graph import Graph
from msctl.launcher.plan import ComponentRun


class HealthWatch:
    """Follows the graph and each component's first output topic.

    Args:
        session: An open Zenoh session (the caller closes it after :meth:`close`).
        components: What to follow.
        domain: ROS domain id.
    """

    def __init__(self, session: Any, components: Iterable[ComponentRun], domain: int = 0):
        self._lock = threading.Lock()
        self.components = {c.name: c for c in components}
        self._output_seen: dict[str, bool] = dict.fromkeys(self.components, False)
        self._graph = Graph(session, domain)
        self._subscribers = []
        by_topic: dict[str, list[str]] = {}
        for c in self.components.values():
            by_topic.setdefault(c.first_output, []).append(c.name)
        for topic, names in by_topic.items():
            key = f"{domain}/{topic.strip('/')}/*/*"
            self._subscribers.append(
                session.declare_subscriber(key, lambda _s, names=names: self._saw(names))
            )

    def _saw(self, names: list[str]) -> None:
        with self._lock:
            for name in names:
                self._output_seen[name] = True

    def forget(self, names: Iterable[str]) -> None:
        """A process restarted: its components must show themselves again."""
        with self._lock:
            for name in names:
                self._output_seen[name] = False

    def status(self) -> dict[str, tuple[bool, bool]]:
        """``{component: (node seen, output seen)}``."""
        nodes = self._graph.node_names()
        with self._lock:
            return {
                name: (c.node_fqn in nodes, self._output_seen[name])
                for name, c in self.components.items()
            }

    def healthy(self, name: str) -> bool:
        """Whether one component is seen and has published."""
        node, output = self.status()[name]
        return node and output

    def close(self) -> None:
        """Stop watching (idempotent)."""
        for subscriber in self._subscribers:
            try:
                subscriber.undeclare()
            except Exception:
                pass
        self._subscribers.clear()
        self._graph.close()
