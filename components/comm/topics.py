"""Publishers and subscriptions of ROS 2 topics, carried on Zenoh as rmw_zenoh carries them.

Data key: ``<domain>/<topic without outer slashes>/<pkg>::msg::dds_::<Name>_/<RIHS01 hash>``;
payload: CDR with its 4-byte encapsulation header; attachment: see ``attachment.py``.
Latched (transient-local) topics use Zenoh's advanced publisher (with a cache of ``depth``
samples and publisher detection) and advanced subscriber (querying late publishers' history),
as rmw_zenoh does, so a late subscriber gets the last sample.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from components.comm.attachment import (
    CURRENT_FORMAT,
    CURRENT_SIZE,
    Attachment,
    AttachmentError,
    gid_of,
)
from components.comm.liveliness import PREFIX, Entity, EntityKind, TokenError
from components.comm.names import key_name, mangle, qualify
from components.comm.qos import QoS
from components.comm.stats import drops, log
from components.comm.types import dds_type_name, normalize_type_name, registry

if TYPE_CHECKING:
    from components.comm.node import Node


_pack_attachment = CURRENT_FORMAT.pack


def data_key(domain: int, topic: str, type_name: str) -> str:
    """The Zenoh key expression that carries a topic's samples."""
    reg = registry()
    return f"{domain}/{key_name(topic)}/{dds_type_name(type_name)}/{reg.type_hash(type_name)}"


class Publisher:
    """Publishes one topic. Create through :meth:`Node.publisher`.

    Attributes:
        topic: Fully qualified topic name.
        type_name: Canonical message type.
        key: The Zenoh data key.
        gid: This publisher's 16-byte GID (from its liveliness token).
    """

    def __init__(self, node: Node, topic: str, msg_type: str, qos: QoS | None = None) -> None:
        import zenoh
        import zenoh.ext

        self.qos = qos or QoS()
        self.topic = qualify(topic, node.namespace, node.name)
        self.type_name = normalize_type_name(msg_type)
        reg = registry()
        self._serialize = reg.serializer(self.type_name)
        self.key = data_key(node.domain, self.topic, self.type_name)
        self.entity = node.entity(
            EntityKind.PUBLISHER,
            self.topic,
            self.type_name,
            reg.type_hash(self.type_name),
            self.qos,
        )
        self.token_key = self.entity.token()
        self.gid = gid_of(self.token_key)
        self._seq = itertools.count(1)
        reliability = (
            zenoh.Reliability.RELIABLE
            if self.qos.reliability == "reliable"
            else zenoh.Reliability.BEST_EFFORT
        )
        # Reliable topics must not lose samples on our side: block on congestion rather than
        # drop. Best-effort topics (sensor streams) drop, so a slow link never stalls a loop.
        congestion = (
            zenoh.CongestionControl.BLOCK
            if self.qos.reliability == "reliable"
            else zenoh.CongestionControl.DROP
        )
        session = node.session
        if self.qos.latched:
            self._zpub = zenoh.ext.declare_advanced_publisher(
                session,
                self.key,
                reliability=reliability,
                congestion_control=congestion,
                cache=zenoh.ext.CacheConfig(max_samples=self.qos.depth),
                publisher_detection=True,
            )
        else:
            self._zpub = session.declare_publisher(
                self.key, reliability=reliability, congestion_control=congestion
            )
        self._token = session.liveliness().declare_token(self.token_key)
        self._closed = False

    def publish(self, message: Any) -> None:
        """Serialize and send one message."""
        self.publish_raw(self._serialize(message))

    def publish_raw(self, payload: bytes) -> None:
        """Send already-serialized CDR bytes (with header) with a fresh attachment."""
        # Packed directly (not through Attachment) because this runs for every sample.
        attachment = _pack_attachment(next(self._seq), time.time_ns(), 16, self.gid)
        self._zpub.put(payload, attachment=attachment)

    def close(self) -> None:
        """Undeclare the publisher and its token (idempotent)."""
        if self._closed:
            return
        self._closed = True
        for thing in (self._token, self._zpub):
            try:
                thing.undeclare()
            except Exception:  # the session may already be closed
                pass


