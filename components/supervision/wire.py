"""Supervisor requests on the wire, and the one client every asker uses.

A request is written and its response read directly as the CDR rmw_zenoh carries
(``msctl_msgs/srv/AgentRequest``: two strings out, a bool and two strings back), with the
service's type hash as a constant: the type registry (rosbags, numpy and every bundled
definition, about 0.2 s of CPU) is not needed to ask a supervisor, so ``msctl ps`` does
not pay for it. Tests check both against the registry, so a change to ``AgentRequest.srv``
cannot go unnoticed.

Measured worth its copy (``bench/agent_wire.py``, both in one run): the first request of a
fresh process costs 0.05 ms of CPU here against 207 ms through the registry's codec (4.2 s of
wall clock on a loaded 2-core machine), which every ``msctl ps`` would pay. Call for call the
copy is the slower one (0.1 to 0.3 ms against 0.04 ms for the generated codec), which no
asker notices: a request is a network round trip, and the busiest asker polls once a second.
"""

from __future__ import annotations

import itertools
import json
import struct
import time
from typing import Any, NamedTuple

from components.comm.services import SERVICE_QOS, NoServer, ServiceClient, ServiceError
from components.comm.stats import drops
from components.supervision.contract import AGENT_SRV, RequestError, encode_args, host_namespace

#: RIHS01 hash of ``msctl_msgs/srv/AgentRequest`` (REP 2011), as the registry computes it.
AGENT_SRV_HASH = "RIHS01_f040da378ba4fa64a6b18717e7ead7c77c781135f7ece84dbd266048518b760e"
#: CDR encapsulation headers: little- and big-endian plain CDR.
_CDR_LE = b"\x00\x01\x00\x00"
_CDR_BE = b"\x00\x00\x00\x00"


class AgentResponse(NamedTuple):
    """A supervisor's answer as it travels: ``payload`` is JSON text (an error's too)."""

    success: bool
    message: str
    payload: str


def encode_request(verb: str, args: str) -> bytes:
    """``AgentRequest_Request(verb, args)`` as little-endian CDR with its header."""
    body = bytearray()
    for text in (verb, args):
        body += b"\x00" * (-len(body) % 4)  # a string's length is 4-aligned
        data = text.encode() + b"\x00"
        body += struct.pack("<I", len(data)) + data
    return _CDR_LE + bytes(body)


def decode_response(data: bytes) -> AgentResponse:
    """Read an ``AgentRequest_Response`` (CDR with its header).

    Raises:
        ValueError: If ``data`` is not one.
    """
    header, body = bytes(data[:4]), memoryview(data)[4:]
    if header not in (_CDR_LE, _CDR_BE):
        raise ValueError(f"not plain CDR (header {header.hex()})")
    order = "<" if header == _CDR_LE else ">"
    if len(body) < 1 or body[0] > 1:
        raise ValueError("no bool success")
    success, offset = bool(body[0]), 1
    texts = []
    for _ in range(2):
        offset += -offset % 4
        if offset + 4 > len(body):
            raise ValueError("truncated")
        (size,) = struct.unpack_from(order + "I", body, offset)
        start, offset = offset + 4, offset + 4 + size
        if size < 1 or offset > len(body) or body[offset - 1] != 0:
            raise ValueError("malformed string")
        texts.append(bytes(body[start : offset - 1]).decode())
    return AgentResponse(success, texts[0], texts[1])


class _Request(NamedTuple):
    """A request as :meth:`SupervisorClient.call_async` sends it."""

    verb: str
    args: str


