"""The bridge's decisions, pure: what to relay, which way, with what QoS, and its status.

The relays themselves (:mod:`components.bridge.relay`) are I/O: a Zenoh session on one side,
an rclpy participant on the other. They ask this module which topics and services the user's
selection takes, turn each side's offered QoS into the other side's, and keep the counts the
``bridge`` component reports on ``diagnostics``.
"""

from __future__ import annotations

import fnmatch
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

from components.comm.qos import QoS
from components.config import require
from components.executor.core import Core
from components.messages import Level, diagnostic_array, diagnostic_status
from components.roles import RULES, Role

#: Topics every ROS 2 node has, never bridged by ``--all`` (each side has its own).
ROS_TOPICS = frozenset({"/rosout", "/parameter_events"})
#: Services every rclpy node serves, never bridged by ``--all``.
ROS_SERVICE_SUFFIXES = (
    "/describe_parameters",
    "/get_parameter_types",
    "/get_parameters",
    "/get_type_description",
    "/list_parameters",
    "/set_parameters",
    "/set_parameters_atomically",
    "/get_logger_levels",
    "/set_logger_levels",
)
#: msctl's control plane (supervisors, agents): bridged only when named, never by ``--all``.
CONTROL_PREFIX = "/msctl/"


class Direction(Enum):
    """Which way a relay carries data."""

    TO_ROS = "msctl -> ROS"  #: from msctl's Zenoh plane to the DDS graph
    TO_MSCTL = "ROS -> msctl"  #: from the DDS graph to msctl's Zenoh plane


def _hidden(name: str) -> bool:
    return any(part.startswith("_") for part in name.split("/") if part)


def _split(text: str) -> tuple[str, ...]:
    return tuple(p for p in text.replace(",", " ").split() if p)


@dataclass(frozen=True)
class Selection:
    """What a bridge relays.

    Attributes:
        topics: Topic names or shell patterns (``/limb1/*``) to relay.
        services: Service names or patterns to relay.
        all_topics: Relay every topic (but ROS's own ``/rosout`` and ``/parameter_events``,
            and hidden names).
        all_services: Relay every service (but rclpy's parameter and type services, msctl's
            control services, and hidden names).
    """

    topics: tuple[str, ...] = ()
    services: tuple[str, ...] = ()
    all_topics: bool = False
    all_services: bool = False

    def __post_init__(self) -> None:
        for name in (*self.topics, *self.services):
            if not name.startswith("/"):
                raise ValueError(f"{name!r}: give a fully qualified name, like /limb1/joint_read")
        if not (self.topics or self.services or self.all_topics or self.all_services):
            raise ValueError("nothing to bridge: name --topics or --services, or give --all")

    @classmethod
    def from_text(cls, topics: str, services: str) -> Selection:
        """A selection from space- or comma-separated lists; ``*`` alone means everything."""
        named_topics, named_services = _split(topics), _split(services)
        return cls(
            topics=tuple(t for t in named_topics if t != "*"),
            services=tuple(s for s in named_services if s != "*"),
            all_topics="*" in named_topics,
            all_services="*" in named_services,
        )

    def takes_topic(self, topic: str) -> bool:
        """Whether ``topic`` is relayed."""
        if any(fnmatch.fnmatchcase(topic, p) for p in self.topics):
            return True
        return self.all_topics and topic not in ROS_TOPICS and not _hidden(topic)

    def takes_service(self, service: str) -> bool:
        """Whether ``service`` is relayed."""
        if any(fnmatch.fnmatchcase(service, p) for p in self.services):
            return True
        return (
            self.all_services
            and not service.endswith(ROS_SERVICE_SUFFIXES)
            and not service.startswith(CONTROL_PREFIX)
            and not _hidden(service)
        )


def refused_into_msctl(topic: str, role: Role | None) -> str:
    """Why a ROS publisher's ``topic`` is not carried into msctl's plane ("" when it is),
    from the role msctl's interfaces declare for it (:mod:`components.roles`).

    Raw motor commands and feedback come only from the module's own components (their
    senders are checked by node at run time, and the bridge is not one): never from ROS, even
    when named. Commands stay bridged (a ROS node moving a joint through ``joint_set`` is
    what the bridge is for); the joint managers keep them on the claim holder.
    """
    if role is None or not RULES[role].own_senders:
        return ""
    return f"{role.value} (only {RULES[role].who} publishes it): never bridged from ROS"


