"""rclpy topics for msctl's data plane: publishers and subscriptions that carry CDR bytes.

Part of :mod:`components.ros.plane` (which makes them from an :class:`RclpyNode`): messages
are published and taken serialized (rclpy's ``raw``) and coded by msctl's codec; a
subscription limited to some senders refuses a topic another node publishes on (see the
plane's module docstring).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Collection
from typing import TYPE_CHECKING, Any

from components.comm.names import qualify
from components.comm.qos import QoS
from components.comm.stats import drops
from components.comm.topics import INTRUDER
from components.comm.types import normalize_type_name, registry

#: What rclpy names a publisher whose participant's node names have not arrived yet (DDS
#: discovers an endpoint before the ``ros_discovery_info`` that names its node).
UNKNOWN_NODE = "_NODE_NAME_UNKNOWN_"
#: Seconds a guarded subscription trusts the publishers it read, their count unchanged: a
#: publisher replaced by another (the count the same) is read again within this.
PUBLISHERS_FRESH_S = 1.0

if TYPE_CHECKING:
    from components.ros.plane import RclpyNode

log = logging.getLogger("msctl.ros")


def qos_profile(qos: QoS) -> Any:
    """The rclpy ``QoSProfile`` of an msctl :class:`QoS`."""
    from rclpy.qos import (
        DurabilityPolicy,
        HistoryPolicy,
        QoSProfile,
        ReliabilityPolicy,
    )

    return QoSProfile(
        reliability=(
            ReliabilityPolicy.RELIABLE
            if qos.reliability == "reliable"
            else ReliabilityPolicy.BEST_EFFORT
        ),
        durability=(DurabilityPolicy.TRANSIENT_LOCAL if qos.latched else DurabilityPolicy.VOLATILE),
        history=HistoryPolicy.KEEP_LAST if qos.history == "keep_last" else HistoryPolicy.KEEP_ALL,
        depth=qos.depth,
    )


def msctl_qos(profile: Any) -> QoS:
    """The msctl :class:`QoS` of an rclpy ``QoSProfile`` (what a DDS endpoint offers)."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, ReliabilityPolicy

    keep_all = profile.history == HistoryPolicy.KEEP_ALL
    return QoS(
        reliability=(
            "best_effort" if profile.reliability == ReliabilityPolicy.BEST_EFFORT else "reliable"
        ),
        durability=(
            "transient_local"
            if profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
            else "volatile"
        ),
        history="keep_all" if keep_all else "keep_last",
        depth=max(int(profile.depth or 1), 1),
    )


class RclpyPublisher:
    """Publishes one topic as serialized CDR. Create through :meth:`RclpyNode.publisher`."""

    def __init__(self, node: RclpyNode, topic: str, msg_type: str, qos: QoS | None) -> None:
        from components.ros.typesupport import message_class

        self.qos = qos or QoS()
        self.topic = qualify(topic, node.namespace, node.name)
        self.type_name = normalize_type_name(msg_type)
        self._serialize = registry().serializer(self.type_name, stream=True)
        self._node = node
        self._pub = node.ros.create_publisher(
            message_class(self.type_name), self.topic, qos_profile(self.qos)
        )
        self.published = 0
        self._closed = False

    def publish(self, message: Any) -> None:
        """Serialize and send one message."""
        self.publish_raw(self._serialize(message))

    def publish_raw(self, payload: bytes) -> None:
        """Send CDR bytes (with their encapsulation header) as they are."""
        if self._closed:
            return
        self._pub.publish(bytes(payload))
        self.published += 1

    def subscribers(self) -> int:
        """Matched subscriptions on the graph."""
        return self._pub.get_subscription_count()

    def close(self) -> None:
        """Destroy the publisher (idempotent)."""
        if self._closed:
            return
        self._closed = True
        try:
            self._node.ros.destroy_publisher(self._pub)
        except Exception as exc:  # its node may be destroyed already
            log.debug("publisher %s: not destroyed: %s: %s", self.topic, type(exc).__name__, exc)


