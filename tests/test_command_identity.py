"""Only a module's own joint manager commands its motors (issue 10, finding 1).

A subscription given ``senders`` takes samples only from publishers whose GID (in the
rmw_zenoh attachment) hashes a liveliness token of an allowed node. Everything else is
refused, counted in ``drops`` under ``intruder``, and warned about once per intruding node.

Real Zenoh sessions on a loopback router (random port, no multicast); every session is
closed at teardown. Deliveries and drops are polled with deadlines, never slept for.
"""

from __future__ import annotations

import itertools
import logging
import os
import re
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import free_port, quick_peer_settings, quick_router, resolved_assembly, wait_until

from components.comm import Node
from components.comm import topics as topics_module
from components.comm.attachment import Attachment
from components.comm.session import SessionSettings, open_session
from components.comm.stats import drops
from components.comm.topics import INTRUDER
from components.messages import JOINT_STATE, JointSample, joint_samples, joint_state

ROOT = Path(__file__).resolve().parents[1]
_names = itertools.count()


def unique_namespace() -> str:
    """A module namespace no other test uses (drop counters are per process, per topic)."""
    return f"/idm{next(_names)}_{int(time.monotonic() * 1000) % 100000}"


def command(position: float, joint: str = "limb1_joint2") -> Any:
    return joint_state([JointSample(joint, position, None, None)])


def send_until(send: Callable[[], None], done: Callable[[], Any], timeout: float = 10.0) -> Any:
    """Send repeatedly until ``done()``: the first samples may precede route discovery."""

    def attempt() -> Any:
        if not done():
            send()
            time.sleep(0.02)
        return done()

    return wait_until(attempt, timeout)


@pytest.fixture
def router_endpoint() -> Iterator[str]:
    """Overrides conftest's: the same real router, without the 0.5 s opening wait."""
    yield from quick_router()


@pytest.fixture
def session_settings(router_endpoint: str) -> SessionSettings:
    """Overrides conftest's: peers that open at once (deliveries are polled anyway)."""
    return quick_peer_settings(router_endpoint)


class Motors:
    """A motor-interface stand-in: ``joint_commands`` from ``joint_manager`` only."""

    def __init__(self, session: Any, namespace: str) -> None:
        self.node = Node(session, "motor_interface", namespace)
        self.got: list[Any] = []
        self.sub = self.node.subscription(
            "joint_commands", JOINT_STATE, self.got.append, senders=("joint_manager",)
        )
        self.topic = self.sub.topic

    def refused(self) -> int:
        return drops.count(self.topic, INTRUDER)

    def close(self) -> None:
        self.node.close()


def warnings_about(caplog: pytest.LogCaptureFixture, topic: str) -> list[str]:
    return [
        r.getMessage()
        for r in caplog.records
        if r.levelno == logging.WARNING and r.getMessage().startswith(f"{topic}: refused")
    ]


def test_senders_are_qualified_in_the_node_namespace(open_sessions) -> None:
    namespace = unique_namespace()
    motors = Motors(open_sessions(), namespace)
    try:
        assert motors.sub.senders == frozenset({f"{namespace}/joint_manager"})
    finally:
        motors.close()


def test_the_joint_manager_passes_a_foreign_node_and_a_raw_publisher_do_not(
    open_sessions, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="msctl.comm")
    namespace = unique_namespace()
    motors = Motors(open_sessions(), namespace)
    manager = Node(open_sessions(), "joint_manager", namespace)
    intruder = Node(open_sessions(), "teleop", "/ground1")
    raw_session = open_sessions()
    raw = raw_session.declare_publisher(motors.sub.key)
    try:
        legit = manager.publisher("joint_commands", JOINT_STATE)
        send_until(lambda: legit.publish(command(0.1)), lambda: motors.got)
        assert joint_samples(motors.got[-1]) == [JointSample("limb1_joint2", 0.1, None, None)]
        # (A first sample may outrun the manager's token: refused, but never warned about.)
        assert warnings_about(caplog, motors.topic) == []

        # Another node's publisher on the module's topic: refused, named once.
        foreign = intruder.publisher(f"{namespace}/joint_commands", JOINT_STATE)
        delivered = len(motors.got)
        send_until(lambda: foreign.publish(command(1.5)), lambda: motors.refused() >= 5)
        assert len(motors.got) == delivered
        named = warnings_about(caplog, motors.topic)
        assert len(named) == 1 and "node /ground1/teleop" in named[0], named
        assert f"only {namespace}/joint_manager may publish here" in named[0]

        # A raw Zenoh put with no attachment (not a ROS node at all): refused, said once.
        before = motors.refused()
        payload = legit._serialize(command(1.5))
        send_until(lambda: raw.put(payload), lambda: motors.refused() >= before + 5)
        assert len(motors.got) == delivered
        said = warnings_about(caplog, motors.topic)
        assert len(said) == 2 and "no rmw_zenoh attachment" in said[1], said

        # The legitimate manager still passes, and every refusal was counted once, as intruder.
        send_until(lambda: legit.publish(command(0.2)), lambda: len(motors.got) > delivered)
        assert joint_samples(motors.got[-1])[0].position == 0.2
        assert drops.snapshot()[motors.topic] == {INTRUDER: motors.refused()}
        assert len(warnings_about(caplog, motors.topic)) == 2
    finally:
        raw.undeclare()
        intruder.close()
        manager.close()
        motors.close()


