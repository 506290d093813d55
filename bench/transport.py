"""Transport benchmark: msctl's rmw_zenoh-compatible publisher/subscription vs bare zenoh-python.

In one run, between two processes on loopback (peers linked through a local router):
  * round-trip latency (p50/p99) of a 6-joint JointState ping-pong, ours and bare;
  * one-way throughput of JointState messages, one publisher -> one subscriber, ours and
    bare, reliable, with the count of lost messages.

Ours pays what a component pays: CDR encode/decode of a real message, the 33-byte
attachment, liveliness tokens. Bare forwards the same CDR bytes with ``put`` and no decoding:
the floor. Targets (issue): our p50 within 1.5x of bare; our throughput >= 50,000/s, no loss.

Run: ``python bench/transport.py [--pings N] [--messages N]``.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench._common import free_port, print_table, summary

PING, PONG, FLOOD = "bench/ping", "bench/pong", "bench/flood"
JOINTS = [f"limb1_joint{i}" for i in range(1, 7)]


def _settings(endpoint: str):
    from components.comm.session import SessionSettings

    return SessionSettings(mode="peer", connect=(endpoint,), listen=("tcp/127.0.0.1:0",))


def _sample_message():
    from components.messages import JointSample, joint_state

    return joint_state(
        [JointSample(n, 0.1 * i, 0.01 * i, 0.5) for i, n in enumerate(JOINTS)], stamp=time.time()
    )


# ----------------------------------------------------------------------------- child roles
def role_echo(endpoint: str, flavour: str, seconds: float) -> None:
    """Answer every ping with a pong until told to stop (or ``seconds`` pass)."""
    from components.comm import Node, open_session
    from components.messages import JOINT_STATE

    with open_session(_settings(endpoint)) as session:
        if flavour == "ours":
            node = Node(session, "bench_echo")
            pong = node.publisher(PONG, JOINT_STATE)
            node.subscription(PING, JOINT_STATE, pong.publish)
        else:
            publisher = session.declare_publisher("bare/pong")
            session.declare_subscriber("bare/ping", lambda s: publisher.put(s.payload.to_bytes()))
            node = None
        print("ready", flush=True)
        sys.stdin.readline()  # the parent closes stdin when done
        if node is not None:
            node.close()


def role_flood(endpoint: str, flavour: str, count: int) -> None:
    """Publish ``count`` messages as fast as possible once the parent says go."""
    import zenoh

    from components.comm import Node, open_session
    from components.comm.qos import QoS
    from components.messages import JOINT_STATE

    message = _sample_message()
    with open_session(_settings(endpoint)) as session:
        node = Node(session, "bench_flood")
        if flavour == "ours":
            publisher = node.publisher(FLOOD, JOINT_STATE, QoS(history="keep_all"))
            send = publisher.publish
            item = message
        else:
            bare = session.declare_publisher(
                "bare/flood",
                reliability=zenoh.Reliability.RELIABLE,
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
            send = bare.put
            item = publisher_bytes(message)
        print("ready", flush=True)
        sys.stdin.readline()
        start = time.perf_counter()
        for _ in range(count):
            send(item)
        print(f"sent {time.perf_counter() - start:.6f}", flush=True)
        sys.stdin.readline()
        node.close()


def publisher_bytes(message) -> bytes:
    """The CDR bytes our publisher would put for ``message``."""
    from components.comm.types import registry

    return registry().serialize(message, "sensor_msgs/msg/JointState")


# ----------------------------------------------------------------------------- parent side
def _spawn(role: str, endpoint: str, flavour: str, arg: str) -> subprocess.Popen:
    process = subprocess.Popen(
        [
            sys.executable,
            __file__,
            "--role",
            role,
            "--endpoint",
            endpoint,
            "--flavour",
            flavour,
            "--arg",
            arg,
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    line = process.stdout.readline().strip()
    if line != "ready":
        process.kill()
        raise RuntimeError(f"{role} child failed to start: {line!r}")
    return process


def _finish(process: subprocess.Popen) -> None:
    try:
        process.stdin.close()
        process.wait(timeout=10)
    except Exception:
        process.kill()


def measure_latency(endpoint: str, flavour: str, pings: int) -> list[float]:
    """Round trips in seconds."""
    from components.comm import Node, open_session
    from components.messages import JOINT_STATE

    child = _spawn("echo", endpoint, flavour, "0")
    got = threading.Event()
    rtts: list[float] = []
    try:
        with open_session(_settings(endpoint)) as session:
            node = Node(session, "bench_ping")
            if flavour == "ours":
                ping = node.publisher(PING, JOINT_STATE)
                node.subscription(PONG, JOINT_STATE, lambda _m: got.set())
                send, item = ping.publish, _sample_message()
            else:
                bare = session.declare_publisher("bare/ping")
                sub = session.declare_subscriber("bare/pong", lambda _s: got.set())
                send, item = bare.put, publisher_bytes(_sample_message())
            warmup = 200
            for i in range(warmup + pings):
                got.clear()
                t0 = time.perf_counter()
                send(item)
                if not got.wait(2.0):
                    if i < warmup:  # routes may still be settling
                        continue
                    raise RuntimeError(f"{flavour}: pong {i} lost")
                if i >= warmup:
                    rtts.append(time.perf_counter() - t0)
            if flavour != "ours":
                sub.undeclare()
            node.close()
    finally:
        _finish(child)
    return rtts


def measure_throughput(endpoint: str, flavour: str, count: int) -> dict[str, float]:
    """Messages per second received (and decoded, for ours), and how many were lost."""
    from components.comm import Node, open_session
    from components.comm.qos import QoS
    from components.messages import JOINT_STATE

    child = _spawn("flood", endpoint, flavour, str(count))
    received = 0
    first = last = 0.0
    done = threading.Event()

    def on_message(_m) -> None:
        nonlocal received, first, last
        now = time.perf_counter()
        if received == 0:
            first = now
        received += 1
        last = now
        if received == count:
            done.set()

    try:
        with open_session(_settings(endpoint)) as session:
            node = Node(session, "bench_sink")
            if flavour == "ours":
                node.subscription(FLOOD, JOINT_STATE, on_message, QoS(history="keep_all"))
            else:
                sub = session.declare_subscriber("bare/flood", lambda s: on_message(s.payload))
            time.sleep(0.5)  # let the publisher learn the subscription's route
            child.stdin.write("go\n")
            child.stdin.flush()
            done.wait(timeout=max(30.0, count / 5000))
            time.sleep(0.2)
            if flavour != "ours":
                sub.undeclare()
            node.close()
        sent_line = child.stdout.readline().split()
        send_seconds = float(sent_line[1]) if len(sent_line) == 2 else float("nan")
    finally:
        _finish(child)
    elapsed = max(last - first, 1e-9)
    return {
        "rate": (received - 1) / elapsed if received > 1 else 0.0,
        "received": received,
        "lost": count - received,
        "send_rate": count / send_seconds if send_seconds == send_seconds else float("nan"),
    }


def main() -> None:
    """Run the benchmark (or a child role)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--pings", type=int, default=2000)
    parser.add_argument("--messages", type=int, default=200_000)
    parser.add_argument("--role", choices=["echo", "flood"], help=argparse.SUPPRESS)
    parser.add_argument("--endpoint", help=argparse.SUPPRESS)
    parser.add_argument("--flavour", choices=["ours", "bare"], help=argparse.SUPPRESS)
    parser.add_argument("--arg", default="0", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.role == "echo":
        role_echo(args.endpoint, args.flavour, float(args.arg))
        return
    if args.role == "flood":
        role_flood(args.endpoint, args.flavour, int(args.arg))
        return

    from components.comm.session import SessionSettings, open_session

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(SessionSettings(mode="router", connect=(), listen=(endpoint,)))
    try:
        print(f"transport benchmark: {os.cpu_count()} cores, router {endpoint}")
        lat = {f: summary(measure_latency(endpoint, f, args.pings)) for f in ("bare", "ours")}
        thr = {f: measure_throughput(endpoint, f, args.messages) for f in ("bare", "ours")}
    finally:
        router.close()
    us = 1e6
    print_table(
        f"Round trip, 6-joint JointState ping-pong, {args.pings} round trips (microseconds)",
        ["", "p50", "p99", "mean"],
        [
            [
                f,
                f"{lat[f]['p50'] * us:.0f}",
                f"{lat[f]['p99'] * us:.0f}",
                f"{lat[f]['mean'] * us:.0f}",
            ]
            for f in ("bare", "ours")
        ],
    )
    ratio = lat["ours"]["p50"] / lat["bare"]["p50"]
    print(f"ours/bare p50 ratio: {ratio:.2f} (target <= 1.5)")
    print_table(
        f"Throughput, {args.messages} JointState one publisher -> one subscriber (reliable)",
        ["", "received/s", "sent/s", "received", "lost"],
        [
            [
                f,
                f"{thr[f]['rate']:,.0f}",
                f"{thr[f]['send_rate']:,.0f}",
                thr[f]["received"],
                thr[f]["lost"],
            ]
            for f in ("bare", "ours")
        ],
    )
    print(
        f"ours/bare throughput ratio: {thr['ours']['rate'] / max(thr['bare']['rate'], 1):.2f}; "
        f"ours {thr['ours']['rate']:,.0f}/s (target >= 50,000/s, no loss)"
    )


if __name__ == "__main__":
    main()
