"""The Dynamixel backend through the real dynamixel-sdk, over a pty, against the emulated chain."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest
from conftest import wait_until
from dynamixel_sdk import COMM_SUCCESS, PacketHandler
from motor_rigs import DYNAMIXEL_OPTIONS, TICK, XM430

from components.motors.base import MotorCommand, MotorError, MotorSpec, backend_class
from components.motors.dynamixel.backend import DynamixelBackend
from components.motors.dynamixel.control_table import BUS_WATCHDOG_EXPIRED
from components.motors.dynamixel.port import LatencyAwarePort
from components.motors.dynamixel.units import MODELS, JointUnits
from components.motors.emulation.dynamixel import (
    EmulatedDynamixelChain,
    PacketParser,
    build_packet,
    build_status,
    crc16,
    stuff,
    unstuff,
)

IDS = [1, 2, 3, 4, 5]
OPTIONS = DYNAMIXEL_OPTIONS


def joint(dxl_id: int) -> str:
    return f"limb1_joint{dxl_id}"


def diag(backend: DynamixelBackend, name: str):
    return next(d for d in backend.diagnostics() if d.joint == name)


@pytest.fixture(autouse=True)
def no_leaks() -> Iterator[None]:
    """Every test closes its emulator threads and file descriptors."""
    fds_before = set(os.listdir("/proc/self/fd"))
    yield
    leaked = [t.name for t in threading.enumerate() if t.name.startswith("dynamixel-emulator")]
    assert not leaked
    assert set(os.listdir("/proc/self/fd")) <= fds_before


@pytest.fixture
def chain() -> Iterator[EmulatedDynamixelChain]:
    with EmulatedDynamixelChain(ids=IDS) as emulated:
        yield emulated


@pytest.fixture
def backend(chain: EmulatedDynamixelChain) -> Iterator[DynamixelBackend]:
    motors = [MotorSpec(joint(i), i, "XM430-W350") for i in IDS]
    dxl = DynamixelBackend(chain.port, motors, {**OPTIONS, "baudrate": 1_000_000})
    dxl.open()
    yield dxl
    dxl.close()


# -- protocol pieces -------------------------------------------------------------------------


def test_crc_and_packets_match_the_protocol_manual() -> None:
    # Examples from the ROBOTIS Protocol 2.0 e-manual: PING id 1, its status (XM430-W210,
    # firmware 0x26), and READ of Present Position (132, 4 bytes) from id 1.
    assert build_packet(1, 0x01) == bytes.fromhex("FFFFFD00 01 0300 01 194E")
    assert build_status(1, 0, bytes([0x06, 0x04, 0x26])) == bytes.fromhex(
        "FFFFFD00 01 0700 55 00 060426 655D"
    )
    assert build_packet(1, 0x02, bytes([0x84, 0, 4, 0])) == bytes.fromhex(
        "FFFFFD00 01 0700 02 84000400 1D15"
    )
    assert crc16(bytes.fromhex("FFFFFD00 01 0300 01")) == 0x4E19


def test_crc_agrees_with_the_sdk() -> None:
    sdk = PacketHandler(2.0)
    for size in (1, 7, 64, 300):
        data = os.urandom(size)
        assert crc16(data) == sdk.updateCRC(0, list(data), size)


def test_stuffing_round_trip_and_parser() -> None:
    body = bytes([0x03, 0xFF, 0xFF, 0xFD, 0x01, 0xFF, 0xFF, 0xFD, 0xFD, 0xFF, 0xFF, 0xFD])
    stuffed = stuff(body)
    assert stuffed.count(0xFD) == body.count(0xFD) + 3
    assert b"\xff\xff\xfd\x00" not in stuffed
    assert unstuff(stuffed) == body

    params = bytes([0x74, 0x00, 0xFF, 0xFF, 0xFD, 0x00])
    good = build_packet(7, 0x03, params)
    corrupt = bytearray(build_packet(8, 0x01))
    corrupt[-1] ^= 0xFF
    parser = PacketParser()
    # Line noise first, then a packet split across two reads, then one with a bad CRC.
    packets = list(parser.feed(b"\x00\xff\x12" + good[:5]))
    packets += list(parser.feed(good[5:] + bytes(corrupt)))
    assert [(p.dxl_id, p.instruction, p.params, p.crc_ok) for p in packets] == [
        (7, 0x03, params, True),
        (8, 0x01, b"", False),
    ]


def test_sdk_unstuffs_what_the_emulator_stuffs(chain: EmulatedDynamixelChain) -> None:
    # Goal Position bytes FF FF FD 00 force the emulator to stuff its status packet.
    chain.set_register(1, "goal_position", 0x00FDFFFF)
    # The SDK's own read path; only its reply timeout is widened (16 ms latency hard-coded:
    # the emulator's thread answered later than that on a loaded machine, COMM_RX_TIMEOUT).
    port = LatencyAwarePort(chain.port, latency_timer_ms=1000.0)
    assert port.openPort()
    try:
        value, result, error = PacketHandler(2.0).read4ByteTxRx(port, 1, 116)
    finally:
        port.closePort()
    assert (result, error, value) == (COMM_SUCCESS, 0, 0x00FDFFFF)


# -- units -----------------------------------------------------------------------------------


def test_units_convert_in_one_place() -> None:
    units = JointUnits(XM430, XM430.torque_constant)
    assert units.position(2048) == 0.0
    assert units.position(3072) == pytest.approx(math.pi / 2)
    assert units.position_ticks(-math.pi / 2) == 1024
    assert units.velocity(100) == pytest.approx(100 * 0.229 * 2 * math.pi / 60)
    assert units.velocity_units(units.velocity(-37)) == -37
    # 100 units of 2.69 mA through the XM430-W350's ~1.78 N·m/A.
    assert units.effort(100) == pytest.approx(0.269 * 4.1 / 2.3)
    load = JointUnits(MODELS["XL430-W250"], 1.0)
    assert load.effort(500) == pytest.approx(0.75)  # 50.0 % of 1.5 N·m stall torque
    finger = JointUnits(MODELS["XL330-M288"], MODELS["XL330-M288"].torque_constant, 0.008)
    assert finger.position(3072) == pytest.approx(0.008 * math.pi / 2)
    assert finger.effort(1000) == pytest.approx(1.0 * 0.52 / 1.47 / 0.008)


# -- through the pty -------------------------------------------------------------------------


def test_registry_finds_the_backend() -> None:
    assert backend_class("dynamixel") is DynamixelBackend


def test_open_pings_sets_mode_and_enables_torque(
    chain: EmulatedDynamixelChain, backend: DynamixelBackend
) -> None:
    # A reply that came too late at open (a loaded machine) is picked up at the next re-probe.
    for i in IDS:
        wait_until(lambda i=i: chain.register(i, "torque_enable") == 1, 15.0, f"id {i} torque on")
        assert chain.register(i, "operating_mode") == 3
    wait_until(lambda: all(d.level == 0 for d in backend.diagnostics()), 15.0, "every servo OK")
    states = backend.read()
    assert sorted(states) == [joint(i) for i in IDS]
    assert states[joint(1)].position == pytest.approx(0.0)
    assert states[joint(1)].temperature == 35.0


def test_position_goals_move_the_joints(
    chain: EmulatedDynamixelChain, backend: DynamixelBackend
) -> None:
    goals = {joint(1): 0.5, joint(2): -0.3, joint(5): 1.2}
    backend.write([MotorCommand(name, position=value) for name, value in goals.items()])
    # SYNC_WRITE has no reply: the emulator applies it a moment later.
    wait_until(lambda: chain.register(1, "goal_position") == 2048 + round(0.5 / TICK))

    def arrived() -> bool:
        states = backend.read()
        return all(abs(states[name].position - value) < 2 * TICK for name, value in goals.items())

    wait_until(arrived)
    assert backend.read()[joint(3)].position == pytest.approx(0.0)


def test_position_goals_are_clamped_to_the_servo_limits(
    chain: EmulatedDynamixelChain, backend: DynamixelBackend
) -> None:
    backend.write([MotorCommand(joint(1), position=10.0)])
    wait_until(lambda: chain.register(1, "goal_position") == 4095)


def test_velocity_mode_switch_and_effort(
    chain: EmulatedDynamixelChain, backend: DynamixelBackend
) -> None:
    backend.write([MotorCommand(joint(2), velocity=1.0)])
    wait_until(lambda: chain.register(2, "operating_mode") == 1, what="velocity mode")
    wait_until(lambda: chain.register(2, "torque_enable") == 1, what="torque back on")
    state = wait_until(lambda: (s := backend.read()[joint(2)]).velocity > 0.9 and s)
    assert state.velocity == pytest.approx(1.0, abs=0.03)
    start = state.position
    later = wait_until(lambda: (s := backend.read()[joint(2)]).position > start + 0.05 and s)
    assert later.velocity == pytest.approx(1.0, abs=0.03)
    # At constant speed the emulated current is steady: effort is its conversion.
    raw_current = chain.register(2, "present_current")
    assert raw_current > 0
    assert later.effort == pytest.approx(raw_current * 2.69e-3 * 4.1 / 2.3)

    # A position command switches back (torque off -> mode -> torque on) and holds there.
    backend.write([MotorCommand(joint(2), position=0.2)])
    wait_until(lambda: abs(backend.read()[joint(2)].position - 0.2) < 2 * TICK)
    assert chain.register(2, "operating_mode") == 3
    assert chain.register(2, "torque_enable") == 1


def test_hardware_error_names_joint_and_bit_then_recover_clears_it(
    chain: EmulatedDynamixelChain, backend: DynamixelBackend
) -> None:
    chain.set_hardware_error(2, 1 << 5)

    def flagged():
        backend.read()
        d = diag(backend, joint(2))
        return d.level == 2 and d

    message = wait_until(flagged).message
    assert "limb1_joint2" in message and "servo id 2" in message and "overload" in message
    assert chain.register(2, "torque_enable") == 0  # the servo shut down by itself
    assert all(diag(backend, joint(i)).level == 0 for i in IDS if i != 2)

    backend.recover()
    wait_until(lambda: diag(backend, joint(2)).level == 0, what=f"{joint(2)} OK after recover")
    assert chain.register(2, "hardware_error_status") == 0
    assert chain.register(2, "torque_enable") == 1


def test_over_temperature(chain: EmulatedDynamixelChain) -> None:
    motors = [
        MotorSpec(joint(1), 1, "XM430-W350"),
        MotorSpec(joint(2), 2, "XM430-W350", {"temperature_limit": 60}),
    ]
    with DynamixelBackend(chain.port, motors, OPTIONS) as dxl:
        # Past the servo's own limit (80 °C): the servo flags overheating and shuts down.
        chain.set_temperature(1, 85)
        # Past the module data's tighter limit only: the backend's own threshold.
        chain.set_temperature(2, 65)
        wait_until(lambda: dxl.read()[joint(1)].temperature == 85.0, what="85 °C read")
        overheated = wait_until(lambda: (d := diag(dxl, joint(1))).level == 2 and d)
        assert "overheating" in overheated.message
        over_limit = wait_until(lambda: (d := diag(dxl, joint(2))).level == 2 and d)
        assert "over temperature: 65 °C (limit 60 °C)" in over_limit.message
        chain.set_temperature(2, 57)
        # Hot: within 5 °C of the limit.
        wait_until(lambda: diag(dxl, joint(2)).level == 1, what="WARN at 57 °C")


def test_silent_servo_is_reported_alone_and_picked_up_again(
    chain: EmulatedDynamixelChain, backend: DynamixelBackend
) -> None:
    chain.silence(3)

    def reported():
        d = diag(backend, joint(3))
        states = backend.read()  # as of the same cycle or a later one
        return d.level == 2 and (states, d)

    # No wall-clock bound: how soon it is named depends on the machine's load, not the code.
    states, d = wait_until(reported, 15.0, "id 3 reported not answering")
    assert d.message == "limb1_joint3: servo id 3 not answering"
    assert sorted(states) == [joint(i) for i in IDS if i != 3]
    assert all(diag(backend, joint(i)).level == 0 for i in IDS if i != 3)

    # The rest of the chain still reads and moves while id 3 is gone.
    backend.write([MotorCommand(joint(4), position=0.3)])
    wait_until(lambda: abs(backend.read()[joint(4)].position - 0.3) < 2 * TICK)

    # Back, after a power cycle that left its torque off: re-enabled and OK again.
    chain.resume(3)
    assert chain.register(3, "torque_enable") == 0
    wait_until(lambda: joint(3) in backend.read() and diag(backend, joint(3)).level == 0)
    assert chain.register(3, "torque_enable") == 1


def test_servo_silencing_the_rest_of_a_sync_read_does_not_blind_the_chain() -> None:
    with (
        EmulatedDynamixelChain(ids=IDS, gap_stops_sync_read=True) as strict,
        DynamixelBackend(
            strict.port, [MotorSpec(joint(i), i, "XM430-W350") for i in IDS], OPTIONS
        ) as dxl,
    ):
        strict.silence(2)
        # Ids 3..5 miss the group reply too; individual reads still get them in the same
        # cycle, so they are never reported silent.
        levels = [0, 2, 0, 0, 0]
        seen = wait_until(lambda: (d := [d.level for d in dxl.diagnostics()[1:]])[1] == 2 and d)
        assert seen == levels
        assert sorted(dxl.read()) == [joint(i) for i in IDS if i != 2]
        for _ in range(5):  # cycle after cycle: a fresh reading of id 5 each time
            stamp = dxl.read()[joint(5)].stamp
            wait_until(lambda stamp=stamp: dxl.read()[joint(5)].stamp > stamp, what="a cycle")
            assert [d.level for d in dxl.diagnostics()[1:]] == levels
            assert sorted(dxl.read()) == [joint(i) for i in IDS if i != 2]


def test_servo_absent_at_open_does_not_raise(chain: EmulatedDynamixelChain) -> None:
    chain.silence(2)
    motors = [MotorSpec(joint(i), i, "XM430-W350") for i in (1, 2)]
    with DynamixelBackend(chain.port, motors, {**OPTIONS, "reprobe_interval_s": 0.1}) as dxl:
        d = diag(dxl, joint(2))
        assert d.level == 2 and "servo id 2 not answering" in d.message
        assert sorted(dxl.read()) == [joint(1)]
        chain.resume(2)
        wait_until(lambda: joint(2) in dxl.read())
        assert chain.register(2, "torque_enable") == 1


def test_halt_holds_position_and_stops_velocity(
    chain: EmulatedDynamixelChain, backend: DynamixelBackend
) -> None:
    # A reading may be missing for a cycle when a loaded machine makes a servo's reply late
    # (it is reported silent, then picked up again): each wait looks for the reading it needs.
    def reading(number: int) -> Any:
        return backend.read().get(joint(number))

    backend.write([MotorCommand(joint(1), velocity=2.0), MotorCommand(joint(2), position=2.5)])
    wait_until(lambda: (r := reading(2)) is not None and r.position > 0.5)
    backend.halt()
    wait_until(lambda: chain.register(1, "goal_velocity") == 0)
    # Goal pulled back to where the joint was, not left 2.5 rad away.
    wait_until(lambda: chain.register(2, "goal_position") < 2048 + 2.0 / TICK)
    wait_until(lambda: (r := reading(1)) is not None and abs(r.velocity) < 1e-9)
    held = wait_until(lambda: (r := reading(2)) is not None and abs(r.velocity) < 1e-9 and r)
    assert held.position < 2.0


def test_close_is_idempotent_and_turns_torque_off(chain: EmulatedDynamixelChain) -> None:
    dxl = DynamixelBackend(chain.port, [MotorSpec(joint(1), 1, "XM430-W350")], OPTIONS)
    dxl.open()
    dxl.close()
    dxl.close()
    wait_until(lambda: chain.register(1, "torque_enable") == 0)  # a reply-less SYNC_WRITE
    assert dxl.read() == {}
    dxl.write([MotorCommand(joint(1), position=1.0)])
    assert diag(dxl, "").level == 2


def test_hold_on_close_keeps_torque(chain: EmulatedDynamixelChain) -> None:
    motors = [MotorSpec(joint(1), 1, "XM430-W350")]
    with DynamixelBackend(chain.port, motors, {**OPTIONS, "hold_on_close": True}):
        pass
    time.sleep(0.05)  # nothing to wait for: there must be no torque-off packet at all
    assert chain.register(1, "torque_enable") == 1


def test_bus_that_goes_away_is_a_diagnostic_not_an_exception() -> None:
    chain = EmulatedDynamixelChain(ids=[1, 2])
    motors = [MotorSpec(joint(i), i, "XM430-W350") for i in (1, 2)]
    with DynamixelBackend(chain.port, motors, {**OPTIONS, "reopen_interval_s": 0.05}) as dxl:
        assert sorted(dxl.read()) == [joint(1), joint(2)]
        chain.close()
        wait_until(lambda: not dxl.read() and diag(dxl, "").level == 2)
        dxl.write([MotorCommand(joint(1), position=0.1)])
        dxl.halt()
        dxl.recover()
        assert diag(dxl, joint(1)).level == 2
        assert "lost" in diag(dxl, "").message


def test_unopenable_device_names_the_path_and_the_fix() -> None:
    dxl = DynamixelBackend("/dev/ttyUSB-missing-42", [MotorSpec(joint(1), 1, "XM430-W350")], {})
    with pytest.raises(MotorError, match=r"/dev/ttyUSB-missing-42.*dialout"):
        dxl.open()
    dxl.close()


def test_unknown_model_is_a_motor_error_naming_the_joint(chain: EmulatedDynamixelChain) -> None:
    dxl = DynamixelBackend(chain.port, [MotorSpec(joint(1), 1, "AX-12A")], {})
    with pytest.raises(MotorError, match=r"limb1_joint1.*AX-12A"):
        dxl.open()


def test_model_mismatch_is_a_warning() -> None:
    with (
        EmulatedDynamixelChain(ids=[1], model="XL430-W250") as other,
        DynamixelBackend(other.port, [MotorSpec(joint(1), 1, "XM430-W350")], OPTIONS) as dxl,
    ):
        d = diag(dxl, joint(1))
        assert d.level == 1 and "XL430-W250" in d.message


# -- bus watchdog ----------------------------------------------------------------------------

#: The backend's default: 100 ms = 5 units of 20 ms.
WATCHDOG_S = 0.1

#: A msctl process driving joint 2 by velocity at 100 Hz until it is killed.
DRIVER = textwrap.dedent(
    """
    import sys, time
    from components.motors.base import MotorCommand, MotorSpec
    from components.motors.dynamixel.backend import DynamixelBackend

    dxl = DynamixelBackend(sys.argv[1], [MotorSpec("limb1_joint2", 2, "XM430-W350")],
                           {"latency_timer_ms": 40.0})
    dxl.open()
    print("open", flush=True)
    while True:
        dxl.read()
        dxl.write([MotorCommand("limb1_joint2", velocity=1.0)])
        time.sleep(0.01)
    """
)


@pytest.mark.e2e
def test_servo_stops_by_itself_when_the_driving_process_is_killed(
    chain: EmulatedDynamixelChain,
) -> None:
    with subprocess.Popen(
        [sys.executable, "-c", DRIVER, chain.port], stdout=subprocess.PIPE, text=True
    ) as driver:
        try:
            assert driver.stdout is not None and driver.stdout.readline() == "open\n"
            wait_until(lambda: chain.register(2, "present_velocity") > 35, what="turning")
            assert chain.register(2, "bus_watchdog") == 5  # armed with the default 100 ms
            # Fed at 100 Hz, it never trips while the process lives: the servo hears the
            # process for three watchdog periods (its own clock says when), still turning.
            since = chain.watchdog(2)[0]
            wait_until(lambda: chain.watchdog(2)[0] > since + 3 * WATCHDOG_S, 15.0, "fed 0.3 s")
            assert chain.register(2, "present_velocity") > 35
            assert chain.watchdog(2)[2] == 0
        finally:
            driver.send_signal(signal.SIGKILL)  # no close(), no torque off: just gone
            driver.wait()
    wait_until(lambda: chain.register(2, "present_velocity") == 0, 15.0, "stop")
    # How soon it stopped, on the servo's own clock (one period after the last packet),
    # not the test's: the test's wall clock only measures the machine's load.
    heard_at, expired_at, trips = chain.watchdog(2)
    assert trips == 1 and expired_at is not None
    assert expired_at - heard_at == pytest.approx(WATCHDOG_S)
    assert chain.register(2, "goal_velocity") == 0
    assert chain.register(2, "bus_watchdog") == BUS_WATCHDOG_EXPIRED
    assert chain.register(2, "torque_enable") == 1  # stopped under torque, not dropped
    position = chain.register(2, "present_position")
    time.sleep(2 * WATCHDOG_S)
    assert chain.register(2, "present_position") == position


def test_backend_abandoned_without_close_lets_the_servo_stop(
    chain: EmulatedDynamixelChain,
) -> None:
    # No reopen within the test: the port stays gone.
    options = {**OPTIONS, "reopen_interval_s": 60.0}
    dxl = DynamixelBackend(chain.port, [MotorSpec(joint(1), 1, "XM430-W350")], options)
    dxl.open()
    try:
        dxl.write([MotorCommand(joint(1), velocity=-1.5)])
        wait_until(lambda: dxl.read()[joint(1)].velocity < -1.4)
        # The process "dies": the port goes without the graceful close path, and the caller
        # keeps calling as if nothing happened.
        dxl._port.closePort()  # a crash, not the API
        wait_until(
            lambda: not dxl.read() and chain.register(1, "present_velocity") == 0, 15.0, "stop"
        )
        # Stopped by its watchdog one period after the last packet, on the servo's own clock.
        heard_at, expired_at, _ = chain.watchdog(1)
        assert expired_at is not None and expired_at - heard_at == pytest.approx(WATCHDOG_S)
        assert chain.register(1, "bus_watchdog") == BUS_WATCHDOG_EXPIRED
    finally:
        dxl.close()


def test_pause_longer_than_the_watchdog_is_reported_and_rearmed(
    chain: EmulatedDynamixelChain, backend: DynamixelBackend
) -> None:
    backend.write([MotorCommand(joint(2), velocity=1.0)])
    wait_until(lambda: backend.read()[joint(2)].velocity > 0.9)
    assert chain.register(2, "bus_watchdog") == 5
    assert diag(backend, joint(2)).values["bus_watchdog"] == "100 ms"

    # The caller stalls: no read, no write. The I/O thread goes on, but stops talking to the
    # armed servo (as if the whole process had stalled), so its watchdog stops it.
    time.sleep(3 * WATCHDOG_S)  # the stall itself (its length is asserted below), not a wait
    wait_until(lambda: chain.register(2, "bus_watchdog") == BUS_WATCHDOG_EXPIRED, 15.0, "expiry")
    assert chain.register(2, "present_velocity") == 0
    heard_at, expired_at, _ = chain.watchdog(2)
    assert expired_at is not None and expired_at - heard_at == pytest.approx(WATCHDOG_S)

    # Back: the next cycle finds the expiry, clears it, re-arms, and says which joint.
    backend.read()
    d = wait_until(lambda: (d := diag(backend, joint(2))).level == 1 and d, what="WARN")
    assert d.message == (
        "limb1_joint2: servo id 2 stopped by its bus watchdog (no command for 100 ms); re-armed"
    )
    assert d.values["bus_watchdog_trips"] == "1"
    assert int(d.values["bus_watchdog_last_gap_ms"]) >= 299  # the pause, as this side saw it
    assert chain.register(2, "bus_watchdog") == 5
    # Not resumed on its own: the old velocity needs a new command.
    assert chain.register(2, "goal_velocity") == 0
    assert all(diag(backend, joint(i)).level == 0 for i in IDS if i != 2)

    backend.write([MotorCommand(joint(2), velocity=-0.5)])
    state = wait_until(lambda: (s := backend.read()[joint(2)]).velocity < -0.45 and s)
    assert state.velocity == pytest.approx(-0.5, abs=0.03)
    assert chain.watchdog(2)[2] == 1


def test_write_after_a_pause_is_not_swallowed_by_the_expired_watchdog(
    chain: EmulatedDynamixelChain, backend: DynamixelBackend
) -> None:
    # Generous bounds: the emulated chain and the backend's I/O thread share a busy machine.
    backend.write([MotorCommand(joint(3), velocity=1.0)])
    wait_until(lambda: chain.register(3, "present_velocity") > 35, 20.0, "moving")
    # The caller stalls until the watchdog expires.
    wait_until(lambda: chain.register(3, "bus_watchdog") == BUS_WATCHDOG_EXPIRED, 20.0, "expiry")
    # A write comes first after the pause: the goal must land, not be refused.
    backend.write([MotorCommand(joint(3), velocity=0.7)])
    wait_until(
        lambda: chain.register(3, "goal_velocity") == JointUnits(XM430, 1.0).velocity_units(0.7),
        20.0,
        "the new goal",
    )
    assert chain.register(3, "bus_watchdog") == 5
    wait_until(lambda: "bus watchdog" in diag(backend, joint(3)).message, 20.0, "the report")


def test_position_mode_and_close_leave_the_watchdog_off(chain: EmulatedDynamixelChain) -> None:
    motors = [MotorSpec(joint(i), i, "XM430-W350") for i in (1, 2)]
    dxl = DynamixelBackend(chain.port, motors, {**OPTIONS, "bus_watchdog_ms": 200})
    dxl.open()
    assert [chain.register(i, "bus_watchdog") for i in (1, 2)] == [0, 0]
    dxl.write([MotorCommand(joint(1), velocity=1.0), MotorCommand(joint(2), position=0.3)])
    wait_until(lambda: dxl.read() and chain.register(1, "bus_watchdog") == 10)  # 200 ms
    wait_until(lambda: abs(dxl.read()[joint(2)].position - 0.3) < 2 * TICK)
    assert chain.register(2, "bus_watchdog") == 0
    assert diag(dxl, joint(2)).values["bus_watchdog"] == "off"
    # Back to position: off again (a held position must not be dropped by a pause).
    dxl.write([MotorCommand(joint(1), position=0.0)])
    wait_until(lambda: dxl.read() and chain.register(1, "bus_watchdog") == 0)
    dxl.write([MotorCommand(joint(1), velocity=0.5)])
    wait_until(lambda: dxl.read() and chain.register(1, "bus_watchdog") == 10)
    dxl.close()
    wait_until(lambda: chain.register(1, "bus_watchdog") == 0)  # a reply-less SYNC_WRITE
    assert chain.register(1, "torque_enable") == 0
    time.sleep(0.3)  # longer than the period: nothing left to expire
    assert [chain.register(i, "bus_watchdog") for i in (1, 2)] == [0, 0]
    assert chain.watchdog(1)[2] == 0


def test_hold_on_close_stops_velocity_joints_and_disarms(chain: EmulatedDynamixelChain) -> None:
    motors = [MotorSpec(joint(1), 1, "XM430-W350")]
    with DynamixelBackend(chain.port, motors, {**OPTIONS, "hold_on_close": True}) as dxl:
        dxl.write([MotorCommand(joint(1), velocity=1.0)])
        wait_until(lambda: chain.register(1, "present_velocity") > 35)
    wait_until(lambda: chain.register(1, "bus_watchdog") == 0)
    assert chain.register(1, "goal_velocity") == 0
    assert chain.register(1, "torque_enable") == 1


def test_watchdog_option_zero_disables_it(chain: EmulatedDynamixelChain) -> None:
    motors = [MotorSpec(joint(1), 1, "XM430-W350")]
    with DynamixelBackend(chain.port, motors, {**OPTIONS, "bus_watchdog_ms": 0}) as dxl:
        dxl.write([MotorCommand(joint(1), velocity=1.0)])
        wait_until(lambda: chain.register(1, "present_velocity") > 35, what="turning")
        # The caller is silent longer than a watchdog would allow: the servo hears the I/O
        # thread for two periods (its own clock says when) and keeps turning.
        since = chain.watchdog(1)[0]
        wait_until(lambda: chain.watchdog(1)[0] > since + 2 * WATCHDOG_S, 15.0, "0.2 s heard")
        assert chain.register(1, "bus_watchdog") == 0
        assert chain.register(1, "present_velocity") > 35
    with pytest.raises(MotorError, match=r"bus_watchdog_ms"):
        DynamixelBackend(chain.port, motors, {"bus_watchdog_ms": 5000}).open()


def test_slow_paths_keep_feeding_armed_servos(chain: EmulatedDynamixelChain) -> None:
    # Three servos go silent at once and a fourth needs a reboot: retries, re-probes and the
    # boot wait each block for a reply timeout (~82 ms here), which would add up to several
    # hundred ms of silence towards joint 1 if nothing fed it in between.
    options = {**OPTIONS, "bus_watchdog_ms": 200, "reprobe_interval_s": 0.05}
    motors = [MotorSpec(joint(i), i, "XM430-W350") for i in IDS]
    with DynamixelBackend(chain.port, motors, options) as dxl:
        dxl.write([MotorCommand(joint(1), velocity=1.0)])
        wait_until(lambda: chain.register(1, "present_velocity") > 35)
        for i in (2, 3, 5):
            chain.silence(i)
        chain.set_hardware_error(4, 1 << 5)
        # The caller keeps calling (read every 20 ms) while the thread works through it all.
        wait_until(
            lambda: dxl.read() and [diag(dxl, joint(i)).level for i in (2, 3, 4, 5)] == [2] * 4,
            5.0,
            "silent servos and the hardware error reported",
        )
        dxl.recover()
        wait_until(lambda: dxl.read() and diag(dxl, joint(4)).level == 0, 5.0, "id 4 rebooted")
        assert chain.register(1, "bus_watchdog") == 10
        assert chain.watchdog(1)[2] == 0
        assert chain.register(1, "present_velocity") > 35
        assert diag(dxl, joint(1)).level == 0
