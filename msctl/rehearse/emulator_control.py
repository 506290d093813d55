"""The link emulator's control socket: its protocol, its client, and the emulator's side.

The control socket speaks one JSON object per line each way (see :func:`control`):

- ``{"op": "status"}``: per host its address, profile and both directions' counters;
- ``{"op": "set", "host": H, "profile": P}``: change a host's link profile, live;
- ``{"op": "down", "host": H, "seconds": S}``: an outage of ``S`` seconds (null: until up);
- ``{"op": "up", "host": H}``: end any outage;
- ``{"op": "stop"}``: exit (as SIGTERM and SIGINT do).

Every reply has ``"ok"``; a refused request is ``{"ok": false, "error": "..."}`` naming
what is wrong (and the known hosts or profiles), never a crash of the emulator.
"""

from __future__ import annotations

import json
import logging
import math
import os
import selectors
import socket
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from msctl.errors import (
    InputError,
    MsctlError,
    NetworkError,
    NotFoundError,
    OperationTimeout,
    did_you_mean,
)
from msctl.rehearse.profiles import find_profile

if TYPE_CHECKING:
    from msctl.rehearse.emulator import _Host
    from msctl.rehearse.emulator_spec import Spec
    from msctl.rehearse.link_profile import LinkProfile

log = logging.getLogger(__name__)

#: Longest line the control socket accepts, bytes.
MAX_REQUEST = 64 * 1024

#: Operations of the control protocol.
OPS = ("status", "set", "down", "up", "stop")


def control(socket_path: Path, request: Mapping[str, Any], timeout: float = 5.0) -> dict[str, Any]:
    """Send one request to a running emulator and return its reply.

    Args:
        socket_path: The emulator's control socket (the spec's ``control``).
        request: ``{"op": "status"}`` and the like (see the module's docstring).
        timeout: Seconds to wait for the reply.

    Returns:
        The reply; ``reply["ok"]`` is False for a refused request, with ``reply["error"]``.

    Raises:
        NetworkError: No emulator answers at ``socket_path``.
        OperationTimeout: It did not reply in time.
    """
    path = Path(socket_path)
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(timeout)
        try:
            sock.connect(str(path))
        except (FileNotFoundError, ConnectionRefusedError) as error:
            raise NetworkError(
                f"no link emulator is running at {path} ({error.strerror})",
                hint="start the rehearsal (`msctl rehearse`) first",
            ) from None
        except TimeoutError:
            raise OperationTimeout(
                f"the link emulator at {path} did not accept in {timeout} s"
            ) from None
        data = b""
        try:
            sock.sendall(json.dumps(dict(request)).encode() + b"\n")
            while not data.endswith(b"\n"):
                chunk = sock.recv(65536)
                if not chunk:
                    break
                data += chunk
        except TimeoutError:
            raise OperationTimeout(
                f"the link emulator at {path} did not answer {request!r} in {timeout} s"
            ) from None
        except (BrokenPipeError, ConnectionResetError) as error:
            raise NetworkError(f"the link emulator at {path} hung up: {error}") from None
    if not data.endswith(b"\n"):
        raise NetworkError(f"the link emulator at {path} hung up before answering {request!r}")
    return json.loads(data)


@dataclass(eq=False)
class ControlClient:
    """A control connection: what it sent that is not a whole line yet, what is not sent."""

    sock: socket.socket
    inbox: bytes = b""
    outbox: bytes = b""


class _Refused(Exception):
    """A control request refused; its message is the reply's error."""


