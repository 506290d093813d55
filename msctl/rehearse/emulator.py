"""The simulated access point of ``msctl rehearse``: one process that links every computer.

Each computer's network namespace gets a TUN device (IFF_TUN | IFF_NO_PI, not persistent:
it vanishes with this process, so a crash leaves nothing behind) holding the computer's
address on the rehearsal's subnet. An IPv4 packet a computer sends to another one's address
comes out of the sender's TUN here, goes through the sender's ``up``
:class:`~msctl.rehearse.link.LinkDirection`, then through the receiver's ``down`` one, and
is written to the receiver's TUN when both let it leave. Anything else (unknown addresses,
broadcast, multicast, not IPv4) is dropped and counted per sender.

Run it as ``python -m msctl.rehearse.emulator SPEC.json`` (as root, or inside the user
namespace that owns the namespaces: it enters them and creates devices), or call
:func:`serve`. The spec (:class:`Spec`) is JSON::

    {
      "control": "/run/msr/ctl.sock",          # unix socket of the control protocol
      "ready": "/run/msr/ready",               # written (atomically) once every device is up
      "seed": 1,                                # seeds every link (a run can be replayed)
      "profiles_file": null,                    # a user profiles file, null: $MSCTL_LINK_PROFILES
      "subnet": "10.77.0.0/24",
      "hosts": [
        {"name": "ground1", "netns": "msr-ab12-ground1", "address": "10.77.0.11",
         "profile": "wifi", "device": "rh0"}
      ]
    }

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

import ctypes
import errno
import fcntl
import heapq
import ipaddress
import itertools
import json
import logging
import math
import os
import re
import selectors
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from msctl.errors import (
    InputError,
    MsctlError,
    NetworkError,
    NotFoundError,
    OperationTimeout,
    did_you_mean,
)
from msctl.rehearse.link import Link
from msctl.rehearse.link_profile import LinkProfile
from msctl.rehearse.profiles import find_profile, load_profiles

log = logging.getLogger(__name__)

T = TypeVar("T")

#: MTU of every TUN device: below Ethernet's 1500 so that the rehearsal's packets also fit
#: through a tunnel or VPN in the field.
MTU = 1400

#: Packets read from one TUN device before the loop looks at the others (fairness).
READ_BATCH = 64

#: Longest line the control socket accepts, bytes.
MAX_REQUEST = 64 * 1024

#: Operations of the control protocol.
OPS = ("status", "set", "down", "up", "stop")

#: Why an IPv4 packet could not be routed; the keys of a host's ``unroutable`` counters.
UNROUTABLE = ("not_ipv4", "unknown", "broadcast", "multicast")

_CLONE_NEWNET = 0x40000000
_TUNSETIFF = 0x400454CA
_IFF_TUN = 0x0001
_IFF_NO_PI = 0x1000
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
_SPEC_KEYS = ("control", "ready", "seed", "profiles_file", "subnet", "hosts")
_HOST_KEYS = ("name", "netns", "address", "profile", "device")


# --------------------------------------------------------------------------- the spec
@dataclass(frozen=True)
class HostSpec:
    """One computer of the rehearsal, as the emulator sees it.

    Attributes:
        name: The computer's name (``ground1``), as the control protocol names it.
        netns: Its network namespace, under ``/run/netns``.
        address: Its IPv4 address on the rehearsal's subnet.
        profile: The link profile it starts with.
        device: The TUN device's name in its namespace (15 characters at most).
    """

    name: str
    netns: str
    address: str
    profile: str
    device: str = "rh0"


@dataclass(frozen=True)
class Spec:
    """What the emulator serves. See the module's docstring for the JSON form.

    Attributes:
        control: The control socket's path.
        ready: The file written once every device is up.
        hosts: The computers, in order.
        seed: Seeds every link.
        profiles_file: A user profiles file over the built-ins; None: ``$MSCTL_LINK_PROFILES``.
        subnet: The rehearsal's IPv4 subnet; every address is in it.
    """

    control: Path
    ready: Path
    hosts: tuple[HostSpec, ...]
    seed: int = 0
    profiles_file: Path | None = None
    subnet: str = "10.77.0.0/24"

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], source: str = "spec") -> Spec:
        """A spec from its JSON form, checked.

        Args:
            data: The parsed JSON.
            source: Names the spec in errors (its file).

        Raises:
            InputError: Naming the source and the field at fault.
        """
        if not isinstance(data, Mapping):
            raise InputError(f"{source}: a spec is a JSON object, got {data!r}")
        _known_keys(data, _SPEC_KEYS, source)
        for key in ("control", "ready", "hosts"):
            if key not in data:
                raise InputError(f"{source}: {key} is missing")
        control, ready = (_text(data, key, source) for key in ("control", "ready"))
        seed = data.get("seed", 0)
        if isinstance(seed, bool) or not isinstance(seed, int):
            raise InputError(f"{source}: seed must be a whole number, got {seed!r}")
        profiles_file = data.get("profiles_file")
        if profiles_file is not None:
            profiles_file = Path(_text(data, "profiles_file", source))
        subnet_text = data.get("subnet", "10.77.0.0/24")
        try:
            subnet = ipaddress.IPv4Network(subnet_text)
        except (ValueError, TypeError) as error:
            raise InputError(
                f"{source}: subnet must be an IPv4 network like 10.77.0.0/24, got {subnet_text!r}"
            ) from error
        hosts_data = data["hosts"]
        if not isinstance(hosts_data, list) or not hosts_data:
            raise InputError(f"{source}: hosts must be a non-empty list, got {hosts_data!r}")
        hosts = tuple(
            _host(item, f"{source}: hosts[{index}]", subnet)
            for index, item in enumerate(hosts_data)
        )
        for key in ("name", "address"):
            seen: dict[str, str] = {}
            for host in hosts:
                value = getattr(host, key)
                if value in seen:
                    raise InputError(
                        f"{source}: hosts {seen[value]!r} and {host.name!r} have the same "
                        f"{key} {value!r}"
                    )
                seen[value] = host.name
        pairs = [(h.netns, h.device) for h in hosts]
        if len(set(pairs)) != len(pairs):
            raise InputError(f"{source}: two hosts have the same device in the same netns")
        return cls(
            control=Path(control),
            ready=Path(ready),
            hosts=hosts,
            seed=seed,
            profiles_file=profiles_file,
            subnet=str(subnet),
        )

    @classmethod
    def load(cls, path: Path) -> Spec:
        """A spec from a JSON file.

        Raises:
            NotFoundError: No such file.
            InputError: Not JSON, or a field at fault.
        """
        try:
            data = json.loads(Path(path).read_text())
        except FileNotFoundError:
            raise NotFoundError(f"{path}: no such emulator spec") from None
        except ValueError as error:
            raise InputError(f"{path}: not valid JSON: {error}") from error
        return cls.from_dict(data, str(path))

    def to_dict(self) -> dict[str, Any]:
        """The JSON form (what :meth:`from_dict` reads)."""
        return {
            "control": str(self.control),
            "ready": str(self.ready),
            "seed": self.seed,
            "profiles_file": None if self.profiles_file is None else str(self.profiles_file),
            "subnet": self.subnet,
            "hosts": [
                {
                    "name": h.name,
                    "netns": h.netns,
                    "address": h.address,
                    "profile": h.profile,
                    "device": h.device,
                }
                for h in self.hosts
            ],
        }


def _known_keys(data: Mapping[str, Any], known: Sequence[str], where: str) -> None:
    for key in data:
        if key not in known:
            near = did_you_mean(str(key), known)
            raise InputError(
                f"{where}: unknown field {key!r}"
                + (f" ({near})" if near else "")
                + f"; fields: {', '.join(known)}"
            )


def _text(data: Mapping[str, Any], key: str, where: str) -> str:
    value = data.get(key)
    if not isinstance(value, str) or not value:
        raise InputError(f"{where}: {key} must be a non-empty string, got {value!r}")
    return value


def _host(item: object, where: str, subnet: ipaddress.IPv4Network) -> HostSpec:
    if not isinstance(item, Mapping):
        raise InputError(f"{where} must be an object, got {item!r}")
    _known_keys(item, _HOST_KEYS, where)
    name, netns, address, profile = (
        _text(item, key, where) for key in ("name", "netns", "address", "profile")
    )
    device = _text(item, "device", where) if "device" in item else "rh0"
    for key, value in (("name", name), ("netns", netns), ("device", device)):
        if not _NAME.match(value):
            raise InputError(
                f"{where}: {key} must be letters, digits, '_', '.' or '-', got {value!r}"
            )
    if len(device) > 15:
        raise InputError(f"{where}: device must be at most 15 characters, got {device!r}")
    try:
        parsed = ipaddress.IPv4Address(address)
    except ValueError:
        raise InputError(f"{where}: address must be an IPv4 address, got {address!r}") from None
    if parsed not in subnet or parsed in (subnet.network_address, subnet.broadcast_address):
        raise InputError(f"{where}: address must be a host address of {subnet}, got {address!r}")
    return HostSpec(name=name, netns=netns, address=address, profile=profile, device=device)


# --------------------------------------------------------------------------- namespaces
def netns_path(netns: str) -> Path:
    """The file of a named network namespace (as ``ip netns add`` makes it)."""
    return Path("/run/netns") / netns


def run_in_netns(netns: str, function: Callable[[], T]) -> T:
    """Call ``function`` inside network namespace ``netns`` and return what it returns.

    It runs on a new thread that enters the namespace (setns only moves the calling thread)
    and then ends, so the caller's namespace never changes. Sockets and devices made there
    stay in that namespace after it returns: a socket opened this way talks from that
    computer. Needs CAP_SYS_ADMIN over it: root, or the user namespace that owns it.

    Raises:
        NotFoundError: No such namespace.
        OSError: The namespace could not be entered; or what ``function`` raised.
    """
    outcome: dict[str, Any] = {}

    def inside() -> None:
        try:
            try:
                fd = os.open(netns_path(netns), os.O_RDONLY | os.O_CLOEXEC)
            except FileNotFoundError:
                raise NotFoundError(
                    f"no network namespace {netns!r} (no {netns_path(netns)})",
                    hint="`ip netns list` shows the ones there are",
                ) from None
            try:
                libc = ctypes.CDLL(None, use_errno=True)
                if libc.setns(fd, _CLONE_NEWNET) != 0:
                    code = ctypes.get_errno()
                    raise OSError(
                        code, f"cannot enter network namespace {netns!r}: {os.strerror(code)}"
                    )
            finally:
                os.close(fd)
            outcome["value"] = function()
        except BaseException as error:
            outcome["error"] = error

    thread = threading.Thread(target=inside, name=f"netns-{netns}", daemon=True)
    thread.start()
    thread.join()
    if "error" in outcome:
        raise outcome["error"]
    return outcome["value"]


def open_tun(netns: str, device: str) -> int:
    """Create TUN device ``device`` in namespace ``netns`` (no packet info, non-blocking).

    It is not persistent: it goes away when the returned descriptor is closed. IPv6 is
    turned off on it, so the kernel sends no router solicitations or MLD reports through
    the radio.

    Returns:
        The device's descriptor.
    """

    def create() -> int:
        fd = os.open("/dev/net/tun", os.O_RDWR | os.O_CLOEXEC | os.O_NONBLOCK)
        try:
            request = struct.pack("16sH22x", device.encode(), _IFF_TUN | _IFF_NO_PI)
            fcntl.ioctl(fd, _TUNSETIFF, request)
        except OSError as error:
            os.close(fd)
            raise OSError(
                error.errno, f"cannot create TUN device {device!r} in {netns!r}: {error.strerror}"
            ) from error
        # /proc/sys/net shows the namespace of the thread that opens it: this one.
        ipv6 = Path(f"/proc/sys/net/ipv6/conf/{device}/disable_ipv6")
        if ipv6.exists():
            ipv6.write_text("1")
        return fd

    return run_in_netns(netns, create)


def _ip(netns: str, *args: str) -> None:
    command = ["ip", "-n", netns, *args]
    result = subprocess.run(command, capture_output=True, text=True, check=False)
    if result.returncode != 0:
        raise MsctlError(
            f"`{' '.join(command)}` failed: {result.stderr.strip() or result.returncode}",
            exit_code=3,
        )


# --------------------------------------------------------------------------- the client
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


# --------------------------------------------------------------------------- the server
@dataclass(eq=False)
class _Host:
    """A computer while the emulator runs."""

    spec: HostSpec
    index: int
    fd: int
    link: Link
    profile: str
    unroutable: dict[str, int] = field(default_factory=lambda: dict.fromkeys(UNROUTABLE, 0))
    #: Why its device can no longer be read (deleted under the emulator), or None.
    device_error: str | None = None


@dataclass(eq=False)
class _Client:
    """A control connection: what it sent that is not a whole line yet, what is not sent."""

    sock: socket.socket
    inbox: bytes = b""
    outbox: bytes = b""


class _Refused(Exception):
    """A control request refused; its message is the reply's error."""