def test_a_forged_or_replayed_gid_is_refused(open_sessions, caplog, monkeypatch) -> None:
    caplog.set_level(logging.INFO, logger="msctl.comm")
    monkeypatch.setattr(topics_module, "UNKNOWN_GRACE", 0.0)
    namespace = unique_namespace()
    motors = Motors(open_sessions(), namespace)
    manager = Node(open_sessions(), "joint_manager", namespace)
    raw_session = open_sessions()
    raw = raw_session.declare_publisher(motors.sub.key)
    try:
        legit = manager.publisher("joint_commands", JOINT_STATE)
        send_until(lambda: legit.publish(command(0.1)), lambda: motors.got)
        payload = legit._serialize(command(1.5))
        made_up = Attachment(1, time.time_ns(), bytes(range(16))).encode()
        send_until(lambda: raw.put(payload, attachment=made_up), lambda: motors.refused() >= 3)
        (said,) = warnings_about(caplog, motors.topic)
        assert f"no graph token (GID {bytes(range(16)).hex()})" in said

        # The manager's GID is only good while its token lives: replayed after it left, no.
        replay = Attachment(99, time.time_ns(), legit.gid).encode()
        manager.close()
        wait_until(lambda: legit.gid not in motors.sub._allowed, what="the token's removal")
        delivered, before = len(motors.got), motors.refused()
        send_until(
            lambda: raw.put(payload, attachment=replay), lambda: motors.refused() >= before + 3
        )
        assert len(motors.got) == delivered
    finally:
        raw.undeclare()
        manager.close()
        motors.close()


def test_start_up_each_new_manager_is_taken_and_never_warned_about(open_sessions, caplog) -> None:
    """A publisher declares its token before its first sample, and the subscription follows
    the tokens, so a new manager's commands are taken at once or within a moment (a sample
    that outruns its token on another route is refused, counted, and never warned about:
    the safe side of the race). Five managers in a row, each on a fresh publisher."""
    caplog.set_level(logging.INFO, logger="msctl.comm")
    namespace = unique_namespace()
    motors = Motors(open_sessions(), namespace)
    session = open_sessions()

    def one_manager() -> None:
        manager = Node(session, "joint_manager", namespace)
        legit = manager.publisher("joint_commands", JOINT_STATE)
        got = len(motors.got)
        send_until(lambda: legit.publish(command(0.1)), lambda: len(motors.got) > got)
        manager.close()
        wait_until(lambda: legit.gid not in motors.sub._allowed, what="token removal")

    try:
        for _ in range(5):
            one_manager()
        assert warnings_about(caplog, motors.topic) == []
        # Whatever was refused came before its token: said at INFO, never as an intrusion.
        early = [
            r.getMessage() for r in caplog.records if "known from its graph token" in r.getMessage()
        ]
        assert sum(int(re.search(r"; (\d+) sample", m).group(1)) for m in early) == motors.refused()
    finally:
        motors.close()


def test_start_up_a_late_motor_interface_takes_a_running_manager(open_sessions, caplog) -> None:
    """The manager already streams when the motor interface starts: its token comes from the
    liveliness history, the stream is taken from then on, and no WARN names it."""
    caplog.set_level(logging.INFO, logger="msctl.comm")
    namespace = unique_namespace()
    manager = Node(open_sessions(), "joint_manager", namespace)
    legit = manager.publisher("joint_commands", JOINT_STATE)
    stop = threading.Event()

    def stream() -> None:
        while not stop.is_set():
            legit.publish(command(0.1))
            stop.wait(0.005)

    streamer = threading.Thread(target=stream, daemon=True)
    streamer.start()
    motors = Motors(open_sessions(), namespace)
    try:
        wait_until(lambda: len(motors.got) >= 20, timeout=10.0, what="the manager's stream")
        assert warnings_about(caplog, motors.topic) == []
    finally:
        stop.set()
        streamer.join(5.0)
        motors.close()
        manager.close()


