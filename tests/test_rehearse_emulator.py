"""The link emulator end to end: real namespaces, real TUN devices, real traffic.

Three network namespaces (``msrt-<random>-a``, ``-b``, ``-c``) joined by the emulator run as
a real subprocess (``python -m msctl.rehearse.emulator SPEC``). A small UDP echo server and
TCP sink runs in ``b`` under ``ip netns exec``; the clients are sockets this test opens inside
``a`` and ``c`` (:func:`~msctl.rehearse.emulator.run_in_netns`). Each test sets the profiles
it needs through the control socket, and compares what the traffic saw with what the
emulator's counters say. Needs root and working ``ip netns``; skipped otherwise.
"""

from __future__ import annotations

import json
import math
import os
import secrets
import selectors
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from conftest import wait_until

from msctl.errors import InputError, NetworkError
from msctl.rehearse.emulator_control import control
from msctl.rehearse.emulator_spec import Spec
from msctl.rehearse.netns import run_in_netns

pytestmark = pytest.mark.e2e

SUBNET = "10.77.0.0/24"
ADDRESSES = {"a": "10.77.0.11", "b": "10.77.0.12", "c": "10.77.0.13"}
PORT = 7700

#: Bound of every wait: a loaded 2-core machine still meets it easily.
WAIT = 30.0

PROFILES = """
[t-delay]
description = "50 ms each way and nothing else"
delay_ms = 50

[t-lossy]
description = "20 % independent loss from the computer, none towards it"
up.loss = 0.2

[t-rate]
description = "1000 kbit/s each way"
rate_kbit = 1000
queue_ms = 300
"""

#: The peer in ``b``: echoes every UDP datagram; a TCP connection's reply, once the client
#: has shut its side, is the number of bytes it sent.
SERVER = r"""
import selectors, socket, sys

port = int(sys.argv[1])
udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
udp.bind(("0.0.0.0", port))
tcp = socket.socket()
tcp.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
tcp.bind(("0.0.0.0", port))
tcp.listen(8)
selector = selectors.DefaultSelector()
selector.register(udp, selectors.EVENT_READ, "udp")
selector.register(tcp, selectors.EVENT_READ, "tcp")
received = {}
print("ready", flush=True)
while True:
    for key, _ in selector.select():
        if key.data == "udp":
            data, peer = udp.recvfrom(65536)
            udp.sendto(data, peer)
        elif key.data == "tcp":
            conn, _ = tcp.accept()
            received[conn] = 0
            selector.register(conn, selectors.EVENT_READ, "conn")
        else:
            conn = key.fileobj
            data = conn.recv(1 << 16)
            if data:
                received[conn] += len(data)
            else:
                selector.unregister(conn)
                conn.sendall(b"%d\n" % received.pop(conn))
                conn.close()
"""


def ip(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=check)


def device_exists(netns: str, device: str) -> bool:
    return ip("-n", netns, "link", "show", "dev", device, check=False).returncode == 0


@pytest.fixture(scope="module")
def namespaces() -> Iterator[dict[str, str]]:
    """Three fresh namespaces with loopback up; deleted afterwards whatever happened."""
    if os.geteuid() != 0:
        pytest.skip("the link emulator needs root (network namespaces, TUN devices)")
    if shutil.which("ip") is None:
        pytest.skip("the link emulator needs iproute2's `ip`")
    prefix = f"msrt-{secrets.token_hex(3)}"
    names = {host: f"{prefix}-{host}" for host in ADDRESSES}
    made: list[str] = []
    try:
        for name in names.values():
            result = ip("netns", "add", name, check=False)
            if result.returncode != 0:
                pytest.skip(f"`ip netns add` does not work here: {result.stderr.strip()}")
            made.append(name)
            ip("-n", name, "link", "set", "lo", "up")
        yield names
    finally:
        for name in made:
            ip("netns", "del", name, check=False)


@dataclass
class Emulator:
    """A running emulator subprocess."""

    spec: Spec
    process: subprocess.Popen[bytes]
    log: Path

    def control(self, request: dict[str, Any]) -> dict[str, Any]:
        return control(self.spec.control, request)

    def stderr(self) -> str:
        return self.log.read_text()

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(10)


