"""ROS 2 services on Zenoh, as rmw_zenoh carries them.

A server is a queryable declared ``complete=True`` on
``<domain>/<service>/<pkg>::srv::dds_::<Name>_/<service hash>``. A client sends a query with
the CDR request as payload and an attachment (client sequence number, time, client GID),
targeting ALL_COMPLETE; the server replies with the CDR response and an attachment carrying
the request's sequence number and the client's GID, so the client can match the reply.
"""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from typing import TYPE_CHECKING, Any

from components.comm.attachment import Attachment, AttachmentError, gid_of
from components.comm.liveliness import PREFIX, Entity, EntityKind, TokenError, follow_tokens
from components.comm.names import key_name, mangle, qualify
from components.comm.qos import QoS
from components.comm.stats import drops, log
from components.comm.types import dds_type_name, normalize_type_name, registry
from components.errors import ComponentError, DeadlineError, swallowed

if TYPE_CHECKING:
    from components.comm.node import Node

#: rmw_zenoh announces services with the "services default" QoS (reliable, keep last 10).
SERVICE_QOS = QoS(depth=10)

#: Most clients a server remembers by GID (a short-lived ``msctl service call`` each adds
#: one while it lives); beyond this a caller is reported by GID only.
MAX_CALLERS = 256

_handling: ContextVar[PendingRequest | None] = ContextVar("msctl_service_request", default=None)


def current_caller() -> str | None:
    """Who sent the request being handled on this thread, for a handler that must say so
    (e.g. one that writes to disk): the client's node (``/ground1/teleop``), ``"GID <hex>"``
    for a client whose graph token is not known, or ``None`` outside a request handler.

    Set while a server's handler runs (see :meth:`PendingRequest.handling`).
    """
    pending = _handling.get()
    return None if pending is None else pending.caller


class ServiceError(ComponentError, RuntimeError):
    """A service call that got no usable answer; the message names the service and why."""


class ServiceTimeout(ServiceError, DeadlineError):
    """No server answered within the timeout."""


class NoServer(ServiceTimeout):
    """The query ended early with no answer: most often the network knew no server for it.

    Not a proof that no server got the request (a link that dropped while it waited ends it
    early too): only a request that is safe to repeat is sent again on it.
    """


def service_key(domain: int, service: str, srv_type: str) -> str:
    """The Zenoh key expression of a service."""
    return (
        f"{domain}/{key_name(service)}/{dds_type_name(srv_type)}/{registry().type_hash(srv_type)}"
    )


def _identify(endpoint: Any, node: Node, kind: EntityKind, service: str, srv_type: str) -> None:
    """Give a server or client its service name, type, key, graph entity and GID."""
    endpoint.service = qualify(service, node.namespace, node.name)
    endpoint.srv_type = normalize_type_name(srv_type)
    reg = registry()
    endpoint.parts = reg.service(endpoint.srv_type)
    endpoint.key = service_key(node.domain, endpoint.service, endpoint.srv_type)
    endpoint.entity = node.entity(
        kind, endpoint.service, endpoint.srv_type, reg.type_hash(endpoint.srv_type), SERVICE_QOS
    )
    endpoint.token_key = endpoint.entity.token()
    endpoint.gid = gid_of(endpoint.token_key)


