"""Motor interface core with plain calls, fake time and a recording backend."""

from __future__ import annotations

import gc
import logging

import pytest

from components.messages import ERROR, OK, WARN, JointSample, joint_state
from components.motor_interface.core import MotorInterfaceConfig, MotorInterfaceCore
from components.motors.base import (
    FAULT_KEY,
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
        self.closed = 0
        self.halts = 0

    def _open(self) -> None:
        if self.fail_open:
            self.fail_open -= 1
            raise MotorError("fake0: no such bus")
        self.opened += 1

    def _close(self) -> None:
        self.closed += 1

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


# -- the base class's lifecycle and never-raise rule, through the fake bus -------------------


def test_before_open_and_after_close_nothing_reaches_the_bus() -> None:
    backend = RecordingBackend()
    assert not backend.is_open
    assert backend.read() == {}
    backend.write([MotorCommand("joint1", 0.5)])
    backend.halt()
    backend.recover()
    assert backend.written == [] and backend.halts == 0
    bus, *joints = backend.diagnostics()
    assert bus.joint == "" and bus.level == ERROR and "fake0 is not open" in bus.message
    assert [(d.joint, d.level) for d in joints] == [("joint1", ERROR), ("joint2", ERROR)]
    backend.close()  # closing what never opened: nothing to do
    assert backend.closed == 0

    with backend:
        assert backend.is_open and set(backend.read()) == {"joint1", "joint2"}
        backend.open()  # already open: nothing happens
        assert backend.opened == 1
    backend.close()
    assert backend.closed == 1 and not backend.is_open
    assert backend.read() == {}
    backend.write([MotorCommand("joint1", 0.5)])
    assert backend.written == []


def test_an_exception_inside_the_backend_is_an_error_diagnostic_never_raised(
    caplog: pytest.LogCaptureFixture,
) -> None:
    backend = RecordingBackend()
    core = MotorInterfaceCore("limb1/motor_interface", "limb1", backend)
    core.start(0.0)

    def broken(*_: object) -> None:
        raise RuntimeError("register map mismatch")

    backend._read = broken  # type: ignore[method-assign]
    backend._write = broken  # type: ignore[method-assign]
    with caplog.at_level(logging.ERROR, "components.motors.base"):
        core.tick(0.1)
        core.tick(0.2)
        command(core, 0.3, JointSample("limb1_joint1", 0.5))
        backend.halt()  # the fake's own halt still works
    assert core.outbox.on("joint_states") == []
    assert backend.halts == 1
    # Logged once per kind of failure, not once per call.
    assert [r.getMessage() for r in caplog.records] == [
        "RecordingBackend bus fake0: read failed",
        "RecordingBackend bus fake0: write failed",
    ]

    statuses = {s.name: s for s in core.diagnostics()}
    fault = statuses["limb1/motor_backend"]
    assert fault.level == ERROR
    assert "fake0" in fault.message  # the backend and its channel
    # The first tick's report took the first read failure; this one has the second.
    assert "read failed: RuntimeError: register map mismatch" in fault.message
    assert "write failed: RuntimeError: register map mismatch" in fault.message
    assert "limb1/bus" in statuses  # the bus's own status is not hidden
    # Reported once: the next report is clean again.
    assert "limb1/motor_backend" not in {s.name for s in core.diagnostics()}

    backend._diagnostics = broken  # type: ignore[method-assign]
    (entry,) = backend.diagnostics()
    assert entry.level == ERROR and entry.values[FAULT_KEY] == "diagnostics"


def test_open_raises_only_motor_errors_with_the_cause_kept() -> None:
    backend = RecordingBackend()

    def broken() -> None:
        raise OSError(19, "No such device")

    backend._open = broken  # type: ignore[method-assign]
    expected = r"RecordingBackend bus fake0: cannot open \(OSError"
    with pytest.raises(MotorError, match=expected) as info:
        backend.open()
    assert isinstance(info.value.__cause__, OSError)
    assert not backend.is_open


def test_a_backend_dropped_while_open_is_closed_with_a_warning(
    caplog: pytest.LogCaptureFixture,
) -> None:
    backend = RecordingBackend()
    backend.open()
    closes: list[int] = []
    backend._close = lambda: closes.append(1)  # type: ignore[method-assign]
    with caplog.at_level(logging.WARNING, "components.motors.base"):
        del backend
        gc.collect()
    assert closes == [1]
    assert any("garbage-collected while open" in r.getMessage() for r in caplog.records)
