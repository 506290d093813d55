"""The emulated drive's behaviour: its CiA 402 state machine driven by the controlword, the
statusword it reports, faults, monitoring (temperature, the master's heartbeat) and profile
position / profile velocity motion with a plausible torque model."""

from __future__ import annotations

import math
import struct
from typing import Any

from components.motors.emulation.cia402.profile import (
    FAULT,
    FAULT_REACTION_ACTIVE,
    HEARTBEAT_ERROR,
    MODE_PROFILE_POSITION,
    MODE_PROFILE_VELOCITY,
    NOT_READY_TO_SWITCH_ON,
    OPERATION_ENABLED,
    OVER_TEMPERATURE,
    POWERED,
    QUICK_STOP_ACTIVE,
    READY_TO_SWITCH_ON,
    STATE_BITS,
    SWITCH_ON_DISABLED,
    SWITCHED_ON,
    error_register_for,
)


class DriveMotion:
    """The drive's state machine and motion (a mixin of
    :class:`~components.motors.emulation.cia402.drive.EmulatedCia402Drive`; the bus lock is
    held by whoever calls in).
    """

    node_id: int
    temperature_limit: float
    torque_per_acceleration: float
    torque_per_velocity: float
    _values: dict[tuple[int, int], Any]
    _state: str
    _controlword: int
    _position: float
    _velocity: float
    _acceleration: float
    _torque: int
    _load: float
    _temperature: float
    _pp_target: float
    _pp_velocity: float
    _setpoint_ack: bool
    _master_heartbeat_at: float | None
    _heartbeat_tripped: bool

    def _statusword(self) -> int:
        word = STATE_BITS[self._state] | 0x0200  # bit 9: remote (controlled over CAN)
        if self._state in POWERED:
            word |= 0x0010  # voltage enabled
        if self._temperature > self.temperature_limit - 10.0:
            word |= 0x0080  # warning
        if self._state == OPERATION_ENABLED:
            mode = int(self._values[(0x6060, 0)])
            halted = bool(self._controlword & 0x0100)
            if mode == MODE_PROFILE_POSITION:
                settled = abs(self._velocity) < 1.0
                if (halted and settled) or (
                    not halted and abs(self._pp_target - self._position) < 1.0 and settled
                ):
                    word |= 0x0400  # target reached
                if self._setpoint_ack:
                    word |= 0x1000  # set-point acknowledge
            elif mode == MODE_PROFILE_VELOCITY:
                target = 0.0 if halted else float(self._values[(0x60FF, 0)])
                if abs(self._velocity - target) < 1.0:
                    word |= 0x0400
                if abs(self._velocity) < 1.0:
                    word |= 0x1000  # speed = 0
        return word

    def _on_controlword(self, word: int) -> None:
        previous, self._controlword = self._controlword, word
        state = self._state
        if state == FAULT:
            if word & 0x80 and not previous & 0x80:
                if self._temperature > self.temperature_limit:
                    self._fault(OVER_TEMPERATURE)  # still hot: the fault stays
                    return
                self._state = SWITCH_ON_DISABLED
                self._values[(0x603F, 0)] = 0
                self._values[(0x1001, 0)] = 0
                self._send(0x80 + self.node_id, bytes(8))  # EMCY "error reset / no error"
            return
        if state in (FAULT_REACTION_ACTIVE, NOT_READY_TO_SWITCH_ON) or word & 0x80:
            return
        new = state
        if not word & 0x02:  # disable voltage
            new = SWITCH_ON_DISABLED
        elif not word & 0x04:  # quick stop
            stopping = state in (OPERATION_ENABLED, QUICK_STOP_ACTIVE)
            new = QUICK_STOP_ACTIVE if stopping else SWITCH_ON_DISABLED
        elif not word & 0x01:  # shutdown
            if state in (SWITCH_ON_DISABLED, SWITCHED_ON, OPERATION_ENABLED):
                new = READY_TO_SWITCH_ON
        elif not word & 0x08:  # switch on / disable operation
            if state in (READY_TO_SWITCH_ON, OPERATION_ENABLED):
                new = SWITCHED_ON
        elif state in (READY_TO_SWITCH_ON, SWITCHED_ON, QUICK_STOP_ACTIVE):  # enable operation
            new = OPERATION_ENABLED
        if new == OPERATION_ENABLED and state != OPERATION_ENABLED:
            # Entering operation holds where the motor is: no jump to a stale target.
            self._pp_target = self._position
            self._setpoint_ack = False
        self._state = new
        if new == OPERATION_ENABLED and self._values[(0x6060, 0)] == MODE_PROFILE_POSITION:
            new_setpoint = bool(word & 0x10)
            if new_setpoint and not previous & 0x10:
                self._pp_target = float(self._values[(0x607A, 0)])
                self._pp_velocity = float(self._values[(0x6081, 0)])
                self._setpoint_ack = True
            elif not new_setpoint:
                self._setpoint_ack = False

    def _fault(self, code: int, data: bytes = b"") -> None:
        register = error_register_for(code)
        self._values[(0x603F, 0)] = code
        self._values[(0x1001, 0)] = register
        self._state = FAULT
        self._setpoint_ack = False
        self._send(0x80 + self.node_id, struct.pack("<HB5s", code, register, data[:5]))

    def _monitor(self, now: float) -> None:
        if self._temperature > self.temperature_limit and self._state != FAULT:
            self._fault(OVER_TEMPERATURE)
        consumer = int(self._values[(0x1016, 1)])
        timeout = (consumer & 0xFFFF) / 1000.0
        if (
            consumer
            and timeout > 0
            and self._master_heartbeat_at is not None
            and not self._heartbeat_tripped
            and now - self._master_heartbeat_at > timeout
        ):
            self._heartbeat_tripped = True
            if self._state in POWERED:
                self._fault(HEARTBEAT_ERROR)

    def _move(self, dt: float) -> None:
        if dt <= 0:
            return
        acceleration = float(self._values[(0x6083, 0)])
        deceleration = float(self._values[(0x6084, 0)])
        quick_stop = float(self._values[(0x6085, 0)])
        mode = int(self._values[(0x6060, 0)])
        halted = bool(self._controlword & 0x0100)
        v = self._velocity
        pp_active = False
        if self._state == OPERATION_ENABLED and not halted:
            if mode == MODE_PROFILE_POSITION:
                pp_active = True
                error = self._pp_target - self._position
                # A little margin on the braking curve absorbs the thread's tick jitter.
                reach = math.sqrt(2.0 * 0.8 * deceleration * abs(error))
                wanted = math.copysign(min(self._pp_velocity, reach), error)
            elif mode == MODE_PROFILE_VELOCITY:
                wanted = float(self._values[(0x60FF, 0)])
            else:
                wanted = 0.0
            limit = acceleration if abs(wanted) > abs(v) else deceleration
        elif self._state == OPERATION_ENABLED:
            wanted, limit = 0.0, deceleration
            if mode == MODE_PROFILE_POSITION and abs(v) < 1.0:
                self._pp_target = self._position  # halted: hold here
        else:
            wanted, limit = 0.0, quick_stop
        # Max torque (0x6072) caps what is left for accelerating once friction and load
        # are paid for: an effort limit really limits the motion.
        max_torque = float(self._values[(0x6072, 0)])
        spare = max_torque - abs(self.torque_per_velocity * v) - abs(self._load)
        if self._state == OPERATION_ENABLED:
            limit = min(limit, max(spare, 0.0) / self.torque_per_acceleration)
        change = max(-limit * dt, min(limit * dt, wanted - v))
        new_v = v + change
        before = self._pp_target - self._position
        self._position += 0.5 * (v + new_v) * dt
        after = self._pp_target - self._position
        # Arrived (or stepped across the target at crawl speed): settle exactly on it.
        crossed = after == 0 or (before > 0) != (after > 0)
        if pp_active and (abs(after) < 0.5 or (crossed and abs(new_v) <= 2 * limit * dt + 1)):
            self._position, new_v = self._pp_target, 0.0
        self._acceleration = (new_v - v) / dt
        self._velocity = new_v
        # Quick stop option codes 1-4 end in SWITCH ON DISABLED once stopped; 5-8 stay.
        option = int(self._values[(0x605A, 0)])
        if self._state == QUICK_STOP_ACTIVE and abs(new_v) < 1.0 and 1 <= option <= 4:
            self._state = SWITCH_ON_DISABLED
        torque = 0.0
        if self._state == OPERATION_ENABLED or self._state == QUICK_STOP_ACTIVE:
            torque = (
                self.torque_per_acceleration * self._acceleration
                + self.torque_per_velocity * new_v
                + self._load
            )
            torque = max(-max_torque, min(max_torque, torque))
        self._torque = round(torque)