class PendingRequest:
    """A request the server has received and not yet answered.

    Lets an executor answer from its own thread after the Zenoh callback returned: call
    :meth:`reply` exactly once.
    """

    def __init__(self, server: ServiceServer, query: Any, request: Any, attachment: Attachment):
        self._server = server
        self._query = query
        self.request = request
        self.attachment = attachment
        self._done = False

    @property
    def caller(self) -> str:
        """The client's node from the graph (its GID is its client token's hash), or
        ``"GID <hex>"`` if no client token with that GID is known."""
        node = self._server.caller_node(self.attachment.gid)
        return node if node is not None else f"GID {self.attachment.gid.hex()}"

    @contextmanager
    def handling(self) -> Iterator[PendingRequest]:
        """While in this block, :func:`current_caller` names this request's caller (an
        executor wraps the handler call in it)."""
        token = _handling.set(self)
        try:
            yield self
        finally:
            _handling.reset(token)

    def reply(self, response: Any) -> None:
        """Send the response (serialized per the service's response type)."""
        if self._done:
            raise RuntimeError("this request was already answered")
        self._done = True
        server = self._server
        try:
            payload = server._serialize(response)
        except Exception as exc:
            self.fail(f"the server built a response that does not serialize: {exc}")
            return
        attachment = Attachment(
            self.attachment.sequence_number, time.time_ns(), self.attachment.gid
        ).encode()
        try:
            self._query.reply(server.key, payload, attachment=attachment, **server._reply_options)
        finally:
            self._release()

    def fail(self, message: str) -> None:
        """Answer with an error reply instead of a response."""
        self._done = True
        try:
            self._query.reply_err(message.encode())
        finally:
            self._release()

    def _release(self) -> None:
        # Dropping the query finalizes it, which tells the client no more replies come.
        try:
            self._query.drop()
        except Exception as exc:  # finalized already (the session closing): nothing waits
            swallowed("service request: query not dropped", exc)
        self._query = None


class ServiceServer:
    """Answers one service. Create through :meth:`Node.service`.

    ``handler(request) -> response`` runs on the server's receiving thread unless
    ``deferred=True``, in which case ``handler(pending)`` receives a :class:`PendingRequest`
    to answer later. With ``raw=True``, requests and responses are CDR bytes, never decoded
    (a bridge's relay).

    The receiving thread is a Python thread of the server's own, fed by Zenoh, so a handler
    may block. A deferred handler that only queues the request and never blocks (an
    executor's) says ``queue_only=True``: it then runs on Zenoh's network thread itself,
    which spares a thread's wake-up per request; on a loaded computer, that wake-up alone
    can delay a halt by tens of milliseconds. An ``urgent`` server (a halt) answers at
    Zenoh's real-time priority, unbatched, as an urgent call asks
    (:meth:`ServiceClient.call_async`).
    """

    def __init__(
        self,
        node: Node,
        service: str,
        srv_type: str,
        handler: Callable[[Any], Any],
        deferred: bool = False,
        raw: bool = False,
        queue_only: bool = False,
        urgent: bool = False,
    ) -> None:
        _identify(self, node, EntityKind.SERVICE, service, srv_type)
        import zenoh

        reg = registry()
        self._deserialize: Callable[[bytes], Any] = bytes
        self._serialize: Callable[[Any], bytes] = bytes
        if not raw:
            self._deserialize = reg.deserializer(self.parts.request, stream=True)
            self._serialize = reg.serializer(self.parts.response, stream=True)
        self._handler = handler
        self._deferred = deferred
        self._reply_options = _urgency(urgent)
        # Callers by GID, from the client tokens of this service (with history, so clients
        # that existed before this server are known too): who asked, for handlers that log it.
        self._callers: dict[bytes, str] = {}
        self._callers_lock = threading.Lock()
        self._clients = follow_tokens(
            node.session,
            f"{PREFIX}/{node.domain}/*/*/*/{EntityKind.CLIENT.value}/*/*/*/"
            f"{mangle(self.service)}/*/*/*",
            self._on_client_token,
        )
        try:
            self._zqueryable = node.session.declare_queryable(
                self.key,
                zenoh.handlers.Callback(self._on_query, indirect=not (deferred and queue_only)),
                complete=True,
            )
        except Exception:
            self._clients.undeclare()
            raise
        self._token = node.session.liveliness().declare_token(self.token_key)
        self._closed = False

    def _on_client_token(self, sample: Any) -> None:
        import zenoh

        key = str(sample.key_expr)
        try:
            node = Entity.parse(key).node_fqn
        except TokenError:
            return
        gid = gid_of(key)
        with self._callers_lock:
            if sample.kind != zenoh.SampleKind.PUT:
                self._callers.pop(gid, None)
            elif len(self._callers) < MAX_CALLERS:
                self._callers[gid] = node

    def caller_node(self, gid: bytes) -> str | None:
        """The node of the client with this GID, if its token is known."""
        with self._callers_lock:
            return self._callers.get(gid)

    def _on_query(self, query: Any) -> None:
        if query.attachment is None:
            drops.drop(self.service, "bad_attachment", "request without attachment")
            query.reply_err(b"service request without attachment")
            return
        try:
            attachment = Attachment.decode(query.attachment.to_bytes())
        except AttachmentError as exc:
            drops.drop(self.service, "bad_attachment", str(exc))
            query.reply_err(f"bad attachment: {exc}".encode())
            return
        payload = query.payload.to_bytes() if query.payload is not None else b""
        try:
            request = self._deserialize(payload)
        except Exception as exc:
            drops.drop(self.service, "malformed", f"{type(exc).__name__}: {exc}")
            query.reply_err(f"malformed request for {self.srv_type}".encode())
            return
        pending = PendingRequest(self, query, request, attachment)
        if self._deferred:
            self._handler(pending)
            return
        try:
            with pending.handling():
                response = self._handler(request)
        except Exception as exc:
            log.exception("service %s handler failed", self.service)
            drops.drop(self.service, "handler_error")
            pending.fail(f"{self.service} failed: {type(exc).__name__}: {exc}")
            return
        pending.reply(response)

    def close(self) -> None:
        """Undeclare the queryable and its token (idempotent)."""
        if self._closed:
            return
        self._closed = True
        for thing in (self._token, self._zqueryable, self._clients):
            try:
                thing.undeclare()
            except Exception as exc:  # the session may be closed already
                swallowed(f"service {self.service}: not undeclared", exc)


