"""What one step of the I/O thread does on the bus: the read cycle, the queued goals, a halt.

Bus traffic per read cycle is one SYNC_READ of the block ``present_current ..
present_temperature``; servos missing from the group reply get ``retries`` single READs, then
are reported not answering and re-probed every ``reprobe_interval_s``. Steps that can block
for a reply timeout are each followed by a feeding SYNC_READ of the armed servos
(:mod:`components.motors.dynamixel.watchdog`).
"""

from __future__ import annotations

import logging
import math
import time

from components.motors.base import MotorCommand, MotorState
from components.motors.dynamixel.control_table import (
    ALERT_BIT,
    OPERATING_MODES,
    POSITION_MODES,
    READ_BLOCK_START,
    SIGNED_REGISTERS,
    VELOCITY_MODE,
    hardware_error_text,
    to_signed,
)
from components.motors.dynamixel.port import NoAnswer
from components.motors.dynamixel.servo import Servo

log = logging.getLogger("components.motors.dynamixel")


class ChainCycle:
    """The bus work of the I/O thread (a mixin of
    :class:`~components.motors.dynamixel.backend.DynamixelBackend`).
    """

    retries: int
    reprobe_interval: float
    status_interval: float
    _servos: list[Servo]
    _by_joint: dict[str, Servo]
    _halts: int

    def _do_halt(self) -> None:
        """Velocity servos to goal 0 at once, position servos to where they are now."""
        self._halts += 1
        if self._port is None:
            return
        answering = [s for s in self._servos if s.answering]
        self._sync_write("goal_velocity", {s.sid: 0 for s in answering if s.mode == VELOCITY_MODE})
        holding = [s for s in answering if s.mode != VELOCITY_MODE]
        replies = self._sync_read_block(holding)
        stamp = time.time()
        positions: dict[int, int] = {}
        for servo in holding:
            if servo.sid in replies:
                self._decode(servo, replies[servo.sid][0], stamp)
            if servo.state is not None and servo.state.position is not None:
                positions[servo.sid] = self._clamp_ticks(
                    servo, servo.units.position_ticks(servo.state.position)
                )
        self._sync_write("goal_position", positions)

    def _read_cycle(self, now: float) -> None:
        if self._port is None:
            self._try_reopen(now)
            return
        self._check_watchdogs(now)
        live = [s for s in self._servos if s.answering and self._talks_to(s)]
        replies = self._sync_read_block(live)
        for servo in live:
            if servo.sid in replies:
                continue
            for _ in range(max(self.retries, 0)):
                self._feed_watchdogs()
                reply = self._read_block_single(servo)
                if reply is not None:
                    replies[servo.sid] = reply
                    break
            else:
                log.warning("%s: servo id %d not answering", servo.joint, servo.sid)
                servo.answering = False
                servo.torque_on = False
                servo.next_probe = now + self.reprobe_interval
        stamp = time.time()
        for servo in live:
            if servo.sid in replies:
                data, error = replies[servo.sid]
                self._decode(servo, data, stamp)
                self._track_alert(servo, error, now)
                self._feed_watchdogs()
        for servo in self._servos:
            if not servo.answering and now >= servo.next_probe and self._talks_to(servo):
                self._feed_watchdogs()
                if self._probe(servo, now):
                    reply = self._read_block_single(servo)
                    if reply is not None:
                        self._decode(servo, reply[0], time.time())
        self._feed_watchdogs()

    def _decode(self, servo: Servo, data: bytes, stamp: float) -> None:
        """The one place a state block becomes SI units."""
        model = servo.model

        def field_value(name: str) -> int:
            address, size = model.registers[name]
            offset = address - READ_BLOCK_START
            value = int.from_bytes(data[offset : offset + size], "little")
            return to_signed(value, size) if name in SIGNED_REGISTERS else value

        servo.voltage = field_value("present_input_voltage") * 0.1
        servo.state_at = time.monotonic()
        units = servo.units
        servo.state = MotorState(
            joint=servo.joint,
            position=units.position(field_value("present_position")),
            velocity=units.velocity(field_value("present_velocity")),
            effort=units.effort(field_value("present_current")),
            temperature=float(field_value("present_temperature")),
            stamp=stamp,
        )

    def _track_alert(self, servo: Servo, error: int, now: float) -> None:
        if not error & ALERT_BIT:
            servo.hardware_error = 0
            return
        if servo.hardware_error and now < servo.next_status_read:
            return
        servo.next_status_read = now + self.status_interval
        try:
            servo.hardware_error, _ = self._read_register(servo, "hardware_error_status")
            torque, _ = self._read_register(servo, "torque_enable")
            servo.torque_on = bool(torque)
        except NoAnswer:
            pass  # the next group read decides whether the servo is gone
        if servo.hardware_error:
            log.warning(
                "%s: servo id %d hardware error: %s",
                servo.joint,
                servo.sid,
                hardware_error_text(servo.hardware_error),
            )

    def _clamp_ticks(self, servo: Servo, ticks: int) -> int:
        if servo.mode == OPERATING_MODES["position"]:
            return max(servo.min_ticks, min(servo.max_ticks, ticks))
        return ticks

    def _write_commands(self, commands: list[MotorCommand]) -> None:
        # Before the goals: a servo whose watchdog expired would drop them without a word.
        self._check_watchdogs(time.monotonic())
        halts = self._halts
        positions: dict[int, int] = {}
        velocities: dict[int, int] = {}
        for command in commands:
            if self._halts != halts:
                return  # a halt came in between two mode switches: it wins over the rest
            servo = self._by_joint.get(command.joint)
            if servo is None or not servo.answering:
                continue
            if command.position is not None and math.isfinite(command.position):
                if servo.mode not in POSITION_MODES:
                    servo.mode = servo.position_mode  # so clamping uses the new mode's range
                    goal = self._clamp_ticks(servo, servo.units.position_ticks(command.position))
                    self._switch_mode(servo, servo.position_mode, goal)
                    self._feed_watchdogs()
                    continue
                positions[servo.sid] = self._clamp_ticks(
                    servo, servo.units.position_ticks(command.position)
                )
            elif command.velocity is not None and math.isfinite(command.velocity):
                units = servo.units.velocity_units(command.velocity)
                units = max(-servo.velocity_limit, min(servo.velocity_limit, units))
                if servo.mode != VELOCITY_MODE:
                    self._switch_mode(servo, VELOCITY_MODE, units)
                    self._feed_watchdogs()
                    continue
                velocities[servo.sid] = units
        if self._halts != halts:
            return
        self._sync_write("goal_position", positions)
        self._sync_write("goal_velocity", velocities)
