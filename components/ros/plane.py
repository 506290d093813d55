"""rclpy as msctl's data plane: one context, and nodes shaped like msctl's Zenoh nodes.

An :class:`RclpyPlane` owns an rclpy context (one DDS participant) and the thread that spins
it. Its :class:`RclpyNode` offers what :class:`components.comm.node.Node` offers (``publisher``,
``subscription``, ``service``, ``client``, ``close``), with the same callback contract, so
:class:`~components.executor.executor.Executor` binds a core to either plane through one code
path: samples are decoded by msctl's codec and queued for the executor thread, service
requests reach the executor as pending requests it answers from its own thread.

Every message crosses as CDR bytes: topics are published and taken serialized (rclpy's
``raw``), services through :mod:`components.ros.typesupport`, so no ROS message class is
needed, and msctl_msgs types work without a compiled package.

What DDS cannot say, and what is done instead:

* who sent a sample (rclpy gives no publisher GID per sample): a subscription limited to some
  senders takes nothing while a publisher of any other node is on the topic (checked against
  the graph at every sample, by publisher count, and re-read when it changes), and warns once
  naming that node. Safe for command inputs: commands stop, the watchdogs stop the motors.
* who called a service: the caller is reported as ``a ROS 2 client``.
* an error answer: a server that cannot answer sends the response with ``success`` false and
  ``message`` saying why when the type has them, else the type's default response.
* a claim's session: claims name ``<node>@<zid>``; on DDS only the node name is checked.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Collection, Iterator
from contextlib import contextmanager
from typing import Any

from components.comm.names import check_node_name, normalize_namespace, qualify
from components.comm.qos import QoS
from components.comm.services import PendingRequest, ServiceError, ServiceTimeout
from components.comm.stats import drops
from components.comm.topics import INTRUDER
from components.comm.types import normalize_type_name, registry
from components.ros import require_rclpy

log = logging.getLogger("msctl.ros")

#: Seconds a server waits for the executor to answer a request before giving up on it.
ANSWER_TIMEOUT = 30.0
#: Threads rclpy runs callbacks on: requests wait on one each while the executor answers.
SPIN_THREADS = 4
#: What a server reports as the caller (DDS does not tell rclpy who asked).
DDS_CALLER = "a ROS 2 client"


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


def failure_response(response_type: str, why: str) -> bytes:
    """The CDR of a response saying a request failed, as DDS has no error answer:
    ``success`` false and ``message`` saying why when the type has them, else its default.

    Args:
        response_type: The service's response message type (``std_srvs/srv/Trigger_Response``).
        why: What went wrong.
    """
    from components.messages import msg

    reg = registry()
    fields = {name for name, _ in reg.fields(response_type)}
    values: dict[str, Any] = {}
    if "success" in fields:
        values["success"] = False
    if "message" in fields:
        values["message"] = why
    return reg.serializer(response_type)(msg(response_type, **values))


class RclpyPlane:
    """An rclpy context, spun on a thread of its own. Close it when done.

    Args:
        domain: ROS domain id (``None``: ``ROS_DOMAIN_ID``, else 0).
        threads: Callback threads (a request waits on one while the executor answers it).

    Raises:
        RclpyUnavailable: If rclpy cannot be imported.
    """

    def __init__(self, domain: int | None = None, threads: int = SPIN_THREADS) -> None:
        rclpy = require_rclpy()
        from rclpy.context import Context
        from rclpy.executors import MultiThreadedExecutor
        from rclpy.signals import SignalHandlerOptions

        self.context = Context()
        # msctl's executor owns SIGINT/SIGTERM: rclpy must not install its own handlers.
        rclpy.init(
            context=self.context,
            domain_id=domain,
            signal_handler_options=SignalHandlerOptions.NO,
        )
        self.domain = self.context.get_domain_id()
        self.executor = MultiThreadedExecutor(num_threads=threads, context=self.context)
        self._stop = threading.Event()
        self._closed = False
        self._lock = threading.Lock()
        self._nodes: list[RclpyNode] = []
        self._graph_node: Any = None
        self._thread = threading.Thread(target=self._spin, name="rclpy", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set():
            try:
                self.executor.spin_once(timeout_sec=0.1)
            except Exception as exc:  # a callback's error must not end the plane
                if self._stop.is_set() or not self.context.ok():
                    return
                log.error("rclpy callback failed: %s: %s", type(exc).__name__, exc)

    def node(self, name: str, namespace: str = "/") -> RclpyNode:
        """A new node on this plane (closed with it)."""
        node = RclpyNode(self, name, namespace)
        with self._lock:
            self._nodes.append(node)
        return node

    def graph_node(self) -> Any:
        """A hidden rclpy node that only reads the graph (made on first use)."""
        with self._lock:
            if self._graph_node is None:
                from rclpy.node import Node as RosNode

                # A leading underscore hides it from `ros2 node list`.
                self._graph_node = RosNode(
                    f"_msctl_graph_{id(self):x}",
                    context=self.context,
                    start_parameter_services=False,
                    enable_rosout=False,
                    use_global_arguments=False,
                )
            return self._graph_node

    def forget(self, node: RclpyNode) -> None:
        """A node closed itself."""
        with self._lock:
            if node in self._nodes:
                self._nodes.remove(node)

    def close(self) -> None:
        """Destroy every node, stop spinning, shut the context down (idempotent)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            nodes, self._nodes = list(self._nodes), []
        for node in reversed(nodes):
            node.close()
        self._stop.set()
        self._thread.join(timeout=5.0)
        try:
            self.executor.shutdown(timeout_sec=2.0)
        except Exception:
            pass
        if self._graph_node is not None:
            try:
                self._graph_node.destroy_node()
            except Exception:
                pass
        self.context.try_shutdown()

    def __enter__(self) -> RclpyPlane:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class RclpyNode:
    """One rclpy node with the interface of :class:`components.comm.node.Node`.

    Parameter services and ``/rosout`` are off: cores have neither ROS parameters nor rclpy
    loggers, and every endpoint is discovery traffic on a DDS network.
    """

    def __init__(self, plane: RclpyPlane, name: str, namespace: str = "/") -> None:
        from rclpy.callback_groups import ReentrantCallbackGroup
        from rclpy.node import Node as RosNode

        self.plane = plane
        self.name = check_node_name(name)
        self.namespace = normalize_namespace(namespace)
        self.domain = plane.domain
        self.ros = RosNode(
            self.name,
            namespace=self.namespace,
            context=plane.context,
            start_parameter_services=False,
            enable_rosout=False,
            use_global_arguments=False,
        )
        # Requests wait for the executor's answer: in a group of their own, they never hold
        # up the node's subscriptions (which share its default, one-at-a-time group).
        self.requests = ReentrantCallbackGroup()
        self._owned: list[Any] = []
        self._closed = False
        plane.executor.add_node(self.ros)

    @property
    def fqn(self) -> str:
        """Fully qualified node name, ``/limb1/joint_manager``."""
        return self.namespace.rstrip("/") + "/" + self.name

    def qualify_node(self, name: str) -> str:
        """A node name taken in this node's namespace when relative."""
        return qualify(name, self.namespace)

    def _own(self, endpoint: Any) -> Any:
        if self._closed:
            endpoint.close()
            raise RuntimeError(f"node {self.fqn} is closed")
        self._owned.append(endpoint)
        return endpoint

    def publisher(self, topic: str, msg_type: str, qos: QoS | None = None) -> RclpyPublisher:
        """A publisher (topic relative to the namespace unless absolute)."""
        return self._own(RclpyPublisher(self, topic, msg_type, qos))

    def subscription(
        self,
        topic: str,
        msg_type: str,
        callback: Callable[[Any], None],
        qos: QoS | None = None,
        raw: bool = False,
        senders: Collection[str] | None = None,
        guarded: bool = False,
    ) -> RclpySubscription:
        """A subscription whose callback gets decoded messages (or CDR bytes if ``raw``)."""
        qualified = None if senders is None else [self.qualify_node(s) for s in senders]
        return self._own(
            RclpySubscription(self, topic, msg_type, callback, qos, raw, qualified, guarded)
        )

    def service(
        self,
        service: str,
        srv_type: str,
        handler: Callable[[Any], Any],
        deferred: bool = False,
        queue_only: bool = False,
        urgent: bool = False,
    ) -> RclpyServer:
        """A service server (``handler(request) -> response``, or ``handler(pending)`` when
        ``deferred``). ``queue_only`` and ``urgent`` are Zenoh's thread and priority hints
        (:class:`components.comm.services.ServiceServer`); DDS has neither, so they change
        nothing here."""
        del queue_only, urgent
        return self._own(RclpyServer(self, service, srv_type, handler, deferred))

    def client(self, service: str, srv_type: str, announce: bool = True) -> RclpyClient:
        """A service client. ``announce`` is the Zenoh graph's token timing
        (:class:`components.comm.services.ServiceClient`); a DDS client is always seen."""
        del announce
        return self._own(RclpyClient(self, service, srv_type))

    def close(self) -> None:
        """Destroy every endpoint and the node (idempotent)."""
        if self._closed:
            return
        self._closed = True
        for endpoint in reversed(self._owned):
            endpoint.close()
        self._owned.clear()
        try:
            self.plane.executor.remove_node(self.ros)
        except Exception:
            pass
        try:
            self.ros.destroy_node()
        except Exception:
            pass
        self.plane.forget(self)

    def __enter__(self) -> RclpyNode:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


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
        except Exception:
            pass


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
        with self._lock:
            if count != self._seen_publishers:
                nodes = {
                    f"{info.node_namespace.rstrip('/')}/{info.node_name}"
                    for info in ros.get_publishers_info_by_topic(self.topic)
                }
                self._intruders = sorted(n for n in nodes if n not in senders)
                self._seen_publishers = count
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
        except Exception:
            pass


