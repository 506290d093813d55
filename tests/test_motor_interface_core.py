"""Motor interface core with plain calls, fake time and a recording backend."""

from __future__ import annotations

from components.messages import OK, WARN, JointSample, joint_state
from components.motor_interface.core import MotorInterfaceConfig, MotorInterfaceCore
from components.motors.base import (
    MotorBackend,
    MotorCommand,
    MotorDiagnostic,
    MotorError,
    MotorSpec,
    MotorState,
)


class RecordingBackend(MotorBackend):
    """A bus that records what it is told and reports fixed states."""

    def __init__(self, fail_open: int = 0) -> None:
        super().__init__("fake0", [MotorSpec("joint1", 1, "m"), MotorSpec("joint2", 2, "m")], {})
        self.written: list[MotorCommand] = []
        self.fail_open = fail_open
        self.opened = 0
        self.halts = 0

    def _open(self) -> None:
        if self.fail_open:
            self.fail_open -= 1
            raise MotorError("fake0: no such bus")
        self.opened += 1

    def _close(self) -> None:
        pass

    def _read(self) -> dict[str, MotorState]:
        return {m.joint: MotorState(m.joint, 0.1, 0.0, 0.0) for m in self.motors}

    def _write(self, commands: list[MotorCommand]) -> None:
        self.written.extend(commands)

    def _halt(self) -> None:
        self.halts += 1

    def _diagnostics(self) -> list[MotorDiagnostic]:
        return []


def command(core: MotorInterfaceCore, now: float, *samples: JointSample) -> None:
    core.on_joint_commands(joint_state(samples), now)


def test_commands_reach_the_backend_by_raw_name_and_others_are_refused() -> None:
    backend = RecordingBackend()
    core = MotorInterfaceCore("limb1/motor_interface", "limb1", backend)
    core.start(0.0)
    command(core, 0.1, JointSample("limb1_joint1", 0.5), JointSample("limb2_joint1", 0.3))
    assert backend.written == [MotorCommand("joint1", 0.5, None, None)]
    assert core.refused_unknown == 1
    core.tick(0.11)
    (states,) = core.outbox.on("joint_states")
    assert list(states.name) == ["limb1_joint1", "limb1_joint2"]


def test_velocity_stops_when_commands_stop_and_position_targets_stay() -> None:
    backend = RecordingBackend()
    core = MotorInterfaceCore(
        "limb1/motor_interface", "limb1", backend, MotorInterfaceConfig(command_timeout=1.0)
    )
    core.start(0.0)
    command(core, 0.0, JointSample("limb1_joint1", None, 0.8))
    command(core, 0.0, JointSample("limb1_joint2", 0.4))
    backend.written.clear()
    core.tick(0.9)
    assert backend.written == []  # still within the timeout
    core.tick(1.05)
    # Only the joint that was turning is stopped; a position target is already a hold.
    assert backend.written == [MotorCommand("joint1", velocity=0.0)]
    core.tick(2.0)
    assert backend.written == [MotorCommand("joint1", velocity=0.0)]  # once, no storm
    statuses = {s.name: s for s in core.diagnostics()}
    assert statuses["limb1/motor_interface"].level == WARN
    assert "joint manager" in statuses["limb1/motor_interface"].message


def test_zero_velocity_or_a_later_position_clears_the_watch() -> None:
    backend = RecordingBackend()
    core = MotorInterfaceCore("m", "limb1", backend, MotorInterfaceConfig(command_timeout=1.0))
    core.start(0.0)
    command(core, 0.0, JointSample("limb1_joint1", None, 0.8))
    command(core, 0.2, JointSample("limb1_joint1", 0.3))
    backend.written.clear()
    core.tick(5.0)
    assert backend.written == []
    assert core.watchdog_stops == 0


def test_a_bus_that_will_not_open_is_reported_and_retried() -> None:
    backend = RecordingBackend(fail_open=1)
    core = MotorInterfaceCore("m", "limb1", backend, MotorInterfaceConfig(reopen_period=2.0))
    core.start(0.0)
    assert not core.is_open
    (status,) = core.diagnostics()
    assert status.level != OK and "fake0" in status.message
    command(core, 0.5, JointSample("limb1_joint1", 0.5))
    assert backend.written == []  # nothing reaches a bus that is not open
    core.tick(1.0)
    assert not core.is_open  # retried only after the period
    core.tick(2.1)
    assert core.is_open and backend.opened == 1
