"""Transport benchmark: msctl's publisher/subscription vs pyzeros vs bare zenoh-python.

In one run, between two processes on loopback (peers linked through a local router):
  * round-trip latency (p50/p99) of a 6-joint JointState ping-pong;
  * one-way throughput of JointState messages, one publisher -> one subscriber, reliable
    (blocking on congestion), with the count of lost messages.

Three flavours, each with its own topic:
  * ``ours``: msctl's Node publisher and subscription, what a component pays: CDR encode and
    decode of a real message, the 33-byte attachment, liveliness tokens;
  * ``pyzeros``: the MoonBots authors' pure-Python ROS 2 on Zenoh, with its own typed
    messages and codec (``ros2_pyterfaces.cydr``): ``Pub.publish`` of a message, and a
    ``RawSub`` whose callback decodes each sample (what its typed ``Sub`` does before handing
    the message to asyncio, so both sides deliver a decoded message on Zenoh's thread);
  * ``bare``: ``put`` of the same CDR bytes, no attachment, no decoding: the floor;
  * ``codec``: a reference between the two, not a target: bare ``put`` and subscriber with
    msctl's generated CDR codec on each side (encode before the put, decode in the
    callback), no attachment, no node. ``ours`` over ``codec`` is what msctl's publisher and
    subscription add (attachment, GID, checks); ``codec`` over ``bare`` is what encoding and
    decoding a message in Python costs where it runs, between two waits for the network
    (several times its cost in a loop, the caches cold).

The load of a shared machine drifts, so the flavours take turns: the round trips in
``--rounds`` rounds of ``pings / rounds`` each, the floods one flood per flavour per
``--flood-rounds`` round; every child process and subscription is made once, before the first
round. A flavour's round trips are pooled over its rounds; its throughput is the median of
its rounds. On a 2-core machine, ten rounds of 500 (the default) gave an ours/bare p50 of
1.24-1.28 in four runs in a row; three rounds of ~670 gave 1.23-1.41 for the same code.
Targets (issue 16): ours >= 1.2x pyzeros' throughput with no loss; our p50 <= 1.3x bare.

Run: ``python bench/transport.py [--pings N] [--messages N] [--rounds N] [--flood-rounds N]
[--json]``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench._common import free_port, print_table, summary

FLAVOURS = ("bare", "codec", "pyzeros", "ours")
JOINTS = [f"limb1_joint{i}" for i in range(1, 7)]
#: Each flavour's topics (ping, pong, flood): ROS topic names for ours and pyzeros, plain
#: Zenoh keys for bare.
TOPICS = {
    "ours": ("/bench/ping", "/bench/pong", "/bench/flood"),
    "pyzeros": ("/bench/pz_ping", "/bench/pz_pong", "/bench/pz_flood"),
    "bare": ("bare/ping", "bare/pong", "bare/flood"),
    "codec": ("codec/ping", "codec/pong", "codec/flood"),
}
JOINT_STATE = "sensor_msgs/msg/JointState"


def _settings(endpoint: str) -> Any:
    from components.comm.session import SessionSettings

    return SessionSettings(mode="peer", connect=(endpoint,), listen=("tcp/127.0.0.1:0",))


def _codec_cache() -> None:
    """Point pyzeros' codec compiler (cydr) at a temporary directory: by default it compiles
    into ``./.cydr_cache`` wherever the benchmark runs. Set before cydr is imported; the
    children inherit it."""
    if not os.environ.get("CYDR_CACHE_DIR"):
        user = os.getuid() if hasattr(os, "getuid") else "user"
        os.environ["CYDR_CACHE_DIR"] = str(Path(tempfile.gettempdir()) / f"msctl-bench-cydr-{user}")


def _sample_message() -> Any:
    from components.messages import JointSample, joint_state

    return joint_state(
        [JointSample(n, 0.1 * i, 0.01 * i, 0.5) for i, n in enumerate(JOINTS)], stamp=time.time()
    )


def _pyzeros_message() -> Any:
    """The same JointState as :func:`_sample_message`, as pyzeros' own typed message."""
    import numpy as np
    from ros2_pyterfaces.cydr.all_msgs import Header, JointState, Time

    stamp = time.time()
    return JointState(
        header=Header(stamp=Time(sec=int(stamp), nanosec=int(stamp % 1 * 1e9)), frame_id=b""),
        name=np.array([n.encode() for n in JOINTS]),
        position=np.array([0.1 * i for i in range(len(JOINTS))]),
        velocity=np.array([0.01 * i for i in range(len(JOINTS))]),
        effort=np.full(len(JOINTS), 0.5),
    )


def publisher_bytes(message: Any) -> bytes:
    """The CDR bytes our publisher would put for ``message``."""
    from components.comm.types import registry

    return registry().serializer(JOINT_STATE)(message)


