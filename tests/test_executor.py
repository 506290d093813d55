"""The Executor over real Zenoh: cores kept apart, keep-last inboxes, failures contained,
services and timers, and a prompt, clean exit on SIGTERM in a real subprocess.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import quick_peer_settings, quick_router, wait_until

from components.comm import Node, ServiceError, ServiceTimeout
from components.comm.graph import snapshot
from components.comm.qos import QoS
from components.comm.session import SessionSettings
from components.comm.topics import Subscription
from components.executor import Core, Every, InterfaceSpec, Publish, Serve, Subscribe
from components.executor.executor import Component, Executor
from components.messages import msg

STRING = "std_msgs/msg/String"
STATE = (Publish("state", STRING),)


class Counter(Core):
    """Counts commands and answers each with its running count on ``state``."""

    SPEC = InterfaceSpec(
        subscribe=(Subscribe("cmd", STRING, "on_cmd"),),
        publish=STATE,
        serve=(Serve("count", "std_srvs/srv/Trigger", "on_count"),),
    )

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.seen: list[str] = []
        self.started = self.stopped = False

    def start(self, now: float) -> None:
        self.started = True

    def stop(self, now: float) -> None:
        self.stopped = True

    def on_cmd(self, message: Any, now: float) -> None:
        if message.data == "boom":
            raise RuntimeError("a bug in this core")
        self.seen.append(message.data)
        self.publish("state", msg(STRING, data=f"{self.name}:{len(self.seen)}"))

    def on_count(self, request: Any, now: float) -> Any:
        if self.seen and self.seen[-1] == "refuse":
            return None
        return msg("std_srvs/srv/Trigger_Response", success=True, message=str(len(self.seen)))


@pytest.fixture
def router_endpoint() -> Iterator[str]:
    """Overrides conftest's: the same real router, without the 0.5 s opening wait."""
    yield from quick_router()


@pytest.fixture
def session_settings(router_endpoint: str) -> SessionSettings:
    """Overrides conftest's: peers that open at once (deliveries are polled anyway)."""
    return quick_peer_settings(router_endpoint)


@pytest.fixture
def driver(open_sessions: Callable[[], Any]) -> Iterator[Node]:
    """A node on its own session that pokes the executor's cores from outside."""
    node = Node(open_sessions(), "driver")
    yield node
    node.close()


class Running:
    """An executor running on a background thread (signals stay with pytest's main thread)."""

    def __init__(self, executor: Executor) -> None:
        self.executor = executor
        self.thread = threading.Thread(target=executor.run, daemon=True)

    def __enter__(self) -> Executor:
        self.thread.start()
        return self.executor

    def __exit__(self, *exc: object) -> None:
        self.executor.stop()
        self.thread.join(5.0)
        assert not self.thread.is_alive(), "executor did not stop within 5 s"


def send_until(send: Callable[[], None], done: Callable[[], Any], timeout: float = 5.0) -> Any:
    """Send until ``done()``: the first sample may precede route discovery."""

    def attempt() -> Any:
        if not done():
            send()
            time.sleep(0.03)
        return done()

    return wait_until(attempt, timeout)


def test_two_cores_in_one_process_keep_their_own_state(
    session_settings: SessionSettings, driver: Node
) -> None:
    executor = Executor(settings=session_settings)
    left, right = Counter("left"), Counter("right")
    left_c = executor.add(left, Counter.SPEC, namespace="/left")
    right_c = executor.add(right, Counter.SPEC, namespace="/right")
    assert left_c.node is not right_c.node
    assert left_c.publishers["state"] is not right_c.publishers["state"]
    assert left_c.publishers["state"].topic == "/left/state"
    assert (left.outbox, right.outbox) == (left_c, right_c)
    states: list[str] = []
    driver.subscription("/left/state", STRING, lambda m: states.append(m.data))
    driver.subscription("/right/state", STRING, lambda m: states.append(m.data))
    to_left = driver.publisher("/left/cmd", STRING)
    to_right = driver.publisher("/right/cmd", STRING)
    with Running(executor):
        send_until(lambda: to_left.publish(msg(STRING, data="L")), lambda: left.seen)
        for _ in range(2):
            to_left.publish(msg(STRING, data="L"))
        send_until(lambda: to_right.publish(msg(STRING, data="R")), lambda: right.seen)
        wait_until(lambda: len(left.seen) >= 3)
        count_client = driver.client("/right/count", "std_srvs/srv/Trigger")
        reply = count_client.call(msg("std_srvs/srv/Trigger_Request"), timeout=2.0)
        wait_until(lambda: {f"left:{len(left.seen)}", f"right:{len(right.seen)}"} <= set(states))
    assert set(left.seen) == {"L"} and set(right.seen) == {"R"}
    assert reply.success and reply.message == str(len(right.seen))
    # Each core counted only its own commands and published only on its own namespace.
    lefts = [int(s.split(":")[1]) for s in states if s.startswith("left:")]
    rights = [int(s.split(":")[1]) for s in states if s.startswith("right:")]
    assert len(lefts) + len(rights) == len(states)
    assert lefts == sorted(lefts) and lefts[-1] == len(left.seen)
    assert rights == sorted(rights) and rights[-1] == len(right.seen)
    assert left.started and right.started and left.stopped and right.stopped
    assert (left_c.errors, right_c.errors) == (0, 0)
    assert executor.session.is_closed()


