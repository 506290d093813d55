"""rmw_zenoh liveliness tokens: how every node, publisher, subscription, service and client
announces itself on the graph (what ``ros2 node list`` and ``ros2 topic list`` read).

Form::

    @ros2_lv/<domain>/<zid>/<node id>/<entity id>/<kind>/<enclave>/<namespace>/<node name>
        [/<topic>/<dds type>/<type hash>/<qos>]

with ``kind`` one of NN (node), MP (publisher), MS (subscription), SS (service server),
SC (service client), and every ``/`` inside a name mangled to ``%``.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from enum import StrEnum
from typing import Any, NamedTuple

from components.comm.names import mangle, unmangle
from components.comm.qos import QoS
from components.comm.types import UnknownTypeError, normalize_type_name

PREFIX = "@ros2_lv"
#: An endpoint token's fields (``@ros2_lv/domain/zid/node/entity/kind/enclave/namespace/
#: node name/topic/type/hash/qos``), and where its (mangled) topic is among them.
ENDPOINT_FIELDS = 13
TOPIC_FIELD = 9


class EntityKind(StrEnum):
    """The graph entity kinds of rmw_zenoh."""

    NODE = "NN"
    PUBLISHER = "MP"
    SUBSCRIPTION = "MS"
    SERVICE = "SS"
    CLIENT = "SC"


class TokenError(ValueError):
    """A liveliness key that is not an rmw_zenoh token."""


#: Seconds past a liveliness query's own timeout to wait for Zenoh to end it.
END_GRACE = 2.0


def follow_tokens(session: Any, key: str, callback: Callable[[Any], None]) -> Any:
    """Declare a liveliness subscriber of ``key`` with history (the tokens alive now, then
    every change): msctl's one way to, so that the session's graph questions go through a
    client of its router from then on (:func:`~components.comm.session.graph_questions`).

    Returns:
        The Zenoh liveliness subscriber (the caller undeclares it).
    """
    from components.comm.session import ask_through_a_client

    ask_through_a_client(session)
    return session.liveliness().declare_subscriber(key, callback, history=True)


def ask_tokens(session: Any, key: str, timeout: float) -> list[str]:
    """The keys of the live tokens matching ``key``, asked of the network now.

    The answers are gathered by a callback, never through Zenoh's default channel: a
    session's own routing tables answer it inside ``get`` itself, before the caller can
    read anything, and past the channel's 256 answers that blocked for good (a peer of
    two_dragons knows 625 tokens). The question of a peer, or of a session that follows
    tokens, goes through a client of its router
    (:func:`~components.comm.session.graph_questions`): Zenoh answers those with part of the
    tokens.

    Args:
        session: An open Zenoh session.
        key: A key expression of tokens (``@ros2_lv/0/**``).
        timeout: Seconds the answers may take at most.
    """
    import zenoh

    from components.comm.session import graph_questions

    keys: list[str] = []
    ended = threading.Event()

    def on_reply(reply: Any) -> None:
        if reply.ok is not None:
            keys.append(str(reply.ok.key_expr))

    with graph_questions(session) as asked:
        asked.liveliness().get(
            key, zenoh.handlers.Callback(on_reply, ended.set, indirect=False), timeout=timeout
        )
        ended.wait(timeout + END_GRACE)
    # A session asking itself hears its own tokens twice: from its tables and the router.
    return list(dict.fromkeys(keys))


class Entity(NamedTuple):
    """One graph entity, as carried by its liveliness token.

    Attributes:
        topic: Fully qualified topic or service name; ``None`` for a node.
        type_name: Canonical type name (``pkg/msg/Name`` or ``pkg/srv/Name``); ``None`` for a node.
    """

    domain: int
    zid: str
    node_id: int
    entity_id: int
    kind: EntityKind
    namespace: str
    node_name: str
    enclave: str = "/"
    topic: str | None = None
    type_name: str | None = None
    type_hash: str | None = None
    qos: str | None = None

    @property
    def node_key(self) -> tuple[str, int]:
        """Identifies the node this entity belongs to (session id, node id)."""
        return (self.zid, self.node_id)

    @property
    def node_fqn(self) -> str:
        """``/namespace/node`` as ``ros2 node list`` prints it."""
        return (
            (self.namespace.rstrip("/") + "/" + self.node_name)
            if self.namespace
            else self.node_name
        )

    def token(self) -> str:
        """The liveliness key expression of this entity."""
        parts = [
            PREFIX,
            str(self.domain),
            self.zid,
            str(self.node_id),
            str(self.entity_id),
            self.kind.value,
            mangle(self.enclave),
            mangle(self.namespace),
            self.node_name,
        ]
        if self.kind is not EntityKind.NODE:
            if self.topic is None or self.type_name is None or self.type_hash is None:
                raise TokenError(f"a {self.kind.name.lower()} token needs topic, type and hash")
            from components.comm.types import dds_type_name

            parts += [
                mangle(self.topic),
                dds_type_name(self.type_name),
                self.type_hash,
                self.qos if self.qos is not None else QoS().encode(),
            ]
        return "/".join(parts)

    @classmethod
    def parse(cls, key: str) -> Entity:
        """Parse a liveliness key (ours or any rmw_zenoh implementation's).

        Raises:
            TokenError: If the key is not an rmw_zenoh token.
        """
        parts = str(key).split("/")
        if len(parts) < 9 or parts[0] != PREFIX:
            raise TokenError(f"not an rmw_zenoh liveliness token: {key!r}")
        try:
            kind = EntityKind(parts[5])
            domain, node_id, entity_id = int(parts[1]), int(parts[3]), int(parts[4])
        except ValueError as exc:
            raise TokenError(f"malformed liveliness token {key!r}: {exc}") from exc
        common = {
            "domain": domain,
            "zid": parts[2],
            "node_id": node_id,
            "entity_id": entity_id,
            "kind": kind,
            "enclave": unmangle(parts[6]),
            "namespace": unmangle(parts[7]),
            "node_name": parts[8],
        }
        if kind is EntityKind.NODE:
            if len(parts) != 9:
                raise TokenError(f"malformed node token {key!r}")
            return cls(**common)
        if len(parts) != ENDPOINT_FIELDS:
            raise TokenError(f"malformed {kind.name.lower()} token {key!r}")
        try:
            type_name = normalize_type_name(parts[10])
        except UnknownTypeError as exc:
            raise TokenError(f"malformed type in token {key!r}: {exc}") from exc
        return cls(
            **common,
            topic=unmangle(parts[TOPIC_FIELD]),
            type_name=type_name,
            type_hash=parts[11],
            qos=parts[12],
        )
