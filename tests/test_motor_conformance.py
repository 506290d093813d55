"""The contract every motor backend meets, stated once and run against both emulators.

Each test runs twice: on CANopen (real python-can ``virtual`` bus, emulated CiA 402 drives)
and on Dynamixel (real dynamixel-sdk over a pty, emulated servo chain); see ``motor_rigs``.
Only what :class:`~components.motors.base.MotorBackend` promises is tested here: a reading
per motor after open, commands reaching the motors, halt and recover, unknown joints
ignored, faults as diagnostics (never as exceptions out of read/write/halt/recover), an
idempotent close, and a backend that opens again after a failure. Backend specifics (units,
watchdogs, emergencies) are in each backend's own test file.

What a motor does is read from the emulator (the shaft), not only from the backend, so a
backend that reports a move without making it fails. Everything in-process: no ``e2e``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import wait_until
from motor_rigs import CanopenRig, DynamixelRig, MotorRig

from components.motors.base import (
    ERROR,
    FAULT_KEY,
    OK,
    MotorBackend,
    MotorCommand,
    MotorError,
    MotorState,
)

J1, J2 = "limb1_joint1", "limb1_joint2"
#: Generous bounds for the emulators on a loaded two-core machine (they are polled: a
#: passing test takes a fraction of these).
MOVE_S = 5.0
FAULT_S = 5.0
#: Fresh readings to watch a motor that must stay still (each is a new feedback cycle).
STILL_READINGS = 10


@pytest.fixture(params=["canopen", "dynamixel"])
def rig(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[MotorRig]:
    """Two emulated motors on each kind of bus in turn."""
    made: MotorRig = CanopenRig() if request.param == "canopen" else DynamixelRig(tmp_path)
    try:
        yield made
    finally:
        made.close()


@pytest.fixture
def backend(rig: MotorRig) -> Iterator[MotorBackend]:
    """The rig's backend, open; at the end, no exception may have leaked out of it."""
    opened = rig.backend()
    opened.open()
    try:
        yield opened
        leaked = [d for d in opened.diagnostics() if FAULT_KEY in d.values]
        assert not leaked, f"the backend let exceptions out: {leaked}"
    finally:
        opened.close()


# ---------------------------------------------------------------------------- helpers


def finite(value: Any) -> bool:
    """A real number that is not NaN or infinite."""
    return isinstance(value, float | int) and not isinstance(value, bool) and math.isfinite(value)


def settled(
    rig: MotorRig, backend: MotorBackend, targets: dict[str, float], resend: bool = False
) -> Callable[[], dict[str, MotorState] | None]:
    """A predicate: every joint in ``targets`` is there, at rest, on the shaft and as read.

    With ``resend`` the command is written on every poll, as the joint manager streams it.
    """
    commands = [MotorCommand(joint, position=value) for joint, value in targets.items()]

    def check() -> dict[str, MotorState] | None:
        if resend:
            backend.write(commands)
        states = backend.read()
        for joint, value in targets.items():
            state = states.get(joint)
            if state is None or abs(state.position - value) > rig.position_tolerance:
                return None
            if abs(state.velocity) > rig.velocity_tolerance:
                return None
            if abs(rig.true_position(joint) - value) > rig.position_tolerance:
                return None
        return states

    return check


def turning(
    rig: MotorRig, backend: MotorBackend, joint: str, velocity: float
) -> Callable[[], MotorState | None]:
    """A predicate streaming a velocity command: true once the shaft and the reading turn at
    that speed."""

    def check() -> MotorState | None:
        backend.write([MotorCommand(joint, velocity=velocity)])
        state = backend.read().get(joint)
        if state is None or abs(state.velocity - velocity) > rig.velocity_tolerance:
            return None
        if abs(rig.true_velocity(joint) - velocity) > rig.velocity_tolerance:
            return None
        return state

    return check


def wait_fresh_readings(backend: MotorBackend, joint: str, count: int = STILL_READINGS) -> None:
    """Wait for ``count`` new feedback cycles of ``joint`` (its stamp moving on)."""
    seen = [backend.read()[joint].stamp]

    def newer() -> bool:
        state = backend.read().get(joint)
        if state is not None and state.stamp > seen[-1]:
            seen.append(state.stamp)
        return len(seen) > count

    wait_until(newer, MOVE_S, f"{count} fresh readings of {joint}")


def levels(backend: MotorBackend) -> dict[str, int]:
    """Diagnostic level per joint (``""``: the bus)."""
    return {d.joint: d.level for d in backend.diagnostics()}


# ------------------------------------------------------------------------------ tests


