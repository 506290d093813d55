"""The ROS graph as seen from the liveliness tokens: nodes, topics, services.

Built from every ``@ros2_lv`` token on the network, so it sees rmw_zenoh ROS 2 nodes as well
as msctl components. Either a live view (:class:`Graph`, kept up to date by a liveliness
subscriber) or a one-shot :func:`snapshot`.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable
from typing import Any, NamedTuple

from components.comm.liveliness import (
    PREFIX,
    Entity,
    EntityKind,
    TokenError,
    ask_tokens,
    follow_tokens,
)
from components.comm.stats import drops
from components.errors import swallowed

# The records of the graph layer (here, and the QoS, entities, attachments and session
# settings beside it) are plain classes and named tuples, not dataclasses: importing
# dataclasses (and the inspect it pulls in) and building the classes cost ``msctl ps`` and
# ``msctl topic list`` 12-13 ms of their ~70 ms (bench/cli.py; a bare session takes 33).


class TopicInfo:
    """A topic on the graph (filled in from its tokens by :meth:`GraphView.topics`).

    Attributes:
        name: The fully qualified topic name.
        types: Every type published or subscribed on it.
        publishers: How many publishers.
        subscribers: How many subscribers.
        publisher_nodes: The publishing nodes' names.
        subscriber_nodes: The subscribing nodes' names.
    """

    __slots__ = (
        "name",
        "publisher_nodes",
        "publishers",
        "subscriber_nodes",
        "subscribers",
        "types",
    )

    def __init__(self, name: str) -> None:
        self.name = name
        self.types: set[str] = set()
        self.publishers = 0
        self.subscribers = 0
        self.publisher_nodes: set[str] = set()
        self.subscriber_nodes: set[str] = set()

    def __repr__(self) -> str:
        return (
            f"TopicInfo({self.name!r}, types={sorted(self.types)}, "
            f"publishers={self.publishers}, subscribers={self.subscribers})"
        )


class ServiceInfo:
    """A service on the graph (filled in from its tokens by :meth:`GraphView.services`).

    Attributes:
        name: The fully qualified service name.
        types: Every service type served or called on it.
        servers: How many servers.
        clients: How many clients.
        server_nodes: The serving nodes' names.
    """

    __slots__ = ("clients", "name", "server_nodes", "servers", "types")

    def __init__(self, name: str) -> None:
        self.name = name
        self.types: set[str] = set()
        self.servers = 0
        self.clients = 0
        self.server_nodes: set[str] = set()

    def __repr__(self) -> str:
        return (
            f"ServiceInfo({self.name!r}, types={sorted(self.types)}, "
            f"servers={self.servers}, clients={self.clients})"
        )


class NodeInfo(NamedTuple):
    """A node on the graph."""

    fqn: str
    namespace: str
    name: str
    zid: str


class GraphView:
    """Queries over a set of entities (shared by the live and one-shot views)."""

    def entities(self) -> list[Entity]:
        """Every entity currently known."""
        raise NotImplementedError

    def nodes(self) -> list[NodeInfo]:
        """Every node, sorted by fully qualified name."""
        found = {
            (e.zid, e.node_id): NodeInfo(e.node_fqn, e.namespace, e.node_name, e.zid)
            for e in self.entities()
            if e.kind is EntityKind.NODE
        }
        return sorted(found.values(), key=lambda n: (n.fqn, n.zid))

    def topics(self) -> dict[str, TopicInfo]:
        """Every topic with its types and publisher/subscriber counts."""
        topics: dict[str, TopicInfo] = {}
        for e in self.entities():
            if e.kind not in (EntityKind.PUBLISHER, EntityKind.SUBSCRIPTION) or e.topic is None:
                continue
            info = topics.setdefault(e.topic, TopicInfo(e.topic))
            if e.type_name:
                info.types.add(e.type_name)
            if e.kind is EntityKind.PUBLISHER:
                info.publishers += 1
                info.publisher_nodes.add(e.node_fqn)
            else:
                info.subscribers += 1
                info.subscriber_nodes.add(e.node_fqn)
        return dict(sorted(topics.items()))

    def services(self) -> dict[str, ServiceInfo]:
        """Every service with its types and server/client counts."""
        services: dict[str, ServiceInfo] = {}
        for e in self.entities():
            if e.kind not in (EntityKind.SERVICE, EntityKind.CLIENT) or e.topic is None:
                continue
            info = services.setdefault(e.topic, ServiceInfo(e.topic))
            if e.type_name:
                info.types.add(e.type_name)
            if e.kind is EntityKind.SERVICE:
                info.servers += 1
                info.server_nodes.add(e.node_fqn)
            else:
                info.clients += 1
        return dict(sorted(services.items()))

    def node_names(self) -> set[str]:
        """Fully qualified names of every node."""
        return {n.fqn for n in self.nodes()}


class Snapshot(GraphView):
    """The graph at one moment."""

    def __init__(self, entities: Iterable[Entity]) -> None:
        self._entities = list(entities)

    def entities(self) -> list[Entity]:
        """Every entity in the snapshot."""
        return list(self._entities)


def _parse(key: str) -> Entity | None:
    try:
        return Entity.parse(key)
    except TokenError as exc:
        drops.drop("@ros2_lv", "bad_token", str(exc))
        return None


#: The node tokens only (zid/node/entity/kind ``NN``/...), for :class:`Graph` and
#: :func:`snapshot`: a watcher of nodes that took every token parsed each of a two_dragons'
#: 625 (each endpoint has one) to keep its 53 nodes, in each of its ~15 processes that watch,
#: on the network threads the start-up of every component needs.
NODE_TOKENS = f"*/*/*/{EntityKind.NODE.value}/**"


def snapshot(session: Any, domain: int = 0, timeout: float = 1.0, tokens: str = "**") -> Snapshot:
    """Ask the network for the live tokens of ``domain`` and return the graph.

    Args:
        session: An open Zenoh session.
        domain: ROS domain id.
        timeout: Seconds the answers may take at most (the query ends when they are in).
        tokens: Which tokens, as a key expression below ``@ros2_lv/<domain>/`` (default all);
            the router answers only those (e.g. one service type's servers).
    """
    keys = ask_tokens(session, f"{PREFIX}/{domain}/{tokens}", timeout)
    return Snapshot(e for key in keys if (e := _parse(key)) is not None)


class Graph(GraphView):
    """A live graph, updated as tokens appear and vanish. Close it when done.

    Args:
        session: An open Zenoh session.
        domain: ROS domain id.
        on_change: Called (on a Zenoh thread) with ``(entity, alive)`` for every change.
        tokens: Which tokens, as a key expression below ``@ros2_lv/<domain>/`` (default
            all; :data:`NODE_TOKENS`: the nodes only).
    """

    def __init__(
        self,
        session: Any,
        domain: int = 0,
        on_change: Callable[[Entity, bool], None] | None = None,
        tokens: str = "**",
    ) -> None:
        self._lock = threading.Lock()
        self._entities: dict[str, Entity] = {}
        self._on_change = on_change
        self._changed = threading.Condition(self._lock)
        self._subscriber = follow_tokens(session, f"{PREFIX}/{domain}/{tokens}", self._on_token)

    def _on_token(self, sample: Any) -> None:
        import zenoh

        key = str(sample.key_expr)
        alive = sample.kind == zenoh.SampleKind.PUT
        entity = _parse(key)
        if entity is None:
            return
        with self._lock:
            if alive:
                self._entities[key] = entity
            else:
                self._entities.pop(key, None)
            self._changed.notify_all()
        if self._on_change is not None:
            try:
                self._on_change(entity, alive)
            except Exception:
                drops.drop("@ros2_lv", "callback_error")

    def entities(self) -> list[Entity]:
        """Every entity alive now."""
        with self._lock:
            return list(self._entities.values())

    def wait_for(self, predicate: Callable[[GraphView], bool], timeout: float) -> bool:
        """Block until ``predicate(self)`` holds or ``timeout`` passes; returns whether it held."""
        deadline = time.monotonic() + timeout
        with self._changed:
            while True:
                self._lock.release()
                try:
                    if predicate(self):
                        return True
                finally:
                    self._lock.acquire()
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._changed.wait(min(remaining, 0.1))

    def close(self) -> None:
        """Stop following the graph (idempotent)."""
        sub, self._subscriber = self._subscriber, None
        if sub is not None:
            try:
                sub.undeclare()
            except Exception as exc:
                swallowed("graph: liveliness subscriber not undeclared", exc)

    def __enter__(self) -> Graph:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
