"""``msctl bridge``: msctl's Zenoh data plane and a DDS ROS 2 graph, relayed both ways.

Real parts on both sides: msctl on a loopback Zenoh router (random port, no multicast), and
plain rclpy nodes with the package index's message packages on Fast DDS, in a ROS domain of
the test's own, discovering on localhost only (:mod:`ros_rigs`).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from conftest import wait_until
from ros_rigs import RosPeer, domain, needs_rclpy, ros_environment
from running import ROOT, Up

from components.comm.node import Node
from components.comm.qos import LATCHED, QoS
from components.comm.session import SessionSettings, open_session
from components.messages import msg

pytestmark = needs_rclpy
__all__ = ["domain"]  # the fixture, used by name

STRING = "std_msgs/msg/String"


def bridge(settings: SessionSettings, held: int, *, topics: str = "*", services: str = "*"):
    """An in-process bridge on its own session (both closed by the caller's ``with``)."""
    from components.bridge.core import Selection
    from components.bridge.relay import Bridge

    class Opened:
        def __enter__(self) -> Any:
            self.session = open_session(settings)
            self.events: list[str] = []
            self.bridge = Bridge(
                self.session,
                Selection.from_text(topics, services),
                domain=held,
                discovery_period=0.2,
                on_event=self.events.append,
            )
            self.bridge.events = self.events
            return self.bridge

        def __exit__(self, *exc: object) -> None:
            self.bridge.close()
            self.session.close()

    return Opened()


def msctl(env: dict[str, str], *args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    """One msctl command, as a subprocess."""
    return subprocess.run(
        [sys.executable, "-m", "msctl", *args],
        env={**os.environ, **env},
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=ROOT,
        check=False,
    )


def publish_until(publish: Any, done: Any, timeout: float = 30.0) -> Any:
    """Publish until ``done()``: discovery on both sides takes a moment."""

    def attempt() -> Any:
        if not done():
            publish()
            time.sleep(0.05)
        return done()

    return wait_until(attempt, timeout)


# ---------------------------------------------------------------------------- the three
@pytest.mark.e2e
def test_an_rclpy_node_reads_joint_read_and_its_joint_set_moves_the_joint(
    domain: int, tmp_path: Path
) -> None:
    """A simulated Dragon on msctl's Zenoh plane, `msctl bridge --all`, and a ROS 2 node on
    Fast DDS that reads limb1's joints and moves one through its joint manager."""
    from sensor_msgs.msg import JointState

    up = Up(tmp_path / "home", "dragon", env=ros_environment(domain))
    bridging = subprocess.Popen(
        [sys.executable, "-m", "msctl", "bridge", "--all"],
        env=up.env,
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        with RosPeer(domain, "ros_user") as peer:
            read = peer.collect(JointState, "/limb1/joint_read")

            def position() -> float | None:
                """limb1_joint1's latest position: a joint_read carries the joints that
                changed (and every joint at its keepalive), not always this one."""
                for message in reversed(list(read)):
                    if "limb1_joint1" in message.name:
                        return message.position[list(message.name).index("limb1_joint1")]
                return None

            found = wait_until(
                lambda: (p := position()) is not None and [p],  # 0.0 is a position too
                60.0,
                "limb1_joint1 in limb1's joint_read on DDS",
            )
            start = found[0]
            target = start + 0.08
            command = JointState(name=["limb1_joint1"], position=[target])
            joint_set = peer.node.create_publisher(JointState, "/limb1/joint_set", 10)

            def moved() -> bool:
                latest = position()
                return latest is not None and abs(latest - target) < 0.01

            publish_until(lambda: joint_set.publish(command), moved, 60.0)
    finally:
        bridging.send_signal(2)
        _, err = bridging.communicate(timeout=60)
        up.down()
    assert bridging.returncode == 0, err
    assert "bridging topic /limb1/joint_read (sensor_msgs/msg/JointState) msctl -> ROS" in err
    assert "bridging topic /limb1/joint_set (sensor_msgs/msg/JointState) ROS -> msctl" in err


def test_msctl_service_call_reaches_a_service_of_an_rclpy_node(
    domain: int, session_settings: SessionSettings, zenoh_env: dict[str, str]
) -> None:
    from std_srvs.srv import SetBool

    with RosPeer(domain, "switch") as peer, bridge(session_settings, domain) as relays:
        asked: list[bool] = []

        def answer(request: Any, response: Any) -> Any:
            asked.append(request.data)
            return SetBool.Response(success=request.data, message="switched by ROS")

        peer.serve(SetBool, "/switch/set", answer)
        relays.wait_for(lambda s: any(r.name == "/switch/set" for r in s.relays), 30.0)
        called = msctl(
            {**zenoh_env, **ros_environment(domain)},
            "service",
            "call",
            "/switch/set",
            "std_srvs/srv/SetBool",
            "{data: true}",
            "--json",
            "--timeout",
            "20",
        )
        assert called.returncode == 0, called.stderr
        assert json.loads(called.stdout) == {"success": True, "message": "switched by ROS"}
        assert asked == [True]
        served = next(r for r in relays.status().relays if r.name == "/switch/set")
        assert served.direction.value == "ROS -> msctl" and served.relayed == 1


def test_msctl_topic_echo_sees_an_rclpy_publisher(
    domain: int, session_settings: SessionSettings, zenoh_env: dict[str, str]
) -> None:
    from std_msgs.msg import String

    # The bridge first: the ROS publisher appears later and is found (continuous discovery).
    with bridge(session_settings, domain) as relays, RosPeer(domain, "talker") as peer:
        talker = peer.node.create_publisher(String, "/chatter", 10)
        echo = subprocess.Popen(
            [sys.executable, "-m", "msctl", "topic", "echo", "/chatter", "--once", "--json"],
            env={**os.environ, **zenoh_env, **ros_environment(domain)},
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            publish_until(
                lambda: talker.publish(String(data="hello from ROS")),
                lambda: echo.poll() is not None,
                60.0,
            )
            out, err = echo.communicate(timeout=30)
        finally:
            if echo.poll() is None:
                echo.kill()
        assert echo.returncode == 0, err
        assert json.loads(out.splitlines()[0]) == {"data": "hello from ROS"}
        assert any(e.startswith("bridging topic /chatter") for e in relays.events)


# ---------------------------------------------------------------------------- the bridge's rules
def test_a_message_bridged_one_way_is_never_bridged_back(
    domain: int, session_settings: SessionSettings
) -> None:
    """One topic with publishers on both sides: each side gets every message exactly once."""
    from std_msgs.msg import String

    with bridge(session_settings, domain, topics="/both") as relays, RosPeer(domain) as peer:
        session = open_session(session_settings)
        node = Node(session, "zenoh_side", domain=domain)
        try:
            on_zenoh: list[str] = []
            node.subscription("/both", STRING, lambda m: on_zenoh.append(m.data))
            on_ros = peer.collect(String, "/both")
            zenoh_pub = node.publisher("/both", STRING)
            ros_pub = peer.node.create_publisher(String, "/both", 10)
            # Both directions up (each source seen), then a counted exchange.
            relays.wait_for(lambda s: len([r for r in s.relays if r.name == "/both"]) == 2, 30)
            publish_until(
                lambda: zenoh_pub.publish(msg(STRING, data="warm-z")),
                lambda: "warm-z" in [m.data for m in on_ros],
            )
            publish_until(
                lambda: ros_pub.publish(String(data="warm-r")), lambda: "warm-r" in on_zenoh
            )
            for i in range(20):  # paced: a burst past the history depth may drop (QoS)
                zenoh_pub.publish(msg(STRING, data=f"z{i}"))
                ros_pub.publish(String(data=f"r{i}"))
                time.sleep(0.02)
            wait_until(lambda: "z19" in [m.data for m in on_ros] and "r19" in on_zenoh, 30.0)
            time.sleep(1.0)  # an echo, were there one, would have arrived by now
            ros_seen = [m.data for m in on_ros]
            for i in range(20):
                assert on_zenoh.count(f"z{i}") == 1, on_zenoh  # its own, never back via ROS
                assert on_zenoh.count(f"r{i}") == 1, on_zenoh
                assert ros_seen.count(f"r{i}") == 1, ros_seen
                assert ros_seen.count(f"z{i}") == 1, ros_seen
            assert sum(r.echoes for r in relays.status().relays) > 0  # seen, and dropped
        finally:
            node.close()
            session.close()


def test_qos_is_mapped_a_latched_msctl_topic_reaches_a_late_ros_subscriber(
    domain: int, session_settings: SessionSettings
) -> None:
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String

    session = open_session(session_settings)
    node = Node(session, "describer", domain=domain)
    try:
        latched = node.publisher("/robot_description", STRING, LATCHED)
        latched.publish(msg(STRING, data="<robot/>"))
        sensor = node.publisher("/scan_like", STRING, QoS(reliability="best_effort", depth=5))
        with bridge(session_settings, domain, topics="/robot_description /scan_like") as relays:
            relays.wait_for(lambda s: len(s.relays) == 2, 30.0)
            with RosPeer(domain) as peer:
                # A ROS subscriber that joins later, asking for transient local, gets it.
                profile = QoSProfile(
                    depth=1,
                    durability=DurabilityPolicy.TRANSIENT_LOCAL,
                    reliability=ReliabilityPolicy.RELIABLE,
                )
                description = peer.collect(String, "/robot_description", profile)
                wait_until(lambda: description, 30.0, "the latched sample on DDS")
                assert description[0].data == "<robot/>"

                def offered(topic: str) -> Any:
                    infos = peer.node.get_publishers_info_by_topic(topic)
                    return infos[0].qos_profile if infos else None

                wait_until(lambda: offered("/scan_like"), 30.0)
                assert offered("/scan_like").reliability == ReliabilityPolicy.BEST_EFFORT
                assert offered("/robot_description").durability == (
                    DurabilityPolicy.TRANSIENT_LOCAL
                )
                sensor.publish(msg(STRING, data="x"))
    finally:
        node.close()
        session.close()


PROBE = textwrap.dedent(
    """
    import sys, time
    from components.comm.types import registry
    from components.comm.session import SessionSettings, open_session
    from components.comm.node import Node
    from components.ros.plane import RclpyPlane
    from components.messages import msg

    registry().register_msg("probe_msgs/msg/Probe", "float64 reading\\n")
    session = open_session(SessionSettings(connect=(sys.argv[1],), multicast=False))
    zenoh = Node(session, "zenoh_probe", domain=int(sys.argv[2]))
    with RclpyPlane(int(sys.argv[2])) as plane:
        ros = plane.node("ros_probe")
        publishers = [
            zenoh.publisher("/probe_zenoh", "probe_msgs/msg/Probe"),
            ros.publisher("/probe_ros", "probe_msgs/msg/Probe"),
        ]
        print("ready", flush=True)
        while sys.stdin.readline().strip() != "stop":
            pass
    zenoh.close()
    session.close()
    """
)


def test_a_type_known_on_one_side_only_is_reported_once_and_skipped(
    domain: int, session_settings: SessionSettings, router_endpoint: str
) -> None:
    """A type the bridge's registry lacks, published on each side by another process: each
    topic is skipped, said once, while the rest is bridged."""
    with bridge(session_settings, domain) as relays:
        probe = subprocess.Popen(
            [sys.executable, "-c", PROBE, router_endpoint, str(domain)],
            env={**os.environ, **ros_environment(domain), "PYTHONPATH": str(ROOT)},
            cwd=ROOT,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        try:
            assert probe.stdout.readline().strip() == "ready"
            relays.wait_for(lambda s: {"/probe_zenoh", "/probe_ros"} <= set(s.skipped), 60.0)
            time.sleep(1.5)  # several more looks at both graphs
            status = relays.status()
            assert "known on the msctl side only" in status.skipped["/probe_zenoh"]
            assert "known on the ROS (DDS) side only" in status.skipped["/probe_ros"]
            for topic in ("/probe_zenoh", "/probe_ros"):
                said = [e for e in relays.events if e.startswith(f"skipped {topic}:")]
                assert len(said) == 1, relays.events
            assert not any(r.name.startswith("/probe") for r in status.relays)
        finally:
            probe.communicate("stop\n", timeout=60)


def test_the_bridge_kind_runs_as_a_station_component(
    domain: int, session_settings: SessionSettings, tmp_path: Path
) -> None:
    """Through the kind registry: built from a plan, run by the executor, its relays under
    the component's node, its status on the station's diagnostics."""
    from std_msgs.msg import String

    from components import kinds
    from components.assembly import ComponentPlan
    from components.build import build_component
    from components.executor.runner import run_built

    assert kinds.get("bridge").builder == "components.bridge.build:build"
    plan = ComponentPlan(
        name="gc1/bridge",
        kind="bridge",
        host="ground1",
        module=None,
        namespace="/gc1",
        params={"topics": "/chatter", "services": "", "discovery_period": 0.2},
    )
    built = build_component(plan, None)  # the bridge needs nothing of the assembly
    executors: list[Any] = []
    runner = threading.Thread(
        target=run_built,
        args=([built], session_settings._replace(domain=domain)),
        kwargs={"on_ready": executors.append},
        daemon=True,
    )
    runner.start()
    session = open_session(session_settings)
    node = Node(session, "listener", domain=domain)
    try:
        heard: list[str] = []
        status: list[Any] = []
        node.subscription("/chatter", STRING, lambda m: heard.append(m.data))
        node.subscription("/gc1/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", status.append)
        with RosPeer(domain, "talker") as peer:
            talker = peer.node.create_publisher(String, "/chatter", 10)
            publish_until(lambda: talker.publish(String(data="via the station")), lambda: heard)
            wait_until(lambda: status and "1 ROS -> msctl" in status[-1].status[0].message, 30)
        assert status[-1].status[0].name == "gc1/bridge"
        # The talker gone, its relay stops.
        wait_until(lambda: "0 ROS -> msctl" in status[-1].status[0].message, 30.0)
    finally:
        node.close()
        session.close()
        wait_until(lambda: executors, 30.0)
        executors[0].stop()
        runner.join(30.0)
    assert not runner.is_alive()


def test_the_bridge_kind_checks_its_parameters_at_assemble() -> None:
    from components import kinds

    bridge_kind = kinds.get("bridge")
    kinds.check_params(bridge_kind, {"topics": "/limb1/* /chatter", "services": "*"})
    with pytest.raises(kinds.KindError, match="discovery_period must be > 0"):
        kinds.check_params(bridge_kind, {"discovery_period": 0})
    with pytest.raises(kinds.KindError, match="nothing to bridge"):
        kinds.check_params(bridge_kind, {"topics": "", "services": ""})
    with pytest.raises(kinds.KindError, match="fully qualified"):
        kinds.check_params(bridge_kind, {"topics": "chatter"})


def test_a_ros_node_never_speaks_for_a_modules_motors_through_the_bridge(
    domain: int, session_settings: SessionSettings
) -> None:
    """A ROS publisher of a module's feedback (``joint_states``) and raw commands
    (``joint_commands``), by the roles msctl's interfaces declare, is skipped even with
    ``--all`` and named, and nothing reaches msctl's plane; a command (``joint_set``) and
    plain data are still bridged (issue 32, item 2: the bridge's exclusions from the roles)."""
    from sensor_msgs.msg import JointState

    with bridge(session_settings, domain, topics="*") as relays, RosPeer(domain) as peer:
        session = open_session(session_settings)
        node = Node(session, "zenoh_side", domain=domain)
        heard: dict[str, int] = {}
        try:
            names = ("/limb9/joint_states", "/limb9/joint_commands", "/limb9/joint_set")
            for name in names:
                node.subscription(
                    name,
                    "sensor_msgs/msg/JointState",
                    lambda _m, n=name: heard.__setitem__(n, heard.get(n, 0) + 1),
                )
            publishers = [peer.node.create_publisher(JointState, n, 10) for n in names]
            sample = JointState(name=["limb9_joint1"], position=[0.1])
            publish_until(
                lambda: [p.publish(sample) for p in publishers],
                lambda: heard.get("/limb9/joint_set", 0) > 0,
            )
            status = relays.status()
            for name, role in (("/limb9/joint_states", "feedback"),
                               ("/limb9/joint_commands", "raw_command")):  # fmt: skip
                assert status.skipped[name].startswith(role), status.skipped
                assert "never bridged from ROS" in status.skipped[name]
                assert name not in heard
            assert "/limb9/joint_set" not in status.skipped
        finally:
            node.close()
            session.close()