def _zenoh_subscription(component: Component) -> Subscription:
    return next(e for e in component.node._owned if isinstance(e, Subscription))


def test_keep_last_depth_holds_only_the_newest_pending_samples(
    session_settings: SessionSettings, driver: Node
) -> None:
    spec = InterfaceSpec(
        subscribe=(Subscribe("cmd", STRING, "on_cmd", QoS(depth=3)),), publish=STATE
    )
    with Executor(settings=session_settings) as executor:
        slow = Counter("slow")
        component = executor.add(slow, spec, namespace="/slow")
        pub = driver.publisher("/slow/cmd", STRING)

        def warm() -> bool:
            executor.spin_once()
            return bool(slow.seen)

        send_until(lambda: pub.publish(msg(STRING, data="warm-up")), warm)
        while slow.seen and executor._work.qsize():  # drain stray warm-ups
            executor.spin_once()
        zsub = _zenoh_subscription(component)
        before = zsub.received
        slow.seen.clear()
        # The core is "busy" (nobody spins) while ten samples arrive.
        for n in range(10):
            pub.publish(msg(STRING, data=str(n)))
        wait_until(lambda: zsub.received == before + 10)
        executor.spin_once(timeout=1.0)
        assert slow.seen == ["7", "8", "9"]
        assert component.errors == 0


def test_keep_last_under_a_slow_running_core(
    session_settings: SessionSettings, driver: Node
) -> None:
    class Slow(Counter):
        def on_cmd(self, message: Any, now: float) -> None:
            super().on_cmd(message, now)
            if message.data == "first":
                release.wait(5.0)

    release = threading.Event()
    spec = InterfaceSpec(
        subscribe=(Subscribe("cmd", STRING, "on_cmd", QoS(depth=2)),), publish=STATE
    )
    executor = Executor(settings=session_settings)
    slow = Slow("slow")
    component = executor.add(slow, spec, namespace="/busy")
    pub = driver.publisher("/busy/cmd", STRING)
    with Running(executor):
        send_until(lambda: pub.publish(msg(STRING, data="first")), lambda: slow.seen)
        zsub = _zenoh_subscription(component)
        before = zsub.received
        for n in range(20):
            pub.publish(msg(STRING, data=f"n{n}"))
        wait_until(lambda: zsub.received >= before + 20)
        release.set()
        wait_until(lambda: slow.seen[-1] == "n19")
    after_first = slow.seen[slow.seen.index("first") + 1 :]
    after_first = [s for s in after_first if s != "first"]
    assert after_first == ["n18", "n19"]


def test_a_failing_core_is_counted_and_the_other_keeps_running(
    session_settings: SessionSettings, driver: Node
) -> None:
    class Ticker(Counter):
        SPEC = InterfaceSpec(
            subscribe=(Subscribe("/cmd", STRING, "on_cmd"),),
            publish=STATE,
            every=(Every(0.02, "tick"),),
        )

        def __init__(self, name: str) -> None:
            super().__init__(name)
            self.ticks = 0

        def tick(self, now: float) -> None:
            self.ticks += 1

    executor = Executor(settings=session_settings)
    fragile, sturdy = Counter("fragile"), Ticker("sturdy")
    fragile_c = executor.add(
        fragile,
        InterfaceSpec(subscribe=(Subscribe("/cmd", STRING, "on_cmd"),), publish=STATE),
        "/a",
    )
    sturdy_c = executor.add(sturdy, Ticker.SPEC, "/b")
    pub = driver.publisher("/cmd", STRING)
    with Running(executor):
        send_until(lambda: pub.publish(msg(STRING, data="hi")), lambda: sturdy.seen)
        for _ in range(3):
            pub.publish(msg(STRING, data="boom"))  # raises in both cores' on_cmd
        pub.publish(msg(STRING, data="after"))
        wait_until(lambda: "after" in sturdy.seen and "after" in fragile.seen)
        ticks = sturdy.ticks
        wait_until(lambda: sturdy.ticks >= ticks + 3)
    assert fragile_c.errors == 3 and sturdy_c.errors == 3
    assert fragile.seen[-1] == sturdy.seen[-1] == "after"
    assert fragile_c.handled > fragile_c.errors


