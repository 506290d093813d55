"""The CANopen CiA 402 backend against emulated drives on python-can's virtual bus.

Real python-can, real ``canopen`` on the backend side, real CANopen frames: only the drives
are emulated (``components.motors.emulation.cia402``). Each test has its own channel so the
tests can run in parallel.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from typing import Any

import pytest
from conftest import wait_until
from motor_rigs import (
    CANOPEN_JOINTS,
    CANOPEN_OPTIONS,
    CANOPEN_PARAMS,
    COUNTS_PER_RAD,
    GEAR_RATIO,
    RATED_TORQUE,
    canopen_channel,
)

from components.motors.base import MotorCommand, MotorError, MotorSpec, backend_class
from components.motors.canopen.backend import CanopenBackend
from components.motors.canopen.cia402 import decode_state
from components.motors.canopen.units import Conversion
from components.motors.emulation.cia402 import EmulatedCia402Bus

PARAMS = CANOPEN_PARAMS
JOINTS = CANOPEN_JOINTS
OPTIONS = CANOPEN_OPTIONS


def diag(backend: CanopenBackend, joint: str) -> Any:
    """The diagnostic entry of one joint."""
    return next(d for d in backend.diagnostics() if d.joint == joint)


@pytest.fixture
def rig() -> Iterator[tuple[EmulatedCia402Bus, CanopenBackend]]:
    """Two emulated drives (node 1 and 2) and an open backend on a fresh virtual channel."""
    channel = canopen_channel()
    specs = [MotorSpec(joint, node, "cia402", dict(PARAMS)) for node, joint in JOINTS.items()]
    with EmulatedCia402Bus(channel, JOINTS) as emulator:
        backend = CanopenBackend(channel, specs, dict(OPTIONS))
        backend.open()
        try:
            yield emulator, backend
        finally:
            backend.close()


def settle_at(backend: CanopenBackend, joint: str, position: float, tol: float = 1e-4) -> Any:
    """Command ``position`` and wait until read() reports it, at rest."""

    def arrived() -> Any:
        backend.write([MotorCommand(joint, position=position)])
        state = backend.read().get(joint)
        ok = state and abs(state.position - position) < tol and abs(state.velocity) < 1e-3
        return state if ok else None

    return wait_until(arrived, 3.0, f"{joint} at {position} rad")


def test_open_enables_every_drive_in_profile_position(rig):
    emulator, backend = rig
    for node, joint in JOINTS.items():
        drive = emulator.drive(node)
        assert drive.state == "OPERATION ENABLED"
        assert drive.nmt_state == 0x05
        assert drive.mode == 1
        # The backend armed the drive's watchdog on its own heartbeat (node 127).
        assert drive.read_object(0x1016, 1) >> 16 == 127
        # Enabled on the drive; the backend reports it OK at its next poll.
        wait_until(lambda j=joint: diag(backend, j).level == 0, 10.0, f"{joint} reported OK")
        assert joint in diag(backend, joint).message
    wait_until(lambda: diag(backend, "").level == 0, 10.0, "the bus reported OK")
    assert set(backend.read()) == set(JOINTS.values())


def test_position_command_moves_the_joint_and_reads_back_in_radians(rig):
    emulator, backend = rig
    state = settle_at(backend, "limb1_joint1", 0.5)
    # Settled within 1e-4 rad as read back, so the drive is within as many counts (plus one).
    assert emulator.drive(1).position == pytest.approx(
        0.5 * COUNTS_PER_RAD, abs=1e-4 * COUNTS_PER_RAD + 1
    )
    assert state.position == pytest.approx(0.5, abs=1e-4)
    assert emulator.drive(2).position == 0.0  # the other joint did not move
    # A stream of new targets is taken one after another (set-point handshake).
    state = settle_at(backend, "limb1_joint1", -0.25)
    assert emulator.drive(1).position == pytest.approx(
        -0.25 * COUNTS_PER_RAD, abs=1e-4 * COUNTS_PER_RAD + 1
    )


def test_velocity_command_then_back_to_position(rig):
    emulator, backend = rig
    joint = "limb1_joint2"
    backend.write([MotorCommand(joint, velocity=1.2)])
    wait_until(lambda: emulator.drive(2).mode == 3, what="profile velocity mode")

    def at_speed() -> bool:
        state = backend.read().get(joint)
        return bool(state and abs(state.velocity - 1.2) < 1e-3)

    wait_until(at_speed, what="1.2 rad/s")
    assert emulator.drive(2).velocity == pytest.approx(1.2 * COUNTS_PER_RAD, abs=1.0)
    assert diag(backend, joint).values["mode"] == "profile velocity"
    settle_at(backend, joint, 0.1)
    assert emulator.drive(2).mode == 1


def test_effort_reads_back_in_newton_metres_and_limits_torque(rig):
    emulator, backend = rig
    emulator.drive(1).set_load(300)  # per-mille of rated torque, held at rest
    expected = 0.300 * RATED_TORQUE * GEAR_RATIO

    def effort() -> Any:
        state = backend.read().get("limb1_joint1")
        return state and state.effort is not None and abs(state.effort - expected) < 1e-6

    wait_until(effort, what=f"{expected} N·m")
    backend.write([MotorCommand("limb1_joint1", position=0.2, effort=10.0)])
    permille = round(10.0 / (RATED_TORQUE * GEAR_RATIO) * 1000)
    wait_until(lambda: emulator.drive(1).read_object(0x6072) == permille, what="max torque")


def test_temperature_and_over_temperature_fault(rig):
    emulator, backend = rig
    wait_until(lambda: backend.read()["limb1_joint1"].temperature == pytest.approx(25.0))
    emulator.drive(1).set_temperature(95.0)
    entry = wait_until(
        lambda: (e := diag(backend, "limb1_joint1")).level == 2 and "0x4210" in e.message and e,
        what="over-temperature ERROR",
    )
    assert "over-temperature" in entry.message
    emulator.drive(1).set_temperature(40.0)
    backend.recover()
    wait_until(lambda: diag(backend, "limb1_joint1").level == 0, what="OK after recover")


def test_silent_drive_is_an_error_then_picked_up_again(rig):
    emulator, backend = rig
    joint = "limb1_joint2"
    emulator.drive(2).silence()
    # No wall-clock bound: how soon it is named depends on the machine's load, not the code.
    entry = wait_until(
        lambda: (e := diag(backend, joint)).level == 2 and e, 15.0, "ERROR for a silent drive"
    )
    assert entry.message.startswith(f"{joint}: drive node 2 stopped answering (no heartbeat for")
    assert joint not in backend.read()  # its last state is not passed off as fresh
    backend.write([MotorCommand(joint, position=1.0), MotorCommand("limb1_joint1", velocity=0.1)])
    backend.halt()  # none of this raises
    assert diag(backend, "limb1_joint1").level == 0  # the other drive is unaffected

    emulator.drive(2).resume()
    wait_until(lambda: diag(backend, joint).level == 0, 15.0, "OK after the drive returns")
    assert emulator.drive(2).state == "OPERATION ENABLED"
    settle_at(backend, joint, 0.3)


def test_emergency_is_an_error_until_recover(rig):
    emulator, backend = rig
    joint = "limb1_joint1"
    emulator.drive(1).raise_fault(0x2310)
    entry = wait_until(
        lambda: (e := diag(backend, joint)).level == 2 and e, what="ERROR after EMCY"
    )
    assert "0x2310" in entry.message and "over-current" in entry.message
    assert joint in entry.message
    time.sleep(0.2)  # a real fault stays until someone resets it
    assert emulator.drive(1).state == "FAULT"
    assert diag(backend, joint).level == 2
    backend.recover()
    wait_until(lambda: diag(backend, joint).level == 0, what="OK after recover")
    assert emulator.drive(1).state == "OPERATION ENABLED"
    settle_at(backend, joint, -0.2)


def test_halt_stops_motion_and_holds(rig):
    emulator, backend = rig
    joint = "limb1_joint1"
    backend.write([MotorCommand(joint, velocity=2.0)])
    wait_until(lambda: emulator.drive(1).velocity > 0.5 * COUNTS_PER_RAD, what="moving")
    backend.halt()
    wait_until(lambda: abs(emulator.drive(1).velocity) < 1.0, what="stopped")
    held = emulator.drive(1).position
    time.sleep(0.1)
    assert emulator.drive(1).position == pytest.approx(held, abs=1.0)
    assert "halted" in diag(backend, joint).message
    # A new command lifts the halt.
    settle_at(backend, joint, 0.0)


def test_close_is_idempotent_and_disables_the_drives(rig):
    emulator, backend = rig
    backend.close()
    backend.close()
    assert backend.read() == {}
    assert backend.diagnostics()[0].level == 2  # the bus is not open: ERROR
    for node in JOINTS:
        wait_until(lambda node=node: emulator.drive(node).state == "SWITCHED ON")
        assert emulator.drive(node).read_object(0x1016, 1) == 0  # watchdog disarmed
        assert emulator.drive(node).nmt_state == 0x7F


def test_unknown_interface_is_a_motor_error_naming_channel_and_fix():
    backend = CanopenBackend("can7", [MotorSpec("j", 1, "cia402")], {"interface": "nosuchbus"})
    with pytest.raises(MotorError) as info:
        backend.open()
    text = str(info.value)
    assert "'can7'" in text and "'nosuchbus'" in text and "socketcan" in text
    backend.close()  # closing a backend that never opened is harmless


def test_drive_that_never_answers_is_an_error_not_an_exception():
    channel = canopen_channel()
    with EmulatedCia402Bus(channel, [1]):
        specs = [MotorSpec("limb1_joint1", 1, "cia402"), MotorSpec("limb1_joint9", 9, "cia402")]
        with CanopenBackend(channel, specs, dict(OPTIONS, sdo_timeout=0.1)) as backend:
            entry = diag(backend, "limb1_joint9")
            assert entry.level == 2 and "drive node 9 not answering" in entry.message
            # The answering drive goes on enabling (WARN) to OK; only the silent one is an error.
            wait_until(lambda: diag(backend, "limb1_joint1").level == 0, 10.0, "drive 1 enabled")
            assert set(backend.read()) == {"limb1_joint1"}


def test_conversion_is_in_one_place_and_checked():
    spec = MotorSpec("j", 1, "cia402", {"counts_per_rev": 1000, "gear_ratio": 2.0})
    conv = Conversion.from_spec(spec)
    assert conv.position(1000) == pytest.approx(math.pi)
    assert conv.position_counts(math.pi) == 1000
    rpm = Conversion.from_spec(MotorSpec("j", 1, "cia402", {"velocity_units": "rpm"}))
    assert rpm.velocity(60) == pytest.approx(2 * math.pi)
    with pytest.raises(MotorError, match=r"limb9_joint1: motor_params\.gear_ratio"):
        Conversion.from_spec(MotorSpec("limb9_joint1", 1, "cia402", {"gear_ratio": 0}))
    with pytest.raises(MotorError, match="velocity_units"):
        Conversion.from_spec(MotorSpec("j", 1, "cia402", {"velocity_units": "furlongs"}))
    assert decode_state(0x0627) == "OPERATION ENABLED"
    assert decode_state(0x0008) == "FAULT"
    assert backend_class("canopen") is CanopenBackend


def test_feedback_on_sync_as_the_module_data_asks():
    channel = canopen_channel()
    options = {"interface": "virtual", "sync_period": 0.01, "heartbeat_ms": 100}
    with EmulatedCia402Bus(channel, [3]) as emulator:
        spec = MotorSpec("limb1_joint3", 3, "cia402", dict(PARAMS))
        with CanopenBackend(channel, [spec], options) as backend:
            assert emulator.drive(3).read_object(0x1801, 2) == 1  # TPDO2 follows SYNC
            assert emulator.drive(3).read_object(0x1017) == 100
            settle_at(backend, "limb1_joint3", 0.4)


def test_bus_that_goes_away_is_an_error_and_is_reopened(rig):
    _, backend = rig
    # Fault injection: the adapter vanishes under the backend (its python-can bus dies).
    backend._network.bus.shutdown()
    entry = wait_until(lambda: (e := diag(backend, "")).level == 2 and e, what="bus ERROR")
    assert backend.channel in entry.message
    backend.write([MotorCommand("limb1_joint1", position=0.3)])  # never raises
    backend.read()
    wait_until(lambda: all(d.level == 0 for d in backend.diagnostics()), 4.0, "all OK after reopen")
    settle_at(backend, "limb1_joint1", 0.3)