def test_open_then_read_gives_a_finite_reading_per_motor(
    rig: MotorRig, backend: MotorBackend
) -> None:
    states = backend.read()  # at once: open() brought every answering motor up
    assert sorted(states) == sorted(rig.joints)
    for joint, state in states.items():
        assert state.joint == joint
        for quantity in ("position", "velocity", "effort"):
            value = getattr(state, quantity)
            assert finite(value), f"{rig.name} {joint}.{quantity} = {value!r}"
        assert abs(state.position - rig.true_position(joint)) <= rig.position_tolerance
    diagnostics = backend.diagnostics()
    assert diagnostics[0].joint == ""  # the bus first, then one entry per motor
    assert sorted(d.joint for d in diagnostics[1:]) == sorted(rig.joints)
    assert all(d.level == OK for d in diagnostics), diagnostics


def test_a_position_write_is_reached(rig: MotorRig, backend: MotorBackend) -> None:
    # One write is enough: the backend carries the command to the motor by itself.
    backend.write([MotorCommand(J1, position=0.4), MotorCommand(J2, position=-0.3)])
    wait_until(settled(rig, backend, {J1: 0.4, J2: -0.3}), MOVE_S, "both joints at their goals")
    # The next goal is taken after the first one (a stream of set-points).
    backend.write([MotorCommand(J1, position=-0.2)])
    wait_until(settled(rig, backend, {J1: -0.2, J2: -0.3}), MOVE_S, f"{J1} at its next goal")


def test_a_velocity_write_moves(rig: MotorRig, backend: MotorBackend) -> None:
    start = rig.true_position(J1)
    state = wait_until(turning(rig, backend, J1, 1.0), MOVE_S, f"{J1} at 1 rad/s")
    assert state.velocity == pytest.approx(1.0, abs=rig.velocity_tolerance)
    wait_until(
        lambda: turning(rig, backend, J1, 1.0)() and rig.true_position(J1) > start + 0.1,
        MOVE_S,
        f"{J1} turned 0.1 rad",
    )
    assert abs(rig.true_position(J2)) <= rig.position_tolerance  # the other one did not move
    # Backwards too.
    wait_until(turning(rig, backend, J1, -0.5), MOVE_S, f"{J1} at -0.5 rad/s")


def test_halt_stops_motion_and_holds(rig: MotorRig, backend: MotorBackend) -> None:
    # J1 turns by velocity, J2 is on its way to a far goal.
    wait_until(turning(rig, backend, J1, 1.0), MOVE_S, f"{J1} turning")
    backend.write([MotorCommand(J2, position=3.0)])
    wait_until(lambda: backend.read() and rig.true_position(J2) > 0.3, MOVE_S, f"{J2} moving")
    backend.halt()

    def stopped() -> bool:
        states = backend.read()
        return all(
            joint in states
            and abs(states[joint].velocity) <= rig.velocity_tolerance
            and abs(rig.true_velocity(joint)) <= rig.velocity_tolerance
            for joint in (J1, J2)
        )

    wait_until(stopped, MOVE_S, "both joints stopped")
    held = {joint: rig.true_position(joint) for joint in (J1, J2)}
    assert held[J2] < 3.0 - 0.1, "the far goal was not dropped"
    wait_fresh_readings(backend, J1)
    for joint, position in held.items():
        assert rig.true_position(joint) == pytest.approx(position, abs=rig.position_tolerance)
        assert backend.read()[joint].position == pytest.approx(position, abs=rig.position_tolerance)


def test_recover_after_halt_accepts_commands_again(rig: MotorRig, backend: MotorBackend) -> None:
    backend.halt()
    backend.recover()
    backend.write([MotorCommand(J2, position=0.25)])
    wait_until(settled(rig, backend, {J2: 0.25}), MOVE_S, f"{J2} at its goal after recover")
    wait_until(turning(rig, backend, J1, 0.5), MOVE_S, f"{J1} turning after recover")
    wait_until(lambda: levels(backend)[J1] == OK, FAULT_S, f"{J1} OK")


def test_commands_to_unknown_joints_are_ignored(rig: MotorRig, backend: MotorBackend) -> None:
    before = {joint: rig.true_position(joint) for joint in rig.joints}
    backend.write(
        [MotorCommand("limb9_joint1", position=1.0), MotorCommand("limb9_joint2", velocity=2.0)]
    )
    wait_fresh_readings(backend, J1)
    for joint, position in before.items():
        assert rig.true_position(joint) == pytest.approx(position, abs=rig.position_tolerance)
    assert sorted(backend.read()) == sorted(rig.joints)
    # Nothing is said about the unknown joints, and every known one is (or, after a bus cycle
    # late on a loaded machine, soon is again) OK.
    assert not any("limb9" in d.joint or "limb9" in d.message for d in backend.diagnostics())
    wait_until(
        lambda: all(level == OK for level in levels(backend).values()),
        FAULT_S,
        f"every joint OK: {[(d.joint, d.level, d.message) for d in backend.diagnostics()]}",
    )
    # In a batch with a known joint, the known one is carried out as usual.
    backend.write([MotorCommand("limb9_joint1", position=1.0), MotorCommand(J1, position=0.3)])
    wait_until(settled(rig, backend, {J1: 0.3}), MOVE_S, f"{J1} at its goal")