def test_services_through_the_executor(session_settings: SessionSettings, driver: Node) -> None:
    executor = Executor(settings=session_settings)
    core = Counter("served")
    component = executor.add(core, Counter.SPEC, "/srv")
    client = driver.client("/srv/count", "std_srvs/srv/Trigger")
    cmd = driver.publisher("/srv/cmd", STRING)
    request = msg("std_srvs/srv/Trigger_Request")

    def answered() -> Any:
        try:
            return client.call(request, timeout=0.5)
        except ServiceTimeout:
            return None

    with Running(executor):
        first = wait_until(answered)
        send_until(lambda: cmd.publish(msg(STRING, data="refuse")), lambda: core.seen)
        with pytest.raises(ServiceError, match="could not answer"):
            client.call(request, timeout=2.0)
    assert (first.success, first.message) == (True, "0")
    assert component.errors == 0


def test_undeclared_output_and_missing_handler_are_refused(
    session_settings: SessionSettings,
) -> None:
    with Executor(settings=session_settings) as executor:
        component = executor.add(Counter("c"), Counter.SPEC, "/x")
        with pytest.raises(KeyError, match="nowhere"):
            component.publish("nowhere", msg(STRING))
        bad = InterfaceSpec(subscribe=(Subscribe("cmd", STRING, "on_missing"),))
        with pytest.raises(AttributeError, match="on_missing"):
            executor.add(Counter("d"), bad, "/y")
        assert [c.name for c in executor.components] == ["c"]


SIGTERM_SCRIPT = textwrap.dedent(
    """
    from components.executor import Core, Every, InterfaceSpec, Publish, Subscribe
    from components.executor.executor import Executor
    from components.messages import msg

    class Worker(Core):
        def start(self, now):
            print("started", self.name, flush=True)
        def stop(self, now):
            print("stopped", self.name, flush=True)
        def on_cmd(self, message, now):
            pass
        def tick(self, now):
            self.publish("beat", msg("std_msgs/msg/String", data="beat"))

    spec = InterfaceSpec(
        subscribe=(Subscribe("cmd", "std_msgs/msg/String", "on_cmd"),),
        publish=(Publish("beat", "std_msgs/msg/String"),),
        every=(Every(0.05, "tick"),),
    )
    executor = Executor()
    executor.add(Worker("w1"), spec, "/sig1", node_name="worker")
    executor.add(Worker("w2"), spec, "/sig2", node_name="worker")
    print("ready", flush=True)
    executor.run()
    print("session closed:", executor.session.is_closed(), flush=True)
    """
)


@pytest.mark.e2e
def test_sigterm_ends_the_process_promptly_with_sessions_closed(
    zenoh_env: dict[str, str], open_sessions: Callable[[], Any], tmp_path: Path
) -> None:
    script = tmp_path / "executor_main.py"
    script.write_text(SIGTERM_SCRIPT)
    observer = open_sessions()
    beats: list[str] = []
    watcher = Node(observer, "watcher")
    watcher.subscription("/sig1/beat", STRING, lambda m: beats.append(m.data))
    env = {**os.environ, **zenoh_env}
    errors = (tmp_path / "stderr.txt").open("w")
    proc = subprocess.Popen(
        [sys.executable, str(script)],
        stdout=subprocess.PIPE,
        stderr=errors,
        text=True,
        env=env,
        cwd=Path(__file__).resolve().parent.parent,
    )
    lines: list[str] = []
    try:
        assert proc.stdout is not None
        lines.append(proc.stdout.readline().strip())
        assert lines == ["ready"]
        wait_until(lambda: beats, timeout=10.0)  # running, with a live callback subscriber
        assert wait_until(
            lambda: {"/sig1/worker", "/sig2/worker"} <= snapshot(observer).node_names()
        )
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30.0)  # stops, and does not hang (how fast: not on a busy machine)
        lines += proc.stdout.read().splitlines()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        errors.close()
        watcher.close()
    err = (tmp_path / "stderr.txt").read_text()
    assert proc.returncode == 0, err
    assert {"started w1", "started w2", "stopped w1", "stopped w2"} <= set(lines)
    assert lines[-1] == "session closed: True"
    wait_until(lambda: not {"/sig1/worker", "/sig2/worker"} & snapshot(observer).node_names())