def start_emulator(
    directory: Path,
    namespaces: dict[str, str],
    device: str = "rh0",
    subnet: str = SUBNET,
    profiles_file: Path | None = None,
    extra_hosts: list[dict[str, str]] | None = None,
    wait_ready: bool = True,
) -> Emulator:
    """Write a spec for ``namespaces`` (lan everywhere) and start the emulator on it."""
    directory.mkdir(parents=True, exist_ok=True)
    base = subnet.rsplit(".", 1)[0]
    hosts = [
        {
            "name": host,
            "netns": netns,
            "address": f"{base}.{ADDRESSES[host].rsplit('.', 1)[1]}",
            "profile": "lan",
            "device": device,
        }
        for host, netns in namespaces.items()
    ]
    spec_data = {
        "control": str(directory / "ctl.sock"),
        "ready": str(directory / "ready"),
        "seed": 1,
        "profiles_file": None if profiles_file is None else str(profiles_file),
        "subnet": subnet,
        "hosts": hosts + (extra_hosts or []),
    }
    spec_path = directory / "spec.json"
    spec_path.write_text(json.dumps(spec_data))
    log = directory / "emulator.log"
    with log.open("wb") as stderr:
        process = subprocess.Popen(
            [sys.executable, "-m", "msctl.rehearse.emulator", str(spec_path)],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=stderr,
        )
    emulator = Emulator(Spec.from_dict(spec_data), process, log)
    if wait_ready:
        try:
            wait_until(
                lambda: emulator.spec.ready.exists() or process.poll() is not None,
                WAIT,
                "the emulator's ready file",
            )
        except BaseException:
            emulator.stop()
            raise
        if process.poll() is not None:
            raise AssertionError(f"the emulator exited {process.returncode}: {emulator.stderr()}")
    return emulator


@dataclass
class Rig:
    """The module's emulator, the server in ``b`` and helpers to talk through them."""

    emulator: Emulator
    namespaces: dict[str, str]
    sockets: list[socket.socket] = field(default_factory=list)
    sequence: int = 0

    def control(self, request: dict[str, Any]) -> dict[str, Any]:
        reply = self.emulator.control(request)
        return reply

    def set(self, host: str, profile: str) -> None:
        reply = self.control({"op": "set", "host": host, "profile": profile})
        assert reply == {"ok": True, "host": host, "profile": profile}

    def host(self, name: str) -> dict[str, Any]:
        reply = self.control({"op": "status"})
        assert reply["ok"], reply
        return reply["hosts"][name]

    def udp(self, host: str) -> socket.socket:
        sock = run_in_netns(
            self.namespaces[host], lambda: socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        )
        self.sockets.append(sock)
        return sock

    def tcp(self, host: str) -> socket.socket:
        sock = run_in_netns(self.namespaces[host], socket.socket)
        self.sockets.append(sock)
        return sock

    def payload(self, tag: str) -> bytes:
        self.sequence += 1
        return f"{tag}:{self.sequence}".encode()

    def echo(self, sock: socket.socket, tag: str, timeout: float) -> float | None:
        """One echo from ``b``: its round-trip time, or None if none came in ``timeout``."""
        payload = self.payload(tag)
        start = time.monotonic()
        sock.sendto(payload, (ADDRESSES["b"], PORT))
        while (remaining := start + timeout - time.monotonic()) > 0:
            sock.settimeout(remaining)
            try:
                data = sock.recv(2048)
            except TimeoutError:
                return None
            if data == payload:  # a late echo of an earlier request is not this one's
                return time.monotonic() - start
        return None


def diff(after: dict[str, Any], before: dict[str, Any], *path: str) -> int:
    for key in path:
        after, before = after[key], before[key]
    return after - before  # type: ignore[operator]