class _Emulator:
    """The access point's loop. Built by :func:`serve`."""

    def __init__(self, spec: Spec, profiles: dict[str, LinkProfile], now: float) -> None:
        self.spec = spec
        self.profiles = profiles
        self.started = now
        self.hosts: list[_Host] = []
        self.by_name: dict[str, _Host] = {}
        self.by_address: dict[bytes, _Host] = {}
        net = ipaddress.IPv4Network(spec.subnet)
        self.subnet_broadcast = net.broadcast_address.packed
        self.selector = selectors.DefaultSelector()
        # (time, sequence, stage, receiver, packet): stage 0 arrives at the access point
        # (then the receiver's down direction), stage 1 is written to the receiver's device.
        self.heap: list[tuple[float, int, int, _Host, bytes]] = []
        self.sequence = itertools.count()
        self.listener: socket.socket | None = None
        self.clients: dict[int, _Client] = {}
        self.stopping = False
        self.wakeup: tuple[int, int] | None = None
        self.old_handlers: dict[int, Any] = {}

    # ------------------------------------------------------------ set-up and tear-down
    def add_host(self, host: HostSpec, now: float) -> None:
        profile = find_profile(self.profiles, host.profile)
        fd = open_tun(host.netns, host.device)
        entry = _Host(
            spec=host,
            index=len(self.hosts),
            fd=fd,
            link=Link(profile, seed=f"{self.spec.seed}:{host.name}", now=now),
            profile=host.profile,
        )
        self.hosts.append(entry)
        self.by_name[host.name] = entry
        self.by_address[ipaddress.IPv4Address(host.address).packed] = entry
        prefix = ipaddress.IPv4Network(self.spec.subnet).prefixlen
        _ip(host.netns, "addr", "add", f"{host.address}/{prefix}", "dev", host.device)
        _ip(host.netns, "link", "set", "dev", host.device, "mtu", str(MTU), "up")
        self.selector.register(fd, selectors.EVENT_READ, entry)
        log.info(
            "%s: %s in %s at %s, profile %s",
            host.name,
            host.device,
            host.netns,
            host.address,
            host.profile,
        )

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

    def catch_signals(self) -> None:
        """Stop on SIGTERM and SIGINT (only possible on the main thread)."""
        if threading.current_thread() is not threading.main_thread():
            return
        read, write = os.pipe()
        os.set_blocking(read, False)
        os.set_blocking(write, False)
        self.wakeup = (read, write)
        signal.set_wakeup_fd(write)
        self.selector.register(read, selectors.EVENT_READ, "signal")
        for signum in (signal.SIGTERM, signal.SIGINT):
            self.old_handlers[signum] = signal.signal(signum, self._on_signal)

    def _on_signal(self, signum: int, _frame: object) -> None:
        log.info("stopping on %s", signal.Signals(signum).name)
        self.stopping = True

    def write_ready(self) -> None:
        ready = self.spec.ready
        ready.parent.mkdir(parents=True, exist_ok=True)
        partial = ready.with_name(f".{ready.name}.{os.getpid()}")
        partial.write_text(
            json.dumps(
                {
                    "pid": os.getpid(),
                    "control": str(self.spec.control),
                    "hosts": {
                        h.spec.name: {"netns": h.spec.netns, "device": h.spec.device}
                        for h in self.hosts
                    },
                }
            )
            + "\n"
        )
        os.replace(partial, ready)

    def close(self) -> None:
        for client in list(self.clients.values()):
            # The last replies (that of ``stop`` above all) go out before the socket closes.
            if client.outbox:
                try:
                    client.sock.settimeout(1.0)
                    client.sock.sendall(client.outbox)
                except OSError:
                    pass
            self._drop_client(client)
        if self.listener is not None:
            self.listener.close()
            try:
                self.spec.control.unlink()
            except FileNotFoundError:
                pass
        for host in self.hosts:
            os.close(host.fd)
        if self.wakeup is not None:
            signal.set_wakeup_fd(-1)
            for signum, handler in self.old_handlers.items():
                signal.signal(signum, handler)
            for fd in self.wakeup:
                os.close(fd)
        self.selector.close()
        try:
            self.spec.ready.unlink()
        except FileNotFoundError:
            pass

    # ------------------------------------------------------------ the loop
    def run(self) -> None:
        clock = time.monotonic
        heap = self.heap
        while not self.stopping:
            timeout = None
            if heap:
                timeout = max(0.0, heap[0][0] - clock())
            for key, mask in self.selector.select(timeout):
                what = key.data
                if isinstance(what, _Host):
                    self._read(what, clock())
                elif what == "accept":
                    self._accept()
                elif what == "signal":
                    self._drain_wakeup()
                elif isinstance(what, _Client):
                    self._serve(what, mask)
            if heap:
                self._due(clock())

    def _read(self, host: _Host, now: float) -> None:
        fd = host.fd
        # Due packets first, so every direction sees its times in order.
        self._due(now)
        for _ in range(READ_BATCH):
            try:
                packet = os.read(fd, 65536)
            except BlockingIOError:
                return
            except OSError as error:
                # The device was deleted under us: stop watching it, or the loop would spin
                # on its error; the computer is cut off, and status says why.
                log.warning("%s: reading %s: %s", host.spec.name, host.spec.device, error)
                host.device_error = str(error)
                self.selector.unregister(fd)
                return
            self._route(host, packet, now)

    def _route(self, sender: _Host, packet: bytes, now: float) -> None:
        if len(packet) < 20 or packet[0] >> 4 != 4:
            sender.unroutable["not_ipv4"] += 1
            return
        destination = packet[16:20]
        receiver = self.by_address.get(destination)
        if receiver is None:
            if 224 <= packet[16] <= 239:
                sender.unroutable["multicast"] += 1
            elif destination in (b"\xff\xff\xff\xff", self.subnet_broadcast):
                sender.unroutable["broadcast"] += 1
            else:
                sender.unroutable["unknown"] += 1
            return
        at = sender.link.up.offer(len(packet), now)
        if at is None:
            return
        if at <= now:
            self._arrive(receiver, packet, at, now)
        else:
            heapq.heappush(self.heap, (at, next(self.sequence), 0, receiver, packet))

    def _arrive(self, receiver: _Host, packet: bytes, at: float, now: float) -> None:
        leave = receiver.link.down.offer(len(packet), at)
        if leave is None:
            return
        if leave <= now:
            self._write(receiver, packet)
        else:
            heapq.heappush(self.heap, (leave, next(self.sequence), 1, receiver, packet))

    def _due(self, now: float) -> None:
        heap = self.heap
        while heap and heap[0][0] <= now:
            at, _, stage, receiver, packet = heapq.heappop(heap)
            if stage == 0:
                self._arrive(receiver, packet, at, now)
            else:
                self._write(receiver, packet)

    def _write(self, receiver: _Host, packet: bytes) -> None:
        try:
            os.write(receiver.fd, packet)
        except OSError as error:
            # A full device queue (EAGAIN, ENOBUFS) or a device set down (EIO): the packet
            # is lost at the access point's last hop, as a full radio queue loses it.
            receiver.link.down.discard(len(packet), "queue")
            if error.errno not in (errno.EAGAIN, errno.ENOBUFS):
                log.debug("%s: writing: %s", receiver.spec.name, error)

    def _drain_wakeup(self) -> None:
        assert self.wakeup is not None
        try:
            while os.read(self.wakeup[0], 512):
                pass
        except BlockingIOError:
            pass

    # ------------------------------------------------------------ control
    def _accept(self) -> None:
        assert self.listener is not None
        try:
            sock, _ = self.listener.accept()
        except BlockingIOError:
            return
        sock.setblocking(False)
        client = _Client(sock)
        self.clients[sock.fileno()] = client
        self.selector.register(sock, selectors.EVENT_READ, client)

    def _serve(self, client: _Client, mask: int) -> None:
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

    def _flush(self, client: _Client) -> None:
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

    def _drop_client(self, client: _Client) -> None:
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
            return {"ok": False, "error": f"a request is one JSON object per line: {error}"}
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
            return {"ok": False, "error": f"internal error: {type(error).__name__}: {error}"}

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
        log.info("%s: down for %s", host.spec.name, "ever" if seconds is None else f"{seconds} s")
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


