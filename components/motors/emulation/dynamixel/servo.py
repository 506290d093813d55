"""One emulated X-series servo: its control table (from the datasheet), motion physics, the
Bus Watchdog and fault state."""

from __future__ import annotations

from components.motors.emulation.dynamixel.datasheet import (
    BUS_WATCHDOG_EXPIRED,
    BUS_WATCHDOG_MAX_UNITS,
    BUS_WATCHDOG_UNIT_MS,
    OPERATING_MODES,
    RAM_START,
    TABLE_SIZE,
    ServoDatasheet,
)
from components.motors.emulation.dynamixel.protocol import (
    ALERT,
    ERR_ACCESS,
    ERR_DATA_LIMIT,
    ERR_DATA_RANGE,
)

#: The goal registers a Bus Watchdog expiry makes read-only until the watchdog is cleared.
GOAL_REGISTERS = ("goal_pwm", "goal_current", "goal_velocity", "goal_position")


class EmulatedServo:
    """One X-series servo: a control table, motion physics and fault state.

    Bus Watchdog (register 98), as the X-series e-manual describes it: 0 is off, 1..127 arms
    it in units of 20 ms. While torque is on and it is armed, a gap between instruction
    packets for this servo (:meth:`heard`) longer than the period stops the servo: Goal
    Velocity becomes 0 (a position-mode servo keeps its shaft where it is), the register
    reads 0xFF (-1), and writes to the goal registers are refused with a range error until
    0 is written to register 98. Which packets count is this emulator's reading of "all
    instruction packets": those addressed to the servo, broadcast ones, and SYNC ones that
    list it. There is no acceleration profile, so the stop is immediate.

    Attributes:
        heard_at: ``time.monotonic()`` of the last instruction packet for this servo.
        watchdog_expired_at: When the Bus Watchdog last expired (None: never).
        watchdog_trips: How many times it expired.
    """

    def __init__(self, dxl_id: int, model: ServoDatasheet, now: float):
        self.dxl_id = dxl_id
        self.model = model
        self.table = bytearray(TABLE_SIZE)
        self._read_only = [r for r in model.control_table.values() if r.access == "R"]
        self.silenced = False
        self.booting_until = 0.0
        self.heard_at = now
        self.watchdog_expired_at: float | None = None
        self.watchdog_trips = 0
        self._position = float(model.ticks_per_rev // 2)  # mid-range, as shipped
        self._t = now
        self._factory_defaults()
        self._ram_defaults()

    # -- control table --------------------------------------------------------------------

    def has(self, name: str) -> bool:
        """Whether this model's control table has the register."""
        return name in self.model.control_table

    def get(self, name: str) -> int:
        """A register's value (signed where the register is)."""
        register = self.model.control_table[name]
        address, size = register.address, register.size
        value = int.from_bytes(self.table[address : address + size], "little")
        if register.signed and value & (1 << (8 * size - 1)):
            value -= 1 << (8 * size)
        return value

    def set(self, name: str, value: int) -> None:
        """Store a register's value without protocol checks (for physics and fault hooks)."""
        register = self.model.control_table[name]
        address, size = register.address, register.size
        mask = (1 << (8 * size)) - 1
        self.table[address : address + size] = (int(value) & mask).to_bytes(size, "little")

    def _factory_defaults(self) -> None:
        model = self.model
        self.set("model_number", model.model_number)
        self.set("firmware_version", 48)
        self.set("id", self.dxl_id)
        self.set("baud_rate", 3)  # 1 Mbps
        self.set("return_delay_time", 250)
        self.set("operating_mode", OPERATING_MODES["position"])
        self.set("temperature_limit", model.temperature_limit)
        self.set("max_voltage_limit", 160)
        self.set("min_voltage_limit", 95)
        self.set("pwm_limit", 885)
        if self.has("current_limit"):
            self.set("current_limit", 1193)
        self.set("velocity_limit", round(model.no_load_speed_rpm / model.velocity_unit_rpm))
        self.set("max_position_limit", model.ticks_per_rev - 1)
        self.set("min_position_limit", 0)
        self.set("shutdown", 0b0011_0100)  # overheating, electrical shock, overload
        self.set("present_temperature", 35)

    def _ram_defaults(self) -> None:
        """What power-on (or REBOOT) leaves in RAM: torque off, goal = where the shaft is."""
        temperature = self.get("present_temperature")
        self.table[RAM_START:] = bytes(len(self.table) - RAM_START)
        self.set("status_return_level", 2)
        self.set("present_input_voltage", 120)
        self.set("present_temperature", temperature)
        self.set("goal_position", round(self._position))
        self.set("present_position", round(self._position))
        self.set("position_trajectory", round(self._position))

    def reboot(self, now: float, boot_time: float) -> None:
        """Restart: RAM to defaults, hardware error cleared, silent for ``boot_time``."""
        self._ram_defaults()
        self.booting_until = now + boot_time
        self._t = now

    def answering(self, now: float) -> bool:
        """Whether the servo would see and answer a packet now."""
        return not self.silenced and now >= self.booting_until

    def status_error(self) -> int:
        """The error byte of the next status packet (alert bit while any hardware error)."""
        return ALERT if self.get("hardware_error_status") else 0

    def raise_hardware_error(self, bits: int) -> None:
        """Set Hardware Error Status bits; shutdown bits turn torque off as the firmware does."""
        self.set("hardware_error_status", self.get("hardware_error_status") | bits)
        if bits & self.get("shutdown"):
            self.set("torque_enable", 0)

    def heard(self, now: float) -> None:
        """An instruction packet for this servo arrived: it feeds the Bus Watchdog.

        Motion is brought up to ``now`` first, so a watchdog that expired just before the
        packet still counts as expired.
        """
        self.step(now)
        self.heard_at = now

    def write(self, address: int, data: bytes) -> int:
        """A WRITE/SYNC_WRITE to this servo; returns the status error number (0 = done)."""
        end = address + len(data)
        if not data or end > len(self.table):
            return ERR_DATA_RANGE
        watchdog_expired = self.get("bus_watchdog") == BUS_WATCHDOG_EXPIRED
        if watchdog_expired and any(self._touches(name, address, end) for name in GOAL_REGISTERS):
            return ERR_DATA_RANGE  # goals are read-only until the watchdog error is cleared
        if any(r.address < end and address < r.address + r.size for r in self._read_only):
            return ERR_ACCESS
        if address < RAM_START and self.get("torque_enable"):
            return ERR_ACCESS  # EEPROM is locked while torque is on
        previous = bytes(self.table[address:end])
        self.table[address:end] = data
        error = self._check_limits(address, end)
        if not error and self._touches("bus_watchdog", address, end):
            value = self.get("bus_watchdog")
            # 1..127 arms, 0 disarms and is the only way out of the error state.
            if value > BUS_WATCHDOG_MAX_UNITS or (watchdog_expired and value != 0):
                error = ERR_DATA_RANGE
        if error:
            self.table[address:end] = previous
            return error
        self._after_write(address, end)
        return 0

    def _touches(self, name: str, address: int, end: int) -> bool:
        register = self.model.control_table.get(name)
        if register is None:
            return False  # not on this model
        return address < register.address + register.size and register.address < end

    def _check_limits(self, address: int, end: int) -> int:
        if self._touches("goal_position", address, end) and self.get("operating_mode") == 3:
            goal = self.get("goal_position")
            if not self.get("min_position_limit") <= goal <= self.get("max_position_limit"):
                return ERR_DATA_LIMIT
        too_fast = abs(self.get("goal_velocity")) > self.get("velocity_limit")
        if self._touches("goal_velocity", address, end) and too_fast:
            return ERR_DATA_LIMIT
        unknown_mode = self.get("operating_mode") not in OPERATING_MODES.values()
        if self._touches("operating_mode", address, end) and unknown_mode:
            return ERR_DATA_RANGE
        return 0

    def _after_write(self, address: int, end: int) -> None:
        shut_down = self.get("hardware_error_status") & self.get("shutdown")
        if self._touches("torque_enable", address, end) and shut_down:
            self.set("torque_enable", 0)  # shutdown holds until reboot
        if self._touches("operating_mode", address, end) and self.get("operating_mode") == 3:
            # Single-turn position mode works within one revolution.
            self._position %= self.model.ticks_per_rev
            self.set("present_position", round(self._position))

    # -- physics --------------------------------------------------------------------------

    def _watchdog_deadline(self) -> float | None:
        """When the armed Bus Watchdog expires unless a packet comes (None: not counting)."""
        units = self.get("bus_watchdog")
        if not self.get("torque_enable") or not 1 <= units <= BUS_WATCHDOG_MAX_UNITS:
            return None
        return self.heard_at + units * BUS_WATCHDOG_UNIT_MS / 1000.0

    def _expire_watchdog(self, when: float) -> None:
        self.set("goal_velocity", 0)
        if self.get("operating_mode") in (3, 4, 5):
            self.set("goal_position", round(self._position))
        self.set("bus_watchdog", BUS_WATCHDOG_EXPIRED)
        self.watchdog_expired_at = when
        self.watchdog_trips += 1

    def step(self, now: float) -> None:
        """Advance motion, current and thermal state (and the Bus Watchdog) to ``now``."""
        deadline = self._watchdog_deadline()
        if deadline is not None and deadline <= now:
            # Move at the old goal until the moment of expiry, then stop from there.
            self._advance(max(deadline, self._t))
            self._expire_watchdog(deadline)
        self._advance(now)

    def _advance(self, now: float) -> None:
        dt = now - self._t
        if dt <= 0:
            return
        self._t = now
        if self.get("present_temperature") > self.get("temperature_limit"):
            self.raise_hardware_error(1 << 2)
        ticks_per_unit = self.model.velocity_unit_rpm / 60.0 * self.model.ticks_per_rev
        mode = self.get("operating_mode")
        velocity = 0.0  # ticks/s
        tracking_error = 0.0
        if self.get("torque_enable") and self.answering(now):
            if mode in (3, 4, 5):
                goal = self.get("goal_position")
                if mode == 3:
                    goal = max(
                        self.get("min_position_limit"), min(self.get("max_position_limit"), goal)
                    )
                limit = self.get("profile_velocity") or self.get("velocity_limit")
                max_step = limit * ticks_per_unit * dt
                step = max(-max_step, min(max_step, goal - self._position))
                self._position += step
                velocity = step / dt
                tracking_error = goal - self._position
            elif mode == OPERATING_MODES["velocity"]:
                limit = self.get("velocity_limit")
                units = max(-limit, min(limit, self.get("goal_velocity")))
                velocity = units * ticks_per_unit
                self._position += velocity * dt
        velocity_units = round(velocity / ticks_per_unit)
        # A viscous term plus a holding term: enough to make current follow motion plausibly.
        # Present Load is in 0.1 % of stall torque: at most 100 %.
        limit = self.get("current_limit") if self.has("current_limit") else 1000
        effort = round(0.9 * velocity_units + 0.5 * tracking_error)
        self.set(self.model.effort_register, max(-limit, min(limit, effort)))
        self.set("present_velocity", velocity_units)
        self.set("velocity_trajectory", velocity_units)
        self.set("present_position", round(self._position))
        self.set("position_trajectory", round(self._position))
        self.set("moving", int(velocity_units != 0))
        tick = (self.get("realtime_tick") + round(dt * 1000)) % 32768
        self.set("realtime_tick", tick)
