"""Publishers and subscriptions of ROS 2 topics, carried on Zenoh as rmw_zenoh carries them.

Data key: ``<domain>/<topic without outer slashes>/<pkg>::msg::dds_::<Name>_/<RIHS01 hash>``;
payload: CDR with its 4-byte encapsulation header; attachment: see ``attachment.py``.
Latched (transient-local) topics use Zenoh's advanced publisher (with a cache of ``depth``
samples and publisher detection) and advanced subscriber (querying late publishers' history),
as rmw_zenoh does, so a late subscriber gets the last sample.
"""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Callable, Collection
from typing import TYPE_CHECKING, Any

from components.comm import publishers
from components.comm.attachment import (
    CURRENT_FORMAT,
    CURRENT_SIZE,
    Attachment,
    AttachmentError,
    gid_of,
)
from components.comm.liveliness import Entity, EntityKind, TokenError
from components.comm.names import key_name, mangle, qualify
from components.comm.qos import QoS
from components.comm.stats import drops, log
from components.comm.types import dds_type_name, normalize_type_name, registry
from components.errors import swallowed

if TYPE_CHECKING:
    from components.comm.node import Node


_pack_attachment = CURRENT_FORMAT.pack

#: Seconds a publisher with no graph token may go on being refused before it is warned
#: about: the legitimate sender's first samples can outrun its token by a moment, and that
#: must not read as an intrusion.
UNKNOWN_GRACE = 2.0
#: Most publishers a sender-checking subscription tracks by GID (unknown ones, other nodes'
#: ones, warned ones): a spray of made-up GIDs costs a bounded amount of memory.
MAX_TRACKED = 64
#: Most publishers a guarded subscription knows by GID on its topic (see
#: :meth:`Subscription.allow`); beyond this a new publisher is never allowed (the safe side).
MAX_PUBLISHERS = 1024
#: The drop reason of a sample refused because its publisher is not an allowed sender.
INTRUDER = "intruder"


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
        self._serialize = reg.serializer(self.type_name, stream=True)
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
        # The token first: every link then carries it before this publisher's first sample,
        # so a subscription that checks who sends (see Subscription's ``senders``) knows
        # this GID by the time a sample arrives.
        self._token = session.liveliness().declare_token(self.token_key)
        try:
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
        except Exception:
            self._token.undeclare()
            raise
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
            except Exception as exc:  # the session may already be closed
                swallowed(f"publisher {self.key}: not undeclared", exc)