class RclpySubscription:
    """Receives one topic as CDR bytes; decodes them with msctl's codec unless ``raw``.

    With ``senders``, samples are taken only while every publisher on the topic belongs to
    one of those nodes (see the module: DDS does not name a sample's publisher to rclpy).
    ``guarded`` subscriptions change their senders with :meth:`allow`.

    Attributes:
        received: Samples delivered to the callback.
        senders: The nodes allowed to publish here (``None``: anyone).
    """

    def __init__(
        self,
        node: RclpyNode,
        topic: str,
        msg_type: str,
        callback: Callable[[Any], None],
        qos: QoS | None,
        raw: bool,
        senders: Collection[str] | None,
        guarded: bool,
    ) -> None:
        from components.ros.typesupport import message_class

        self.qos = qos or QoS()
        self.topic = qualify(topic, node.namespace, node.name)
        self.type_name = normalize_type_name(msg_type)
        self._deserialize = registry().deserializer(self.type_name, stream=True)
        self._node = node
        self._raw = raw
        self._callback = callback
        self._guarded = guarded or senders is not None
        self.senders: frozenset[str] | None = None if senders is None else frozenset(senders)
        self._why: str | None = None
        self._reason = INTRUDER
        self._lock = threading.Lock()
        self._seen_publishers = -1  # publisher count when the intruders were last read
        self._read_at = 0.0  # when (monotonic) they were read
        self._intruders: list[str] = []
        self._warned: set[str] = set()
        self.received = 0
        self._closed = False
        self._sub = node.ros.create_subscription(
            message_class(self.type_name),
            self.topic,
            self._on_sample,
            qos_profile(self.qos),
            raw=True,
        )

    def allow(
        self, senders: Collection[str] | None, why: str | None = None, reason: str = INTRUDER
    ) -> None:
        """Change who may publish here (a ``guarded`` subscription only).

        Args:
            senders: Node names, or ``<node>@<zid>`` (a claim's holder: on DDS the node name
                is what is checked); ``None``: anyone; empty: no one.
            why: What a refusal's WARN says after the node.
            reason: The drop reason refusals are counted under.

        Raises:
            RuntimeError: If the subscription was not made ``guarded``.
        """
        if not self._guarded:
            raise RuntimeError(f"{self.topic}: allow() needs a guarded subscription")
        with self._lock:
            self.senders = (
                None if senders is None else frozenset(s.split("@", 1)[0] for s in senders)
            )
            self._why, self._reason = why, reason
            self._seen_publishers = -1  # read the publishers again at the next sample
            self._warned.clear()

    def _refusing(self) -> list[str]:
        """The publishers' nodes that are not allowed senders (empty: take the sample)."""
        senders = self.senders
        if senders is None:
            return []
        ros = self._node.ros
        count = ros.count_publishers(self.topic)
        now = time.monotonic()
        with self._lock:
            if count != self._seen_publishers or now - self._read_at > PUBLISHERS_FRESH_S:
                infos = ros.get_publishers_info_by_topic(self.topic)
                nodes = {f"{i.node_namespace.rstrip('/')}/{i.node_name}" for i in infos}
                self._intruders = sorted(n for n in nodes if n not in senders)
                # A publisher whose node is not named yet is refused for now and read again
                # at the next sample: kept, it refused the module's own motor interface for
                # good once its name came (the count unchanged).
                named = not any(i.node_name == UNKNOWN_NODE for i in infos)
                self._seen_publishers = count if named else -1
                self._read_at = now
            return self._intruders

    def _on_sample(self, payload: bytes) -> None:
        if self._closed:
            return
        intruders = self._refusing()
        if intruders:
            self._refuse(intruders)
            return
        if self._raw:
            message: Any = payload
        else:
            try:
                message = self._deserialize(payload)
            except Exception as exc:
                drops.drop(self.topic, "malformed", f"{type(exc).__name__}: {exc}")
                return
        self.received += 1
        try:
            self._callback(message)
        except Exception:
            drops.drop(self.topic, "callback_error")
            log.exception("subscription callback on %s failed", self.topic)

    def _refuse(self, intruders: list[str]) -> None:
        drops.drop(self.topic, self._reason, quiet=True)
        with self._lock:
            new = [n for n in intruders if n not in self._warned]
            self._warned.update(new)
        for node in new:
            why = self._why or f"only {', '.join(sorted(self.senders or ()))} may publish here"
            log.warning(
                "%s: refused every sample while node %s publishes here too (DDS does not say "
                "which publisher sent a sample): %s",
                self.topic,
                node,
                why,
            )

    def close(self) -> None:
        """Destroy the subscription (idempotent)."""
        if self._closed:
            return
        self._closed = True
        try:
            self._node.ros.destroy_subscription(self._sub)
        except Exception as exc:  # its node may be destroyed already
            log.debug("subscription %s: not destroyed: %s: %s", self.topic, type(exc).__name__, exc)
