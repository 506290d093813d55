"""The emulated servos' control tables and constants, written from the ROBOTIS e-manual.

This map is the emulator's own, copied from the X-series datasheets (Protocol 2.0 control
tables of the XM430, XM540, XH430, XL430 and XL330), never from the driver's table in
:mod:`components.motors.dynamixel.control_table`: a wrong address in the driver then reads the
wrong bytes of an emulated servo and fails a test, instead of agreeing with itself
(``tests/test_dynamixel_datasheet.py`` compares the two).

Addresses, sizes and access are the e-manual's; ``signed`` follows each register's range in
the e-manual (a range below zero is two's complement). The gains, indirect addresses and
indirect data are listed for completeness: the emulator stores them and does nothing with them.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class Register:
    """One control table item.

    Attributes:
        address: First byte.
        size: Bytes, little-endian.
        access: ``"R"`` (read only) or ``"RW"``.
        signed: Whether its range goes below zero (two's complement).
    """

    address: int
    size: int
    access: str = "RW"
    signed: bool = False


def _x_series() -> dict[str, Register]:
    """The control table shared by the XM430, XM540, XH430 and XL330 (e-manual, Protocol 2.0)."""
    ro, signed = "R", True
    table = {
        # EEPROM area: writable only with torque off.
        "model_number": Register(0, 2, ro),
        "model_information": Register(2, 4, ro),
        "firmware_version": Register(6, 1, ro),
        "id": Register(7, 1),
        "baud_rate": Register(8, 1),
        "return_delay_time": Register(9, 1),
        "drive_mode": Register(10, 1),
        "operating_mode": Register(11, 1),
        "secondary_id": Register(12, 1),
        "protocol_type": Register(13, 1),
        "homing_offset": Register(20, 4, signed=signed),
        "moving_threshold": Register(24, 4),
        "temperature_limit": Register(31, 1),
        "max_voltage_limit": Register(32, 2),
        "min_voltage_limit": Register(34, 2),
        "pwm_limit": Register(36, 2),
        "current_limit": Register(38, 2),
        "velocity_limit": Register(44, 4),
        "max_position_limit": Register(48, 4),
        "min_position_limit": Register(52, 4),
        "shutdown": Register(63, 1),
        # RAM area.
        "torque_enable": Register(64, 1),
        "led": Register(65, 1),
        "status_return_level": Register(68, 1),
        "registered_instruction": Register(69, 1, ro),
        "hardware_error_status": Register(70, 1, ro),
        "velocity_i_gain": Register(76, 2),
        "velocity_p_gain": Register(78, 2),
        "position_d_gain": Register(80, 2),
        "position_i_gain": Register(82, 2),
        "position_p_gain": Register(84, 2),
        "feedforward_2nd_gain": Register(88, 2),
        "feedforward_1st_gain": Register(90, 2),
        "bus_watchdog": Register(98, 1),
        "goal_pwm": Register(100, 2, signed=signed),
        "goal_current": Register(102, 2, signed=signed),
        "goal_velocity": Register(104, 4, signed=signed),
        "profile_acceleration": Register(108, 4),
        "profile_velocity": Register(112, 4),
        "goal_position": Register(116, 4, signed=signed),
        "realtime_tick": Register(120, 2, ro),
        "moving": Register(122, 1, ro),
        "moving_status": Register(123, 1, ro),
        "present_pwm": Register(124, 2, ro, signed),
        "present_current": Register(126, 2, ro, signed),
        "present_velocity": Register(128, 4, ro, signed),
        "present_position": Register(132, 4, ro, signed),
        "velocity_trajectory": Register(136, 4, ro, signed),
        "position_trajectory": Register(140, 4, ro, signed),
        "present_input_voltage": Register(144, 2, ro),
        "present_temperature": Register(146, 1, ro),
        "backup_ready": Register(147, 1, ro),
    }
    for n in range(28):
        table[f"indirect_address_{n + 1}"] = Register(168 + 2 * n, 2)
        table[f"indirect_data_{n + 1}"] = Register(224 + n, 1)
        table[f"indirect_address_{n + 29}"] = Register(578 + 2 * n, 2)
        table[f"indirect_data_{n + 29}"] = Register(634 + n, 1)
    return table


def _xl430() -> dict[str, Register]:
    """The XL430-W250's table: no current sensing, so no Current Limit and no Goal Current,
    and Present Load (0.1 % of stall torque) where the others have Present Current."""
    table = {
        name: register
        for name, register in _x_series().items()
        if name not in ("current_limit", "goal_current", "present_current")
    }
    table["present_load"] = Register(126, 2, "R", True)
    return table


X_SERIES_TABLE = _x_series()
XL430_TABLE = _xl430()

#: Bytes of the control table: up to the end of Indirect Data 56.
TABLE_SIZE = 662
#: Where the RAM area starts (Torque Enable): below it is EEPROM, locked while torque is on.
RAM_START = X_SERIES_TABLE["torque_enable"].address

#: Operating Mode (address 11) values.
OPERATING_MODES: dict[str, int] = {
    "current": 0,
    "velocity": 1,
    "position": 3,
    "extended_position": 4,
    "current_position": 5,
    "pwm": 16,
}

#: Bus Watchdog (address 98): 1..127 arms it in units of 20 ms; it reads 0xFF (-1) once it
#: expired, until 0 is written.
BUS_WATCHDOG_UNIT_MS = 20
BUS_WATCHDOG_MAX_UNITS = 127
BUS_WATCHDOG_EXPIRED = 0xFF


@dataclass(frozen=True)
class ServoDatasheet:
    """What the emulator takes from one model's datasheet.

    Attributes:
        name: Model name as module data writes it.
        model_number: What PING and Model Number (address 0) report.
        no_load_speed_rpm: Output speed without load at the rated voltage (its motion limit
            and the default Velocity Limit).
        temperature_limit: Default Temperature Limit, °C.
        control_table: Register name -> item.
        effort_register: ``present_current``, or ``present_load`` on a model without
            current sensing.
        velocity_unit_rpm: One Velocity unit.
        ticks_per_rev: Position resolution.
    """

    name: str
    model_number: int
    no_load_speed_rpm: float
    temperature_limit: int = 80
    control_table: dict[str, Register] = field(default_factory=lambda: X_SERIES_TABLE)
    effort_register: str = "present_current"
    velocity_unit_rpm: float = 0.229
    ticks_per_rev: int = 4096


MODELS: dict[str, ServoDatasheet] = {
    sheet.name: sheet
    for sheet in (
        ServoDatasheet("XM430-W350", 1020, no_load_speed_rpm=46.0),
        ServoDatasheet("XM430-W210", 1030, no_load_speed_rpm=77.0),
        ServoDatasheet("XM540-W270", 1120, no_load_speed_rpm=30.0),
        ServoDatasheet("XM540-W150", 1130, no_load_speed_rpm=53.0),
        ServoDatasheet("XH430-W350", 1010, no_load_speed_rpm=46.0),
        ServoDatasheet(
            "XL430-W250",
            1060,
            no_load_speed_rpm=57.0,
            temperature_limit=72,
            control_table=XL430_TABLE,
            effort_register="present_load",
        ),
        ServoDatasheet("XL330-M288", 1200, no_load_speed_rpm=103.0, temperature_limit=70),
    )
}