class RclpyPendingRequest(PendingRequest):
    """A request an rclpy server holds until the executor answers it (see
    :class:`~components.comm.services.PendingRequest`)."""

    def __init__(self, server: RclpyServer, request: Any) -> None:
        self._rclpy_server = server
        self.request = request
        self.attachment = None
        self._done = False
        self._answered = threading.Event()
        self.cdr = b""

    @property
    def caller(self) -> str:
        """DDS does not tell rclpy who asked."""
        return DDS_CALLER

    def reply(self, response: Any) -> None:
        """Answer with ``response``."""
        if self._done:
            raise RuntimeError("this request was already answered")
        try:
            cdr = self._rclpy_server.encode_response(response)
        except Exception as exc:
            self.fail(f"the server built a response that does not serialize: {exc}")
            return
        self._finish(cdr)

    def fail(self, message: str) -> None:
        """Answer that it failed (see the module: DDS has no error answer)."""
        self._finish(self._rclpy_server.failure(message))

    def _finish(self, cdr: bytes) -> None:
        self._done = True
        self.cdr = cdr
        self._answered.set()

    def wait(self, timeout: float) -> bool:
        """Block until answered; whether it was."""
        return self._answered.wait(timeout)


class RclpyServer:
    """Answers one service. Create through :meth:`RclpyNode.service`."""

    def __init__(
        self,
        node: RclpyNode,
        service: str,
        srv_type: str,
        handler: Callable[[Any], Any],
        deferred: bool,
    ) -> None:
        from components.ros.typesupport import service_class

        self.service = qualify(service, node.namespace, node.name)
        self.srv_type = normalize_type_name(srv_type)
        reg = registry()
        self.parts = reg.service(self.srv_type)
        self._decode = reg.deserializer(self.parts.request, stream=True)
        self._encode = reg.serializer(self.parts.response, stream=True)
        self._handler = handler
        self._deferred = deferred
        self._node = node
        self._class = service_class(self.srv_type)
        self._pending: set[RclpyPendingRequest] = set()
        self._lock = threading.Lock()
        self._closed = False
        self._srv = node.ros.create_service(
            self._class, self.service, self._on_request, callback_group=node.requests
        )

    def encode_response(self, response: Any) -> bytes:
        """CDR of a response."""
        return self._encode(response)

    def failure(self, why: str) -> bytes:
        """The response that says the request failed (see :func:`failure_response`)."""
        return failure_response(self.parts.response, why)

    def _on_request(self, request: Any, response: Any) -> Any:
        del response  # rclpy's empty one; ours is built by the handler
        try:
            decoded = self._decode(request.cdr)
        except Exception as exc:
            drops.drop(self.service, "malformed", f"{type(exc).__name__}: {exc}")
            return self._class.Response(self.failure(f"malformed request for {self.srv_type}"))
        pending = RclpyPendingRequest(self, decoded)
        if not self._deferred:
            try:
                with pending.handling():
                    pending.reply(self._handler(decoded))
            except Exception as exc:
                log.exception("service %s handler failed", self.service)
                drops.drop(self.service, "handler_error")
                pending.fail(f"{self.service} failed: {type(exc).__name__}: {exc}")
            return self._class.Response(pending.cdr)
        with self._lock:
            if self._closed:
                return self._class.Response(self.failure(f"{self.service} is shutting down"))
            self._pending.add(pending)
        try:
            self._handler(pending)
            if not pending.wait(ANSWER_TIMEOUT):
                pending.fail(f"{self.service} did not answer within {ANSWER_TIMEOUT:g} s")
        finally:
            with self._lock:
                self._pending.discard(pending)
        return self._class.Response(pending.cdr)

    def close(self) -> None:
        """Destroy the server; requests still waiting are answered as failed (idempotent)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            waiting = list(self._pending)
        for pending in waiting:
            if not pending._done:
                pending.fail(f"{self.service} is shutting down")
        try:
            self._node.ros.destroy_service(self._srv)
        except Exception:
            pass


class RclpyClient:
    """Calls one service. Create through :meth:`RclpyNode.client`; never call it from an
    rclpy callback (the answer arrives through the same executor)."""

    def __init__(self, node: RclpyNode, service: str, srv_type: str) -> None:
        from components.ros.typesupport import service_class

        self.service = qualify(service, node.namespace, node.name)
        self.srv_type = normalize_type_name(srv_type)
        reg = registry()
        self.parts = reg.service(self.srv_type)
        self._encode = reg.serializer(self.parts.request, stream=True)
        self._decode = reg.deserializer(self.parts.response, stream=True)
        self._class = service_class(self.srv_type)
        self._node = node
        self._cli = node.ros.create_client(self._class, self.service)
        self._closed = False

    def request_type(self) -> type:
        """The request message class."""
        return registry().msg_class(self.parts.request)

    def ready(self) -> bool:
        """Whether a server of this service is on the graph."""
        return self._cli.service_is_ready()

    def call_raw(self, cdr: bytes, timeout: float = 2.0) -> bytes:
        """Send a serialized request, return the serialized response.

        Raises:
            ServiceTimeout: If no server answered within ``timeout`` seconds.
        """
        started = time.monotonic()
        if not self._cli.wait_for_service(timeout_sec=timeout):
            raise ServiceTimeout(
                f"no server of {self.service} ({self.srv_type}) on the ROS graph within "
                f"{timeout:g} s; check it is running (`ros2 service list`)"
            )
        answered = threading.Event()
        future = self._cli.call_async(self._class.Request(cdr))
        future.add_done_callback(lambda _: answered.set())
        left = max(timeout - (time.monotonic() - started), 0.05)
        if not answered.wait(left):
            self._cli.remove_pending_request(future)
            raise ServiceTimeout(
                f"no server answered {self.service} ({self.srv_type}) within {timeout:g} s"
            )
        result = future.result()
        if result is None:
            raise ServiceError(f"service {self.service} gave no response")
        return result.cdr

    def call(self, request: Any, timeout: float = 2.0) -> Any:
        """Send ``request`` and wait for the decoded response.

        Raises:
            ServiceTimeout: If no server answered within ``timeout`` seconds.
            ServiceError: If the response does not decode.
        """
        cdr = self.call_raw(self._encode(request), timeout)
        try:
            return self._decode(cdr)
        except Exception as exc:
            raise ServiceError(
                f"service {self.service} sent a response that is not a {self.parts.response}"
            ) from exc

    def close(self) -> None:
        """Destroy the client (idempotent)."""
        if self._closed:
            return
        self._closed = True
        try:
            self._node.ros.destroy_client(self._cli)
        except Exception:
            pass


@contextmanager
def plane(domain: int | None = None) -> Iterator[RclpyPlane]:
    """An :class:`RclpyPlane` for a ``with`` block."""
    made = RclpyPlane(domain)
    try:
        yield made
    finally:
        made.close()