def relay_qos(offered: Iterable[QoS]) -> QoS:
    """The QoS a relay uses on both sides, from what the source's publishers offer.

    Its subscription on the source side must match every publisher (a reliable reader gets
    nothing from a best-effort writer, a transient-local one nothing from a volatile one), and
    its publisher on the other side offers the same, so the far subscribers match as they
    would the source: best effort if any source is, transient local only if all are, the
    deepest history.
    """
    offers = list(offered) or [QoS()]
    reliable = all(q.reliability == "reliable" for q in offers)
    latched = all(q.latched for q in offers)
    depth = max(q.depth for q in offers if q.history == "keep_last") if offers else 10
    return QoS(
        reliability="reliable" if reliable else "best_effort",
        durability="transient_local" if latched else "volatile",
        depth=max(1, min(depth, 100)),
    )


@dataclass
class RelayStatus:
    """One relay's counts."""

    name: str
    type_name: str
    direction: Direction
    kind: str  # "topic" or "service"
    relayed: int = 0
    echoes: int = 0  # samples of the bridge's own, seen coming back and dropped
    failed: int = 0


@dataclass
class BridgeStatus:
    """What a bridge does now (a snapshot)."""

    relays: list[RelayStatus] = field(default_factory=list)
    skipped: dict[str, str] = field(default_factory=dict)  # name -> why, said once
    error: str = ""


@dataclass(frozen=True)
class BridgeConfig:
    """A ``bridge`` component's parameters, from the station's data.

    Attributes:
        topics: Topic names or patterns to relay, space- or comma-separated; ``*``: all.
        services: Service names or patterns to relay; ``*``: all.
        discovery_period: Seconds between two looks at both graphs for new topics.
        call_timeout: Seconds a relayed service call waits for the far server.
    """

    topics: str = "*"
    services: str = ""
    discovery_period: float = 0.5
    call_timeout: float = 5.0

    def __post_init__(self) -> None:
        require(self, positive=("discovery_period", "call_timeout"))
        self.selection()

    def selection(self) -> Selection:
        """What this configuration relays."""
        return Selection.from_text(self.topics, self.services)


class BridgeCore(Core):
    """The bridge component's logic: report the relays on diagnostics every second.

    Args:
        name: The component's name.
        status: Returns the bridge's current :class:`BridgeStatus`.
        hardware_id: The station's host, named in the diagnostic.
    """

    def __init__(
        self, name: str, status: Callable[[], BridgeStatus], hardware_id: str = ""
    ) -> None:
        super().__init__(name)
        self._status = status
        self._hardware_id = hardware_id

    def tick(self, now: float) -> None:
        """Publish the bridge's status."""
        level, message, values = report(self._status())
        status = diagnostic_status(self.name, level, message, self._hardware_id, values)
        self.publish("diagnostics", diagnostic_array([status], self.stamp(now)))


def report(status: BridgeStatus) -> tuple[Level, str, dict[str, Any]]:
    """Level, one line and key/values of a bridge's status."""
    to_ros = [r for r in status.relays if r.direction is Direction.TO_ROS]
    to_msctl = [r for r in status.relays if r.direction is Direction.TO_MSCTL]
    values: dict[str, Any] = {
        f"{r.kind} {r.name} ({r.direction.value})": f"{r.relayed} relayed, {r.failed} failed"
        for r in status.relays
    }
    values.update({f"skipped {name}": why for name, why in status.skipped.items()})
    if status.error:
        return Level.ERROR, f"not bridging: {status.error}", values
    line = (
        f"{len(to_ros)} relay(s) msctl -> ROS, {len(to_msctl)} ROS -> msctl, "
        f"{sum(r.relayed for r in status.relays)} relayed"
    )
    if status.skipped:
        return Level.WARN, f"{line}; {len(status.skipped)} skipped (see values)", values
    return Level.OK, line, values