class SupervisorClient(ServiceClient):
    """A client of one supervisor's request service (``/msctl/<host>/request``, or an
    agent's ``/msctl/<host>/workspace``): the same graph token, key, attachment and errors
    as a :class:`ServiceClient` (whose :meth:`call_raw` and :meth:`call_repeating` it uses),
    with the request and response coded here. Close it when done.

    Args:
        node: The asking node.
        service: The supervisor's service.
    """

    def __init__(self, node: Any, service: str) -> None:  # no registry: no super().__init__
        from components.comm.attachment import gid_of
        from components.comm.liveliness import EntityKind
        from components.comm.names import key_name, qualify
        from components.comm.types import dds_type_name

        self.service = qualify(service, node.namespace, node.name)
        self.srv_type = AGENT_SRV
        self.key = f"{node.domain}/{key_name(self.service)}/{dds_type_name(AGENT_SRV)}/"
        self.key += AGENT_SRV_HASH
        self.entity = node.entity(
            EntityKind.CLIENT, self.service, AGENT_SRV, AGENT_SRV_HASH, SERVICE_QOS
        )
        self.token_key = self.entity.token()
        self.gid = gid_of(self.token_key)
        self._session = node.session
        self._seq = itertools.count(1)
        self._token = node.session.liveliness().declare_token(self.token_key)
        self._closed = False
        # What ServiceClient.call_async codes with (a request with ``verb`` and ``args``).
        self._serialize = lambda request: encode_request(request.verb, request.args)
        self._deserialize = decode_response

    def ask(self, verb: str, args: str, timeout: float) -> AgentResponse:
        """Send one request and wait for the answer.

        Raises:
            ServiceTimeout: If no supervisor answered within ``timeout`` seconds.
            ServiceError: If it answered with an error or something that is not a response.
        """
        payload = self.call_raw(encode_request(verb, args), timeout)
        try:
            return decode_response(payload)
        except (ValueError, UnicodeDecodeError) as exc:
            drops.drop(self.service, "malformed", f"{type(exc).__name__}: {exc}")
            raise ServiceError(
                f"service {self.service} sent a response that is not a {AGENT_SRV}_Response"
            ) from exc

    def ask_repeating(self, verb: str, args: str, timeout: float, every: float) -> AgentResponse:
        """:meth:`ask`, sent again every ``every`` seconds with no answer, the first answer
        taken (:meth:`ServiceClient.call_repeating`: only for a verb safe to repeat)."""
        return self.call_repeating(_Request(verb, args), timeout, every)

    def call(self, request: Any, timeout: float = 2.0) -> AgentResponse:
        """:meth:`ask` with a request that has ``verb`` and ``args`` (as a registry-made
        ``AgentRequest_Request`` has)."""
        return self.ask(request.verb, request.args, timeout)

    def payload(
        self,
        verb: str,
        args: dict[str, Any] | None = None,
        timeout: float = 5.0,
        grace: float = 0.0,
        attempt: float | None = None,
    ) -> Any:
        """Send a request and return the decoded payload of its answer.

        Args:
            verb: The request's verb.
            args: Its arguments.
            timeout: Seconds to wait for the answer.
            grace: Seconds to keep sending it again while its query ends early with no
                answer (the router knows no server for it: a radio link's route that lapsed
                for a moment is not an agent gone). Only for a verb that is safe to repeat:
                a query that ended early may still have reached its server.
            attempt: Seconds with no answer before the request is sent again (the earlier
                copies still waiting), until ``timeout``; ``None`` sends it once. A radio
                link that closes while a query waits loses the query or its answer for good
                (nothing resends it when the link reopens): only a verb safe to repeat.

        Raises:
            ServiceTimeout: If nobody answered.
            RequestError: If the supervisor refused the request (its message).
        """
        request = _Request(verb, encode_args(args))
        started = time.monotonic()
        while True:
            left = max(timeout - (time.monotonic() - started), 0.1)
            try:
                response = self.call_repeating(request, left, attempt or left)
                break
            except NoServer:
                if time.monotonic() - started + 0.25 >= min(grace, timeout):
                    raise
                time.sleep(0.25)
        if not response.success:
            raise RequestError(response.message)
        return json.loads(response.payload) if response.payload else {}


def call_supervisor(
    node: Any,
    host: str,
    verb: str,
    args: dict[str, Any] | None = None,
    timeout: float = 5.0,
    grace: float = 0.0,
    attempt: float | None = None,
) -> dict[str, Any]:
    """Send one request to ``host``'s supervisor and return its decoded payload
    (:meth:`SupervisorClient.payload`, with a client for that one request).

    Raises:
        ServiceTimeout: If nobody answers for that host.
        RequestError: If the supervisor refused the request ("<host> refused <verb>: why").
    """
    client = SupervisorClient(node, f"{host_namespace(host)}/request")
    try:
        return client.payload(verb, args, timeout, grace, attempt)
    except RequestError as exc:
        raise RequestError(f"{host} refused {verb}: {exc}") from None
    finally:
        client.close()