def test_the_motor_interface_and_the_simulator_take_commands_from_the_joint_manager_only(
    tmp_path: Path,
) -> None:
    from components.motor_interface.build import interface_for
    from components.simulator.interface import simulator_interface

    dragon = resolved_assembly(tmp_path, "dragon")
    for module in dragon.modules:
        if not module.actuated_joints:
            continue
        (sub,) = [s for s in interface_for(dragon, module.slot).subscribe]
        assert sub.topic == "joint_commands"
        assert sub.senders == (f"{module.namespace}/joint_manager",)
    sim = simulator_interface(dragon)
    senders = {s.topic: s.senders for s in sim.subscribe}
    for module in dragon.modules:
        if module.actuated_joints:
            topic = f"{module.namespace}/joint_commands"
            assert senders[topic] == (f"{module.namespace}/joint_manager",)


# --------------------------------------------------------------------------- end to end


class Up:
    """One detached simulated ``minimal`` assembly (its own MSCTL_HOME and router port)."""

    def __init__(self, home: Path) -> None:
        self.home = home
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.env = {
            **os.environ,
            "MSCTL_HOME": str(home),
            "MSCTL_HOST": "identity-test-laptop",  # none of the assembly's computers
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
            env=self.env,
            capture_output=True,
            text=True,
            timeout=timeout,
            cwd=ROOT,
        )

    def settings(self) -> SessionSettings:
        return SessionSettings(connect=(self.endpoint,), listen=("tcp/127.0.0.1:0",))

    def down(self) -> None:
        self.msctl("down", timeout=60.0)


@pytest.mark.e2e
def test_e2e_a_foreign_publisher_cannot_move_a_joint_but_joint_set_still_works(
    tmp_path: Path,
) -> None:
    up = Up(tmp_path / "home")
    session = open_session(up.settings())
    node = Node(session, "intruder", "/field")
    try:
        read: dict[str, float] = {}
        lock = threading.Lock()

        def on_read(message: Any) -> None:
            with lock:
                for sample in joint_samples(message):
                    if sample.position is not None:
                        read[sample.name] = sample.position

        node.subscription("/limb1/joint_read", JOINT_STATE, on_read)
        wait_until(lambda: "limb1_joint2" in read and "limb1_joint4" in read, 30.0, "joint_read")
        with lock:
            start2, start4 = read["limb1_joint2"], read["limb1_joint4"]

        # The finding: `msctl topic pub` on the raw command topic. A large (in-limit) position,
        # so only the identity check can stop it.
        cli = up.msctl(
            "topic",
            "pub",
            "/limb1/joint_commands",
            JOINT_STATE,
            "{name: [limb1_joint2], position: [1.5]}",
            "--times",
            "10",
            "--rate",
            "20",
            timeout=60.0,
        )
        assert cli.returncode == 0, cli.stdout + cli.stderr

        # And a foreign node of our own, streaming the same while joint_set works.
        foreign = node.publisher("/limb1/joint_commands", JOINT_STATE)
        joint_set = node.publisher("/limb1/joint_set", JOINT_STATE)
        stop = threading.Event()

        def stream() -> None:
            while not stop.is_set():
                foreign.publish(command(1.5))
                stop.wait(0.02)

        streamer = threading.Thread(target=stream, daemon=True)
        streamer.start()
        target4 = start4 + (0.3 if start4 < 0.5 else -0.3)
        lowest = highest = start2

        def joint4_arrived() -> bool:
            nonlocal lowest, highest
            joint_set.publish(joint_state([JointSample("limb1_joint4", target4, None, None)]))
            with lock:
                lowest, highest = (
                    min(lowest, read["limb1_joint2"]),
                    max(highest, read["limb1_joint2"]),
                )
                return abs(read["limb1_joint4"] - target4) < 0.02

        try:
            wait_until(joint4_arrived, 60.0, "joint_set moving limb1_joint4", interval=0.05)
        finally:
            stop.set()
            streamer.join(5.0)
        # Commanded to 1.5 rad away by the intruders; joint4's motion may nudge it a little.
        assert highest - lowest < 0.1, (start2, lowest, highest)

        logs = up.msctl("logs", "-n", "1000", timeout=60.0)
        text = logs.stdout + logs.stderr
        warned = re.findall(r"/limb1/joint_commands: refused samples from node (\S+):", text)
        # One WARN per intruding node: ours once (and the CLI's, if its samples got through
        # the router before it exited, once too).
        assert warned.count("/field/intruder") == 1, text[-3000:]
        assert set(warned) <= {"/field/intruder"} | {w for w in warned if "msctl_pub_" in w}
        assert len(warned) == len(set(warned)), warned
    finally:
        node.close()
        session.close()
        up.down()
