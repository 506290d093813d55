"""Judging components healthy from the ROS graph, for ``msctl up`` on the rclpy transport.

The same judgement (:class:`components.health_monitor.startup_watch.ComponentWatch`) as
:class:`msctl.launcher.watch.HealthWatch` makes on Zenoh: a component is healthy once its
node is on the graph and its first output has arrived. Here both come
from rclpy: the node list of :class:`~components.ros.graph.RclpyGraph`, and a subscription to
each first output, made once the topic (and so its type) appears on the graph; samples are
taken as bytes and never decoded.
"""

from __future__ import annotations

import threading
from collections.abc import Iterable
from typing import Any

from components.comm.types import UnknownTypeError, normalize_type_name, registry
from components.health_monitor.startup_watch import ComponentWatch
from components.ros.graph import RclpyGraph
from components.ros.plane import RclpyPlane

#: Seconds between two looks for first-output topics not subscribed yet.
TOPIC_POLL = 0.2


class RclpyHealthWatch(ComponentWatch):
    """Follows the ROS graph and each component's first output topic. Close it when done.

    Args:
        components: What to follow (each with ``name``, ``node_fqn`` and ``first_output``).
        domain: ROS domain id (``None``: ``ROS_DOMAIN_ID``).
    """

    def __init__(self, components: Iterable[Any], domain: int | None = None) -> None:
        super().__init__(components)
        self._by_topic = self.outputs()
        self.plane = RclpyPlane(domain)
        self._node = self.plane.node(f"_msctl_health_{id(self):x}")
        self._graph = RclpyGraph(self.plane)
        self._subscriptions: dict[str, Any] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._follow, name="health-topics", daemon=True)
        self._thread.start()

    def _follow(self) -> None:
        """Subscribe to each first output as soon as the graph says its type."""
        while not self._stop.wait(TOPIC_POLL) and len(self._subscriptions) < len(self._by_topic):
            try:
                listing = dict(self._node.ros.get_topic_names_and_types())
            except Exception:
                return  # the context is going down
            for topic, names in self._by_topic.items():
                if topic in self._subscriptions or topic not in listing:
                    continue
                for ros_type in listing[topic]:
                    try:
                        type_name = normalize_type_name(ros_type)
                    except UnknownTypeError:
                        continue
                    if registry().known(type_name):
                        self._subscribe(topic, type_name, names)
                        break

    def _subscribe(self, topic: str, type_name: str, names: list[str]) -> None:
        from components.comm.qos import QoS

        # Best effort, keep last 1 and volatile: matches every publisher's offer, and only
        # "something arrived" matters.
        self._subscriptions[topic] = self._node.subscription(
            topic,
            type_name,
            lambda _payload, names=names: self.saw(names),
            QoS(reliability="best_effort", depth=1),
            raw=True,
        )

    def node_names(self) -> set[str]:
        """The nodes on the ROS graph now."""
        return self._graph.node_names()

    def close(self) -> None:
        """Stop watching and shut the rclpy context down (idempotent)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        self._graph.close()
        self.plane.close()
