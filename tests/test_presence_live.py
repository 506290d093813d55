"""A joint manager watching its operators on real Zenoh (loopback router, random port).

``limb1``'s joint manager of the shipped ``dragon`` is built as on its own computer
(``MSCTL_HOST=hl-limb-01``) and run by ``run_built``, as the launcher runs it. Its operators
come and go as real liveliness tokens do: a node of station ``gc1``, the ground computer's
agent (``/msctl/ground1``), a claim of ``limb1``. What the manager does is read from its own
outputs on the data plane (``diagnostics``, ``joint_commands``).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import pytest
from conftest import resolved_assembly, wait_until

from components.assembly import ResolvedAssembly
from components.build import build_component
from components.claims import Claims
from components.comm.node import Node
from components.comm.session import SessionSettings
from components.executor.executor import Executor
from components.executor.runner import run_built
from components.messages import (
    DIAGNOSTIC_ARRAY,
    ERROR,
    JOINT_STATE,
    JointSample,
    Level,
    diagnostic_values,
    joint_samples,
    joint_state,
)

#: Generous: three seconds of template threshold, a lease, and a loaded machine.
BOUND = 30.0


@pytest.fixture(scope="module")
def dragon(tmp_path_factory: pytest.TempPathFactory) -> ResolvedAssembly:
    return resolved_assembly(tmp_path_factory.mktemp("dragon"), "dragon")


class Manager:
    """What the running manager says: its latest own status, and the holds it sent."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.status: Any = None
        self.commands: list[JointSample] = []

    def on_diagnostics(self, message: Any) -> None:
        for status in message.status:
            if status.name == "limb1/joint_manager":
                with self.lock:
                    self.status = status

    def on_commands(self, message: Any) -> None:
        with self.lock:
            self.commands.extend(joint_samples(message))

    def held(self) -> set[str]:
        """The joints told to stop (velocity 0) on ``joint_commands`` so far."""
        with self.lock:
            return {s.name for s in self.commands if s.velocity == 0.0}

    def says(self, text: str, level: Level | None = None) -> dict[str, str] | None:
        """The status values once its message holds ``text`` (at ``level``), else None."""
        with self.lock:
            status = self.status
        if status is None or text not in status.message:
            return None
        if level is not None and Level.of(status.level) is not level:
            return None
        return diagnostic_values(status)


def test_off_robot_the_manager_watches_no_operators(
    dragon: ResolvedAssembly, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Off-robot the whole assembly runs on one computer, its stations too: no radio between.
    monkeypatch.setenv("MSCTL_HOST", "a-laptop")
    built = build_component(dragon.component("limb1/joint_manager"), dragon)
    assert built.core.presence is None and built.on_bound is None


def test_operators_coming_and_going_hold_and_free_the_module(
    dragon: ResolvedAssembly,
    session_settings: SessionSettings,
    open_sessions: Callable[[], Any],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("MSCTL_HOST", "hl-limb-01")
    built = build_component(dragon.component("limb1/joint_manager"), dragon)
    assert built.core.presence is not None and built.core.presence.timeout == 3.0

    ground = open_sessions()
    station_node = Node(ground, "data_monitor", "/gc1")  # gc1 is there before the robot
    manager = Manager()
    observer = Node(open_sessions(), "observer", "/")
    observer.subscription("/limb1/diagnostics", DIAGNOSTIC_ARRAY, manager.on_diagnostics)
    observer.subscription("/limb1/joint_commands", JOINT_STATE, manager.on_commands)
    joint_set = observer.publisher("/limb1/joint_set", JOINT_STATE)

    executors: list[Executor] = []
    runner = threading.Thread(
        target=run_built,
        kwargs={"built": [built], "settings": session_settings, "on_ready": executors.append},
        name="joint-manager",
        daemon=True,
    )
    runner.start()
    agent: Node | None = None
    claims: Claims | None = None
    try:
        wait_until(lambda: manager.says("", None), timeout=BOUND, what="the manager's health")
        seen = wait_until(
            lambda: (v := manager.says("")) and v["operators"] == "gc1" and v,
            timeout=BOUND,
            what="gc1 seen by the manager",
        )
        assert seen["presence_holds"] == "0"

        # The station's last node goes (as a cut link's tokens do): held after 3 s.
        station_node.close()
        values = wait_until(
            lambda: manager.says("no operator: gc1 (ground1) unreachable", ERROR),
            timeout=BOUND,
            what="the presence hold in the manager's health",
        )
        assert values["presence_holds"] == "1" and values["operators"] == "none: held"
        # The halt path's hold went out: limb1 has no feedback here, so velocity 0 (on
        # another topic than the health: it may arrive a moment after).
        wait_until(
            lambda: manager.held() == set(built.core.joint_names),
            timeout=BOUND,
            what="a hold of every joint on joint_commands",
        )
        # Commands are refused, counted and said so.
        first = built.core.joint_names[0]

        def refused() -> bool:
            joint_set.publish(joint_state([JointSample(first, 0.1, None, None)]))
            values = manager.says("held until one is visible")
            return values is not None and int(values["refused_no_operator"]) >= 1

        wait_until(refused, timeout=BOUND, what="a command refused for want of an operator")

        # The ground computer's agent alone shows the station: the hold lifts by itself.
        agent = Node(ground, "request_server", "/msctl/ground1")
        values = wait_until(
            lambda: manager.says("operator back: gc1 (ground1) visible again"),
            timeout=BOUND,
            what="the hold lifted by the agent's return",
        )
        assert values["operators"] == "gc1"

        # A claim holder attends the module alone: the ground may go.
        robot_side = open_sessions()
        claims = Claims(robot_side, modules=["limb1"])
        teleop = Node(robot_side, "teleop", "/hl_limb_01")
        claim = claims.claim("limb1", "tech@hl-limb-01", teleop)
        wait_until(
            lambda: (v := manager.says("")) and v["operators"] == "tech@hl-limb-01, gc1",
            timeout=BOUND,
            what="the claim holder seen",
        )
        agent.close()
        wait_until(
            lambda: (v := manager.says("")) and v["operators"] == "tech@hl-limb-01",
            timeout=BOUND,
            what="the agent gone, the holder still there",
        )
        assert manager.says("")["presence_holds"] == "1"
        claim.release()
        values = wait_until(
            lambda: manager.says(
                "no operator: claim holder tech@hl-limb-01, gc1 (ground1) unreachable", ERROR
            ),
            timeout=BOUND,
            what="held again once the claim is gone too",
        )
        assert values["presence_holds"] == "2"
        teleop.close()
    finally:
        if claims is not None:
            claims.close()
        for node in (agent, observer):
            if node is not None:
                node.close()
        wait_until(lambda: executors, timeout=BOUND, what="the executor running")
        executors[0].stop()
        runner.join(timeout=BOUND)
        assert not runner.is_alive(), "the executor did not stop"