@pytest.fixture(scope="module")
def rig(namespaces: dict[str, str], tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rig]:
    directory = tmp_path_factory.mktemp("emulator")
    profiles = directory / "profiles.toml"
    profiles.write_text(PROFILES)
    emulator = start_emulator(directory / "main", namespaces, profiles_file=profiles)
    server = subprocess.Popen(
        ["ip", "netns", "exec", namespaces["b"], sys.executable, "-c", SERVER, str(PORT)],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
    )
    rig = Rig(emulator, namespaces)
    try:
        assert server.stdout is not None
        with selectors.DefaultSelector() as selector:
            selector.register(server.stdout, selectors.EVENT_READ)
            assert selector.select(WAIT), "the echo server did not start"
        assert server.stdout.readline() == b"ready\n"
        yield rig
    finally:
        for sock in rig.sockets:
            sock.close()
        server.terminate()
        try:
            server.wait(10)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait(10)
        emulator.stop()


# --------------------------------------------------------------------------- traffic
def test_added_delay_shows_in_the_round_trip(rig: Rig) -> None:
    rig.set("a", "t-delay")
    before = rig.host("a")
    sock = rig.udp("a")
    rtts = [rig.echo(sock, "delay", 10.0) for _ in range(10)]
    assert all(rtt is not None for rtt in rtts), rtts
    # 50 ms up from a, 50 ms down to a; b is on lan.
    assert min(rtts) >= 2 * 0.050  # type: ignore[type-var]
    assert sorted(rtts)[len(rtts) // 2] < 2 * 0.050 + 2.0  # type: ignore[operator]
    after = rig.host("a")
    assert diff(after, before, "up", "delayed") == 10
    assert diff(after, before, "down", "delayed") == 10
    assert after["profile"] == "t-delay"
    assert after["up"]["asked"]["delay_ms"] == 50
    # Applied since the profile was set: exactly what was asked, each way.
    for direction in ("up", "down"):
        assert after[direction]["applied"]["delivered"] == 10
        assert after[direction]["applied"]["mean_delay_ms"] == pytest.approx(50)
        assert after[direction]["applied"]["max_delay_ms"] == pytest.approx(50)


def test_loss_seen_by_the_receiver_matches_the_asked_fraction_and_the_counters(rig: Rig) -> None:
    rig.set("c", "t-lossy")
    before_c, before_b = rig.host("c"), rig.host("b")
    sock = rig.udp("c")
    sock.setblocking(False)
    count = 400
    echoed: set[bytes] = set()

    def drain() -> None:
        while True:
            try:
                echoed.add(sock.recv(2048))
            except BlockingIOError:
                return

    for index in range(count):
        sock.sendto(b"loss:%d" % index, (ADDRESSES["b"], PORT))
        drain()
        time.sleep(0.001)  # pacing: no queue on the way may overflow

    def settled() -> bool:
        drain()
        status = rig.host("c")
        offered = diff(status, before_c, "up", "packets")
        delivered = diff(status, before_c, "up", "delivered")
        return offered == count and len(echoed) == delivered

    wait_until(settled, WAIT, "every datagram offered and every delivered one echoed")
    after_c, after_b = rig.host("c"), rig.host("b")
    lost = diff(after_c, before_c, "up", "dropped", "loss")
    # What b received (and echoed, over a lossless way back) is what the counters say.
    assert len(echoed) == count - lost
    assert diff(after_b, before_b, "down", "delivered") == len(echoed)
    assert diff(after_c, before_c, "down", "dropped", "loss") == 0
    # 400 Bernoulli(0.2) trials: sd 0.02; five of them either side.
    fraction = lost / count
    assert abs(fraction - 0.2) < 5 * math.sqrt(0.2 * 0.8 / count), fraction
    assert after_c["up"]["applied"]["loss_fraction"] == pytest.approx(fraction)
    assert after_c["up"]["asked"]["loss"] == 0.2
    rig.set("c", "lan")


def test_rate_limit_holds_a_tcp_transfer_to_the_asked_rate(rig: Rig) -> None:
    rig.set("a", "t-rate")
    size = 200_000
    before = rig.host("a")
    with rig.tcp("a") as sock:
        sock.settimeout(WAIT)
        start = time.monotonic()
        sock.connect((ADDRESSES["b"], PORT))
        sock.sendall(b"x" * size)
        sock.shutdown(socket.SHUT_WR)
        reply = b""
        while not reply.endswith(b"\n"):
            chunk = sock.recv(64)
            assert chunk, "the sink closed without its count"
            reply += chunk
        elapsed = time.monotonic() - start
    assert int(reply) == size
    # A 1000 kbit/s link passes the first bucket at once and the rest at 125 000 bytes/s
    # (headers only add to it): a lower bound; the upper one is the wait's, not a speed test.
    assert elapsed >= (size - 1500) * 8 / 1_000_000
    after = rig.host("a")
    assert diff(after, before, "up", "delivered_bytes") >= size
    assert after["up"]["asked"]["rate_kbit"] == 1000
    rig.set("a", "lan")


def test_an_outage_stops_traffic_until_the_link_is_up_again(rig: Rig) -> None:
    rig.set("a", "lan")
    a, c = rig.udp("a"), rig.udp("c")
    assert rig.echo(a, "before", 5.0) is not None
    before = rig.host("a")
    reply = rig.control({"op": "down", "host": "a", "seconds": None})
    assert reply["ok"] and reply["outage"]["until"] is None
    assert all(rig.echo(a, "during", 0.2) is None for _ in range(5))
    # The other computers' links are not touched.
    assert rig.echo(c, "beside", 5.0) is not None
    during = rig.host("a")
    assert during["up"]["outage"]["cause"] == "scripted"
    assert during["up"]["outage"]["left_s"] is None and during["up"]["outage"]["down_for_s"] > 0
    assert diff(during, before, "up", "dropped", "outage") == 5
    assert diff(during, before, "up", "delivered") == 0
    assert rig.control({"op": "up", "host": "a"}) == {"ok": True, "host": "a", "outage": None}
    assert rig.echo(a, "after", 5.0) is not None
    # A timed outage ends by itself.
    began = time.monotonic()
    assert rig.control({"op": "down", "host": "a", "seconds": 1.0})["ok"]
    assert rig.echo(a, "timed", 0.1) is None
    wait_until(lambda: rig.echo(a, "timed", 0.2) is not None, WAIT, "traffic after 1 s down")
    assert time.monotonic() - began >= 1.0
    assert rig.host("a")["up"]["outage"] is None


def test_unroutable_packets_are_dropped_and_counted(rig: Rig) -> None:
    before = rig.host("a")["unroutable"]
    sock = rig.udp("a")
    sock.sendto(b"nobody", ("10.77.0.99", PORT))
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
    sock.sendto(b"everybody", ("10.77.0.255", PORT))
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(ADDRESSES["a"]))
    sock.sendto(b"some", ("239.1.2.3", PORT))

    def counted() -> bool:
        now = rig.host("a")["unroutable"]
        return all(now[k] > before[k] for k in ("unknown", "broadcast", "multicast"))

    wait_until(counted, WAIT, "an unknown, a broadcast and a multicast packet counted")