class Subscription:
    """Receives one topic. Create through :meth:`Node.subscription`.

    The callback runs on a Zenoh thread with the decoded message. Samples whose payload or
    attachment do not decode are dropped and counted in :data:`components.comm.stats.drops`
    under the topic name; a publisher of another type (or another version of the type) on
    the topic is counted there once, from its liveliness token, naming its node. An
    exception in the callback is logged and counted, and never reaches Zenoh.

    Attributes:
        received: Samples delivered to the callback.
        last_attachment: The attachment of the latest good sample, if it had one.
    """

    def __init__(
        self,
        node: Node,
        topic: str,
        msg_type: str,
        callback: Callable[[Any], None],
        qos: QoS | None = None,
        raw: bool = False,
    ) -> None:
        import zenoh.ext

        self.qos = qos or QoS()
        self.topic = qualify(topic, node.namespace, node.name)
        self.type_name = normalize_type_name(msg_type)
        reg = registry()
        self._deserialize = reg.deserializer(self.type_name)
        self._raw = raw
        self._callback = callback
        self.key = data_key(node.domain, self.topic, self.type_name)
        self.entity = node.entity(
            EntityKind.SUBSCRIPTION,
            self.topic,
            self.type_name,
            reg.type_hash(self.type_name),
            self.qos,
        )
        self.token_key = self.entity.token()
        self.type_hash = reg.type_hash(self.type_name)
        self.received = 0
        self._last_attachment: bytes | None = None
        # The exact key, as rmw_zenoh subscribes: a wildcard here (to see samples of other
        # types) cost ~20 us a round trip. Publishers of another type, or of another version
        # of the type, are found from their liveliness tokens instead (_on_publisher_token),
        # which also names the node at fault.
        session = node.session
        if self.qos.latched:
            self._zsub = zenoh.ext.declare_advanced_subscriber(
                session,
                self.key,
                self._on_sample,
                history=zenoh.ext.HistoryConfig(
                    detect_late_publishers=True, max_samples=self.qos.depth
                ),
                subscriber_detection=True,
            )
        else:
            self._zsub = session.declare_subscriber(self.key, self._on_sample)
        self._mismatched: set[str] = set()
        self._publishers = session.liveliness().declare_subscriber(
            f"{PREFIX}/{node.domain}/*/*/*/{EntityKind.PUBLISHER.value}/*/*/*/"
            f"{mangle(self.topic)}/*/*/*",
            self._on_publisher_token,
            history=True,
        )
        self._token = session.liveliness().declare_token(self.token_key)
        self._closed = False

    def _on_publisher_token(self, sample: Any) -> None:
        import zenoh

        if sample.kind != zenoh.SampleKind.PUT:
            return
        key = str(sample.key_expr)
        try:
            entity = Entity.parse(key)
        except TokenError:
            return  # counted by the graph view; nothing of ours
        if (entity.type_name, entity.type_hash) == (self.type_name, self.type_hash):
            return
        if key in self._mismatched:
            return
        self._mismatched.add(key)
        # Its samples never reach this subscription (another key): count the publisher once.
        drops.drop(
            self.topic,
            "wrong_type",
            f"(node {entity.node_fqn} publishes {entity.type_name} {entity.type_hash}; "
            f"this subscription takes {self.type_name} {self.type_hash})",
        )

    def _on_sample(self, sample: Any) -> None:
        attachment = sample.attachment
        if attachment is not None:
            raw_attachment = attachment.to_bytes()
            # The current 33-byte form is checked with two comparisons; only the rare older
            # keyed form (or a malformed one) pays for a full parse.
            if len(raw_attachment) != CURRENT_SIZE or raw_attachment[16] != 16:
                try:
                    Attachment.decode(raw_attachment)
                except AttachmentError as exc:
                    drops.drop(self.topic, "bad_attachment", str(exc))
                    return
            self._last_attachment = raw_attachment
        payload = sample.payload.to_bytes()
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

    @property
    def last_attachment(self) -> Attachment | None:
        """The attachment of the latest good sample, if it had one."""
        if self._last_attachment is None:
            return None
        return Attachment.decode(self._last_attachment)

    def close(self) -> None:
        """Undeclare the subscriber and its token (idempotent)."""
        if self._closed:
            return
        self._closed = True
        for thing in (self._token, self._publishers, self._zsub):
            try:
                thing.undeclare()
            except Exception:
                pass
