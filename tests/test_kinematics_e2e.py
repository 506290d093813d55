"""End to end on real Zenoh with the MuJoCo simulator: the ``minimal`` assembly's joint
manager, kinematics manager and tip location publisher in one Executor; a target goes in on
``/limb1/ik_target`` and the tip, as simulated, comes back on ``/limb1/tip_pose`` and
``/limb1/pose/tip_link``.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pinocchio as pin
import pytest
from conftest import resolved_assembly, wait_until

from components.assembly import (
    ComponentPlan,
    ResolvedAssembly,
)
from components.build import BuiltComponent, build_component
from components.comm.node import Node
from components.comm.session import SessionSettings
from components.executor.executor import Executor
from components.kinematics_manager.poses import pose_stamped
from components.messages import POSE_STAMPED

pytestmark = pytest.mark.e2e


@pytest.fixture(scope="module")
def minimal(tmp_path_factory: pytest.TempPathFactory) -> ResolvedAssembly:
    """The shipped ``minimal`` template, resolved with its default units."""
    return resolved_assembly(tmp_path_factory.mktemp("minimal"), "minimal")


class Latest:
    """The newest PoseStamped seen on a topic (Zenoh threads write, the test reads)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.pose: pin.SE3 | None = None
        self.frame = ""

    def on_message(self, message: Any) -> None:
        p, o = message.pose.position, message.pose.orientation
        placement = pin.SE3(
            pin.Quaternion(o.w, o.x, o.y, o.z).normalized().toRotationMatrix(),
            np.array([p.x, p.y, p.z]),
        )
        with self.lock:
            self.pose, self.frame = placement, message.header.frame_id

    def get(self) -> pin.SE3 | None:
        with self.lock:
            return self.pose


@pytest.fixture
def system(
    minimal: ResolvedAssembly,
    session_settings: SessionSettings,
    open_sessions: Callable[[], Any],
) -> Iterator[tuple[BuiltComponent, Latest, Latest, Callable[[pin.SE3], None]]]:
    parts = [
        build_component(minimal.component(name), minimal)
        for name in ("limb1/joint_manager", "limb1/kinematics_manager", "limb1/location_tip")
    ]
    parts.append(
        build_component(
            ComponentPlan("sim", "simulator", "localhost", None, "/sim"), minimal, {"speed": 1.0}
        )
    )
    executor = Executor(settings=session_settings)
    for part in parts:
        executor.add(part.core, part.spec, part.namespace, part.node_name)
    runner = threading.Thread(target=executor.run, name="executor", daemon=True)
    runner.start()

    tip, located = Latest(), Latest()
    client = Node(open_sessions(), "operator", "/")
    client.subscription("/limb1/tip_pose", POSE_STAMPED, tip.on_message)
    client.subscription("/limb1/pose/tip_link", POSE_STAMPED, located.on_message)
    publisher = client.publisher("/limb1/ik_target", POSE_STAMPED)

    def send(target: pin.SE3) -> None:
        publisher.publish(pose_stamped(target, time.time(), "limb1_base_link"))

    try:
        wait_until(lambda: tip.get() is not None and located.get() is not None, timeout=10)
        yield parts[1], tip, located, send
    finally:
        client.close()
        executor.stop()
        runner.join(timeout=10)
        assert not runner.is_alive(), "the executor did not stop"
        for part in reversed(parts):
            part.close()


def test_ik_target_moves_the_simulated_tip_there(system: Any) -> None:
    kinematics, tip, located, send = system
    core = kinematics.core
    start = tip.get()
    assert tip.frame == "limb1_base_link"
    # A reachable target: the tip at a configuration a fair way from the start.
    wanted = core.chain.tip(np.array([0.4, 0.5, -0.3, 0.6, 0.2, -0.4, 0.3]))
    assert np.linalg.norm(wanted.translation - start.translation) > 0.1
    last_sent, previous = -1.0, start

    def settled_near() -> bool:
        nonlocal last_sent, previous
        # Resend now and then: the first sample may beat the route to the manager.
        if time.monotonic() - last_sent > 1.0:
            send(wanted)
            last_sent = time.monotonic()
        now = tip.get()
        still = np.linalg.norm(now.translation - previous.translation) < 1e-4
        previous = now
        return still and np.linalg.norm(now.translation - wanted.translation) < 0.015

    wait_until(settled_near, timeout=20, interval=0.2)
    # What the manager commanded solves the target (the IK part: 1 mm, 1 degree) ...
    result = core.last_result
    assert result is not None and result.reachable
    assert result.position_error < 1e-3 and math.degrees(result.orientation_error) < 1.0
    # ... and the simulated limb got there within its position servo's steady-state error
    # (the MuJoCo position actuators sag ~0.007 rad under gravity on joints 2 and 4, which
    # is ~9 mm at this tip; see docs/kinematics.md).
    reached = tip.get()
    assert np.linalg.norm(reached.translation - wanted.translation) < 0.015
    angle = np.linalg.norm(pin.log3(reached.rotation.T @ wanted.rotation))
    assert math.degrees(angle) < 1.5
    assert np.max(np.abs(core.q - result.q)) < 0.015
    # tip_pose is the forward kinematics of what joint_read says.
    assert np.linalg.norm(core.chain.tip(core.q).translation - reached.translation) < 1e-3
    # The location publisher, from the same joint_read, agrees.
    wait_until(
        lambda: np.linalg.norm(located.get().translation - reached.translation) < 1e-3, timeout=5
    )
    assert core.counters["unreachable"] == 0