# --------------------------------------------------------------------------- control
def test_status_reports_every_host_and_direction(rig: Rig) -> None:
    status = rig.control({"op": "status"})
    assert status["ok"] and status["seed"] == 1 and status["uptime_s"] > 0
    assert list(status["hosts"]) == ["a", "b", "c"]
    for name, host in status["hosts"].items():
        assert host["address"] == ADDRESSES[name]
        assert host["netns"] == rig.namespaces[name] and host["device"] == "rh0"
        for direction in ("up", "down"):
            counters = host[direction]
            assert set(counters["dropped"]) == {"loss", "outage", "queue"}
            assert counters["delivered"] + sum(counters["dropped"].values()) == counters["packets"]
            assert {"asked", "applied", "queued_bytes", "outage", "delayed"} <= set(counters)


def test_bad_control_requests_are_answered_with_errors(rig: Rig) -> None:
    def error(request: Any) -> str:
        reply = rig.control(request)
        assert reply["ok"] is False, reply
        return reply["error"]

    assert "did you mean 'status'" in error({"op": "stauts"})
    assert "hosts: a, b, c" in error({"op": "set", "host": "z", "profile": "lan"})
    assert "needs a host" in error({"op": "up"})
    message = error({"op": "set", "host": "a", "profile": "t-dealy"})
    assert "did you mean 't-delay'" in message and "profiles: lan, wifi" in message
    assert "seconds must be a number above 0" in error({"op": "down", "host": "a", "seconds": -1})
    # Not JSON, not an object, and several requests on one connection.
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(WAIT)
        sock.connect(str(rig.emulator.spec.control))
        sock.sendall(b'not json\n["status"]\n{"op": "status"}\n')
        data = b""
        while data.count(b"\n") < 3:
            chunk = sock.recv(1 << 16)
            assert chunk
            data += chunk
    first, second, third = (json.loads(line) for line in data.splitlines())
    assert first["ok"] is False and "one JSON object per line" in first["error"]
    assert second["ok"] is False and "a JSON object like" in second["error"]
    assert third["ok"] is True
    assert rig.emulator.process.poll() is None


