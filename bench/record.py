"""Recording benchmark: ``msctl record``'s recorder against two baselines measured in the run.

Scenarios (publishers in child processes, a router in its own process, the recorder in this
one so its CPU is this process's CPU):
  * flood: one publisher sends 6-joint JointStates as fast as it can;
  * fleet: 40 publishers at 200 Hz each (8,000 messages/s in all);
  * large: one publisher sends 1 MB messages as fast as it can.

For each: messages/s and MB/s recorded, messages lost (sent minus recorded, and gaps in the
attachments' sequence numbers), messages the recorder dropped, and the recorder's CPU (this
process's CPU time over the recording, in cores). Baselines, same run, same traffic:
  * ``bare``: a bare zenoh subscriber that copies each payload and writes nothing;
  * ``mcap``: the ``mcap`` library's writer writing the same bytes in a loop (no network).

Targets (issue 13): >= 50,000 small messages/s with 0 lost; >= 200 MB/s for large messages;
the recorder under one core. The bench prints; it asserts nothing.

Run: ``python bench/record.py [--flood N] [--large N] [--fleet-seconds S]``.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench._common import free_port, print_table

JOINTS = [f"limb1_joint{i}" for i in range(1, 7)]
MB = 1e6


def _settings(endpoint: str) -> Any:
    from components.comm.session import SessionSettings

    return SessionSettings(mode="peer", connect=(endpoint,), listen=("tcp/127.0.0.1:0",))


def _joint_state_bytes() -> bytes:
    from components.comm.types import registry
    from components.messages import JOINT_STATE, JointSample, joint_state

    message = joint_state(
        [JointSample(n, 0.1 * i, 0.01 * i, 0.5) for i, n in enumerate(JOINTS)], stamp=time.time()
    )
    return registry().serializer(JOINT_STATE)(message)


def _large_bytes(size: int) -> bytes:
    from components.comm.types import registry
    from components.messages import msg

    # A uint8[] image-like payload: CDR header, sequence length, bytes.
    message = msg("std_msgs/msg/UInt8MultiArray", data=__import__("numpy").zeros(size, "uint8"))
    return registry().serializer("std_msgs/msg/UInt8MultiArray")(message)


# ----------------------------------------------------------------------------- child role
def role_publish(endpoint: str, kind: str, count: int, publishers: int, rate: float) -> None:
    """Publish ``count`` messages on each of ``publishers`` topics (at ``rate`` Hz each, or as
    fast as possible with 0), after a line "ready" and a line "go" on stdin; then print
    "sent <total>"."""
    from components.comm import Node, open_session

    type_name = "sensor_msgs/msg/JointState" if kind != "large" else "std_msgs/msg/UInt8MultiArray"
    payload = _joint_state_bytes() if kind != "large" else _large_bytes(1_000_000)
    with open_session(_settings(endpoint)) as session:
        node = Node(session, f"bench_{kind}_{os.getpid()}")
        outs = [
            node.publisher(f"/bench/{kind}_{os.getpid()}_{i}", type_name) for i in range(publishers)
        ]
        # Ready once every publisher has a subscriber (the listener's interest arrived), so
        # no message is sent into the void: losses counted later are the listener's.
        deadline = time.monotonic() + 60.0
        while not all(out._zpub.matching_status.matching for out in outs):
            if time.monotonic() > deadline:
                print("no subscriber", flush=True)
                return
            time.sleep(0.01)
        print("ready", flush=True)
        sys.stdin.readline()
        sent = 0
        if rate <= 0:
            for _ in range(count):
                for out in outs:
                    out.publish_raw(payload)
                    sent += 1
        else:
            period = 1.0 / rate
            due = time.monotonic()
            for _ in range(count):
                for out in outs:
                    out.publish_raw(payload)
                    sent += 1
                due += period
                delay = due - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
        time.sleep(0.5)  # let the last samples leave before the session closes
        print(f"sent {sent}", flush=True)
        node.close()


# ----------------------------------------------------------------------------- parent
class _Children:
    """Publisher processes: start, wait until ready, release together, collect their counts."""

    def __init__(self, endpoint: str, kind: str, processes: int, **args: Any) -> None:
        command = [sys.executable, __file__, "--role", "publish", "--endpoint", endpoint]
        command += ["--kind", kind, "--count", str(args["count"])]
        command += ["--publishers", str(args["publishers"]), "--rate", str(args["rate"])]
        self.procs = [
            subprocess.Popen(
                command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=os.getcwd()
            )
            for _ in range(processes)
        ]
        for proc in self.procs:
            assert proc.stdout is not None
            line = proc.stdout.readline().strip()
            if line != "ready":
                raise RuntimeError(f"publisher did not start: {line!r}")

    def go(self) -> None:
        for proc in self.procs:
            assert proc.stdin is not None
            proc.stdin.write("go\n")
            proc.stdin.flush()

    def sent(self) -> int:
        total = 0
        for proc in self.procs:
            assert proc.stdout is not None
            line = proc.stdout.readline().strip()
            total += int(line.split()[1]) if line.startswith("sent") else 0
            proc.wait(timeout=60)
        return total


def _measure(
    endpoint: str,
    kind: str,
    processes: int,
    count: int,
    publishers: int,
    rate: float,
    received: Callable[[], tuple[int, int]],
) -> dict[str, float]:
    """Run one traffic pattern against whatever listens; ``received`` -> (messages, bytes).

    The window runs from the release of the publishers to the last arrival seen (the
    listener is given 5 s of silence to catch up before the window is closed).
    """
    children = _Children(endpoint, kind, processes, count=count, publishers=publishers, rate=rate)
    start_messages, start_bytes = received()
    cpu0, wall0 = time.process_time(), time.monotonic()
    children.go()
    sent = children.sent()
    last, still, cpu_at_last = received()[0], time.monotonic(), time.process_time()
    while received()[0] - start_messages < sent and time.monotonic() - still < 5.0:
        time.sleep(0.02)
        now = received()[0]
        if now != last:
            last, still, cpu_at_last = now, time.monotonic(), time.process_time()
    if received()[0] - start_messages >= sent:
        still, cpu_at_last = time.monotonic(), time.process_time()
    messages, size = received()
    wall = max(still - wall0, 1e-9)
    got = messages - start_messages
    return {
        "sent": sent,
        "received": got,
        "lost": sent - got,
        "rate": got / wall,
        "mbps": (size - start_bytes) / MB / wall,
        "cpu": (cpu_at_last - cpu0) / wall,
    }


def _bare(session: Any) -> tuple[Any, Callable[[], tuple[int, int]]]:
    counts = [0, 0]

    def on_sample(sample: Any) -> None:
        data = sample.payload.to_bytes()
        counts[0] += 1
        counts[1] += len(data)

    subscriber = session.declare_subscriber("0/**", on_sample)
    return subscriber, lambda: (counts[0], counts[1])


def _mcap_baseline(payload: bytes, count: int, directory: Path) -> dict[str, float]:
    from mcap.writer import CompressionType, Writer

    path = directory / "baseline.mcap"
    started = time.monotonic()
    with open(path, "wb") as stream:
        writer = Writer(stream, compression=CompressionType.NONE)
        writer.start("ros2", "bench")
        schema = writer.register_schema("sensor_msgs/msg/JointState", "ros2msg", b"")
        channel = writer.register_channel("/bench", "cdr", schema)
        for i in range(count):
            now = time.time_ns()
            writer.add_message(channel, now, payload, now, i)
        writer.finish()
    wall = time.monotonic() - started
    path.unlink()
    return {"rate": count / wall, "mbps": count * len(payload) / MB / wall}


def run(flood: int, large: int, fleet_seconds: float) -> None:
    from components.comm.session import SessionSettings, open_session
    from components.data_archiver.core import TopicSelection
    from components.recording.recorder import Recorder

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(SessionSettings(mode="router", connect=(), listen=(endpoint,)))
    workdir = Path(tempfile.mkdtemp(prefix="msctl-bench-record-"))
    rows = []
    scenarios = [
        ("flood 6-joint JointState", "flood", 1, flood, 1, 0.0),
        ("40 publishers x 200 Hz", "fleet", 4, int(fleet_seconds * 200), 10, 200.0),
        ("1 MB messages", "large", 1, large, 1, 0.0),
    ]
    print(f"record benchmark: {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}")
    try:
        with open_session(_settings(endpoint)) as session:
            for title, kind, processes, count, publishers, rate in scenarios:
                subscriber, counter = _bare(session)
                try:
                    bare = _measure(endpoint, kind, processes, count, publishers, rate, counter)
                finally:
                    subscriber.undeclare()
                bag = workdir / f"bag_{kind}"
                recorder = Recorder(session, bag, TopicSelection(all_topics=True)).start()
                try:
                    ours = _measure(
                        endpoint,
                        kind,
                        processes,
                        count,
                        publishers,
                        rate,
                        lambda r=recorder: (r.status().messages, r.status().bytes),
                    )
                finally:
                    status = recorder.stop()
                # Lost: against what the bag holds once the recorder has written everything.
                ours["lost"] = ours["sent"] - status.messages
                payload = _large_bytes(1_000_000) if kind == "large" else _joint_state_bytes()
                writer = _mcap_baseline(
                    payload, min(count * publishers * processes, 200_000), workdir
                )
                rows.append(
                    (
                        title,
                        f"{ours['rate']:,.0f}",
                        f"{ours['mbps']:,.1f}",
                        f"{ours['lost']:,}",
                        f"{status.lost:,}",
                        f"{status.dropped:,}",
                        f"{ours['cpu']:.2f}",
                        f"{bare['rate']:,.0f} ({ours['rate'] / bare['rate']:.2f}x)",
                        f"{bare['cpu']:.2f}",
                        f"{writer['rate']:,.0f} ({ours['rate'] / writer['rate']:.2f}x)",
                    )
                )
                shutil.rmtree(bag, ignore_errors=True)
    finally:
        router.close()
        shutil.rmtree(workdir, ignore_errors=True)
    print_table(
        "recording (ours = msctl's recorder; ratios are ours / baseline)",
        (
            "scenario",
            "ours msg/s",
            "ours MB/s",
            "lost",
            "seq gaps",
            "dropped",
            "ours CPU",
            "bare sub msg/s",
            "bare CPU",
            "mcap writer msg/s",
        ),
        rows,
    )
    print(
        "\ntargets: flood >= 50,000 msg/s with 0 lost; 1 MB messages >= 200 MB/s; "
        "recorder CPU < 1.0 core"
    )
    print(f"load average at the end: {os.getloadavg()[0]:.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--role", default="")
    parser.add_argument("--endpoint", default="")
    parser.add_argument("--kind", default="flood")
    parser.add_argument("--count", type=int, default=0)
    parser.add_argument("--publishers", type=int, default=1)
    parser.add_argument("--rate", type=float, default=0.0)
    parser.add_argument("--flood", type=int, default=100_000, help="messages in the flood")
    parser.add_argument("--large", type=int, default=300, help="1 MB messages")
    parser.add_argument("--fleet-seconds", type=float, default=5.0)
    args = parser.parse_args()
    if args.role == "publish":
        role_publish(args.endpoint, args.kind, args.count, args.publishers, args.rate)
        return
    run(args.flood, args.large, args.fleet_seconds)


if __name__ == "__main__":
    threading.current_thread().name = "bench"
    main()
