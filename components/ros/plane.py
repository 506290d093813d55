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
from collections.abc import Callable, Collection, Iterator
from contextlib import contextmanager
from typing import Any

from components.comm.names import check_node_name, normalize_namespace, qualify
from components.comm.qos import QoS
from components.ros import require_rclpy
from components.ros.plane_services import (
    ANSWER_TIMEOUT,
    DDS_CALLER,
    RclpyClient,
    RclpyPendingRequest,
    RclpyServer,
    failure_response,
)
from components.ros.plane_topics import RclpyPublisher, RclpySubscription, msctl_qos, qos_profile

__all__ = [
    "ANSWER_TIMEOUT",
    "DDS_CALLER",
    "SPIN_THREADS",
    "RclpyClient",
    "RclpyNode",
    "RclpyPendingRequest",
    "RclpyPlane",
    "RclpyPublisher",
    "RclpyServer",
    "RclpySubscription",
    "failure_response",
    "msctl_qos",
    "plane",
    "qos_profile",
]

log = logging.getLogger("msctl.ros")

#: Threads rclpy runs callbacks on: requests wait on one each while the executor answers.
SPIN_THREADS = 4


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
        except Exception as exc:  # the context goes down below all the same
            log.debug("rclpy plane: executor not shut down: %s: %s", type(exc).__name__, exc)
        if self._graph_node is not None:
            try:
                self._graph_node.destroy_node()
            except Exception as exc:
                log.debug("rclpy plane: graph node not destroyed: %s: %s", type(exc).__name__, exc)
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
        except Exception as exc:  # the node is destroyed below all the same
            log.debug("rclpy node %s: not removed from its executor: %s", self.name, exc)
        try:
            self.ros.destroy_node()
        except Exception as exc:
            log.debug("rclpy node %s: not destroyed: %s: %s", self.name, type(exc).__name__, exc)
        self.plane.forget(self)

    def __enter__(self) -> RclpyNode:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@contextmanager
def plane(domain: int | None = None) -> Iterator[RclpyPlane]:
    """An :class:`RclpyPlane` for a ``with`` block."""
    made = RclpyPlane(domain)
    try:
        yield made
    finally:
        made.close()