class ServiceClient:
    """Calls one service. Create through :meth:`Node.client`.

    Args:
        node: Its node.
        service: The service's name.
        srv_type: The service's type.
        announce: Declare its liveliness token (the graph's ``SC``) now. An e-stop's client
            declares it only after its first requests left (:meth:`announce`): every
            process watching the graph wakes for a new token, and on a loaded computer
            that wake-up, arriving with the halt, delayed the halt by 20-40 ms.
    """

    def __init__(self, node: Node, service: str, srv_type: str, announce: bool = True) -> None:
        _identify(self, node, EntityKind.CLIENT, service, srv_type)
        reg = registry()
        self._serialize = reg.serializer(self.parts.request, stream=True)
        self._deserialize = reg.deserializer(self.parts.response, stream=True)
        self._session = node.session
        self._seq = itertools.count(1)
        self._token: Any = None
        self._closed = False
        if announce:
            self.announce()

    def announce(self) -> None:
        """Declare this client's liveliness token, if not yet (idempotent)."""
        if self._token is None and not self._closed:
            self._token = self._session.liveliness().declare_token(self.token_key)

    def request_type(self) -> type:
        """The request message class (build requests with it)."""
        return registry().msg_class(self.parts.request)

    def call(self, request: Any, timeout: float = 2.0) -> Any:
        """Send ``request`` and wait for the response.

        Raises:
            ServiceTimeout: If no server answered within ``timeout`` seconds.
            ServiceError: If the server answered with an error or an undecodable response.
        """
        payload = self.call_raw(self._serialize(request), timeout)
        try:
            return self._deserialize(payload)
        except Exception as exc:
            drops.drop(self.service, "malformed", f"{type(exc).__name__}: {exc}")
            raise ServiceError(
                f"service {self.service} sent a response that is not a {self.parts.response}"
            ) from exc

    def call_raw(self, payload: bytes, timeout: float = 2.0) -> bytes:
        """Send a serialized request (CDR with header), return the serialized response as it
        came (a bridge relays both without decoding them).

        Raises:
            ServiceTimeout: If no server answered within ``timeout`` seconds.
            ServiceError: If the server answered with an error.
        """
        import zenoh

        seq = next(self._seq)
        attachment = Attachment(seq, time.time_ns(), self.gid).encode()
        started = time.monotonic()
        replies = self._session.get(
            self.key,
            payload=bytes(payload),
            attachment=attachment,
            target=zenoh.QueryTarget.ALL_COMPLETE,
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=timeout,
        )
        for reply in replies:
            if _timed_out(reply):
                continue  # said below, as no answer
            if reply.err is not None:
                text = reply.err.payload.to_bytes().decode(errors="replace")
                raise ServiceError(f"service {self.service} answered with an error: {text}")
            return reply.ok.payload.to_bytes()
        waited = time.monotonic() - started
        if waited < 0.9 * timeout:
            # The query ended early: the network knows no server for this key at all.
            raise NoServer(
                f"no server of {self.service} ({self.srv_type}) on the network: the query "
                f"ended after {waited:.1f} s with no answer; check it is running "
                "(`msctl service list`)"
            )
        raise ServiceTimeout(
            f"no server answered {self.service} ({self.srv_type}) within {timeout:g} s; "
            "check it is running (`msctl service list`)"
        )

    def call_async(self, request: Any, timeout: float = 2.0, urgent: bool = False) -> PendingCall:
        """Send ``request`` and return at once; the answer arrives on a Zenoh thread.

        Many calls sent this way are in flight together (an e-stop reaching every module at
        once), each stamped with the moment its own answer came.

        Args:
            request: The request message.
            timeout: Seconds to wait for an answer.
            urgent: Send it at Zenoh's real-time priority, unbatched (a halt): on every
                link, it leaves before the samples queued there.
        """
        import zenoh

        call = PendingCall(self, timeout)
        attachment = Attachment(next(self._seq), time.time_ns(), self.gid).encode()
        call.started = time.monotonic()
        self._session.get(
            self.key,
            # The answer's callback only decodes it and sets an event: on Zenoh's own thread,
            # no Python thread of its own has to be woken (and, per call, started).
            zenoh.handlers.Callback(call._on_reply, call._on_end, indirect=False),
            payload=self._serialize(request),
            **_urgency(urgent),
            attachment=attachment,
            target=zenoh.QueryTarget.ALL_COMPLETE,
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=timeout,
        )
        return call

    def call_repeating(self, request: Any, timeout: float, every: float) -> Any:
        """Send ``request``, and again every ``every`` seconds with no answer, until one of
        them is answered or ``timeout`` seconds have passed; every copy waits to the end.

        For a request that is safe to repeat, over a link that may close while it waits: a
        closed link loses the query or its answer for good (nothing resends it when the link
        reopens). Earlier copies stay open, so a server that takes longer than ``every`` to
        answer (and answers its requests in order) is still heard.

        Raises:
            NoServer: If every copy ended early with no answer (the network knew no server).
            ServiceTimeout: If no copy was answered within ``timeout`` seconds.
            ServiceError: If the server answered with an error or an undecodable response.
        """
        deadline = time.monotonic() + timeout
        calls: list[PendingCall] = []
        sent = 0
        while True:
            now = time.monotonic()
            calls.append(self.call_async(request, timeout=max(deadline - now, 0.1)))
            sent += 1
            again = min(deadline, now + every)
            while time.monotonic() < again:
                answered = next((c for c in calls if c.answered is not None), None)
                if answered is not None:
                    return answered.result(0.0)
                if all(c.done.is_set() for c in calls):
                    return calls[-1].result(0.0)  # raises: why the last copy got no answer
                calls[-1].done.wait(0.05)
            if time.monotonic() >= deadline - 0.05:
                # The last copies may still be ending: their answers are not awaited.
                answered = next((c for c in calls if c.answered is not None), None)
                if answered is not None:
                    return answered.result(0.0)
                times = f" (asked {sent} times)" if sent > 1 else ""
                raise ServiceTimeout(
                    f"no server answered {self.service} ({self.srv_type}) within {timeout:g} s"
                    f"{times}; check it is running (`msctl service list`)"
                )

    def close(self) -> None:
        """Undeclare the client's token (idempotent)."""
        if self._closed:
            return
        self._closed = True
        if self._token is None:
            return
        try:
            self._token.undeclare()
        except Exception as exc:  # the session may be closed already
            swallowed(f"client of {self.service}: token not undeclared", exc)


