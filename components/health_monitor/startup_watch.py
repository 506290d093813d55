"""Is a component up? Its node is on the graph and its first output has arrived.

The judgement ``msctl up`` makes of every component it starts, whatever carries the data:
:class:`msctl.launcher.watch.HealthWatch` follows Zenoh's graph, and
:class:`components.ros.health_watch.RclpyHealthWatch` the ROS graph of rclpy. Both are a
:class:`ComponentWatch`: this class keeps which outputs arrived, and when; each transport
says which nodes its graph shows (:meth:`ComponentWatch.node_names`) and feeds
:meth:`ComponentWatch.saw` from its subscriptions.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable
from typing import Any


class ComponentWatch:
    """Which components are seen and have published.

    Args:
        components: What to follow (each with ``name``, ``node_fqn`` and ``first_output``).
        clock: Monotonic time (tests pass a fake one).
    """

    def __init__(self, components: Iterable[Any], clock: Callable[[], float] = time.monotonic):
        self._lock = threading.Lock()
        self._clock = clock
        self.components = {c.name: c for c in components}
        # When each component's first output arrived (absent: not yet, or forgotten).
        self._output_at: dict[str, float] = {}

    def outputs(self) -> dict[str, list[str]]:
        """``{first output topic: names of the components it shows}`` (several components
        of a namespace may share one topic, such as its ``diagnostics``)."""
        by_topic: dict[str, list[str]] = {}
        for component in self.components.values():
            by_topic.setdefault(component.first_output, []).append(component.name)
        return by_topic

    def saw(self, names: Iterable[str]) -> None:
        """An output of these components arrived."""
        now = self._clock()
        with self._lock:
            for name in names:
                self._output_at.setdefault(name, now)

    def forget(self, names: Iterable[str]) -> None:
        """A process restarted: its components must show themselves again."""
        with self._lock:
            for name in names:
                self._output_at.pop(name, None)

    def node_names(self) -> set[str]:
        """Fully qualified names of the nodes the graph shows now."""
        raise NotImplementedError

    def status(self) -> dict[str, tuple[bool, bool]]:
        """``{component: (node seen, output seen)}``."""
        nodes = self.node_names()
        with self._lock:
            return {
                name: (c.node_fqn in nodes, name in self._output_at)
                for name, c in self.components.items()
            }

    def output_age(self, name: str) -> float | None:
        """Seconds since the component's first output arrived (``None``: not yet)."""
        with self._lock:
            at = self._output_at.get(name)
        return None if at is None else self._clock() - at

    def healthy(self, name: str) -> bool:
        """Whether one component is seen and has published."""
        node, output = self.status()[name]
        return node and output
