"""A ROS 2 node on Zenoh: an identity on the graph, and the factory of its endpoints.

A node declares its ``NN`` liveliness token (so ``ros2 node list`` on an rmw_zenoh network
lists it), hands out entity ids, and owns every publisher, subscription, server and client
made through it: :meth:`Node.close` undeclares them all.
"""

from __future__ import annotations

import itertools
import threading
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any

from components.comm.liveliness import Entity, EntityKind
from components.comm.names import check_node_name, normalize_namespace, qualify
from components.comm.qos import QoS
from components.comm.services import ServiceClient, ServiceServer
from components.errors import swallowed

if TYPE_CHECKING:  # imported where used: a CLI node that only calls a service needs neither
    from components.comm.topics import Publisher, Subscription

# Entity ids are unique per session (rmw_zenoh: per context); several nodes share a session.
_counters: dict[str, itertools.count] = {}
_counters_lock = threading.Lock()


def _next_entity_id(zid: str) -> int:
    with _counters_lock:
        counter = _counters.setdefault(zid, itertools.count())
        return next(counter)


class Node:
    """One node: name, namespace and domain on a Zenoh session.

    Args:
        session: An open Zenoh session (the caller keeps ownership and closes it).
        name: Node name (one ROS name component).
        namespace: Node namespace, e.g. ``/limb1``.
        domain: ROS domain id.
        enclave: Security enclave (``/`` when unused).
    """

    def __init__(
        self, session: Any, name: str, namespace: str = "/", domain: int = 0, enclave: str = "/"
    ) -> None:
        self.session = session
        self.name = check_node_name(name)
        self.namespace = normalize_namespace(namespace)
        self.domain = domain
        self.enclave = enclave
        self.zid = str(session.zid())
        self.node_id = _next_entity_id(self.zid)
        self.identity = Entity(
            domain=domain,
            zid=self.zid,
            node_id=self.node_id,
            entity_id=self.node_id,
            kind=EntityKind.NODE,
            namespace=self.namespace,
            node_name=self.name,
            enclave=enclave,
        )
        self._token = session.liveliness().declare_token(self.identity.token())
        self._owned: list[Any] = []
        self._closed = False

    @property
    def fqn(self) -> str:
        """Fully qualified node name, ``/limb1/joint_manager``."""
        return self.identity.node_fqn

    def entity(
        self, kind: EntityKind, topic: str, type_name: str, type_hash: str, qos: QoS
    ) -> Entity:
        """A new graph entity of this node (used by the endpoint classes)."""
        return Entity(
            domain=self.domain,
            zid=self.zid,
            node_id=self.node_id,
            entity_id=_next_entity_id(self.zid),
            kind=kind,
            namespace=self.namespace,
            node_name=self.name,
            enclave=self.enclave,
            topic=topic,
            type_name=type_name,
            type_hash=type_hash,
            qos=qos.encode(),
        )

    def _own(self, endpoint: Any) -> Any:
        if self._closed:
            endpoint.close()
            raise RuntimeError(f"node {self.fqn} is closed")
        self._owned.append(endpoint)
        return endpoint

    def publisher(self, topic: str, msg_type: str, qos: QoS | None = None) -> Publisher:
        """Declare a publisher (topic relative to the namespace unless absolute)."""
        from components.comm.topics import Publisher

        return self._own(Publisher(self, topic, msg_type, qos))

    def subscription(
        self,
        topic: str,
        msg_type: str,
        callback: Callable[[Any], None],
        qos: QoS | None = None,
        raw: bool = False,
        senders: Iterable[str] | None = None,
        guarded: bool = False,
        on_other_type: Callable[[Entity], None] | None = None,
    ) -> Subscription:
        """Declare a subscription whose callback gets decoded messages (or bytes if ``raw``).

        Args:
            senders: Nodes whose samples are taken (others' are refused and counted, see
                :class:`Subscription`): fully qualified (``/limb1/joint_manager``) or
                relative to this node's namespace (``joint_manager``). ``None``: anyone.
            guarded: The senders may change while it runs (:meth:`Subscription.allow`).
            on_other_type: Called (on a Zenoh thread) with each publisher on the topic of
                another type, or another version of the type, instead of logging it.
        """
        from components.comm.topics import Subscription

        qualified = None if senders is None else [self.qualify_node(s) for s in senders]
        return self._own(
            Subscription(
                self, topic, msg_type, callback, qos, raw, qualified, guarded, on_other_type
            )
        )

    def qualify_node(self, name: str) -> str:
        """A node name as ``ros2 node list`` prints it: relative names are taken in this
        node's namespace (``joint_manager`` in ``/limb1`` is ``/limb1/joint_manager``).

        Raises:
            NameError_: If the name is not a valid ROS 2 name.
        """
        return qualify(name, self.namespace)

    def service(
        self,
        service: str,
        srv_type: str,
        handler: Callable[[Any], Any],
        deferred: bool = False,
        queue_only: bool = False,
        urgent: bool = False,
    ) -> ServiceServer:
        """Declare a service server (see :class:`ServiceServer` for the arguments)."""
        return self._own(
            ServiceServer(
                self, service, srv_type, handler, deferred, queue_only=queue_only, urgent=urgent
            )
        )

    def client(self, service: str, srv_type: str, announce: bool = True) -> ServiceClient:
        """Declare a service client (see :class:`ServiceClient` for ``announce``)."""
        return self._own(ServiceClient(self, service, srv_type, announce=announce))

    def close(self) -> None:
        """Undeclare every endpoint and the node token (idempotent). The session stays open."""
        if self._closed:
            return
        self._closed = True
        for endpoint in reversed(self._owned):
            endpoint.close()
        self._owned.clear()
        try:
            self._token.undeclare()
        except Exception as exc:
            swallowed(f"node {self.fqn}: token not undeclared", exc)

    def __enter__(self) -> Node:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
