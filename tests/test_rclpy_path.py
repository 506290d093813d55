"""The rclpy path (``MSCTL_TRANSPORT=rclpy``) on real rclpy over Fast DDS, and its refusal where
rclpy is absent.

With the ``ros`` extra installed, cores run as real rclpy nodes through the one executor, and a
plain rclpy node with the package index's message packages (:class:`ros_rigs.RosPeer`) talks to
them: topics, services (an injected re-zero included), contained handler errors, sender-limited
inputs, clean shutdown; and ``msctl up dragon`` on rclpy reaches all-healthy from the ROS graph.
Without it, the path refuses with what to install, and nothing else imports rclpy.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import wait_until
from ros_rigs import HAVE_RCLPY, RosPeer, domain, needs_rclpy, ros_environment
from running import Up

from components.executor.core import Core
from components.executor.interface import Every, InterfaceSpec, Publish, Serve, Subscribe
from components.messages import msg

__all__ = ["domain"]  # the fixture, used by name

STRING = "std_msgs/msg/String"
without_rclpy = pytest.mark.skipif(HAVE_RCLPY, reason="checks the refusal when rclpy is absent")


class Counter(Core):
    """Counts commands, answers each on ``state``; ``boom`` is a bug, ``refuse`` makes its
    service unable to answer."""

    SPEC = InterfaceSpec(
        subscribe=(Subscribe("cmd", STRING, "on_cmd"),),
        publish=(Publish("state", STRING),),
        serve=(Serve("count", "std_srvs/srv/Trigger", "on_count"),),
        every=(Every(0.02, "tick"),),
    )

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.seen: list[str] = []
        self.ticks = 0
        self.started = self.stopped = False

    def start(self, now: float) -> None:
        self.started = True

    def stop(self, now: float) -> None:
        self.stopped = True

    def tick(self, now: float) -> None:
        self.ticks += 1

    def on_cmd(self, message: Any, now: float) -> None:
        if message.data == "boom":
            raise RuntimeError("a bug in this core")
        self.seen.append(message.data)
        self.publish("state", msg(STRING, data=f"{self.name}:{len(self.seen)}"))

    def on_count(self, request: Any, now: float) -> Any:
        if self.seen and self.seen[-1] == "refuse":
            return None
        return msg("std_srvs/srv/Trigger_Response", success=True, message=str(len(self.seen)))


class Running:
    """An executor running on a background thread (signals stay with pytest's thread)."""

    def __init__(self, executor: Any) -> None:
        self.executor = executor
        self.thread = threading.Thread(target=executor.run, daemon=True)

    def __enter__(self) -> Any:
        self.thread.start()
        return self.executor

    def __exit__(self, *exc: object) -> None:
        self.executor.stop()
        self.thread.join(20.0)
        assert not self.thread.is_alive(), "the rclpy executor did not stop"


def publish_until(publisher: Any, message: Any, done: Any, timeout: float = 30.0) -> Any:
    """Publish until ``done()``: DDS discovery takes a moment before the first delivery."""
    import time

    def attempt() -> Any:
        if not done():
            publisher.publish(message)
            time.sleep(0.05)
        return done()

    return wait_until(attempt, timeout)


# ---------------------------------------------------------------------------- in one process
@needs_rclpy
def test_cores_are_rclpy_nodes_under_the_executors_contract(domain: int) -> None:
    from std_msgs.msg import String
    from std_srvs.srv import Trigger

    from components.executor.rclpy_executor import RclpyExecutor

    executor = RclpyExecutor(domain=domain)
    fragile, sturdy = Counter("fragile"), Counter("sturdy")
    fragile_c = executor.add(fragile, Counter.SPEC, "/a")
    sturdy_c = executor.add(sturdy, Counter.SPEC, "/b")
    with RosPeer(domain) as peer:
        to_a = peer.node.create_publisher(String, "/a/cmd", 10)
        to_b = peer.node.create_publisher(String, "/b/cmd", 10)
        states = peer.collect(String, "/b/state")
        with Running(executor):
            # Each core is a node of its own on the ROS graph.
            wait_until(lambda: {"/a/fragile", "/b/sturdy"} <= peer.nodes(), 30.0)
            publish_until(to_a, String(data="hi"), lambda: fragile.seen)
            publish_until(to_b, String(data="hi"), lambda: states)
            assert states[0].data == "sturdy:1"
            for _ in range(3):
                to_a.publish(String(data="boom"))  # a bug: logged, counted, contained
            to_a.publish(String(data="after"))
            wait_until(lambda: "after" in fragile.seen, 20.0)
            ticks = sturdy.ticks
            wait_until(lambda: sturdy.ticks >= ticks + 3, 30.0)  # the other core runs on

            answer = peer.call(Trigger, "/a/count", Trigger.Request())
            # "hi" may have gone out more than once before the first arrived (publish_until
            # repeats it); the three "boom" were never counted.
            assert fragile.seen[-1] == "after" and set(fragile.seen[:-1]) == {"hi"}
            assert (answer.success, answer.message) == (True, str(len(fragile.seen)))
            publish_until(to_b, String(data="refuse"), lambda: sturdy.seen[-1] == "refuse")
            refused = peer.call(Trigger, "/b/count", Trigger.Request())
            # DDS has no error answer: a failed request says so in success/message.
            assert refused.success is False
            assert "sturdy could not answer" in refused.message
        # Stopped: every core's stop ran, and its node left the ROS graph.
        assert fragile.started and fragile.stopped and sturdy.stopped
        wait_until(lambda: not {"/a/fragile", "/b/sturdy"} & peer.nodes(), 30.0)
    assert fragile_c.errors == 3
    assert sturdy_c.errors == 0  # a handler that cannot answer is no bug
    assert fragile_c.handled > fragile_c.errors


@needs_rclpy
def test_an_injected_rezero_is_served_on_rclpy(domain: int, tmp_path: Path) -> None:
    from sensor_msgs.msg import JointState

    from components.executor.rclpy_executor import RclpyExecutor
    from components.executor.registry import apply_all
    from components.joint_manager import JointManagerConfig, JointManagerCore
    from components.joint_manager.interface import JOINT_MANAGER
    from components.joints import JointCalibration, JointSpec
    from components.ros.plane import RclpyPlane

    unit = tmp_path / "H-0001.toml"
    unit.write_text('hostname = "limb1-nuc"\n\n[joints.joint1]\nzero_offset = 0.5\n')
    core = JointManagerCore(
        "limb1/joint_manager",
        module="limb1",
        joints=[JointSpec("limb1_joint1", lower=-1.0, upper=1.0, max_velocity=2.0)],
        calibration={"joint1": JointCalibration(0.5, 1)},
        config=JointManagerConfig(),
    )
    apply_all(
        core,
        "joint_manager",
        injections=[{"name": "rezero", "calibration_file": str(unit), "max_shift": 1.0}],
    )
    executor = RclpyExecutor(domain=domain)
    component = executor.add(core, JOINT_MANAGER, "/limb1", "joint_manager")
    with RosPeer(domain) as peer, Running(executor):
        states = peer.node.create_publisher(JointState, "/limb1/joint_states", 10)
        read = peer.collect(JointState, "/limb1/joint_read")
        raw = JointState(name=["limb1_joint1"], position=[0.8], velocity=[0.0], effort=[0.0])
        streaming = threading.Event()

        def stream() -> None:  # a motor interface's steady joint_states (re-zero needs fresh)
            while not streaming.wait(0.02):
                states.publish(raw)

        streamer = threading.Thread(target=stream, daemon=True)
        streamer.start()
        try:
            wait_until(lambda: read and read[-1].position[0] == pytest.approx(0.3), 30.0)
            # msctl_msgs has no package on the index: the caller uses msctl's run-time type
            # support, as any rclpy program can.
            with RclpyPlane(domain) as plane:
                node = plane.node("operator")
                client = node.client("/limb1/rezero", "msctl_msgs/srv/Rezero")
                request = msg("msctl_msgs/srv/Rezero_Request", joints=["limb1_joint1"], force=False)
                response = client.call(request, timeout=30.0)
            assert response.success, response.message
            assert list(response.joints) == ["limb1_joint1"]
            assert np.allclose(response.shifts, [0.3])
            assert tomllib.loads(unit.read_text())["joints"]["joint1"]["zero_offset"] == 0.8
            read.clear()
            wait_until(lambda: read and read[-1].position[0] == pytest.approx(0.0), 30.0)
        finally:
            streaming.set()
            streamer.join()
    assert component.errors == 0


@needs_rclpy
def test_a_sender_limited_input_takes_nothing_while_another_node_publishes(domain: int) -> None:
    from std_msgs.msg import String

    from components.comm.stats import drops
    from components.executor.rclpy_executor import RclpyExecutor

    spec = InterfaceSpec(
        subscribe=(Subscribe("cmd", STRING, "on_cmd", senders=("/ops/good",)),),
        publish=(Publish("state", STRING),),
    )
    core = Counter("motor")
    executor = RclpyExecutor(domain=domain)
    executor.add(core, spec, "/m")
    with Running(executor), RosPeer(domain, "good", "/ops") as good:
        to_m = good.node.create_publisher(String, "/m/cmd", 10)
        publish_until(to_m, String(data="from good"), lambda: core.seen)
        with RosPeer(domain, "evil", "/ops") as evil:
            intruder = evil.node.create_publisher(String, "/m/cmd", 10)
            before = drops.count("/m/cmd", "intruder")
            # Once the intruder is on the graph, nothing is taken, not even from good.
            publish_until(
                intruder,
                String(data="from evil"),
                lambda: drops.count("/m/cmd", "intruder") > before,
            )
            to_m.publish(String(data="good while evil is there"))
            intruder.publish(String(data="from evil"))
            wait_until(lambda: drops.count("/m/cmd", "intruder") >= before + 3, 20.0)
            assert "from evil" not in core.seen
            assert "good while evil is there" not in core.seen
        # The intruder gone, the allowed sender is heard again.
        publish_until(to_m, String(data="good again"), lambda: "good again" in core.seen, 30.0)
    assert "from evil" not in core.seen


@needs_rclpy
def test_types_without_a_package_cross_dds_both_ways(domain: int) -> None:
    """msctl's run-time type support meets the compiled packages on the wire: a message
    from it decodes in a plain rclpy node, and the other way round."""
    from geometry_msgs.msg import Twist
    from sensor_msgs.msg import JointState
    from std_srvs.srv import SetBool

    from components.ros.plane import RclpyPlane

    with RclpyPlane(domain) as plane, RosPeer(domain) as peer:
        twists = peer.collect(Twist, "/cmd_vel")
        driver = plane.node("driver").publisher("/cmd_vel", "geometry_msgs/msg/Twist")
        twist = msg(
            "geometry_msgs/msg/Twist",
            linear=msg("geometry_msgs/msg/Vector3", x=0.5, y=0.0, z=0.0),
            angular=msg("geometry_msgs/msg/Vector3", x=0.0, y=0.0, z=-0.25),
        )
        publish_until(driver, twist, lambda: twists)
        assert (twists[0].linear.x, twists[0].angular.z) == (0.5, -0.25)
        node = plane.node("ours")
        theirs = peer.collect(JointState, "/joints")
        ours: list[Any] = []
        node.subscription("/joints_back", "sensor_msgs/msg/JointState", ours.append)
        publisher = node.publisher("/joints", "sensor_msgs/msg/JointState")
        back = peer.node.create_publisher(JointState, "/joints_back", 10)
        sent = msg(
            "sensor_msgs/msg/JointState",
            name=["a", "b"],
            position=np.array([1.5, -2.0]),
            velocity=np.array([0.0, 0.1]),
            effort=np.array([]),
        )
        publish_until(publisher, sent, lambda: theirs)
        assert list(theirs[0].name) == ["a", "b"] and list(theirs[0].position) == [1.5, -2.0]
        publish_until(back, JointState(name=["c"], position=[3.25]), lambda: ours)
        assert ours[0].name == ["c"] and ours[0].position.tolist() == [3.25]

        peer.serve(SetBool, "/switch", lambda req, res: SetBool.Response(success=req.data))
        client = node.client("/switch", "std_srvs/srv/SetBool")
        answer = client.call(msg("std_srvs/srv/SetBool_Request", data=True), timeout=30.0)
        assert answer.success is True


# ---------------------------------------------------------------------------- msctl up
@needs_rclpy
@pytest.mark.e2e
@pytest.mark.timeout(360)  # an up, then waits of 30 + 60 + 30 + 30 s on a loaded machine
def test_msctl_up_dragon_on_rclpy_is_healthy_from_the_ros_graph(
    domain: int, tmp_path: Path
) -> None:
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import JointState

    from components.ros.plane import RclpyPlane

    up = Up(
        tmp_path / "home",
        "dragon",
        env={"MSCTL_TRANSPORT": "rclpy", **ros_environment(domain)},
    )
    try:
        listed = up.msctl("ps", "--json")
        assert listed.returncode == 0, listed.stderr
        components = json.loads(listed.stdout)["components"]
        assert components and all(c["state"] == "running" for c in components), components
        with RosPeer(domain) as peer:
            # Every component is a node on the DDS graph (a new participant discovers them).
            expected = {"/limb1/joint_manager", "/sim/simulator", "/gc1/data_monitor"}
            wait_until(lambda: expected <= peer.nodes(), 30.0)
            read = peer.collect(JointState, "/limb1/joint_read")
            health = peer.collect(DiagnosticArray, "/limb1/health")

            def graph() -> str:
                # What the DDS graph showed when no sample came: publishers or not, and how
                # the run saw itself (a loaded machine, a component not started ...).
                topics = sorted(name for name, _ in peer.node.get_topic_names_and_types())
                publishers = peer.node.count_publishers("/limb1/joint_read")
                ps = up.msctl("ps").stdout[-1500:]
                # Whether msctl's own side sees the samples the peer does not.
                echo = up.msctl("topic", "echo", "/limb1/joint_read", "--once", "--timeout", "20")
                last = (
                    [(st.name, st.level, st.message) for st in health[-1].status]
                    if health
                    else None
                )
                return (
                    f"no /limb1/joint_read sample; {publishers} publisher(s); the peer "
                    f"{peer.spinning()}, {len(health)} /limb1/health sample(s), the last: "
                    f"{last}; "
                    "msctl's echo: "
                    f"exit {echo.returncode} {(echo.stdout + echo.stderr)[-300:]!r}; "
                    f"topics {topics}; ps {ps}"
                )

            # Intermittent before fba97c8 (CI twice, here 2 runs of 4 at idle): no joint_read
            # for 60 s while /limb1/health flowed from the same process. The cause found: the
            # joint manager's guarded joint_states subscription cached the simulator's writer
            # as an unnamed intruder. Should it show again, the rest is still checked, then it
            # is reported as XFAIL with what the graph showed (never a silent pass).
            missing_read = ""
            try:
                wait_until(lambda: read, 60.0, graph)
            except AssertionError as exc:
                missing_read = str(exc)
            else:
                assert any(name.startswith("limb1_") for name in read[-1].name)

            # The health monitor follows the ROS graph: it sees limb1's components running.
            def components_running() -> bool:
                if not health:
                    return False
                entries = [s for s in health[-1].status if "/components/" in s.name]
                return bool(entries) and all(s.level == b"\x00" for s in entries)

            wait_until(components_running, 30.0)
            with RclpyPlane(domain) as plane:
                client = plane.node("operator").client("/limb1/rezero", "msctl_msgs/srv/Rezero")
                # An unknown joint: the injected service answers, and changes nothing.
                request = msg("msctl_msgs/srv/Rezero_Request", joints=["no_such_joint"])
                refusal = client.call(request, timeout=30.0)
            assert refusal.success is False and "no_such_joint" in refusal.message
    finally:
        up.down()
    with RosPeer(domain) as peer:
        wait_until(lambda: "/limb1/joint_manager" not in peer.nodes(), 30.0)
    if missing_read:
        pytest.xfail(f"joint_read over DDS missing again: {missing_read}")


# ---------------------------------------------------------------------------- without rclpy
@without_rclpy
def test_rclpy_executor_refuses_with_what_to_do() -> None:
    from components.executor.rclpy_executor import RclpyExecutor, RclpyUnavailable

    with pytest.raises(RclpyUnavailable) as caught:
        RclpyExecutor()
    text = str(caught.value)
    assert "ROS 2 install" in text and "unset MSCTL_TRANSPORT" in text
    assert "msctl[ros]" in text


def _worker(tmp_path: Path, transport: str) -> subprocess.CompletedProcess:
    home = tmp_path / "home"
    env = {**os.environ, "MSCTL_HOME": str(home)}
    resolved = subprocess.run(
        [sys.executable, "-m", "msctl", "assemble", "minimal"], env=env, capture_output=True
    )
    assert resolved.returncode == 0, resolved.stderr
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "components.executor.worker",
            "--lock",
            str(home / "assembly" / "assembly.lock.json"),
            "--component",
            "limb1/joint_manager",
        ],
        env={**env, "MSCTL_TRANSPORT": transport},
        capture_output=True,
        text=True,
        timeout=60,
    )


@without_rclpy
def test_worker_on_rclpy_transport_exits_3_with_one_clear_line(tmp_path: Path) -> None:
    worker = _worker(tmp_path, "rclpy")
    assert worker.returncode == 3
    assert worker.stderr.strip().splitlines()[-1].startswith("error: MSCTL_TRANSPORT=rclpy needs")


def test_unknown_transport_is_refused(tmp_path: Path) -> None:
    worker = _worker(tmp_path, "dds")
    assert worker.returncode == 2
    assert "MSCTL_TRANSPORT='dds'" in worker.stderr
