"""The Dynamixel X-series control table (Protocol 2.0) as the backend uses it, and what its
values mean: operating modes, hardware error bits, the Bus Watchdog's units.

Register maps are data (LeRobot's habit): addresses and sizes here, conversions in
:mod:`components.motors.dynamixel.units`. The emulated chain keeps its own map, written from
the datasheet, so a wrong address here fails a test instead of agreeing with itself.
"""

from __future__ import annotations

#: X-series (Protocol 2.0) control table: name -> (address, size in bytes).
X_SERIES_REGISTERS: dict[str, tuple[int, int]] = {
    "model_number": (0, 2),
    "firmware_version": (6, 1),
    "id": (7, 1),
    "baud_rate": (8, 1),
    "return_delay_time": (9, 1),
    "drive_mode": (10, 1),
    "operating_mode": (11, 1),
    "homing_offset": (20, 4),
    "temperature_limit": (31, 1),
    "max_voltage_limit": (32, 2),
    "min_voltage_limit": (34, 2),
    "pwm_limit": (36, 2),
    "current_limit": (38, 2),
    "velocity_limit": (44, 4),
    "max_position_limit": (48, 4),
    "min_position_limit": (52, 4),
    "shutdown": (63, 1),
    "torque_enable": (64, 1),
    "led": (65, 1),
    "status_return_level": (68, 1),
    "hardware_error_status": (70, 1),
    "bus_watchdog": (98, 1),
    "goal_pwm": (100, 2),
    "goal_current": (102, 2),
    "goal_velocity": (104, 4),
    "profile_acceleration": (108, 4),
    "profile_velocity": (112, 4),
    "goal_position": (116, 4),
    "realtime_tick": (120, 2),
    "moving": (122, 1),
    "moving_status": (123, 1),
    "present_pwm": (124, 2),
    "present_current": (126, 2),
    "present_velocity": (128, 4),
    "present_position": (132, 4),
    "velocity_trajectory": (136, 4),
    "position_trajectory": (140, 4),
    "present_input_voltage": (144, 2),
    "present_temperature": (146, 1),
}

#: The XL430-W250's: no current sensing, so no Current Limit and no Goal Current; Present Load
#: (0.1 % of stall torque) sits where the others have Present Current and is read under that
#: name (its model's ``effort_register`` says it is a load).
XL430_REGISTERS: dict[str, tuple[int, int]] = {
    name: item
    for name, item in X_SERIES_REGISTERS.items()
    if name not in ("current_limit", "goal_current")
}

#: Registers whose raw value is two's-complement signed.
SIGNED_REGISTERS = frozenset(
    {
        "homing_offset",
        "goal_pwm",
        "goal_current",
        "goal_velocity",
        "goal_position",
        "present_pwm",
        "present_current",
        "present_velocity",
        "present_position",
        "velocity_trajectory",
        "position_trajectory",
        "max_position_limit",
        "min_position_limit",
    }
)

#: Operating Mode (address 11) values by name.
OPERATING_MODES: dict[str, int] = {
    "current": 0,
    "velocity": 1,
    "position": 3,
    "extended_position": 4,
    "current_position": 5,
    "pwm": 16,
}
POSITION_MODES = frozenset({3, 4, 5})
VELOCITY_MODE = OPERATING_MODES["velocity"]

#: Hardware Error Status (address 70) bit -> meaning.
HARDWARE_ERROR_BITS: dict[int, str] = {
    0: "input voltage error",
    2: "overheating",
    3: "motor encoder error",
    4: "electrical shock",
    5: "overload",
}
ALERT_BIT = 0x80

#: Bus Watchdog (address 98): one unit in ms, the largest period in units, and the value the
#: servo shows once it has expired (-1 as a signed byte) until 0 is written.
BUS_WATCHDOG_UNIT_MS = 20
BUS_WATCHDOG_MAX_UNITS = 127
BUS_WATCHDOG_EXPIRED = 0xFF

#: The block read every cycle: present current up to and including present temperature.
READ_BLOCK_START = X_SERIES_REGISTERS["present_current"][0]
READ_BLOCK_LENGTH = X_SERIES_REGISTERS["present_temperature"][0] + 1 - READ_BLOCK_START


def to_signed(value: int, size: int) -> int:
    """Two's-complement interpretation of an unsigned little-endian register value."""
    bits = 8 * size
    return value - (1 << bits) if value & (1 << (bits - 1)) else value


def hardware_error_text(bits: int) -> str:
    """Human meaning of a Hardware Error Status value, e.g. ``"overheating, overload"``."""
    names = [text for bit, text in HARDWARE_ERROR_BITS.items() if bits & (1 << bit)]
    unknown = bits & ~sum(1 << bit for bit in HARDWARE_ERROR_BITS)
    if unknown:
        names.append(f"unknown bits 0x{unknown:02x}")
    return ", ".join(names)
