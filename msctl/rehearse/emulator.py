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
:func:`serve`. The spec (:class:`~msctl.rehearse.emulator_spec.Spec`) says which computers
it links; :mod:`msctl.rehearse.emulator_control` is its control socket (``status``, ``set``,
``down``, ``up``, ``stop``), and :mod:`msctl.rehearse.netns` enters the namespaces and makes
the devices.
"""

from __future__ import annotations

import errno
import heapq
import ipaddress
import itertools
import json
import logging
import os
import selectors
import signal
import socket
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from msctl.errors import MsctlError, NotFoundError
from msctl.rehearse.emulator_control import ControlClient, ControlSocket
from msctl.rehearse.emulator_spec import HostSpec, Spec
from msctl.rehearse.link import Link
from msctl.rehearse.link_profile import LinkProfile
from msctl.rehearse.netns import ip_in, open_tun
from msctl.rehearse.profiles import find_profile, load_profiles

log = logging.getLogger(__name__)

#: MTU of every TUN device: below Ethernet's 1500 so that the rehearsal's packets also fit
#: through a tunnel or VPN in the field.
MTU = 1400

#: Packets read from one TUN device before the loop looks at the others (fairness).
READ_BATCH = 64

#: Why an IPv4 packet could not be routed; the keys of a host's ``unroutable`` counters.
UNROUTABLE = ("not_ipv4", "unknown", "broadcast", "multicast")


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


class _Emulator(ControlSocket):
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
        self.clients: dict[int, ControlClient] = {}
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
        ip_in(host.netns, "addr", "add", f"{host.address}/{prefix}", "dev", host.device)
        ip_in(host.netns, "link", "set", "dev", host.device, "mtu", str(MTU), "up")
        self.selector.register(fd, selectors.EVENT_READ, entry)
        log.info(
            "%s: %s in %s at %s, profile %s",
            host.name,
            host.device,
            host.netns,
            host.address,
            host.profile,
        )

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
                elif isinstance(what, ControlClient):
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
