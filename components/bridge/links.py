"""The bridge's relays: one topic or one service, in one direction, CDR bytes end to end.

Made and closed by :class:`~components.bridge.relay.Bridge` (see its module docstring for the
loop prevention the ledger and the publisher GIDs serve).
"""

from __future__ import annotations

import logging
import threading
from collections import OrderedDict
from typing import TYPE_CHECKING, Any

from components.bridge.core import Direction, RelayStatus
from components.comm.attachment import CURRENT_SIZE, Attachment, AttachmentError
from components.comm.qos import QoS
from components.comm.services import ServiceClient, ServiceError, ServiceServer
from components.comm.topics import Publisher, data_key

if TYPE_CHECKING:
    from components.bridge.relay import Bridge

log = logging.getLogger("msctl.bridge")

#: Own DDS publications remembered per topic, to recognise them coming back.
LEDGER_SIZE = 4096
#: History depth of the relays' DDS subscriptions (at least).
SOURCE_DEPTH = 100


class Ledger:
    """What the bridge wrote on one DDS topic: writer sequence number -> payload hash."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._written: OrderedDict[int, int] = OrderedDict()

    def wrote(self, sequence: int, payload: bytes) -> None:
        with self._lock:
            self._written[sequence] = hash(payload)
            while len(self._written) > LEDGER_SIZE:
                self._written.popitem(last=False)

    def ours(self, sequence: int | None, payload: bytes) -> bool:
        """Whether a sample is one the bridge wrote (forgotten once recognised)."""
        if sequence is None:
            return False
        with self._lock:
            if self._written.get(sequence) != hash(payload):
                return False
            del self._written[sequence]
            return True


def _gid(attachment: Any) -> bytes | None:
    if attachment is None:
        return None
    raw = attachment.to_bytes()
    if len(raw) == CURRENT_SIZE and raw[16] == 16:
        return raw[17:]
    try:
        return Attachment.decode(raw).gid
    except AttachmentError:
        return None


class TopicToRos:
    """Zenoh publishers of one topic -> a DDS publisher."""

    def __init__(self, bridge: Bridge, topic: str, type_name: str, qos: QoS) -> None:
        import zenoh
        import zenoh.ext

        from components.ros.plane_topics import qos_profile
        from components.ros.typesupport import message_class

        self.status = RelayStatus(topic, type_name, Direction.TO_ROS, "topic")
        self._bridge = bridge
        self._ledger = bridge.ledger(topic)
        self._lock = threading.Lock()
        self._written = 0
        self._closed = False
        self._publisher = bridge.ros.ros.create_publisher(
            message_class(type_name), topic, qos_profile(qos)
        )
        key = data_key(bridge.domain, topic, type_name)
        if qos.latched:
            self._subscriber = zenoh.ext.declare_advanced_subscriber(
                bridge.session,
                key,
                self._on_sample,
                history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=qos.depth),
                subscriber_detection=True,
            )
        else:
            self._subscriber = bridge.session.declare_subscriber(key, self._on_sample)

    def _on_sample(self, sample: Any) -> None:
        if self._closed:
            return
        if _gid(sample.attachment) in self._bridge.own_gids:
            self.status.echoes += 1  # the bridge's own relay from DDS: never back
            return
        payload = sample.payload.to_bytes()
        try:
            with self._lock:  # the ledger's numbers are the DDS writer's: one at a time
                self._ledger.wrote(self._written + 1, payload)
                self._publisher.publish(payload)
                self._written += 1
        except Exception as exc:
            self.status.failed += 1
            log.debug("relaying %s to ROS failed: %s", self.status.name, exc)
            return
        self.status.relayed += 1

    def close(self) -> None:
        self._closed = True
        try:
            self._subscriber.undeclare()
        except Exception as exc:  # the session may be closed already
            log.debug("relay %s: subscriber not undeclared: %s", self.status.name, exc)
        try:
            self._bridge.ros.ros.destroy_publisher(self._publisher)
        except Exception as exc:
            log.debug("relay %s: ROS publisher not destroyed: %s", self.status.name, exc)


class TopicToMsctl:
    """DDS publishers of one topic -> a Zenoh publisher."""

    def __init__(self, bridge: Bridge, topic: str, type_name: str, qos: QoS) -> None:
        from components.ros.plane_topics import qos_profile
        from components.ros.typesupport import message_class

        self.status = RelayStatus(topic, type_name, Direction.TO_MSCTL, "topic")
        self._bridge = bridge
        self._ledger = bridge.ledger(topic)
        self._closed = False
        self._publisher = Publisher(bridge.zenoh, topic, type_name, qos)
        bridge.own_gids.add(self._publisher.gid)
        # Deeper than the publishers' history: rclpy takes one sample per turn of its
        # executor, and a burst (or the bridge's own samples coming back) must not push the
        # source's out before they are relayed. Matching does not depend on depth.
        reader = qos._replace(depth=max(qos.depth, SOURCE_DEPTH))
        self._subscription = bridge.ros.ros.create_subscription(
            message_class(type_name), topic, self._on_sample, qos_profile(reader), raw=True
        )

    def _on_sample(self, payload: bytes, info: dict[str, Any]) -> None:
        if self._closed:
            return
        if self._ledger.ours(info.get("publication_sequence_number"), payload):
            self.status.echoes += 1  # the bridge's own relay from Zenoh: never back
            return
        try:
            self._publisher.publish_raw(payload)
        except Exception as exc:
            self.status.failed += 1
            log.debug("relaying %s to msctl failed: %s", self.status.name, exc)
            return
        self.status.relayed += 1

    def close(self) -> None:
        self._closed = True
        try:
            self._bridge.ros.ros.destroy_subscription(self._subscription)
        except Exception as exc:  # the ROS node may be destroyed already
            log.debug("relay %s: ROS subscription not destroyed: %s", self.status.name, exc)
        self._bridge.own_gids.discard(self._publisher.gid)
        self._publisher.close()


class ServiceToRos:
    """A Zenoh server -> a DDS server forwarding each request as a Zenoh query."""

    def __init__(self, bridge: Bridge, service: str, type_name: str) -> None:
        from components.ros.typesupport import service_class

        self.status = RelayStatus(service, type_name, Direction.TO_ROS, "service")
        self._bridge = bridge
        self._client = ServiceClient(bridge.zenoh, service, type_name)
        self._class = service_class(type_name)
        self._server = bridge.ros.ros.create_service(
            self._class, service, self._on_request, callback_group=bridge.ros.requests
        )

    def _on_request(self, request: Any, response: Any) -> Any:
        from components.ros.plane_services import failure_response

        del response
        try:
            answer = self._client.call_raw(request.cdr, self._bridge.call_timeout)
        except ServiceError as exc:
            self.status.failed += 1
            return self._class.Response(failure_response(self._client.parts.response, str(exc)))
        self.status.relayed += 1
        return self._class.Response(answer)

    def close(self) -> None:
        try:
            self._bridge.ros.ros.destroy_service(self._server)
        except Exception as exc:  # the ROS node may be destroyed already
            log.debug("relay %s: ROS server not destroyed: %s", self.status.name, exc)
        self._client.close()


class ServiceToMsctl:
    """A DDS server -> a Zenoh queryable forwarding each request through an rclpy client."""

    def __init__(self, bridge: Bridge, service: str, type_name: str) -> None:
        self.status = RelayStatus(service, type_name, Direction.TO_MSCTL, "service")
        self._bridge = bridge
        self._client = bridge.ros.client(service, type_name)
        self._server = ServiceServer(
            bridge.zenoh, service, type_name, self._on_request, deferred=True, raw=True
        )

    def _on_request(self, pending: Any) -> None:
        # Off the Zenoh thread: the answer takes a DDS round trip.
        self._bridge.calls.submit(self._forward, pending)

    def _forward(self, pending: Any) -> None:
        try:
            answer = self._client.call_raw(pending.request, self._bridge.call_timeout)
        except ServiceError as exc:
            self.status.failed += 1
            pending.fail(f"{self.status.name} on ROS: {exc}")
            return
        except Exception as exc:  # the DDS side is going down
            self.status.failed += 1
            pending.fail(f"{self.status.name} on ROS: {type(exc).__name__}: {exc}")
            return
        pending.reply(answer)
        self.status.relayed += 1

    def close(self) -> None:
        self._server.close()
        self._client.close()
