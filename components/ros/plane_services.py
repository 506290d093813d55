"""rclpy services for msctl's data plane: servers and clients that carry CDR bytes.

Part of :mod:`components.ros.plane` (which makes them from an :class:`RclpyNode`): requests
reach the executor as pending requests it answers from its own thread; a failure is answered
as DDS allows (see the plane's module docstring, :func:`failure_response`).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from components.comm.names import qualify
from components.comm.services import PendingRequest, ServiceError, ServiceTimeout
from components.comm.stats import drops
from components.comm.types import normalize_type_name, registry

if TYPE_CHECKING:
    from components.ros.plane import RclpyNode

log = logging.getLogger("msctl.ros")

#: Seconds a server waits for the executor to answer a request before giving up on it.
ANSWER_TIMEOUT = 30.0
#: What a server reports as the caller (DDS does not tell rclpy who asked).
DDS_CALLER = "a ROS 2 client"


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
        except Exception as exc:  # its node may be destroyed already
            log.debug("server %s: not destroyed: %s: %s", self.service, type(exc).__name__, exc)


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
        except Exception as exc:  # its node may be destroyed already
            log.debug("client %s: not destroyed: %s: %s", self.service, type(exc).__name__, exc)
