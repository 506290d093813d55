"""The CiA 402 drive profile as the backend speaks it: controlword commands, statusword states,
modes of operation, NMT states and what EMCY error codes mean (data, and two decoders)."""

from __future__ import annotations

from canopen.emcy import EmcyError

MODE_PROFILE_POSITION = 1
MODE_PROFILE_VELOCITY = 3
MODE_NAMES = {MODE_PROFILE_POSITION: "profile position", MODE_PROFILE_VELOCITY: "profile velocity"}

# Controlword commands (CiA 402, bits 0-3 and 7) and mode-specific bits.
CW_SHUTDOWN = 0x0006
CW_SWITCH_ON = 0x0007
CW_ENABLE_OPERATION = 0x000F
CW_FAULT_RESET = 0x0080
CW_NEW_SETPOINT = 0x0010
CW_CHANGE_IMMEDIATELY = 0x0020
CW_HALT = 0x0100
SW_SETPOINT_ACK = 0x1000

# (mask, value, state) in the order CiA 402 tells to decode the statusword.
STATUSWORD_STATES = (
    (0x4F, 0x00, "NOT READY TO SWITCH ON"),
    (0x4F, 0x40, "SWITCH ON DISABLED"),
    (0x6F, 0x21, "READY TO SWITCH ON"),
    (0x6F, 0x23, "SWITCHED ON"),
    (0x6F, 0x27, "OPERATION ENABLED"),
    (0x6F, 0x07, "QUICK STOP ACTIVE"),
    (0x4F, 0x0F, "FAULT REACTION ACTIVE"),
    (0x4F, 0x08, "FAULT"),
)

#: What common EMCY / 0x603F error codes mean (CiA 301 and CiA 402), for diagnostics.
EMCY_MEANINGS: dict[int, str] = {
    0x0000: "error reset / no error",
    0x1000: "generic error",
    0x2310: "continuous over-current",
    0x2320: "short circuit at outputs",
    0x2330: "earth leakage",
    0x3110: "mains over-voltage",
    0x3210: "DC link over-voltage",
    0x3220: "DC link under-voltage",
    0x4210: "over-temperature (device)",
    0x4310: "over-temperature (drive)",
    0x4320: "under-temperature (drive)",
    0x5000: "device hardware error",
    0x5530: "EEPROM/data storage error",
    0x6100: "internal software error",
    0x6320: "parameter error",
    0x7121: "motor blocked",
    0x7300: "sensor error",
    0x7305: "incremental encoder 1 broken",
    0x8110: "CAN overrun (frames lost)",
    0x8120: "CAN in error passive mode",
    0x8130: "life guard or heartbeat error (master lost)",
    0x8140: "recovered from bus off",
    0x8210: "PDO not processed (length error)",
    0x8611: "following error",
    0xFF00: "device specific error",
}


def emcy_meaning(code: int) -> str:
    """A short human meaning for an EMCY error code (exact code first, then its class)."""
    if code in EMCY_MEANINGS:
        return EMCY_MEANINGS[code]
    text = EmcyError(code, 0, b"", 0.0).get_desc()
    return f"{text.lower()} error" if text else "unknown error"


def decode_state(statusword: int) -> str:
    """The CiA 402 state a statusword encodes (``"OPERATION ENABLED"``...)."""
    for mask, value, name in STATUSWORD_STATES:
        if statusword & mask == value:
            return name
    return "UNKNOWN"


# Position set-point handshake phases (CiA 402 profile position, single set-point).
SP_IDLE, SP_REQUESTED, SP_RELEASING = "idle", "requested", "releasing"

#: NMT state OPERATIONAL as a heartbeat carries it (CiA 301).
NMT_OPERATIONAL = 0x05