def _urgency(urgent: bool) -> dict[str, Any]:
    """Zenoh's options for an urgent request or its answer (none for the others)."""
    if not urgent:
        return {}
    import zenoh

    return {"priority": zenoh.Priority.REAL_TIME, "express": True}


class PendingCall:
    """A service call in flight, made by :meth:`ServiceClient.call_async`.

    Attributes:
        started: ``time.monotonic()`` when the request was sent.
        answered: ``time.monotonic()`` when the answer (or the error reply) came; ``None``
            until then, and for a call no server answered.
        done: Set once the call is over: answered, refused, or out of time.
    """

    def __init__(self, client: ServiceClient, timeout: float) -> None:
        self._client = client
        self._timeout = timeout
        self.started = 0.0
        self.answered: float | None = None
        self.done = threading.Event()
        self._response: Any = None
        self._error: ServiceError | None = None

    def _on_reply(self, reply: Any) -> None:
        if self.answered is not None or _timed_out(reply):
            return  # the first answer counts (one server per service); a timeout is none
        now = time.monotonic()
        client = self._client
        if reply.err is not None:
            text = reply.err.payload.to_bytes().decode(errors="replace")
            self._error = ServiceError(f"service {client.service} answered with an error: {text}")
        else:
            try:
                self._response = client._deserialize(reply.ok.payload.to_bytes())
            except Exception as exc:
                drops.drop(client.service, "malformed", f"{type(exc).__name__}: {exc}")
                self._error = ServiceError(
                    f"service {client.service} sent a response that is not a "
                    f"{client.srv_type} response"
                )
        self.answered = now
        self.done.set()

    def _on_end(self) -> None:
        if self.answered is None:
            waited = time.monotonic() - self.started
            client = self._client
            if waited < 0.9 * self._timeout:
                self._error = NoServer(
                    f"no server of {client.service} ({client.srv_type}) on the network: the "
                    f"query ended after {waited:.1f} s with no answer; check it is running "
                    "(`msctl service list`)"
                )
            else:
                self._error = ServiceTimeout(
                    f"no server answered {client.service} ({client.srv_type}) within "
                    f"{self._timeout:g} s; check it is running (`msctl service list`)"
                )
        self.done.set()

    def error(self) -> ServiceError | None:
        """Why the call failed (an error reply, or no answer once it is over); ``None`` while
        it is in flight or when it was answered."""
        return self._error

    @property
    def reached_nobody(self) -> bool:
        """The call ended early with no answer (:class:`NoServer`)."""
        return isinstance(self._error, NoServer)

    @property
    def seconds(self) -> float | None:
        """From sending to the answer (``None`` if none came)."""
        return None if self.answered is None else self.answered - self.started

    def result(self, timeout: float | None = None) -> Any:
        """The response, waiting for it up to ``timeout`` seconds more (default: the call's
        own timeout and a margin).

        Raises:
            ServiceTimeout: If no server answered.
            ServiceError: If the server answered with an error or an undecodable response.
        """
        if not self.done.wait(self._timeout + 1.0 if timeout is None else timeout):
            raise ServiceTimeout(
                f"no server answered {self._client.service} within {self._timeout:g} s"
            )
        if self._error is not None:
            raise self._error
        return self._response


def _timed_out(reply: Any) -> bool:
    """Whether ``reply`` is Zenoh's own ``Timeout`` error at the query's end (sent by this
    session or by the router, so its replier says nothing), which means no answer rather
    than an answer. A server's error reply is never that one word (rmw_zenoh's and ours
    say what failed)."""
    return reply.err is not None and reply.err.payload.to_bytes() == b"Timeout"
