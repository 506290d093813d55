"""Pinging a servo and bringing it up: operating mode, a goal that holds still, torque on.

The servo only accepts Operating Mode with torque off, and on torque on it drives to whatever
goal is in its RAM, so every mode change goes torque off, mode, goal, torque on.
"""

from __future__ import annotations

import logging
import time

from dynamixel_sdk import COMM_SUCCESS

from components.motors.dynamixel.control_table import ALERT_BIT, VELOCITY_MODE
from components.motors.dynamixel.port import NoAnswer
from components.motors.dynamixel.servo import Servo

log = logging.getLogger("components.motors.dynamixel")


class ServoBringUp:
    """Bring-up of a servo (a mixin of
    :class:`~components.motors.dynamixel.backend.DynamixelBackend`, run on its I/O thread).
    """

    reprobe_interval: float
    status_interval: float
    _watchdog_units: int

    def _probe(self, servo: Servo, now: float) -> bool:
        """Ping a servo; if it answers, bring it up. Returns whether it is answering now."""
        servo.next_probe = now + self.reprobe_interval
        if self._port is None:
            return False
        servo.sent_at = time.monotonic()
        model_number, result, error = self._packet.ping(self._port, servo.sid)
        self._release()
        if result != COMM_SUCCESS:
            servo.answering = False
            return False
        servo.model_number = model_number
        return self._bring_up_or_drop(servo, now, error)

    def _bring_up_or_drop(self, servo: Servo, now: float, status_error: int = 0) -> bool:
        try:
            self._bring_up(servo, status_error)
        except NoAnswer as exc:
            log.info("%s: servo id %d dropped during bring-up: %s", servo.joint, servo.sid, exc)
            servo.answering = False
            servo.torque_on = False
            servo.next_probe = now + self.reprobe_interval
            return False
        return True

    def _bring_up(self, servo: Servo, status_error: int) -> None:
        """Mode, limits, goal = present, profile, torque on. Raises NoAnswer if it goes silent."""
        servo.note = ""
        if status_error & ALERT_BIT:
            servo.hardware_error, _ = self._read_register(servo, "hardware_error_status")
        else:
            servo.hardware_error = 0
        target_mode = servo.mode if servo.mode is not None else servo.position_mode
        self._set_mode(servo, target_mode, goal=None)
        servo.min_ticks, _ = self._read_register(servo, "min_position_limit")
        servo.max_ticks, _ = self._read_register(servo, "max_position_limit")
        servo.velocity_limit, _ = self._read_register(servo, "velocity_limit")
        if servo.profile_velocity is not None:
            profile = abs(servo.units.velocity_units(servo.profile_velocity))
            self._write_register(servo, "profile_velocity", profile)
        self._enable_torque(servo)
        servo.answering = True
        servo.ever_answered = True
        if servo.hardware_error:
            servo.next_status_read = time.monotonic() + self.status_interval

    def _set_mode(self, servo: Servo, mode: int, goal: int | None) -> None:
        """Put the servo in ``mode`` with a goal that holds still (or ``goal``), torque off.

        The servo only accepts Operating Mode with torque off, and on torque on it drives to
        whatever goal is in its RAM, so the goal is written before torque comes back.
        """
        self._write_register(servo, "torque_enable", 0)
        servo.torque_on = False
        # Cleared first: after an expiry the servo ignores goal writes until it reads 0.
        self._disarm_watchdog(servo)
        current, _ = self._read_register(servo, "operating_mode")
        if current != mode:
            self._write_register(servo, "operating_mode", mode)
        servo.mode = mode
        if mode == VELOCITY_MODE:
            self._write_register(servo, "goal_velocity", 0 if goal is None else goal)
            if self._watchdog_units:
                # Armed with torque still off: it starts counting when torque comes on.
                self._write_register(servo, "bus_watchdog", self._watchdog_units)
                servo.watchdog_units = self._watchdog_units
                servo.next_watchdog_check = time.monotonic() + self.status_interval
        else:
            if goal is None:
                goal, _ = self._read_register(servo, "present_position")
            self._write_register(servo, "goal_position", goal)

    def _enable_torque(self, servo: Servo) -> None:
        # Read back: a servo in hardware-error shutdown acknowledges the write but stays off.
        self._write_register(servo, "torque_enable", 1)
        torque, _ = self._read_register(servo, "torque_enable")
        servo.torque_on = bool(torque)

    def _switch_mode(self, servo: Servo, mode: int, goal: int) -> None:
        try:
            self._set_mode(servo, mode, goal)
            self._enable_torque(servo)
        except NoAnswer:
            servo.answering = False
            servo.torque_on = False
            servo.next_probe = time.monotonic() + self.reprobe_interval
