"""The bridge between msctl's Zenoh data plane and a DDS ROS 2 graph: relays, both ways.

A :class:`Bridge` is one node on each side (``msctl_bridge`` by default): a Zenoh node on
msctl's session and an rclpy node on its own DDS participant. Every ``discovery_period`` it
reads both graphs and keeps one relay per selected topic and direction, and one per service:

* a topic published on Zenoh (by anyone but the bridge) gets a DDS publisher fed by a Zenoh
  subscriber; one published on DDS gets a Zenoh publisher fed by a raw rclpy subscription;
* a service served on Zenoh gets a DDS server that forwards each request as a Zenoh query;
  one served on DDS gets a Zenoh queryable that forwards each request through an rclpy client.

Payloads are CDR bytes end to end: Zenoh samples go out through ``publish`` of serialized
bytes, DDS samples are taken serialized (rclpy's ``raw``), service requests and responses
through msctl's run-time type support (:mod:`components.ros.typesupport`); nothing is decoded
or encoded again. QoS follows what the source's publishers offer
(:func:`~components.bridge.core.relay_qos`). A relay stops when its source leaves the graph.

Loop prevention, so a message bridged one way is never bridged back:

* the bridge's own endpoints are left out of both graphs it reads;
* a Zenoh sample carries its publisher's GID (the rmw_zenoh attachment): samples from the
  bridge's own Zenoh publishers are dropped on arrival;
* a DDS sample carries no publisher identity rclpy can read, but its writer's sequence number:
  each relay publishing on DDS keeps a short ledger of (sequence number, payload hash) of what
  it wrote, and the relay reading that topic drops a sample that matches it. Only a sample of
  another DDS writer with the same sequence number and the same bytes would be mistaken.

A type one side cannot carry (unknown to msctl's type registry, a hash that differs from the
registry's, two types on one name) is reported once and skipped.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from components.bridge.core import (
    BridgeStatus,
    Direction,
    RelayStatus,
    Selection,
    refused_into_msctl,
    relay_qos,
)
from components.bridge.links import (
    Ledger,
    ServiceToMsctl,
    ServiceToRos,
    TopicToMsctl,
    TopicToRos,
)
from components.comm.graph import Graph
from components.comm.liveliness import EntityKind
from components.comm.node import Node
from components.comm.qos import QoS
from components.comm.types import UnknownTypeError, normalize_type_name, registry
from components.roles import declared_names, role_of

log = logging.getLogger("msctl.bridge")

#: Threads answering Zenoh requests for DDS servers (each waits for its DDS answer).
CALL_THREADS = 4


class Bridge:
    """Relays between msctl's Zenoh data plane and a DDS ROS 2 graph until closed.

    Args:
        session: An open Zenoh session on msctl's data plane (the caller closes it).
        selection: What to relay.
        name: The bridge's node name on both sides.
        namespace: Its namespace on both sides.
        domain: msctl's ROS domain on Zenoh (the first part of every key).
        zenoh_node: The bridge's node on Zenoh (default: a new one, ``name`` in ``namespace``,
            closed with the bridge).
        ros_node: Its rclpy node (default: a new one on ``plane``, closed with the bridge).
        plane: The rclpy plane for the DDS side (default: a new one on ``ros_domain``,
            closed with the bridge).
        ros_domain: The DDS graph's domain when the bridge makes its own plane
            (``None``: ``ROS_DOMAIN_ID``).
        discovery_period: Seconds between two looks at both graphs.
        call_timeout: Seconds a relayed service call waits for the far server.
        on_event: Called with one line for each relay started or stopped and each skip.

    Raises:
        RclpyUnavailable: If rclpy cannot be imported.
    """

    def __init__(
        self,
        session: Any,
        selection: Selection,
        name: str = "msctl_bridge",
        namespace: str = "/",
        domain: int = 0,
        zenoh_node: Node | None = None,
        ros_node: Any = None,
        plane: Any = None,
        ros_domain: int | None = None,
        discovery_period: float = 0.5,
        call_timeout: float = 5.0,
        on_event: Callable[[str], None] | None = None,
    ) -> None:
        from components.ros.plane import RclpyPlane

        self.session = session
        self.selection = selection
        # What each of msctl's inputs is, read once: a ROS publisher never speaks for a
        # robot's motors (components.bridge.core.refused_into_msctl).
        self._roles = declared_names()
        self.domain = domain
        self.call_timeout = call_timeout
        self.discovery_period = discovery_period
        self._on_event = on_event or (lambda line: log.info("%s", line))
        self._owned: list[Any] = []
        self._owns_plane = plane is None and ros_node is None
        self.plane = ros_node.plane if ros_node is not None else plane
        if self.plane is None:
            self.plane = RclpyPlane(ros_domain)
        self.own_gids: set[bytes] = set()
        self.calls = ThreadPoolExecutor(CALL_THREADS, thread_name_prefix="bridge-call")
        self._ledgers: dict[str, Ledger] = defaultdict(Ledger)
        self._relays: dict[tuple[str, str, Direction], Any] = {}
        self._skipped: dict[str, str] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.error = ""
        try:
            self.zenoh = zenoh_node
            if self.zenoh is None:
                self.zenoh = Node(session, name, namespace, domain=domain)
                self._owned.append(self.zenoh)
            self.ros = ros_node
            if self.ros is None:
                self.ros = self.plane.node(name, namespace)
                self._owned.append(self.ros)
            self._graph = Graph(session, domain)
            self._owned.append(self._graph)
        except Exception:
            self.close()
            raise
        self._thread = threading.Thread(target=self._run, name="bridge", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ discovery
    def ledger(self, topic: str) -> Ledger:
        """The ledger of what the bridge wrote on DDS topic ``topic``."""
        return self._ledgers[topic]

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.sync()
                self.error = ""
            except Exception as exc:  # one bad look must not end the bridge
                if self._stop.is_set():
                    return
                self.error = f"{type(exc).__name__}: {exc}"
                log.exception("bridge: reading the graphs failed")
            self._stop.wait(self.discovery_period)

    def _skip(self, name: str, why: str) -> None:
        """Report once (again only if the reason changes) and skip ``name``."""
        if self._skipped.get(name) == why:
            return
        self._skipped[name] = why
        self._on_event(f"skipped {name}: {why}")

    def _zenoh_side(self) -> tuple[dict[str, list[Any]], dict[str, set[tuple[str, str]]]]:
        """Zenoh publishers by topic and server types by service, the bridge's left out."""
        publishers: dict[str, list[Any]] = defaultdict(list)
        servers: dict[str, set[tuple[str, str]]] = defaultdict(set)
        own = self.zenoh.identity.node_key
        for entity in self._graph.entities():
            if entity.node_key == own or entity.topic is None or entity.type_name is None:
                continue
            if entity.kind is EntityKind.PUBLISHER and self.selection.takes_topic(entity.topic):
                publishers[entity.topic].append(entity)
            elif entity.kind is EntityKind.SERVICE and self.selection.takes_service(entity.topic):
                servers[entity.topic].add((entity.type_name, entity.type_hash or ""))
        return publishers, servers

    def _ros_side(self) -> tuple[dict[str, list[Any]], dict[str, set[str]]]:
        """DDS publishers by topic and server types by service, the bridge's left out."""
        ros = self.ros.ros
        own = (self.ros.namespace, self.ros.name)

        def theirs(namespace: str, name: str) -> bool:
            return (namespace, name) != own and not name.startswith("_")

        publishers: dict[str, list[Any]] = {}
        for topic, _ in ros.get_topic_names_and_types():
            if not self.selection.takes_topic(topic):
                continue
            infos = [
                info
                for info in ros.get_publishers_info_by_topic(topic)
                if theirs(info.node_namespace, info.node_name)
            ]
            if infos:
                publishers[topic] = infos
        servers: dict[str, set[str]] = defaultdict(set)
        for name, namespace in ros.get_node_names_and_namespaces():
            if not theirs(namespace, name):
                continue
            try:
                listing = ros.get_service_names_and_types_by_node(name, namespace)
            except Exception:  # left between the two calls
                continue
            for service, types in listing:
                if self.selection.takes_service(service):
                    servers[service].update(types)
        return publishers, servers

    def _known(self, name: str, type_name: str, type_hash: str | None, side: str) -> bool:
        """Whether both sides can carry ``type_name`` (else reported once and skipped)."""
        reg = registry()
        if not reg.known(type_name):
            other = "ROS (DDS)" if side == "msctl" else "msctl"
            self._skip(
                name,
                f"{type_name} is known on the {side} side only: {other} has no definition of "
                "it (register it with msctl's type registry to bridge it)",
            )
            return False
        if type_hash and reg.type_hash(type_name) != type_hash:
            self._skip(
                name,
                f"{type_name} on msctl's side has hash {type_hash}, another version than "
                f"{reg.type_hash(type_name)} the bridge knows",
            )
            return False
        return True

    def sync(self) -> None:
        """Read both graphs once; start and stop relays to match them."""
        zpublishers, zservers = self._zenoh_side()
        dpublishers, dservers = self._ros_side()
        wanted: dict[tuple[str, str, Direction], Callable[[], Any]] = {}
        for topic, entities in zpublishers.items():
            types = {(e.type_name, e.type_hash) for e in entities}
            ros_types = {i.topic_type for i in dpublishers.get(topic, ())}
            if len(types) > 1:
                self._skip(topic, f"published with several types on msctl's side: {types}")
                continue
            ((type_name, type_hash),) = types
            if ros_types and ros_types != {type_name}:
                self._skip(topic, f"{type_name} on msctl's side, {sorted(ros_types)} on ROS's")
                continue
            if not self._known(topic, type_name, type_hash, "msctl"):
                continue
            qos = relay_qos(_decode_qos(e.qos) for e in entities)
            wanted[("topic", topic, Direction.TO_ROS)] = lambda t=topic, n=type_name, q=qos: (
                TopicToRos(self, t, n, q)
            )
        for topic, infos in dpublishers.items():
            refused = refused_into_msctl(topic, role_of(topic, self._roles))
            if refused:
                self._skip(topic, refused)
                continue
            names = {_type_name(i.topic_type) for i in infos}
            if len(names) > 1 or None in names:
                self._skip(
                    topic,
                    f"{', '.join(sorted({i.topic_type for i in infos}))} on ROS's side: "
                    "known on the ROS side only",
                )
                continue
            (type_name,) = names
            assert type_name is not None
            if not self._known(topic, type_name, None, "ROS (DDS)"):
                continue
            from components.ros.plane_topics import msctl_qos

            qos = relay_qos(msctl_qos(i.qos_profile) for i in infos)
            wanted[("topic", topic, Direction.TO_MSCTL)] = lambda t=topic, n=type_name, q=qos: (
                TopicToMsctl(self, t, n, q)
            )
        for service, types in zservers.items():
            if len(types) > 1:
                self._skip(service, f"served with several types on msctl's side: {types}")
                continue
            ((type_name, type_hash),) = types
            if service in dservers:
                continue  # served on both sides: each side calls its own
            if not self._known(service, type_name, type_hash, "msctl"):
                continue
            wanted[("service", service, Direction.TO_ROS)] = lambda s=service, n=type_name: (
                ServiceToRos(self, s, n)
            )
        for service, ros_types in dservers.items():
            if service in zservers:
                continue
            names = {_type_name(t) for t in ros_types}
            if len(names) > 1 or None in names:
                self._skip(
                    service, f"{', '.join(sorted(ros_types))} on ROS's side: known there only"
                )
                continue
            (type_name,) = names
            assert type_name is not None
            if not self._known(service, type_name, None, "ROS (DDS)"):
                continue
            wanted[("service", service, Direction.TO_MSCTL)] = lambda s=service, n=type_name: (
                ServiceToMsctl(self, s, n)
            )
        self._apply(wanted)

    def _apply(self, wanted: dict[tuple[str, str, Direction], Callable[[], Any]]) -> None:
        with self._lock:
            if self._stop.is_set():
                return
            gone = [key for key in self._relays if key not in wanted]
            for key in gone:
                relay = self._relays.pop(key)
                relay.close()
                self._on_event(f"stopped {key[0]} {key[1]} ({key[2].value}): its source left")
            for key, make in wanted.items():
                if key in self._relays:
                    continue
                try:
                    relay = make()
                except Exception as exc:
                    self._skip(key[1], f"cannot relay it: {type(exc).__name__}: {exc}")
                    continue
                self._relays[key] = relay
                self._skipped.pop(key[1], None)
                status = relay.status
                self._on_event(f"bridging {key[0]} {key[1]} ({status.type_name}) {key[2].value}")

    # ------------------------------------------------------------------ state
    def status(self) -> BridgeStatus:
        """What the bridge relays now, with counts, and what it skipped."""
        with self._lock:
            relays = [relay.status for relay in self._relays.values()]
        return BridgeStatus(
            relays=[RelayStatus(**vars(r)) for r in relays],
            skipped=dict(self._skipped),
            error=self.error,
        )

    def wait_for(self, predicate: Callable[[BridgeStatus], bool], timeout: float) -> bool:
        """Block until ``predicate(status)`` holds or ``timeout`` passes."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate(self.status()):
                return True
            time.sleep(0.05)
        return predicate(self.status())

    def close(self) -> None:
        """Stop every relay and leave both graphs (idempotent)."""
        self._stop.set()
        thread = getattr(self, "_thread", None)
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=10.0)
        with self._lock:
            relays, self._relays = list(self._relays.values()), {}
        for relay in relays:
            relay.close()
        self.calls.shutdown(wait=False, cancel_futures=True)
        for thing in reversed(self._owned):
            try:
                thing.close()
            except Exception as exc:  # the others are closed still; say which one failed
                log.warning("bridge: closing %r failed: %s: %s", thing, type(exc).__name__, exc)
        if self._owns_plane:
            self.plane.close()

    def __enter__(self) -> Bridge:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _decode_qos(text: str | None) -> QoS:
    if not text:
        return QoS()
    try:
        return QoS.decode(text)
    except ValueError:
        return QoS()


def _type_name(ros_type: str) -> str | None:
    try:
        return normalize_type_name(ros_type)
    except UnknownTypeError:
        return None
