"""One large message must not disable a limb (issue 10, finding 3), end to end.

A simulated ``minimal`` runs under the real ``msctl up --detach`` (temporary MSCTL_HOME, a
random router port). A separate node floods ``/limb1/joint_commands`` and
``/limb1/joint_states`` with valid JointStates of 100,000 names each (distinct names in every
message, as a fuzzer sends them), and the test measures, before and after the flood, the
resident memory of the module's process (joint manager, health monitor...) and of the
simulator's, and the joint_set -> joint_read motion latency.

Asserted: memory does not grow beyond a generous bound (before the fix the health monitor kept
every name it saw), the health monitor counted the refused messages (the joint manager
refuses the flood's ``joint_states`` by sender: not its motor interface), ``joint_set`` still
moves the joint and ``halt`` still answers. Latencies are printed, never asserted (a shared
machine).
"""

from __future__ import annotations

import itertools
import os
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import free_port, wait_until

from components.comm.node import Node
from components.comm.session import SessionSettings, open_session
from components.messages import (
    DIAGNOSTIC_ARRAY,
    JOINT_STATE,
    TRIGGER,
    JointSample,
    diagnostic_values,
    joint_samples,
    joint_state,
    msg,
)

#: Real processes in wall time on a loaded two-core machine: minutes, not the default 120 s.
pytestmark = [pytest.mark.e2e, pytest.mark.timeout(900)]

ROOT = Path(__file__).resolve().parents[1]
FLOOD_NAMES = 100_000
FLOOD_MESSAGES = 10  # per topic
JOINT = "limb1_joint2"
#: Generous: decoding a 100k-name message costs ~10 MB and the allocator keeps some of it
#: (measured: +61 MiB after the first 10 + 10 messages on a quiet machine, +101 MiB on a
#: loaded one, where more of them wait in queues at once; none after the next); keeping
#: every name seen (before the fix) grows without end, which the second round shows.
RSS_GROWTH_BOUND = 100 * 2**20
#: The first round only warms the allocators up: its bound is twice as loose.
WARM_UP_BOUND = 2 * RSS_GROWTH_BOUND
#: Flood rounds: one to warm up, two to judge.
ROUNDS = 3
COUNTED = ("refused_", "feedback_")
#: (status, counter) of the flood counts of the core that reads both topics from anyone: the
#: health monitor (telemetry to it). The joint manager takes ``joint_states`` (feedback, by
#: its role) from the module's own motor interface only, so the transport refuses the flood
#: node's before decoding them (its own oversize check is tested on the core); the
#: simulator's count is printed only, as the transport may refuse joint_commands from a node
#: other than the joint manager before the simulator sees them. A status is named exactly
#: so, or ends with ``/`` and that name.
FLOOD_COUNTERS = (("limb1", "refused_oversize"),)


def _named(status: str, key: str) -> bool:
    return status == key or status.endswith("/" + key)