def test_an_unplugged_bus_is_a_diagnostic_never_an_exception(
    rig: MotorRig, backend: MotorBackend
) -> None:
    rig.unplug()

    def reported() -> bool:
        # Every public call goes on as usual while the motors are gone: none may raise.
        backend.write([MotorCommand(J1, position=0.5), MotorCommand(J2, velocity=1.0)])
        backend.halt()
        backend.recover()
        states = backend.read()
        by_joint = {d.joint: d for d in backend.diagnostics()}
        return not states and all(
            by_joint[joint].level == ERROR and joint in by_joint[joint].message
            for joint in rig.joints
        )

    wait_until(reported, FAULT_S, "every joint ERROR, naming it, and no stale reading")
    # A bus that goes away is the backend's own diagnostic, not an exception it let out.
    assert not [d for d in backend.diagnostics() if FAULT_KEY in d.values]

    # Back: the backend picks the motors up again by itself, and they take commands.
    rig.plug()
    wait_until(
        lambda: (
            sorted(backend.read()) == sorted(rig.joints)
            and all(level == OK for level in levels(backend).values())
        ),
        FAULT_S,
        "every motor back and OK",
    )
    backend.write([MotorCommand(J1, position=0.2)])
    wait_until(settled(rig, backend, {J1: 0.2}), MOVE_S, f"{J1} at its goal after the fault")


def test_an_exception_inside_a_backend_becomes_a_diagnostic(
    rig: MotorRig, backend: MotorBackend, monkeypatch: pytest.MonkeyPatch
) -> None:
    def broken(*args: Any) -> Any:
        raise RuntimeError("emulated backend bug")

    for part in ("_read", "_write", "_halt", "_recover"):
        monkeypatch.setattr(backend, part, broken)
    assert backend.read() == {}
    backend.write([MotorCommand(J1, position=0.1)])
    backend.halt()
    backend.recover()
    backend.read()
    fault = backend.diagnostics()[-1]
    assert fault.level == ERROR
    assert fault.values[FAULT_KEY] == "halt,read,recover,write"
    assert fault.values["count"] == "5"
    assert "RuntimeError: emulated backend bug" in fault.message
    assert rig.name in fault.message
    # Reported once: the next report is clean, and the backend works again once mended.
    monkeypatch.undo()
    assert not [d for d in backend.diagnostics() if FAULT_KEY in d.values]
    assert sorted(backend.read()) == sorted(rig.joints)


def test_close_stops_the_motors_and_is_idempotent(rig: MotorRig) -> None:
    never_opened = rig.backend()
    never_opened.close()  # harmless

    backend = rig.backend()
    backend.open()
    wait_until(turning(rig, backend, J1, 1.0), MOVE_S, f"{J1} turning")
    backend.close()
    assert not backend.is_open
    wait_until(
        lambda: abs(rig.true_velocity(J1)) <= rig.velocity_tolerance, MOVE_S, "stopped at close"
    )
    backend.close()
    # Closed: reads are empty, commands do nothing, diagnostics say so; nothing raises.
    assert backend.read() == {}
    backend.write([MotorCommand(J1, velocity=1.0)])
    backend.halt()
    backend.recover()
    diagnostics = backend.diagnostics()
    assert sorted(d.joint for d in diagnostics) == sorted(["", *rig.joints])
    assert all(d.level == ERROR and "not open" in d.message for d in diagnostics)


def test_reopen_after_a_failure(rig: MotorRig) -> None:
    backend = rig.backend(**({"enable_timeout": 1.0} if rig.name == "canopen" else {}))
    backend.open()
    try:
        rig.unplug()
        wait_until(lambda: not backend.read(), FAULT_S, "the readings gone")
        backend.close()  # with the motors gone: must not raise
        # Opening with the motors still gone either refuses (a MotorError naming the bus)
        # or opens and reports every motor: never another exception.
        try:
            backend.open()
        except MotorError as exc:
            assert backend.channel in str(exc)
            assert not backend.is_open
        else:
            assert backend.read() == {}
            by_joint = {d.joint: d.level for d in backend.diagnostics()}
            assert all(by_joint[joint] == ERROR for joint in rig.joints), by_joint
            backend.close()
        rig.plug()
        backend.open()
        assert backend.is_open
        assert sorted(backend.read()) == sorted(rig.joints)
        backend.write([MotorCommand(J2, position=-0.4)])
        wait_until(settled(rig, backend, {J2: -0.4}), MOVE_S, f"{J2} at its goal after reopen")
        assert not [d for d in backend.diagnostics() if FAULT_KEY in d.values]
    finally:
        backend.close()
