"""What a drive's state means to an operator (diagnostics, levels and hints)."""

from __future__ import annotations

from components.motors.base import ERROR, OK, WARN, MotorDiagnostic
from components.motors.canopen.cia402 import MODE_NAMES, emcy_meaning
from components.motors.canopen.drive import Drive


def drive_diagnostic(d: Drive, now: float, channel: str, bus_error: str | None) -> MotorDiagnostic:
    """One drive's health for the operator, the most urgent finding first."""
    joint = d.spec.joint
    who = f"{joint}: drive node {d.node_id}"
    state = d.state
    values = {
        "node_id": str(d.node_id),
        "channel": channel,
        "state": state or "unknown",
        "mode": MODE_NAMES.get(d.mode_display or 0, str(d.mode_display)),
    }
    if d.statusword is not None:
        values["statusword"] = f"0x{d.statusword:04X}"
    if d.heartbeat_at is not None:
        values["heartbeat_age"] = f"{now - d.heartbeat_at:.2f}"
    if d.error_code:
        values["error_code"] = f"0x{d.error_code:04X}"
    if d.temperature is not None:
        values["temperature"] = f"{d.temperature:.1f}"
    if d.emcys:
        values["emcy"] = ",".join(f"0x{e.code:04X}" for e in d.emcys)
    if bus_error:
        return MotorDiagnostic(joint, ERROR, f"{who}: unreachable, the bus is down", values)
    if d.ever_configured and d.lost_since is not None:
        silent = now - d.lost_since
        return MotorDiagnostic(
            joint,
            ERROR,
            f"{who} stopped answering (no heartbeat for {silent:.1f} s); check its power "
            "and cable, it is picked up again when it returns",
            values,
        )
    if not d.ever_configured:
        why = d.config_error or "no answer yet"
        return MotorDiagnostic(
            joint,
            ERROR if d.config_error else WARN,
            f"{who} not answering on {channel} ({why}); check its power, cable and node id",
            values,
        )
    if d.emcys:
        codes = "; ".join(f"0x{e.code:04X} {emcy_meaning(e.code)}" for e in d.emcys)
        return MotorDiagnostic(
            joint, ERROR, f"{who} emergency {codes}; call recover() to fault-reset", values
        )
    if state == "FAULT":
        meaning = emcy_meaning(d.error_code) if d.error_code else "no error code"
        hint = "resetting" if d.auto_reset else "call recover() to fault-reset"
        return MotorDiagnostic(
            joint, ERROR, f"{who} in FAULT (0x{d.error_code:04X} {meaning}); {hint}", values
        )
    if not d.configured or state != "OPERATION ENABLED":
        return MotorDiagnostic(joint, WARN, f"{who} enabling ({state or 'starting'})", values)
    mode = MODE_NAMES.get(d.mode_display or 0, f"mode {d.mode_display}")
    halted = ", halted" if d.halted else ""
    return MotorDiagnostic(joint, OK, f"{who} operation enabled, {mode}{halted}", values)
