"""The ROS graph as rclpy sees it, as msctl's :class:`~components.comm.graph.GraphView`.

DDS discovery fills rmw's graph cache; rclpy reads it with calls, and signals no changes a
Python caller can wait on, so nodes are polled (every :data:`POLL_PERIOD`, a read of a local
cache) and each change is reported as msctl's Zenoh graph reports it: ``on_change(entity,
alive)`` with a node :class:`~components.comm.liveliness.Entity`. Two nodes of one name (a
restarted process overlapping its predecessor) are two entities. Topics and services are read
when asked (:meth:`RclpyGraph.entities`), with their types, endpoints' nodes and QoS.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

from components.comm.graph import GraphView
from components.comm.liveliness import Entity, EntityKind
from components.comm.types import UnknownTypeError, normalize_type_name, registry

log = logging.getLogger("msctl.ros")

#: Seconds between two reads of the node list.
POLL_PERIOD = 0.2
#: The "session" every DDS entity is filed under (DDS participants are not Zenoh sessions).
DDS_ZID = "dds"


def node_entity(domain: int, namespace: str, name: str, instance: int) -> Entity:
    """The msctl graph entity of one DDS node (``instance``: which of its namesakes)."""
    return Entity(
        domain=domain,
        zid=DDS_ZID,
        node_id=instance,
        entity_id=0,
        kind=EntityKind.NODE,
        namespace=namespace,
        node_name=name,
    )


def _type_name(ros_type: str) -> str | None:
    try:
        return normalize_type_name(ros_type)
    except UnknownTypeError:
        return None


class RclpyGraph(GraphView):
    """A live view of the ROS graph of one rclpy plane. Close it when done.

    Args:
        plane: The :class:`~components.ros.plane.RclpyPlane` whose participant looks.
        on_change: Called (on the poller's thread) with ``(node entity, alive)`` per change.
        period: Seconds between two reads of the node list.
    """

    def __init__(
        self,
        plane: Any,
        on_change: Callable[[Entity, bool], None] | None = None,
        period: float = POLL_PERIOD,
    ) -> None:
        self._plane = plane
        self._ros = plane.graph_node()
        self.domain = plane.domain
        self._on_change = on_change
        self._period = period
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._nodes: Counter[tuple[str, str]] = Counter()
        self._stop = threading.Event()
        self._poll()  # the nodes already up are known (and reported) at once
        self._thread = threading.Thread(target=self._run, name="rclpy-graph", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self._period):
            try:
                self._poll()
            except Exception as exc:  # the context went down under us: stop quietly
                if not self._stop.is_set():
                    log.debug("graph poll failed: %s", exc)
                return

    def _poll(self) -> None:
        now = Counter(
            (namespace, name)
            for name, namespace in self._ros.get_node_names_and_namespaces()
            if not name.startswith("_")  # hidden nodes (ours among them)
        )
        with self._lock:
            before = self._nodes
            self._nodes = now
            if now != before:
                self._changed.notify_all()
        if self._on_change is None or now == before:
            return
        for key in set(before) | set(now):
            old, new = before[key], now[key]
            for instance in range(new, old):
                self._report(node_entity(self.domain, *key, instance), False)
            for instance in range(old, new):
                self._report(node_entity(self.domain, *key, instance), True)

    def _report(self, entity: Entity, alive: bool) -> None:
        try:
            self._on_change(entity, alive)  # type: ignore[misc]
        except Exception:
            log.exception("graph change callback failed")

    def entities(self) -> list[Entity]:
        """Every node, publisher, subscription, server and client on the graph now."""
        with self._lock:
            nodes = Counter(self._nodes)
        found = [
            node_entity(self.domain, namespace, name, instance)
            for (namespace, name), count in nodes.items()
            for instance in range(count)
        ]
        ros = self._ros
        from components.ros.plane_topics import msctl_qos

        for topic, _types in ros.get_topic_names_and_types():
            for kind, infos in (
                (EntityKind.PUBLISHER, ros.get_publishers_info_by_topic(topic)),
                (EntityKind.SUBSCRIPTION, ros.get_subscriptions_info_by_topic(topic)),
            ):
                for index, info in enumerate(infos):
                    type_name = _type_name(info.topic_type)
                    if type_name is None or info.node_name.startswith("_"):
                        continue
                    found.append(
                        self._endpoint(
                            kind,
                            info.node_namespace,
                            info.node_name,
                            index + 1,
                            topic,
                            type_name,
                            msctl_qos(info.qos_profile).encode(),
                        )
                    )
        for namespace, name in nodes:
            for kind, listing in (
                (EntityKind.SERVICE, ros.get_service_names_and_types_by_node),
                (EntityKind.CLIENT, ros.get_client_names_and_types_by_node),
            ):
                try:
                    entries = listing(name, namespace)
                except Exception:  # the node left between the two calls
                    continue
                for index, (service, types) in enumerate(entries):
                    for ros_type in types:
                        type_name = _type_name(ros_type)
                        if type_name is not None:
                            found.append(
                                self._endpoint(
                                    kind, namespace, name, index + 1, service, type_name, None
                                )
                            )
        return found

    def _endpoint(
        self,
        kind: EntityKind,
        namespace: str,
        name: str,
        index: int,
        topic: str,
        type_name: str,
        qos: str | None,
    ) -> Entity:
        reg = registry()
        type_hash = reg.type_hash(type_name) if reg.known(type_name) else ""
        return Entity(
            domain=self.domain,
            zid=DDS_ZID,
            node_id=0,
            entity_id=index,
            kind=kind,
            namespace=namespace,
            node_name=name,
            topic=topic,
            type_name=type_name,
            type_hash=type_hash,
            qos=qos,
        )

    def node_names(self) -> set[str]:
        """Fully qualified names of every node (from the last poll: cheap)."""
        with self._lock:
            return {f"{ns.rstrip('/')}/{name}" for ns, name in self._nodes}

    def wait_for(self, predicate: Callable[[GraphView], bool], timeout: float) -> bool:
        """Block until ``predicate(self)`` holds or ``timeout`` passes; returns whether it held."""
        deadline = time.monotonic() + timeout
        while True:
            if predicate(self):
                return True
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            with self._changed:
                self._changed.wait(min(remaining, self._period))

    def close(self) -> None:
        """Stop polling (idempotent)."""
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)

    def __enter__(self) -> RclpyGraph:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