class Endpoints:
    """One flavour's publishers and subscriptions on one Zenoh session, closed together."""

    def __init__(self, session: Any, flavour: str, name: str) -> None:
        self.flavour = flavour
        self._session = session
        self._things: list[Any] = []
        self._node: Any = None
        if flavour == "ours":
            from components.comm import Node

            self._node = Node(session, name)
        elif flavour == "pyzeros":
            import pyzeros

            self._node = pyzeros.Session(node=name, zenoh_session=session)

    def publisher(self, topic: str, keep_all: bool = False) -> tuple[Callable[[Any], None], Any]:
        """A send function and the item to send with it (a message, or bytes for bare)."""
        import zenoh

        if self.flavour == "ours":
            from components.comm.qos import QoS

            qos = QoS(history="keep_all") if keep_all else None
            publisher = self._node.publisher(topic, JOINT_STATE, qos)
            return publisher.publish, _sample_message()
        if self.flavour == "pyzeros":
            import pyzeros
            from pyzeros.qos import QosProfile
            from ros2_pyterfaces.cydr.all_msgs import JointState

            qos = QosProfile(history="keep_all") if keep_all else None
            pub = pyzeros.Pub(JointState, topic, qos_profile=qos, session=self._node)
            self._things.append(pub)
            message = _pyzeros_message()
            message.serialize()  # cydr compiles its codec on first use: not in the timing
            return pub.publish, message
        bare = self._session.declare_publisher(
            topic,
            reliability=zenoh.Reliability.RELIABLE,
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        self._things.append(bare)
        if self.flavour == "codec":
            from components.comm.types import registry

            encode, put = registry().serializer(JOINT_STATE), bare.put
            return lambda message: put(encode(message)), _sample_message()
        return bare.put, publisher_bytes(_sample_message())

    def subscription(self, topic: str, callback: Callable[[Any], None], keep_all: bool = False):
        """Deliver each sample to ``callback``: decoded (ours, pyzeros) or its payload (bare)."""
        if self.flavour == "ours":
            from components.comm.qos import QoS

            qos = QoS(history="keep_all") if keep_all else None
            self._node.subscription(topic, JOINT_STATE, callback, qos)
        elif self.flavour == "pyzeros":
            from pyzeros.qos import QosProfile
            from pyzeros.sub import RawSub
            from ros2_pyterfaces.cydr.all_msgs import JointState

            decode = JointState.deserialize
            qos = QosProfile(history="keep_all") if keep_all else None
            _pyzeros_message().serialize()  # compile the codec before the first sample
            self._things.append(
                RawSub(
                    JointState,
                    topic,
                    lambda sample: callback(decode(sample.payload.to_bytes())),
                    qos_profile=qos,
                    session=self._node,
                )
            )
        elif self.flavour == "codec":
            from components.comm.types import registry

            decode = registry().deserializer(JOINT_STATE)
            self._things.append(
                self._session.declare_subscriber(
                    topic, lambda s: callback(decode(s.payload.to_bytes()))
                )
            )
        else:
            self._things.append(
                self._session.declare_subscriber(topic, lambda s: callback(s.payload.to_bytes()))
            )

    def close(self) -> None:
        for thing in self._things:
            try:
                thing.close() if hasattr(thing, "close") else thing.undeclare()
            except Exception:  # the session may be closing
                pass
        if self._node is not None:
            self._node.close()


# ----------------------------------------------------------------------------- child roles
def role_echo(endpoint: str, flavour: str) -> None:
    """Answer every ping with a pong until the parent closes stdin."""
    from components.comm import open_session

    ping, pong, _ = TOPICS[flavour]
    with open_session(_settings(endpoint)) as session:
        ends = Endpoints(session, flavour, "bench_echo")
        send, _item = ends.publisher(pong)
        ends.subscription(ping, send)
        print("ready", flush=True)
        sys.stdin.readline()
        ends.close()


def role_flood(endpoint: str, flavour: str, count: int) -> None:
    """Publish ``count`` messages as fast as possible at each "go" line, then say how long it
    took; until stdin closes."""
    from components.comm import open_session

    with open_session(_settings(endpoint)) as session:
        ends = Endpoints(session, flavour, "bench_flood")
        send, item = ends.publisher(TOPICS[flavour][2], keep_all=True)
        print("ready", flush=True)
        while sys.stdin.readline().strip() == "go":
            start = time.perf_counter()
            for _ in range(count):
                send(item)
            print(f"sent {time.perf_counter() - start:.6f}", flush=True)
        ends.close()


# ----------------------------------------------------------------------------- parent side
def _spawn(role: str, endpoint: str, flavour: str, arg: str) -> subprocess.Popen:
    command = [sys.executable, __file__, "--role", role, "--endpoint", endpoint]
    command += ["--flavour", flavour, "--arg", arg]
    process = subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert process.stdout is not None
    line = process.stdout.readline().strip()
    if line != "ready":
        process.kill()
        raise RuntimeError(f"{role} child ({flavour}) failed to start: {line!r}")
    return process


def _finish(process: subprocess.Popen) -> None:
    try:
        assert process.stdin is not None
        process.stdin.close()
        process.wait(timeout=10)
    except Exception:
        process.kill()


class Pinger:
    """Our side of one flavour's ping-pong (the echo child answers)."""

    def __init__(self, session: Any, endpoint: str, flavour: str) -> None:
        self.flavour = flavour
        self.child = _spawn("echo", endpoint, flavour, "0")
        self.got = threading.Event()
        self.ends = Endpoints(session, flavour, "bench_ping")
        ping, pong, _ = TOPICS[flavour]
        self.send, self.item = self.ends.publisher(ping)
        self.ends.subscription(pong, lambda _m: self.got.set())
        self.rtts: list[float] = []
        self.ping(200, warmup=True)  # routes may still be settling

    def ping(self, count: int, warmup: bool = False) -> None:
        got, send, item = self.got, self.send, self.item
        for i in range(count):
            got.clear()
            t0 = time.perf_counter()
            send(item)
            if not got.wait(2.0):
                if warmup:
                    continue
                raise RuntimeError(f"{self.flavour}: pong {i} lost")
            if not warmup:
                self.rtts.append(time.perf_counter() - t0)

    def close(self) -> None:
        self.ends.close()
        _finish(self.child)


class Sink:
    """Our side of one flavour's flood: a subscription counting arrivals, and the child."""

    def __init__(self, session: Any, endpoint: str, flavour: str, count: int) -> None:
        self.flavour, self.count = flavour, count
        self.child = _spawn("flood", endpoint, flavour, str(count))
        self.ends = Endpoints(session, flavour, "bench_sink")
        self.ends.subscription(TOPICS[flavour][2], self._on_message, keep_all=True)
        self.received = 0
        self.first = self.last = 0.0
        self.done = threading.Event()
        self.rounds: list[dict[str, float]] = []

    def _on_message(self, _message: Any) -> None:
        now = time.perf_counter()
        if self.received == 0:
            self.first = now
        self.received += 1
        self.last = now
        if self.received == self.count:
            self.done.set()

    def flood(self) -> None:
        """One round: the child sends ``count`` messages; count what arrives."""
        self.received, self.first, self.last = 0, 0.0, 0.0
        self.done.clear()
        assert self.child.stdin is not None and self.child.stdout is not None
        self.child.stdin.write("go\n")
        self.child.stdin.flush()
        sent_line = self.child.stdout.readline().split()
        self.done.wait(timeout=max(30.0, self.count / 5000))
        time.sleep(0.2)  # stragglers would be counted, not lost
        send_seconds = float(sent_line[1]) if len(sent_line) == 2 else float("nan")
        received = self.received
        elapsed = max(self.last - self.first, 1e-9)
        self.rounds.append(
            {
                "rate": (received - 1) / elapsed if received > 1 else 0.0,
                "received": received,
                "lost": self.count - received,
                "send_rate": self.count / send_seconds,
            }
        )

    def result(self) -> dict[str, float]:
        """The median round's rates, and every round's losses summed."""
        return {
            "rate": statistics.median(r["rate"] for r in self.rounds),
            "send_rate": statistics.median(r["send_rate"] for r in self.rounds),
            "rates": [r["rate"] for r in self.rounds],
            "received": sum(r["received"] for r in self.rounds),
            "lost": sum(r["lost"] for r in self.rounds),
        }

    def close(self) -> None:
        self.ends.close()
        _finish(self.child)


def measure_latency(session: Any, endpoint: str, pings: int, rounds: int) -> dict[str, list]:
    """Round trips in seconds per flavour, the flavours taking turns in ``rounds`` rounds."""
    pingers = []
    try:
        for flavour in FLAVOURS:
            pingers.append(Pinger(session, endpoint, flavour))
        per_round = max(1, pings // rounds)
        for _ in range(rounds):
            for pinger in pingers:
                pinger.ping(per_round)
        return {p.flavour: p.rtts for p in pingers}
    finally:
        for pinger in pingers:
            pinger.close()


def measure_throughput(
    session: Any, endpoint: str, count: int, rounds: int
) -> dict[str, dict[str, float]]:
    """Messages per second received (and decoded, for ours and pyzeros), and losses."""
    sinks = []
    try:
        for flavour in FLAVOURS:
            sinks.append(Sink(session, endpoint, flavour, count))
        time.sleep(0.5)  # let the publishers learn the subscriptions' routes
        for _ in range(rounds):
            for sink in sinks:
                sink.flood()
        return {s.flavour: s.result() for s in sinks}
    finally:
        for sink in sinks:
            sink.close()


def run(pings: int, messages: int, rounds: int, flood_rounds: int) -> dict[str, Any]:
    """Measure everything; the document :func:`main` prints."""
    from components.comm.session import SessionSettings, open_session

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(SessionSettings(mode="router", connect=(), listen=(endpoint,)))
    load = os.getloadavg()[0]
    try:
        with open_session(_settings(endpoint)) as session:
            rtts = measure_latency(session, endpoint, pings, rounds)
            throughput = measure_throughput(session, endpoint, messages, flood_rounds)
    finally:
        router.close()
    latency = {f: summary(rtts[f]) for f in FLAVOURS}
    return {
        "cores": os.cpu_count(),
        "load": [load, os.getloadavg()[0]],
        "pings": sum(len(r) for r in rtts.values()) // len(FLAVOURS),
        "messages": messages,
        "rounds": rounds,
        "flood_rounds": flood_rounds,
        "latency": latency,
        "throughput": throughput,
        "ratios": {
            "p50_ours_bare": latency["ours"]["p50"] / latency["bare"]["p50"],
            "p50_codec_bare": latency["codec"]["p50"] / latency["bare"]["p50"],
            "p50_ours_codec": latency["ours"]["p50"] / latency["codec"]["p50"],
            "p50_ours_pyzeros": latency["ours"]["p50"] / latency["pyzeros"]["p50"],
            "rate_ours_pyzeros": throughput["ours"]["rate"]
            / max(throughput["pyzeros"]["rate"], 1.0),
            "rate_ours_bare": throughput["ours"]["rate"] / max(throughput["bare"]["rate"], 1.0),
        },
    }


def report(doc: dict[str, Any]) -> None:
    """Print the document as tables and the ratios against the targets."""
    lat, thr, ratios = doc["latency"], doc["throughput"], doc["ratios"]
    us = 1e6
    print(
        f"transport benchmark: {doc['cores']} cores, load {doc['load'][0]:.1f} -> "
        f"{doc['load'][1]:.1f}, {doc['rounds']} round(s), flavours taking turns"
    )
    print_table(
        f"Round trip, 6-joint JointState ping-pong, {doc['pings']} round trips each (microseconds)",
        ["", "p50", "p99", "mean"],
        [[f, *(f"{lat[f][k] * us:.0f}" for k in ("p50", "p99", "mean"))] for f in FLAVOURS],
    )
    print(
        f"ours/bare p50: {ratios['p50_ours_bare']:.2f} (target <= 1.3); "
        f"ours/pyzeros p50: {ratios['p50_ours_pyzeros']:.2f}; of which codec/bare "
        f"{ratios['p50_codec_bare']:.2f}, ours/codec {ratios['p50_ours_codec']:.2f}"
    )
    print_table(
        f"Throughput, {doc['messages']:,} JointState a round, one publisher -> one subscriber "
        "(reliable, blocking); median round",
        ["", "received/s", "sent/s", "rounds' received/s", "lost"],
        [
            [
                f,
                f"{thr[f]['rate']:,.0f}",
                f"{thr[f]['send_rate']:,.0f}",
                " ".join(f"{r:,.0f}" for r in thr[f]["rates"]),
                thr[f]["lost"],
            ]
            for f in FLAVOURS
        ],
    )
    print(
        f"ours/pyzeros throughput: {ratios['rate_ours_pyzeros']:.2f} (target >= 1.2, no loss); "
        f"ours/bare: {ratios['rate_ours_bare']:.2f}"
    )


def main() -> None:
    """Run the benchmark (or a child role)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--pings", type=int, default=5000, help="round trips per flavour")
    parser.add_argument("--messages", type=int, default=100_000, help="messages per flood")
    parser.add_argument("--rounds", type=int, default=10, help="turns at the round trips")
    parser.add_argument("--flood-rounds", type=int, default=3, help="turns at the floods")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    parser.add_argument("--role", choices=["echo", "flood"], help=argparse.SUPPRESS)
    parser.add_argument("--endpoint", help=argparse.SUPPRESS)
    parser.add_argument("--flavour", choices=FLAVOURS, help=argparse.SUPPRESS)
    parser.add_argument("--arg", default="0", help=argparse.SUPPRESS)
    args = parser.parse_args()
    _codec_cache()
    if args.role == "echo":
        role_echo(args.endpoint, args.flavour)
        return
    if args.role == "flood":
        role_flood(args.endpoint, args.flavour, int(args.arg))
        return
    doc = run(args.pings, args.messages, max(1, args.rounds), max(1, args.flood_rounds))
    if args.json:
        print(json.dumps(doc, indent=2))
    else:
        report(doc)


if __name__ == "__main__":
    main()