def serve(spec: Spec) -> None:
    """Set up every host's device, write the ready file, and serve until stopped.

    Returns when stopped by the ``stop`` request or SIGTERM/SIGINT (when called on the main
    thread); the devices vanish as their descriptors close, and the control socket and the
    ready file are removed.

    Raises:
        MsctlError: A profile, namespace or device that could not be set up (nothing is
            left behind then, and no ready file is written).
    """
    # A ready file left by an emulator that was killed must not say this one is ready.
    try:
        spec.ready.unlink()
    except FileNotFoundError:
        pass
    profiles = load_profiles(spec.profiles_file)
    for host in spec.hosts:
        try:
            find_profile(profiles, host.profile)
        except NotFoundError as error:
            raise NotFoundError(f"host {host.name!r}: {error.message}") from None
    emulator = _Emulator(spec, profiles, time.monotonic())
    try:
        emulator.catch_signals()
        for host in spec.hosts:
            emulator.add_host(host, time.monotonic())
        emulator.listen()
        if not emulator.stopping:  # a signal during set-up: not ready, just leave
            emulator.write_ready()
            log.info("serving %d hosts on %s", len(spec.hosts), spec.control)
            emulator.run()
    finally:
        emulator.close()


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m msctl.rehearse.emulator SPEC.json``: serve that spec; the exit code."""
    args = list(sys.argv[1:] if argv is None else argv)
    if len(args) != 1 or args[0] in ("-h", "--help"):
        print("usage: python -m msctl.rehearse.emulator SPEC.json", file=sys.stderr)
        return 2
    logging.basicConfig(
        level=logging.DEBUG if os.environ.get("MSCTL_DEBUG") else logging.INFO,
        format="link-emulator: %(message)s",
    )
    try:
        serve(Spec.load(Path(args[0])))
    except MsctlError as error:
        print(f"link-emulator: {error}", file=sys.stderr)
        return error.exit_code
    except OSError as error:
        print(f"link-emulator: {error}", file=sys.stderr)
        return 3
    return 0


if __name__ == "__main__":
    sys.exit(main())