# --------------------------------------------------------------------------- lifecycle
def test_stop_and_sigterm_exit_cleanly_and_leave_no_device(
    namespaces: dict[str, str], tmp_path: Path
) -> None:
    # Beside the module's emulator: other devices on another subnet in the same namespaces.
    for how in ("stop", "sigterm"):
        emulator = start_emulator(tmp_path / how, namespaces, device="rt1", subnet="10.78.0.0/24")
        try:
            assert all(device_exists(netns, "rt1") for netns in namespaces.values())
            ready = json.loads(emulator.spec.ready.read_text())
            assert ready["pid"] == emulator.process.pid
            if how == "stop":
                assert emulator.control({"op": "stop"}) == {"ok": True, "stopping": True}
            else:
                emulator.process.send_signal(signal.SIGTERM)
            assert emulator.process.wait(WAIT) == 0, emulator.stderr()
        finally:
            emulator.stop()
        assert not any(device_exists(netns, "rt1") for netns in namespaces.values())
        assert not emulator.spec.control.exists() and not emulator.spec.ready.exists()
        with pytest.raises(NetworkError, match="no link emulator is running"):
            emulator.control({"op": "status"})


def test_a_missing_namespace_fails_setup_and_leaves_nothing(
    namespaces: dict[str, str], tmp_path: Path
) -> None:
    missing = f"{namespaces['a']}-missing"
    emulator = start_emulator(
        tmp_path,
        {"a": namespaces["a"]},
        device="rt2",
        subnet="10.79.0.0/24",
        extra_hosts=[{"name": "gone", "netns": missing, "address": "10.79.0.20", "profile": "lan"}],
        wait_ready=False,
    )
    try:
        code = emulator.process.wait(WAIT)
    finally:
        emulator.stop()
    assert code != 0
    assert f"no network namespace {missing!r}" in emulator.stderr()
    assert not emulator.spec.ready.exists() and not device_exists(namespaces["a"], "rt2")


def test_spec_errors_name_the_field(tmp_path: Path) -> None:
    host = {"name": "a", "netns": "n", "address": "10.77.0.11", "profile": "lan"}
    good = {"control": "/tmp/c", "ready": "/tmp/r", "hosts": [host]}
    assert Spec.from_dict(good).hosts[0].device == "rh0"
    assert Spec.from_dict(Spec.from_dict(good).to_dict()) == Spec.from_dict(good)
    with pytest.raises(InputError, match=r"unknown field 'host' \(did you mean 'hosts'"):
        Spec.from_dict({**good, "host": []})
    with pytest.raises(InputError, match=r"hosts\[0\]: address must be a host address of"):
        Spec.from_dict({**good, "hosts": [{**host, "address": "10.78.0.1"}]})
    with pytest.raises(InputError, match="same name 'a'"):
        Spec.from_dict({**good, "hosts": [host, {**host, "address": "10.77.0.12"}]})
    with pytest.raises(InputError, match="device must be at most 15 characters"):
        Spec.from_dict({**good, "hosts": [{**host, "device": "a-very-long-name"}]})
    with pytest.raises(NetworkError, match="no link emulator is running"):
        control(tmp_path / "none.sock", {"op": "status"})