class Up:
    """One detached simulated ``minimal``."""

    def __init__(self, home: Path) -> None:
        self.home = home
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.env = {
            **os.environ,
            "MSCTL_HOME": str(home),
            "MSCTL_HOST": "flood-test-laptop",  # none of the assembly's computers: simulated
            "MSCTL_ZENOH_CONNECT": self.endpoint,
            "MSCTL_ZENOH_LISTEN": "tcp/127.0.0.1:0",
            "MSCTL_ZENOH_MULTICAST": "0",
            "PYTHONPATH": str(ROOT),
        }
        result = self.msctl("up", "minimal", "--detach", "--speed", "1", timeout=120.0)
        assert result.returncode == 0, result.stdout + result.stderr

    def msctl(self, *args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
        return subprocess.run(
            [sys.executable, "-m", "msctl", *args],
            check=False,
            env=self.env,
            capture_output=True,
            text=True,
            timeout=timeout,
            cwd=ROOT,
        )

    def pids(self) -> dict[str, int]:
        """Process name (``limb1``, ``sim``) -> pid, from ``msctl ps --json``."""
        import json

        result = self.msctl("ps", "--json")
        assert result.returncode == 0, result.stderr
        found = {}
        for component in json.loads(result.stdout)["components"]:
            if component["pid"]:
                found[component["process"]] = int(component["pid"])
        return found

    def settings(self) -> SessionSettings:
        return SessionSettings(
            connect=(self.endpoint,), listen=("tcp/127.0.0.1:0",), multicast=False
        )

    def down(self) -> None:
        self.msctl("down", timeout=60.0)


def rss(pid: int) -> int:
    """Resident memory of a process, in bytes (Linux /proc)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise AssertionError(f"no VmRSS for pid {pid}")


class Operator:
    """A node in /limb1: joint_read, the counters in diagnostics, joint_set and halt."""

    def __init__(self, up: Up) -> None:
        self.session = open_session(up.settings())
        self.node = Node(self.session, "flood_operator", "/limb1")
        self.lock = threading.Lock()
        self.position: float | None = None
        self.counters: dict[str, dict[str, int]] = {}  # status name -> counter -> value
        self.reports: dict[str, int] = {}  # status name -> how many times it was received
        self.node.subscription("joint_read", JOINT_STATE, self._on_read)
        self.node.subscription("/limb1/diagnostics", DIAGNOSTIC_ARRAY, self._on_diagnostics)
        self.node.subscription("/limb1/health", DIAGNOSTIC_ARRAY, self._on_diagnostics)
        self.node.subscription("/sim/diagnostics", DIAGNOSTIC_ARRAY, self._on_diagnostics)
        self.joint_set = self.node.publisher("joint_set", JOINT_STATE)
        self.flood_commands = self.node.publisher("/limb1/joint_commands", JOINT_STATE)
        self.flood_states = self.node.publisher("/limb1/joint_states", JOINT_STATE)
        self.halt = self.node.client("halt", TRIGGER)
        self.recover = self.node.client("recover", TRIGGER)

    def _on_read(self, message: Any) -> None:
        for sample in joint_samples(message):
            if sample.name == JOINT and sample.position is not None:
                with self.lock:
                    self.position = sample.position

    def _on_diagnostics(self, message: Any) -> None:
        for status in message.status:
            values = diagnostic_values(status)
            counts = {k: int(v) for k, v in values.items() if k.startswith(COUNTED) and v.isdigit()}
            with self.lock:
                self.reports[status.name] = self.reports.get(status.name, 0) + 1
                if counts:
                    self.counters[status.name] = counts

    def reported(self, key: str) -> int:
        with self.lock:
            return sum(n for status, n in self.reports.items() if _named(status, key))

    def counter(self, key: str, name: str) -> int:
        with self.lock:
            found = [c for status, c in self.counters.items() if _named(status, key)]
        return max((c.get(name, 0) for c in found), default=0)

    def latest(self) -> float | None:
        with self.lock:
            return self.position

    def motion_latency(self, goal: float) -> float:
        """Seconds from a joint_set to the first joint_read showing the joint on its way."""
        wait_until(lambda: self.latest() is not None, 30.0, "joint_read")
        start = self.latest()
        assert start is not None
        sent = time.monotonic()
        self.joint_set.publish(joint_state([JointSample(JOINT, goal)]))
        wait_until(lambda: abs(self.latest() - start) > 0.01, 30.0, f"{JOINT} moving")
        latency = time.monotonic() - sent

        # Keep commanding, as an operator streams: one command alone is held where it is by
        # the joint manager's watchdog (0.5 s) if a loaded machine has not finished the move.
        def arrived() -> bool:
            self.joint_set.publish(joint_state([JointSample(JOINT, goal)]))
            return abs(self.latest() - goal) < 0.05

        wait_until(arrived, 60.0, f"{JOINT} at {goal}", interval=0.05)
        return latency

    def latencies(self) -> list[float]:
        return [self.motion_latency(goal) for goal in (0.3, -0.3, 0.3, 0.0)]

    def close(self) -> None:
        self.node.close()
        self.session.close()


@pytest.fixture(scope="module")
def minimal(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Up]:
    up = Up(tmp_path_factory.mktemp("flood_minimal"))
    try:
        yield up
    finally:
        up.down()


def flood(index: int) -> Any:
    names = [f"limb1_flood{index}_{i}" for i in range(FLOOD_NAMES)]
    values = np.arange(FLOOD_NAMES, dtype=np.float64)
    return msg(JOINT_STATE, name=names, position=values, velocity=values, effort=values)


def test_a_100k_name_flood_leaves_memory_flat_and_the_limb_responsive(
    minimal: Up,
) -> None:
    pids = minimal.pids()
    assert {"limb1", "sim"} <= set(pids), pids
    operator = Operator(minimal)
    mib = 2**20
    try:
        wait_until(lambda: operator.latest() is not None, 60.0, "joint_read from limb1")
        before_latency = operator.latencies()
        memory = [{name: rss(pid) for name, pid in pids.items()}]
        counts = [tuple(0 for _ in FLOOD_COUNTERS)]
        # The first round takes the processes' allocators to their working size (a decoded
        # 100k-name message is ~10 MB); the next ones show whether anything is kept.
        for round_ in range(ROUNDS):

            def send(round_: int = round_) -> None:
                for index in range(FLOOD_MESSAGES):
                    message = flood(round_ * FLOOD_MESSAGES + index)
                    operator.flood_commands.publish(message)
                    operator.flood_states.publish(message)

            send()
            counts.append(settle(operator, counts[-1], send))
            memory.append({name: rss(pid) for name, pid in pids.items()})
        in_sim = operator.counter("world", "refused_oversize")
        after_latency = operator.latencies()
        response = operator.halt.call(operator.halt.request_type()(), timeout=10.0)
        assert response.success, response.message
        assert operator.recover.call(operator.recover.request_type()(), timeout=10.0).success
    finally:
        operator.close()
    print(
        f"\nflood: {ROUNDS} x {FLOOD_MESSAGES} x {FLOOD_NAMES} names on joint_commands and "
        f"joint_states; refused and counted (health monitor) {counts[1:]}, "
        f"simulator {in_sim}"
    )
    for name in sorted(pids):
        figures = ", ".join(f"{m[name] / mib:.1f}" for m in memory)
        print(f"  RSS {name} before, then after each round: {figures} MiB")
    print(
        f"  joint_set -> motion: median {statistics.median(before_latency) * 1e3:.1f} ms "
        f"before, {statistics.median(after_latency) * 1e3:.1f} ms after"
    )
    for name in pids:
        growth = [after[name] - before[name] for before, after in itertools.pairwise(memory)]
        assert growth[0] < WARM_UP_BOUND, (name, memory)
        # Flat: nothing kept. Keeping every name grows every round by as much as the last;
        # the allocator's leftovers do not add up (a loaded run measured +55 MiB after one
        # round, then none), so one flat round after the warm-up is the proof.
        assert min(growth[1:]) < RSS_GROWTH_BOUND / 2, (name, memory)


#: Seconds before a round no core has counted is sent again.
RESEND_AFTER = 30.0


def settle(
    operator: Operator, previous: tuple[int, ...], send: Callable[[], None]
) -> tuple[int, ...]:
    """Wait until every core counted more floods than ``previous`` and its counts held over
    two more reports; the counts.

    A best-effort subscriber may drop some of a burst, and on a starved machine all of it
    (a CI run saw a core count none of a round's 10 messages in 300 s): a round not counted
    within ``RESEND_AFTER`` is sent again, as a fuzzer keeps sending.
    """

    def counted() -> tuple[int, ...]:
        return tuple(operator.counter(status, name) for status, name in FLOOD_COUNTERS)

    def more() -> bool:
        return all(now > then for now, then in zip(counted(), previous, strict=True))

    deadline = time.monotonic() + 300.0
    while not more():
        try:
            wait_until(more, RESEND_AFTER, "every core counted the flood")
        except AssertionError:
            if time.monotonic() > deadline:
                raise
            send()
    for _ in range(60):
        seen = counted()
        marks = {status: operator.reported(status) for status, _ in FLOOD_COUNTERS}
        wait_until(
            lambda marks=marks: all(operator.reported(s) >= m + 2 for s, m in marks.items()),
            60.0,
            "two more diagnostics from each core",
        )
        if counted() == seen:
            break
    return seen