class Subscription:
    """Receives one topic. Create through :meth:`Node.subscription`.

    The callback runs on a Zenoh thread with the decoded message. Samples whose payload or
    attachment do not decode are dropped and counted in :data:`components.comm.stats.drops`
    under the topic name; a publisher of another type (or another version of the type) on
    the topic is counted there once, from its liveliness token, naming its node (or, with
    ``on_other_type``, handed to that function as its graph entity instead of logged). An
    exception in the callback is logged and counted, and never reaches Zenoh.

    With ``senders`` (fully qualified node names), only samples published by those nodes
    are taken, as rmw_zenoh's graph tells them: a sample's attachment carries its
    publisher's GID, which is the hash of the publisher's liveliness token
    (:func:`~components.comm.attachment.gid_of`), and the token names the node. The
    publisher tokens on the topic are followed (with history), each hashed once into an
    allowed set, so the check per sample is one set lookup of the GID. Everything else is
    refused and counted under :data:`INTRUDER`, with one WARN per intruding node naming it:

    * a sample with no attachment (a raw Zenoh put): refused, warned once;
    * a GID whose token names another node: refused, warned once for that node;
    * a GID with no token yet: refused (safe: never taken before it is known). The
      legitimate sender's token normally arrives before its first sample (a publisher
      declares its token first; a late subscription gets existing tokens from the
      liveliness history), and its samples are taken from the moment it is known. A GID
      still unknown after :data:`UNKNOWN_GRACE` seconds is warned about once, by GID.

    A sender is a node name (``/limb1/joint_manager``, from any session) or
    ``<node>@<session zid>`` (that node of that one session: a claim's holder). With
    ``guarded``, the senders may change while it runs (:meth:`allow`): every publisher
    token on the topic is followed from the start, so a new sender's GIDs are known at once.

    Attributes:
        received: Samples delivered to the callback.
        last_attachment: The attachment of the latest good sample, if it had one.
        senders: The nodes allowed to publish here (``None``: anyone).
    """

    def __init__(
        self,
        node: Node,
        topic: str,
        msg_type: str,
        callback: Callable[[Any], None],
        qos: QoS | None = None,
        raw: bool = False,
        senders: Collection[str] | None = None,
        guarded: bool = False,
        on_other_type: Callable[[Entity], None] | None = None,
    ) -> None:
        import zenoh.ext

        self.qos = qos or QoS()
        self.topic = qualify(topic, node.namespace, node.name)
        self.type_name = normalize_type_name(msg_type)
        reg = registry()
        self._deserialize = reg.deserializer(self.type_name, stream=True)
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
        # Set before the subscriber is declared: a latched topic's history arrives at once.
        self._closed = False
        self._last_attachment: bytes | None = None
        self.senders: frozenset[str] | None = None if senders is None else frozenset(senders)
        self._guarded = guarded or senders is not None
        # What a refusal says after "only ..." and the drop reason it is counted under
        # (see allow()); by default, the allowed nodes and INTRUDER.
        self._why: str | None = None
        self._reason = INTRUDER
        # Every publisher on the topic, GID -> (node, session zid), while guarded: what
        # allow() recomputes the allowed set from. Bounded like the rest (MAX_PUBLISHERS).
        self._publisher_nodes: dict[bytes, tuple[str, str]] = {}
        # GIDs of the allowed senders' publishers on this topic (-> node): the per-sample check.
        self._allowed: dict[bytes, str] = {}
        # The slow path's bookkeeping (refusals, tokens), all bounded by MAX_TRACKED.
        self._others: dict[bytes, str] = {}  # GID -> node of a publisher not allowed here
        self._unknown: dict[bytes, list[float]] = {}  # GID -> [first refused, refusals]
        self._warned: set[object] = set()
        self._identity_lock = threading.Lock()
        # The exact key, as rmw_zenoh subscribes: a wildcard here (to see samples of other
        # types) cost ~20 us a round trip. Publishers of another type, or of another version
        # of the type, are found from their liveliness tokens instead (_on_publisher_token),
        # which also names the node at fault.
        session = node.session
        self._mismatched: set[str] = set()
        self._on_other_type = on_other_type
        # Tokens before samples: with senders, the allowed set should be filled (from the
        # liveliness history) before the first sample is judged.
        self._publishers = publishers.listen(
            session, node.domain, mangle(self.topic), self._on_publisher_token
        )
        try:
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
        except Exception:
            self._publishers.undeclare()
            raise
        self._token = session.liveliness().declare_token(self.token_key)

    def _on_publisher_token(self, key: str, alive: bool) -> None:
        try:
            entity = Entity.parse(key)
        except TokenError:
            return  # counted by the graph view; nothing of ours
        if self._guarded:
            self._on_sender_token(key, entity, alive)
        if not alive:
            return
        if (entity.type_name, entity.type_hash) == (self.type_name, self.type_hash):
            return
        if key in self._mismatched:
            return
        self._mismatched.add(key)
        # Its samples never reach this subscription (another key): count the publisher once.
        if self._on_other_type is not None:
            # The owner says it in its own words (a CLI names the type, without the hashes).
            drops.drop(self.topic, "wrong_type", quiet=True)
            self._on_other_type(entity)
            return
        drops.drop(
            self.topic,
            "wrong_type",
            f"(node {entity.node_fqn} publishes {entity.type_name} {entity.type_hash}; "
            f"this subscription takes {self.type_name} {self.type_hash})",
        )

    def _admits(self, node: str, zid: str) -> bool:
        senders = self.senders
        return senders is None or node in senders or f"{node}@{zid}" in senders

    def _on_sender_token(self, key: str, entity: Entity, alive: bool) -> None:
        """Keep the allowed GIDs (and the names of the others) as tokens come and go."""
        gid = gid_of(key)
        node = entity.node_fqn
        with self._identity_lock:
            if not alive:
                self._publisher_nodes.pop(gid, None)
                self._allowed.pop(gid, None)
                self._others.pop(gid, None)
                return
            if gid in self._publisher_nodes or len(self._publisher_nodes) < MAX_PUBLISHERS:
                self._publisher_nodes[gid] = (node, entity.zid)
            allowed = self._admits(node, entity.zid)
            if allowed:
                self._allowed[gid] = node
            elif gid in self._others or len(self._others) < MAX_TRACKED:
                self._others[gid] = node
            early = self._unknown.pop(gid, None)
        if self.senders is None:
            return  # anyone may publish: nothing was refused, nothing to say
        if early is None:
            return
        if allowed:
            self._early(node, int(early[1]))
        else:
            self._warn_once(node, f"node {node}")

    def allow(
        self, senders: Collection[str] | None, why: str | None = None, reason: str = INTRUDER
    ) -> None:
        """Change who may publish here, at run time (a ``guarded`` subscription only).

        Takes effect for the next sample: the allowed GIDs are recomputed from the
        publisher tokens already seen. Each refused node is warned about once more under the
        new rule (a claim changing hands is news).

        Args:
            senders: Node names or ``<node>@<zid>`` (see the class); ``None``: anyone; empty:
                no one.
            why: What a refusal's WARN says after the node (default: the allowed nodes).
            reason: The drop reason refusals are counted under.

        Raises:
            RuntimeError: If the subscription was not made ``guarded`` (its publishers'
                tokens were not followed, so the new senders' GIDs would be unknown).
        """
        if not self._guarded:
            raise RuntimeError(f"{self.topic}: allow() needs a guarded subscription")
        new = None if senders is None else frozenset(senders)
        with self._identity_lock:
            self._why, self._reason = why, reason
            if new is None:
                # Open first, then forget: a sample in between is taken either way.
                self.senders = None
                self._allowed = {}
                self._others.clear()
            else:
                admitted = {
                    gid: node
                    for gid, (node, zid) in self._publisher_nodes.items()
                    if node in new or f"{node}@{zid}" in new
                }
                # The allowed set before the senders: the per-sample check reads both
                # without the lock, and each assignment is atomic.
                self._allowed = admitted
                self.senders = new
                self._others = {
                    gid: node
                    for gid, (node, _) in self._publisher_nodes.items()
                    if gid not in admitted
                }
            self._warned.clear()

    def _early(self, node: str, refused: int) -> None:
        log.info(
            "%s: publisher of %s known from its graph token; %d sample(s) it sent before "
            "were refused",
            self.topic,
            node,
            refused,
        )

    def _on_sample(self, sample: Any) -> None:
        attachment = sample.attachment
        raw_attachment = None if attachment is None else attachment.to_bytes()
        gid = None
        if raw_attachment is not None:
            # The current 33-byte form is checked with two comparisons; only the rare older
            # keyed form (or a malformed one) pays for a full parse.
            if len(raw_attachment) != CURRENT_SIZE or raw_attachment[16] != 16:
                try:
                    gid = Attachment.decode(raw_attachment).gid
                except AttachmentError as exc:
                    drops.drop(self.topic, "bad_attachment", str(exc))
                    return
            elif self.senders is not None:
                gid = raw_attachment[17:]
        if self.senders is not None and gid not in self._allowed:
            self._refuse(gid)
            return
        if raw_attachment is not None:
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
        if self._closed:
            # Zenoh may still run a callback for a sample it had in hand when the subscriber
            # was undeclared: once closed, nothing more is delivered.
            return
        self.received += 1
        try:
            self._callback(message)
        except Exception:
            drops.drop(self.topic, "callback_error")
            log.exception("subscription callback on %s failed", self.topic)

    def _refuse(self, gid: bytes | None) -> None:
        """Count a sample from a publisher that is not an allowed sender; warn once per node."""
        drops.drop(self.topic, self._reason, quiet=True)
        if gid is None:
            self._warn_once(
                None, "a publisher with no rmw_zenoh attachment (a raw Zenoh put, not a ROS node)"
            )
            return
        with self._identity_lock:
            allowed = self._allowed.get(gid)
            other = self._others.get(gid)
            key: object = other
            who = f"node {other}"
            if allowed is None and other is None:
                now = time.monotonic()
                early = self._unknown.get(gid)
                if early is None and len(self._unknown) < MAX_TRACKED:
                    self._unknown[gid] = [now, 1.0]
                    return
                if early is None:
                    # Too many unknown GIDs to wait for each: a spray of made-up ones.
                    key, who = "unknown", "publishers with no graph token (many GIDs)"
                else:
                    early[1] += 1
                    if now - early[0] < UNKNOWN_GRACE:
                        return
                    key, who = gid, f"a publisher with no graph token (GID {gid.hex()})"
        if allowed is not None:
            # Its token came between the check and here: an allowed sender after all.
            self._early(allowed, 1)
            return
        self._warn_once(key, who)

    def _warn_once(self, key: object, who: str) -> None:
        with self._identity_lock:
            if key in self._warned or len(self._warned) >= MAX_TRACKED:
                return
            self._warned.add(key)
        why = self._why or f"only {', '.join(sorted(self.senders or ()))} may publish here"
        log.warning(
            "%s: refused samples from %s: %s (%d refused so far)",
            self.topic,
            who,
            why,
            drops.count(self.topic, self._reason),
        )

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
        for thing in (self._token, self._zsub, self._publishers):
            try:
                thing.undeclare()
            except Exception as exc:  # the session may already be closed
                swallowed(f"subscription {self.key}: not undeclared", exc)
