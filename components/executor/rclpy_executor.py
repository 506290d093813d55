"""The optional rclpy path: run cores as ordinary rclpy nodes, for robots whose other software
is a ROS 2 install (any RMW, DDS included).

Chosen with ``MSCTL_TRANSPORT=rclpy`` (or by constructing :class:`RclpyExecutor`); everything
else in msctl runs without rclpy. The cores are the same: samples cross the boundary as CDR
bytes (rclpy's raw subscriptions, serialized publishing), so msctl's codec turns them into the
same message objects the Zenoh path gives, and no per-type conversion code exists.

rclpy cannot be installed from the registries msctl's machines reach, so this module is
imported only when asked, and fails with a clear message when rclpy is absent.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from components.comm.types import registry
from components.executor.core import Core
from components.executor.interface import InterfaceSpec


class RclpyUnavailable(RuntimeError):
    """rclpy (a ROS 2 install) is not importable here."""


def _rclpy() -> Any:
    try:
        import rclpy  # type: ignore[import-not-found]
    except ImportError as exc:
        raise RclpyUnavailable(
            "MSCTL_TRANSPORT=rclpy needs a ROS 2 install (source /opt/ros/<distro>/setup.bash "
            "so that `import rclpy` works), or unset MSCTL_TRANSPORT to use the Zenoh data "
            "plane, which needs no ROS"
        ) from exc
    return rclpy


def _ros_type(type_name: str) -> Any:
    from rosidl_runtime_py.utilities import get_interface  # type: ignore[import-not-found]

    return get_interface(type_name)


class _Outbox:
    def __init__(self, publishers: dict[str, tuple[Any, Callable[[Any], bytes]]]):
        self._publishers = publishers

    def publish(self, topic: str, message: Any) -> None:
        publisher, encode = self._publishers[topic]
        publisher.publish(encode(message))  # rclpy publishes serialized bytes as they are


class RclpyExecutor:
    """Runs cores as rclpy nodes: same ``add`` / ``run`` / ``stop`` as the Zenoh Executor.

    One lock serializes every handler, so a core never sees two callbacks at once even under
    a multi-threaded rclpy executor.
    """

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._rclpy = _rclpy()
        self._rclpy.init()
        self.clock = clock
        self._nodes: list[Any] = []
        self._cores: list[Core] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._wall_offset = time.time() - time.monotonic()

    def add(
        self, core: Core, spec: InterfaceSpec, namespace: str = "/", node_name: str | None = None
    ) -> Any:
        """Bind ``core`` as an rclpy node in ``namespace``."""
        reg = registry()
        node = self._rclpy.create_node(
            node_name or core.name.replace("/", "_"), namespace=namespace
        )
        publishers = {
            p.topic: (
                node.create_publisher(_ros_type(p.msg_type), p.topic, p.qos.depth),
                reg.serializer(p.msg_type),
            )
            for p in spec.publish
        }
        core.bind(_Outbox(publishers), self._wall_offset)
        for sub in spec.subscribe:
            handler, decode = getattr(core, sub.handler), reg.deserializer(sub.msg_type)
            node.create_subscription(
                _ros_type(sub.msg_type),
                sub.topic,
                lambda raw, h=handler, d=decode: self._call(h, d(raw)),
                sub.qos.depth,
                raw=True,
            )
        for serve in spec.serve:
            handler = getattr(core, serve.handler)
            parts = reg.service(serve.srv_type)
            node.create_service(
                _ros_type(serve.srv_type),
                serve.service,
                self._service_callback(handler, parts),
            )
        for every in spec.every:
            handler = getattr(core, every.handler)
            node.create_timer(every.period, lambda h=handler: self._call_timer(h))
        self._nodes.append(node)
        self._cores.append(core)
        return node

    def _call(self, handler: Callable, message: Any) -> None:
        with self._lock:
            handler(message, self.clock())

    def _call_timer(self, handler: Callable) -> None:
        with self._lock:
            handler(self.clock())

    def _service_callback(self, handler: Callable, parts: Any) -> Callable:
        from rclpy.serialization import deserialize_message, serialize_message  # type: ignore

        reg = registry()
        decode, encode = reg.deserializer(parts.request), reg.serializer(parts.response)

        def answer(request: Any, response: Any) -> Any:
            ours = decode(serialize_message(request))
            with self._lock:
                reply = handler(ours, self.clock())
            return deserialize_message(encode(reply), type(response))

        return answer

    def run(self, duration: float | None = None) -> None:
        """Spin until :meth:`stop` or ``duration``; cores' start/stop run around it."""
        from rclpy.executors import SingleThreadedExecutor  # type: ignore

        executor = SingleThreadedExecutor()
        for node in self._nodes:
            executor.add_node(node)
        now = self.clock()
        for core in self._cores:
            core.start(now)
        deadline = None if duration is None else time.monotonic() + duration
        try:
            while not self._stop.is_set() and (deadline is None or time.monotonic() < deadline):
                executor.spin_once(timeout_sec=0.05)
        finally:
            now = self.clock()
            for core in self._cores:
                core.stop(now)
            for node in self._nodes:
                node.destroy_node()
            self._rclpy.shutdown()

    def stop(self) -> None:
        """Ask :meth:`run` to finish."""
        self._stop.set()
