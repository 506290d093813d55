"""What a servo's state and the chain's mean to an operator (diagnostics, levels and hints)."""

from __future__ import annotations

import time

from components.motors.base import ERROR, OK, WARN, MotorDiagnostic
from components.motors.dynamixel.control_table import (
    BUS_WATCHDOG_UNIT_MS,
    OPERATING_MODES,
    hardware_error_text,
)
from components.motors.dynamixel.servo import Servo
from components.motors.dynamixel.units import MODELS_BY_NUMBER


def servo_diagnostic(servo: Servo) -> MotorDiagnostic:
    """One servo's health for the operator, the most urgent finding first."""
    values = {"id": str(servo.sid), "model": servo.model.name}
    if servo.mode is not None:
        mode_name = {v: k for k, v in OPERATING_MODES.items()}.get(servo.mode, str(servo.mode))
        values["operating_mode"] = mode_name
    values["torque"] = "on" if servo.torque_on else "off"
    state = servo.state
    if state is not None and state.temperature is not None:
        values["temperature_c"] = f"{state.temperature:.0f}"
    if servo.voltage is not None:
        values["input_voltage_v"] = f"{servo.voltage:.1f}"
    values["hardware_error_status"] = f"0x{servo.hardware_error:02x}"
    values["bus_watchdog"] = (
        f"{servo.watchdog_units * BUS_WATCHDOG_UNIT_MS} ms" if servo.watchdog_units else "off"
    )
    values["bus_watchdog_trips"] = str(servo.watchdog_trips)
    if servo.watchdog_gap is not None:
        values["bus_watchdog_last_gap_ms"] = f"{servo.watchdog_gap * 1000:.0f}"
    prefix = f"{servo.joint}: servo id {servo.sid}"
    if not servo.answering:
        hint = "" if servo.ever_answered else " (check id, baud rate and cable)"
        return MotorDiagnostic(servo.joint, ERROR, f"{prefix} not answering{hint}", values)
    if servo.hardware_error:
        return MotorDiagnostic(
            servo.joint,
            ERROR,
            f"{prefix} hardware error: {hardware_error_text(servo.hardware_error)}; "
            "call recover to reboot it",
            values,
        )
    if state is not None and state.temperature is not None:
        if state.temperature >= servo.temperature_limit:
            return MotorDiagnostic(
                servo.joint,
                ERROR,
                f"{prefix} over temperature: {state.temperature:.0f} °C "
                f"(limit {servo.temperature_limit:.0f} °C)",
                values,
            )
        if state.temperature >= servo.temperature_limit - 5:
            return MotorDiagnostic(
                servo.joint,
                WARN,
                f"{prefix} hot: {state.temperature:.0f} °C "
                f"(limit {servo.temperature_limit:.0f} °C)",
                values,
            )
    if servo.watchdog_report and time.monotonic() < servo.watchdog_report_until:
        return MotorDiagnostic(servo.joint, WARN, servo.watchdog_report, values)
    if servo.model_number is not None and servo.model_number != servo.model.model_number:
        seen = MODELS_BY_NUMBER.get(servo.model_number)
        seen_name = seen.name if seen else f"model number {servo.model_number}"
        return MotorDiagnostic(
            servo.joint,
            WARN,
            f"{prefix} is a {seen_name}, module data says {servo.model.name}: fix the data",
            values,
        )
    if not servo.torque_on:
        return MotorDiagnostic(
            servo.joint, WARN, f"{prefix} torque off {servo.note}".rstrip(), values
        )
    return MotorDiagnostic(servo.joint, OK, "OK", values)


def bus_diagnostic(
    channel: str, baudrate: int, bus_error: str, reopen_interval: float, servos: list[Servo]
) -> MotorDiagnostic:
    """The chain's health (``joint == ""``): lost, some servos silent, or every one answering."""
    answering = sum(s.answering for s in servos)
    bus_values = {"channel": channel, "baudrate": str(baudrate)}
    if bus_error:
        return MotorDiagnostic(
            "",
            ERROR,
            f"dynamixel bus {channel} lost ({bus_error}); reopening every "
            f"{reopen_interval:g} s: check the USB cable and adapter power",
            bus_values,
        )
    if answering < len(servos):
        return MotorDiagnostic(
            "",
            WARN,
            f"dynamixel bus {channel}: {answering}/{len(servos)} servos answering",
            bus_values,
        )
    return MotorDiagnostic(
        "", OK, f"dynamixel bus {channel}: {answering} servos answering", bus_values
    )