class ControlSocket:
    """The emulator's control socket: accepting clients, reading their lines, answering them.

    A mixin of the emulator's loop (:class:`~msctl.rehearse.emulator._Emulator`), which
    owns the attributes below and calls :meth:`listen` once, then :meth:`_accept` and
    :meth:`_serve` as its selector says.
    """

    spec: Spec
    profiles: dict[str, LinkProfile]
    started: float
    hosts: list[_Host]
    by_name: dict[str, _Host]
    selector: selectors.BaseSelector
    listener: socket.socket | None
    clients: dict[int, ControlClient]
    stopping: bool

    def listen(self) -> None:
        path = self.spec.control
        if len(os.fsencode(path)) >= 108:
            raise InputError(f"control socket path too long for a unix socket: {path}")
        if path.exists():
            # A socket left by an emulator that died is removed; a live one is refused.
            try:
                control(path, {"op": "status"}, timeout=1.0)
            except MsctlError:
                path.unlink()
            else:
                raise MsctlError(f"a link emulator already answers at {path}", exit_code=3)
        path.parent.mkdir(parents=True, exist_ok=True)
        listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        listener.bind(str(path))
        listener.listen(16)
        listener.setblocking(False)
        self.listener = listener
        self.selector.register(listener, selectors.EVENT_READ, "accept")

    def _accept(self) -> None:
        assert self.listener is not None
        try:
            sock, _ = self.listener.accept()
        except BlockingIOError:
            return
        sock.setblocking(False)
        client = ControlClient(sock)
        self.clients[sock.fileno()] = client
        self.selector.register(sock, selectors.EVENT_READ, client)

    def _serve(self, client: ControlClient, mask: int) -> None:
        if mask & selectors.EVENT_WRITE:
            self._flush(client)
        if not mask & selectors.EVENT_READ:
            return
        try:
            data = client.sock.recv(65536)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:
            self._drop_client(client)
            return
        client.inbox += data
        while b"\n" in client.inbox:
            line, client.inbox = client.inbox.split(b"\n", 1)
            if line.strip():
                client.outbox += json.dumps(self.handle(line)).encode() + b"\n"
        if len(client.inbox) > MAX_REQUEST:
            client.outbox += (
                json.dumps({"ok": False, "error": f"request longer than {MAX_REQUEST} bytes"})
                + "\n"
            ).encode()
            client.inbox = b""
        self._flush(client)

    def _flush(self, client: ControlClient) -> None:
        if client.outbox:
            try:
                sent = client.sock.send(client.outbox)
                client.outbox = client.outbox[sent:]
            except BlockingIOError:
                pass
            except OSError:
                self._drop_client(client)
                return
        if client.sock.fileno() < 0:
            return
        events = selectors.EVENT_READ | (selectors.EVENT_WRITE if client.outbox else 0)
        self.selector.modify(client.sock, events, client)

    def _drop_client(self, client: ControlClient) -> None:
        if client.sock.fileno() >= 0:
            self.clients.pop(client.sock.fileno(), None)
            try:
                self.selector.unregister(client.sock)
            except (KeyError, ValueError):
                pass
            client.sock.close()

    def handle(self, line: bytes) -> dict[str, Any]:
        """One control request's reply (never raises)."""
        try:
            request = json.loads(line)
        except ValueError as error:
            return {
                "ok": False,
                "error": f"a request is one JSON object per line: {error}",
            }
        try:
            if not isinstance(request, dict):
                raise _Refused(
                    f'a request is a JSON object like {{"op": "status"}}, got {request!r}'
                )
            op = request.get("op")
            if op not in OPS:
                near = did_you_mean(str(op), OPS) if isinstance(op, str) else ""
                raise _Refused(
                    f"unknown op {op!r}"
                    + (f" ({near})" if near else "")
                    + f"; ops: {', '.join(OPS)}"
                )
            return {"ok": True, **getattr(self, f"_op_{op}")(request, time.monotonic())}
        except _Refused as refused:
            return {"ok": False, "error": str(refused)}
        except Exception as error:  # a bug here must not take the whole rehearsal down
            log.exception("control request %r", request)
            return {
                "ok": False,
                "error": f"internal error: {type(error).__name__}: {error}",
            }

    def _host_of(self, request: Mapping[str, Any]) -> _Host:
        name = request.get("host")
        names = list(self.by_name)
        if name is None:
            raise _Refused(f"{request['op']!r} needs a host: one of {', '.join(names)}")
        host = self.by_name.get(name) if isinstance(name, str) else None
        if host is None:
            near = did_you_mean(str(name), names)
            raise _Refused(
                f"no host {name!r}"
                + (f" ({near})" if near else "")
                + f"; hosts: {', '.join(names)}"
            )
        return host

    def _op_status(self, _request: Mapping[str, Any], now: float) -> dict[str, Any]:
        return {
            "seed": self.spec.seed,
            "uptime_s": now - self.started,
            "hosts": {
                host.spec.name: {
                    "address": host.spec.address,
                    "netns": host.spec.netns,
                    "device": host.spec.device,
                    "profile": host.profile,
                    "unroutable": dict(host.unroutable),
                    "device_error": host.device_error,
                    "up": host.link.up.status(now),
                    "down": host.link.down.status(now),
                }
                for host in self.hosts
            },
        }

    def _op_set(self, request: Mapping[str, Any], now: float) -> dict[str, Any]:
        host = self._host_of(request)
        name = request.get("profile")
        if not isinstance(name, str):
            raise _Refused(f"'set' needs a profile: one of {', '.join(self.profiles)}")
        try:
            profile = find_profile(self.profiles, name)
        except NotFoundError as error:
            raise _Refused(error.message) from None
        host.link.set_profile(profile, now)
        host.profile = name
        log.info("%s: profile %s", host.spec.name, name)
        return {"host": host.spec.name, "profile": name}

    def _op_down(self, request: Mapping[str, Any], now: float) -> dict[str, Any]:
        host = self._host_of(request)
        seconds = request.get("seconds")
        if seconds is not None and (
            isinstance(seconds, bool)
            or not isinstance(seconds, int | float)
            or not math.isfinite(seconds)
            or seconds <= 0
        ):
            raise _Refused(f"seconds must be a number above 0, or null (until up), got {seconds!r}")
        host.link.take_down(now, seconds)
        log.info(
            "%s: down for %s",
            host.spec.name,
            "ever" if seconds is None else f"{seconds} s",
        )
        return {"host": host.spec.name, "outage": _outage(host, now)}

    def _op_up(self, request: Mapping[str, Any], now: float) -> dict[str, Any]:
        host = self._host_of(request)
        host.link.bring_up(now)
        log.info("%s: up", host.spec.name)
        return {"host": host.spec.name, "outage": _outage(host, now)}

    def _op_stop(self, _request: Mapping[str, Any], _now: float) -> dict[str, Any]:
        log.info("stopping on request")
        self.stopping = True
        return {"stopping": True}


def _outage(host: _Host, now: float) -> dict[str, Any] | None:
    outage = host.link.up.outage(now)
    return None if outage is None else outage.as_dict(now)
