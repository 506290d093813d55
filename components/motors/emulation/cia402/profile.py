"""What the emulated drives are made of in CiA 301 / CiA 402 terms: states and the statusword
bits that encode them, modes, NMT states, SDO abort codes and error register bits."""

from __future__ import annotations

from pathlib import Path

#: The object dictionary the emulated drives serve (shared with the backend's default).
EDS_PATH = Path(__file__).resolve().parents[2] / "cia402_drive.eds"

# CiA 402 states and the statusword bits (0-3, 5, 6) that encode them.
NOT_READY_TO_SWITCH_ON = "NOT READY TO SWITCH ON"
SWITCH_ON_DISABLED = "SWITCH ON DISABLED"
READY_TO_SWITCH_ON = "READY TO SWITCH ON"
SWITCHED_ON = "SWITCHED ON"
OPERATION_ENABLED = "OPERATION ENABLED"
QUICK_STOP_ACTIVE = "QUICK STOP ACTIVE"
FAULT_REACTION_ACTIVE = "FAULT REACTION ACTIVE"
FAULT = "FAULT"

STATE_BITS = {
    NOT_READY_TO_SWITCH_ON: 0x0000,
    SWITCH_ON_DISABLED: 0x0040,
    READY_TO_SWITCH_ON: 0x0021,
    SWITCHED_ON: 0x0023,
    OPERATION_ENABLED: 0x0027,
    QUICK_STOP_ACTIVE: 0x0007,
    FAULT_REACTION_ACTIVE: 0x000F,
    FAULT: 0x0008,
}
POWERED = {READY_TO_SWITCH_ON, SWITCHED_ON, OPERATION_ENABLED, QUICK_STOP_ACTIVE}

MODE_PROFILE_POSITION = 1
MODE_PROFILE_VELOCITY = 3

# NMT states as carried in heartbeats.
NMT_BOOTUP, NMT_STOPPED, NMT_OPERATIONAL, NMT_PRE_OPERATIONAL = 0x00, 0x04, 0x05, 0x7F

# SDO abort codes (CiA 301) the server uses.
ABORT_COMMAND = 0x05040001
ABORT_READ_WRITE_ONLY = 0x06010001
ABORT_WRITE_READ_ONLY = 0x06010002
ABORT_NO_OBJECT = 0x06020000
ABORT_LENGTH = 0x06070010
ABORT_NO_SUBINDEX = 0x06090011
ABORT_VALUE_RANGE = 0x06090030
ABORT_GENERAL = 0x08000000

# Error register (0x1001) bits per EMCY error class.
REGISTER_GENERIC, REGISTER_CURRENT, REGISTER_VOLTAGE = 0x01, 0x02, 0x04
REGISTER_TEMPERATURE, REGISTER_COMMUNICATION = 0x08, 0x10

#: Error code a drive raises when the master's heartbeat stops (CiA 301 heartbeat error).
HEARTBEAT_ERROR = 0x8130
#: Error code of an over-temperature fault (CiA 301: excess ambient/device temperature).
OVER_TEMPERATURE = 0x4210


def error_register_for(code: int) -> int:
    """The 0x1001 bits a drive sets alongside an EMCY code (its class decides)."""
    group = code & 0xF000
    bits = REGISTER_GENERIC
    if group == 0x2000:
        bits |= REGISTER_CURRENT
    elif group == 0x3000:
        bits |= REGISTER_VOLTAGE
    elif group == 0x4000:
        bits |= REGISTER_TEMPERATURE
    elif code & 0xFF00 == 0x8100:
        bits |= REGISTER_COMMUNICATION
    return bits


class SdoAbort(Exception):
    """An SDO request the server refuses, with its CiA 301 abort code."""

    def __init__(self, code: int):
        super().__init__(f"SDO abort 0x{code:08X}")
        self.code = code
