"""An emulated chain of CiA 402 servo drives on a python-can bus.

Each :class:`EmulatedCia402Drive` speaks real CANopen framing (CiA 301: NMT, heartbeat
producer and consumer, expedited SDO server, four RPDOs and four TPDOs with configurable
mapping, SYNC, EMCY) and runs the CiA 402 drive state machine driven by the controlword,
with profile position (mode 1) and profile velocity (mode 3) motion. Position is in encoder
counts, velocity in counts/s, torque and current in per-mille of rated, exactly like a real
drive, so the backend's unit conversion is exercised for real.

One background thread serves every drive of one :class:`EmulatedCia402Bus`. Fault injection
for tests and demos: :meth:`EmulatedCia402Drive.silence` / :meth:`~EmulatedCia402Drive.resume`
(a cut cable), :meth:`~EmulatedCia402Drive.raise_fault` (EMCY + FAULT state),
:meth:`~EmulatedCia402Drive.set_temperature` (over-temperature above the limit) and
:meth:`~EmulatedCia402Drive.set_load` (an external torque the drive has to hold).

Example::

    with EmulatedCia402Bus(channel="demo", node_ids=[1, 2, 3]) as bus:
        ...  # open a CanopenBackend on interface "virtual", channel "demo"
        bus.drive(2).silence()
"""

from __future__ import annotations

import logging
import math
import struct
import threading
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import can
import canopen
from canopen.objectdictionary import ODVariable

logger = logging.getLogger(__name__)

#: The object dictionary the emulated drives serve (shared with the backend's default).
EDS_PATH = Path(__file__).resolve().parent.parent / "cia402_drive.eds"

# CiA 402 states and the statusword bits (0-3, 5, 6) that encode them.
NOT_READY_TO_SWITCH_ON = "NOT READY TO SWITCH ON"
SWITCH_ON_DISABLED = "SWITCH ON DISABLED"
READY_TO_SWITCH_ON = "READY TO SWITCH ON"
SWITCHED_ON = "SWITCHED ON"
OPERATION_ENABLED = "OPERATION ENABLED"
QUICK_STOP_ACTIVE = "QUICK STOP ACTIVE"
FAULT_REACTION_ACTIVE = "FAULT REACTION ACTIVE"
FAULT = "FAULT"

_STATE_BITS = {
    NOT_READY_TO_SWITCH_ON: 0x0000,
    SWITCH_ON_DISABLED: 0x0040,
    READY_TO_SWITCH_ON: 0x0021,
    SWITCHED_ON: 0x0023,
    OPERATION_ENABLED: 0x0027,
    QUICK_STOP_ACTIVE: 0x0007,
    FAULT_REACTION_ACTIVE: 0x000F,
    FAULT: 0x0008,
}
_POWERED = {READY_TO_SWITCH_ON, SWITCHED_ON, OPERATION_ENABLED, QUICK_STOP_ACTIVE}

MODE_PROFILE_POSITION = 1
MODE_PROFILE_VELOCITY = 3

# NMT states as carried in heartbeats.
NMT_BOOTUP, NMT_STOPPED, NMT_OPERATIONAL, NMT_PRE_OPERATIONAL = 0x00, 0x04, 0x05, 0x7F

# SDO abort codes (CiA 301) the server uses.
_ABORT_COMMAND = 0x05040001
_ABORT_READ_WRITE_ONLY = 0x06010001
_ABORT_WRITE_READ_ONLY = 0x06010002
_ABORT_NO_OBJECT = 0x06020000
_ABORT_LENGTH = 0x06070010
_ABORT_NO_SUBINDEX = 0x06090011
_ABORT_VALUE_RANGE = 0x06090030
_ABORT_GENERAL = 0x08000000

# Error register (0x1001) bits per EMCY error class.
_REGISTER_GENERIC, _REGISTER_CURRENT, _REGISTER_VOLTAGE = 0x01, 0x02, 0x04
_REGISTER_TEMPERATURE, _REGISTER_COMMUNICATION = 0x08, 0x10

#: Error code a drive raises when the master's heartbeat stops (CiA 301 heartbeat error).
HEARTBEAT_ERROR = 0x8130
#: Error code of an over-temperature fault (CiA 301: excess ambient/device temperature).
OVER_TEMPERATURE = 0x4210


def _error_register_for(code: int) -> int:
    """The 0x1001 bits a drive sets alongside an EMCY code (its class decides)."""
    group = code & 0xF000
    bits = _REGISTER_GENERIC
    if group == 0x2000:
        bits |= _REGISTER_CURRENT
    elif group == 0x3000:
        bits |= _REGISTER_VOLTAGE
    elif group == 0x4000:
        bits |= _REGISTER_TEMPERATURE
    elif code & 0xFF00 == 0x8100:
        bits |= _REGISTER_COMMUNICATION
    return bits


class EmulatedCia402Drive:
    """One emulated CiA 402 drive (one CANopen node) on an :class:`EmulatedCia402Bus`.

    All public methods are thread-safe: they take the bus lock that the serving thread holds
    while it handles a frame or steps the physics.

    Attributes:
        node_id: CANopen node id (1..127).
        temperature_limit: Drive temperature (°C) above which it faults with 0x4210.
    """

    # Plausible torque model, per-mille of rated torque: inertia and viscous friction, for a
    # 4096-count encoder; scaled per drive to its encoder (see ``counts_per_rev``).
    TORQUE_PER_ACCELERATION = 1e-4  # per-mille per count/s²
    TORQUE_PER_VELOCITY = 1e-3  # per-mille per count/s
    REFERENCE_COUNTS_PER_REV = 4096

    def __init__(
        self,
        bus: EmulatedCia402Bus,
        node_id: int,
        eds: str | Path = EDS_PATH,
        counts_per_rev: int = REFERENCE_COUNTS_PER_REV,
    ):
        if not 1 <= node_id <= 127:
            raise ValueError(f"CANopen node id must be 1..127, not {node_id}")
        if not counts_per_rev > 0:
            raise ValueError(f"counts_per_rev must be > 0, not {counts_per_rev}")
        self._bus = bus
        self.node_id = node_id
        # Friction and inertia belong to the motor shaft, not to the encoder: per count they
        # shrink as the resolution grows, or a 19-bit encoder would saturate the drive's
        # torque at a few motor revolutions per second.
        scale = self.REFERENCE_COUNTS_PER_REV / counts_per_rev
        self.torque_per_acceleration = self.TORQUE_PER_ACCELERATION * scale
        self.torque_per_velocity = self.TORQUE_PER_VELOCITY * scale
        self.od = canopen.import_od(str(eds), node_id)
        self.temperature_limit = 80.0
        self._values: dict[tuple[int, int], Any] = {}
        self._silenced = False
        self._power_on()

    # ---------------------------------------------------------------- public, thread-safe

    @property
    def state(self) -> str:
        """Current CiA 402 state name (e.g. ``"OPERATION ENABLED"``)."""
        with self._bus.lock:
            return self._state

    @property
    def nmt_state(self) -> int:
        """Current NMT state as carried in heartbeats (0x05 operational, 0x7F pre-op...)."""
        with self._bus.lock:
            return self._nmt

    @property
    def mode(self) -> int:
        """Mode of operation in effect (1 profile position, 3 profile velocity)."""
        with self._bus.lock:
            return int(self._values[(0x6060, 0)])

    @property
    def position(self) -> float:
        """Motor position in encoder counts."""
        with self._bus.lock:
            return self._position

    @property
    def velocity(self) -> float:
        """Motor velocity in counts/s."""
        with self._bus.lock:
            return self._velocity

    @property
    def torque(self) -> int:
        """Torque actual value in per-mille of rated torque."""
        with self._bus.lock:
            return self._torque

    @property
    def statusword(self) -> int:
        """The statusword the drive reports now."""
        with self._bus.lock:
            return self._statusword()

    @property
    def error_code(self) -> int:
        """Error code (0x603F) of the latest fault, 0 when none."""
        with self._bus.lock:
            return int(self._values[(0x603F, 0)])

    @property
    def silenced(self) -> bool:
        """Whether the drive is cut off the bus (see :meth:`silence`)."""
        return self._silenced

    def read_object(self, index: int, subindex: int = 0) -> Any:
        """The current value of an object, as the SDO server would answer it."""
        with self._bus.lock:
            return self._get(index, subindex)

    def silence(self) -> None:
        """Cut the drive off the bus: it neither receives nor sends (no heartbeat, no SDO).

        The motor keeps moving as it was told; if the master's heartbeat is monitored
        (0x1016) the drive faults with 0x8130 when it misses it, like a real drive.
        """
        with self._bus.lock:
            self._silenced = True

    def resume(self) -> None:
        """Reconnect the drive to the bus: heartbeats and answers resume."""
        with self._bus.lock:
            self._silenced = False
            now = time.monotonic()
            self._next_heartbeat = now
            self._master_heartbeat_at = None  # consumer re-arms on the next master heartbeat

    def raise_fault(self, code: int, data: bytes = b"") -> None:
        """Fault now: EMCY ``code`` on the bus and the 402 state machine goes to FAULT.

        Args:
            code: CiA 301 / 402 error code, e.g. 0x2310 over-current, 0x4210 over-temperature.
            data: Up to 5 bytes of manufacturer-specific EMCY data.
        """
        with self._bus.lock:
            self._fault(code, data)

    def set_temperature(self, celsius: float) -> None:
        """Set the drive temperature; above :attr:`temperature_limit` the drive faults."""
        with self._bus.lock:
            self._temperature = float(celsius)

    def set_load(self, permille: float) -> None:
        """Apply an external load the drive holds, in per-mille of rated torque."""
        with self._bus.lock:
            self._load = float(permille)

    def power_cycle(self) -> None:
        """Reboot: every object back to its default, boot-up message, pre-operational."""
        with self._bus.lock:
            self._power_on()
            self._boot()

    # ------------------------------------------------------------------ serving thread

    def _power_on(self) -> None:
        self._values = {}
        for obj in self.od.values():
            members = obj.values() if not isinstance(obj, ODVariable) else [obj]
            for var in members:
                self._values[(var.index, var.subindex)] = var.default or 0
        self._state = SWITCH_ON_DISABLED
        self._nmt = NMT_BOOTUP
        self._position = 0.0
        self._velocity = 0.0
        self._acceleration = 0.0
        self._torque = 0
        self._load = 0.0
        self._temperature = 25.0
        self._controlword = 0
        self._pp_target = 0.0
        self._pp_velocity = float(self._values[(0x6081, 0)])
        self._setpoint_ack = False
        self._master_heartbeat_at: float | None = None
        self._heartbeat_tripped = False
        now = time.monotonic()
        self._next_heartbeat = now
        self._tpdo_sent_at = [now] * 4
        self._tpdo_last: list[bytes | None] = [None] * 4
        self._sync_count = [0] * 4

    def _boot(self) -> None:
        """Send the boot-up message and enter pre-operational (CiA 301 initialisation)."""
        self._nmt = NMT_PRE_OPERATIONAL
        self._send(0x700 + self.node_id, b"\x00")
        self._next_heartbeat = time.monotonic() + self._heartbeat_period()

    def _send(self, can_id: int, data: bytes) -> None:
        if not self._silenced:
            self._bus.send(can_id, data)

    def _get(self, index: int, subindex: int) -> Any:
        """Live value of an object: process data from the model, the rest from the store."""
        key = (index, subindex)
        if key == (0x6041, 0):
            return self._statusword()
        if key == (0x6061, 0):
            return self._values[(0x6060, 0)]
        if key == (0x6064, 0):
            return round(self._position)
        if key == (0x606C, 0):
            return round(self._velocity)
        if key in ((0x6077, 0), (0x6078, 0)):
            return self._torque
        if key == (0x2100, 0):
            return round(self._temperature * 10)
        return self._values[key]

    def _var(self, index: int, subindex: int) -> ODVariable:
        if index not in self.od:
            raise _SdoAbort(_ABORT_NO_OBJECT)
        obj = self.od[index]
        if isinstance(obj, ODVariable):
            if subindex != 0:
                raise _SdoAbort(_ABORT_NO_SUBINDEX)
            return obj
        if subindex not in obj:
            raise _SdoAbort(_ABORT_NO_SUBINDEX)
        return obj[subindex]

    def _write(self, index: int, subindex: int, value: Any) -> None:
        """Store a value written by SDO or RPDO and apply what it means to the drive."""
        if index == 0x6060 and value not in (0, MODE_PROFILE_POSITION, MODE_PROFILE_VELOCITY):
            raise _SdoAbort(_ABORT_VALUE_RANGE)
        self._values[(index, subindex)] = value
        if index == 0x6040:
            self._on_controlword(int(value))
        elif index == 0x1017 and subindex == 0:
            self._next_heartbeat = time.monotonic() + self._heartbeat_period()
        elif index == 0x1016:
            self._master_heartbeat_at = None
            self._heartbeat_tripped = False

    def _heartbeat_period(self) -> float:
        return int(self._values[(0x1017, 0)]) / 1000.0

    def handle(self, msg: can.Message, now: float) -> None:
        """Handle one frame from the bus (called by the serving thread, lock held)."""
        if self._silenced or msg.is_error_frame or msg.is_remote_frame:
            return
        can_id, data = msg.arbitration_id, bytes(msg.data)
        if can_id == 0x000 and len(data) >= 2:
            self._on_nmt(data[0], data[1])
        elif can_id == 0x080:
            self._on_sync()
        elif can_id == 0x600 + self.node_id:
            if self._nmt in (NMT_PRE_OPERATIONAL, NMT_OPERATIONAL):
                self._on_sdo(data)
        elif 0x701 <= can_id <= 0x77F:
            self._on_heartbeat(can_id - 0x700, now)
        elif self._nmt == NMT_OPERATIONAL:
            self._on_rpdo(can_id, data)

    def _on_nmt(self, command: int, target: int) -> None:
        if target not in (0, self.node_id):
            return
        if command == 0x01:
            self._nmt = NMT_OPERATIONAL
        elif command == 0x02:
            self._nmt = NMT_STOPPED
        elif command == 0x80:
            self._nmt = NMT_PRE_OPERATIONAL
        elif command == 0x81:
            self._power_on()
            self._boot()
        elif command == 0x82:
            for key in list(self._values):
                if 0x1000 <= key[0] < 0x2000:
                    self._values[key] = self._var(*key).default or 0
            self._boot()

    def _on_heartbeat(self, producer: int, now: float) -> None:
        consumer = int(self._values[(0x1016, 1)])
        if consumer and (consumer >> 16) & 0x7F == producer:
            self._master_heartbeat_at = now
            self._heartbeat_tripped = False

    def _on_sdo(self, request: bytes) -> None:
        if len(request) < 8:
            return
        command = request[0]
        index, subindex = struct.unpack_from("<HB", request, 1)
        specifier = command >> 5
        try:
            if specifier == 2:  # initiate upload
                var = self._var(index, subindex)
                if not var.readable:
                    raise _SdoAbort(_ABORT_READ_WRITE_ONLY)
                raw = var.encode_raw(self._get(index, subindex))
                if len(raw) > 4:
                    raise _SdoAbort(_ABORT_GENERAL)  # this dictionary has no long objects
                header = 0x43 | ((4 - len(raw)) << 2)
                self._send_sdo(struct.pack("<BHB", header, index, subindex) + raw.ljust(4, b"\0"))
            elif specifier == 1:  # initiate download
                var = self._var(index, subindex)
                if not var.writable:
                    raise _SdoAbort(_ABORT_WRITE_READ_ONLY)
                if not command & 0x02:
                    raise _SdoAbort(_ABORT_COMMAND)  # segmented: not needed for <= 4 bytes
                size = 4 - ((command >> 2) & 0x3) if command & 0x01 else 4
                if size != len(var) // 8:
                    raise _SdoAbort(_ABORT_LENGTH)
                self._write(index, subindex, var.decode_raw(request[4 : 4 + size]))
                self._send_sdo(struct.pack("<BHB", 0x60, index, subindex) + b"\0\0\0\0")
            elif specifier == 4:  # abort from the client: nothing in flight to cancel
                return
            else:
                raise _SdoAbort(_ABORT_COMMAND)
        except _SdoAbort as abort:
            self._send_sdo(struct.pack("<BHBL", 0x80, index, subindex, abort.code))

    def _send_sdo(self, response: bytes) -> None:
        self._send(0x580 + self.node_id, response)

    def _mapping(self, map_index: int) -> list[ODVariable]:
        count = int(self._values[(map_index, 0)])
        entries = []
        for sub in range(1, count + 1):
            word = int(self._values[(map_index, sub)])
            index, subindex = word >> 16, (word >> 8) & 0xFF
            if index:
                entries.append(self._var(index, subindex))
        return entries

    def _on_rpdo(self, can_id: int, data: bytes) -> None:
        for n in range(4):
            cob = int(self._values[(0x1400 + n, 1)])
            if cob & 0x80000000 or cob & 0x7FF != can_id:
                continue
            offset = 0
            written = []
            for var in self._mapping(0x1600 + n):
                size = len(var) // 8
                if offset + size > len(data):
                    return  # short frame: a real drive ignores it (and may EMCY 0x8210)
                value = var.decode_raw(data[offset : offset + size])
                offset += size
                written.append((var, value))
            # Store every mapped value first so a controlword sees the mode and the target
            # sent in the same frame, as a real drive applies a PDO atomically.
            for var, value in written:
                if var.index != 0x6040:
                    try:
                        self._write(var.index, var.subindex, value)
                    except _SdoAbort:
                        logger.debug("node %d: RPDO value %r out of range", self.node_id, value)
            for var, value in written:
                if var.index == 0x6040:
                    self._write(var.index, var.subindex, value)
            return

    def _on_sync(self) -> None:
        if self._nmt != NMT_OPERATIONAL:
            return
        for n in range(4):
            transmission = int(self._values[(0x1800 + n, 2)])
            if 1 <= transmission <= 240:
                self._sync_count[n] += 1
                if self._sync_count[n] >= transmission:
                    self._sync_count[n] = 0
                    self._send_tpdo(n, time.monotonic())
            elif transmission == 0:
                self._send_tpdo(n, time.monotonic())

    def _tpdo_payload(self, mapping: list[ODVariable]) -> bytes:
        payload = b"".join(var.encode_raw(self._get(var.index, var.subindex)) for var in mapping)
        return payload[:8]

    def _send_tpdo(self, n: int, now: float) -> None:
        payload = self._tpdo_payload(self._mapping(0x1A00 + n))
        self._tpdo_sent_at[n] = now
        self._tpdo_last[n] = payload
        self._send(int(self._values[(0x1800 + n, 1)]) & 0x7FF, payload)

    def _statusword(self) -> int:
        word = _STATE_BITS[self._state] | 0x0200  # bit 9: remote (controlled over CAN)
        if self._state in _POWERED:
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
        register = _error_register_for(code)
        self._values[(0x603F, 0)] = code
        self._values[(0x1001, 0)] = register
        self._state = FAULT
        self._setpoint_ack = False
        self._send(0x80 + self.node_id, struct.pack("<HB5s", code, register, data[:5]))

    def step(self, now: float, dt: float) -> None:
        """Advance motion, monitoring and cyclic transmission (serving thread, lock held)."""
        self._monitor(now)
        self._move(dt)
        if self._nmt == NMT_BOOTUP:
            return
        period = self._heartbeat_period()
        if period > 0 and now >= self._next_heartbeat:
            self._next_heartbeat = now + period
            self._send(0x700 + self.node_id, bytes([self._nmt]))
        if self._nmt != NMT_OPERATIONAL:
            return
        for n in range(4):
            cob = int(self._values[(0x1800 + n, 1)])
            if cob & 0x80000000 or int(self._values[(0x1800 + n, 2)]) < 254:
                continue
            timer = int(self._values[(0x1800 + n, 5)]) / 1000.0
            due = timer > 0 and now - self._tpdo_sent_at[n] >= timer
            # A change of a PDO carrying the statusword is a device-specific event: sent at
            # once, which keeps the set-point handshake and the enable sequence quick.
            changed = False
            mapping = self._mapping(0x1A00 + n)
            if any(v.index == 0x6041 for v in mapping):
                changed = self._tpdo_payload(mapping) != self._tpdo_last[n]
            if due or changed:
                self._send_tpdo(n, now)

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
            if self._state in _POWERED:
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


class _SdoAbort(Exception):
    def __init__(self, code: int):
        super().__init__(f"SDO abort 0x{code:08X}")
        self.code = code


class EmulatedCia402Bus:
    """A chain of emulated CiA 402 drives on one python-can channel, served by one thread.

    Args:
        channel: python-can channel (any name on the ``virtual`` interface; tests use a
            unique one so they can run in parallel).
        node_ids: CANopen node ids of the drives on this bus.
        interface: python-can interface; ``virtual`` unless you have a real or virtual CAN
            adapter to put the emulation on.
        tick: Physics and scheduling period in seconds.
        eds: Object dictionary the drives serve.
        counts_per_rev: Encoder counts per motor revolution, for every drive (an int) or per
            node id (a mapping; absent ids get 4096): scales the torque model to the motor.
        **bus_kwargs: Passed to :class:`can.Bus` (e.g. ``bitrate``).
    """

    def __init__(
        self,
        channel: str,
        node_ids: Iterable[int],
        *,
        interface: str = "virtual",
        tick: float = 0.002,
        eds: str | Path = EDS_PATH,
        counts_per_rev: int | Mapping[int, int] = EmulatedCia402Drive.REFERENCE_COUNTS_PER_REV,
        **bus_kwargs: Any,
    ):
        self.channel = channel
        self.interface = interface
        self.tick = tick
        self.lock = threading.RLock()
        self._bus_kwargs = bus_kwargs
        self._bus: can.BusABC | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.drives: dict[int, EmulatedCia402Drive] = {}
        for node_id in node_ids:
            if node_id in self.drives:
                raise ValueError(f"node id {node_id} appears twice on channel {channel!r}")
            counts = (
                counts_per_rev.get(node_id, EmulatedCia402Drive.REFERENCE_COUNTS_PER_REV)
                if isinstance(counts_per_rev, Mapping)
                else counts_per_rev
            )
            self.drives[node_id] = EmulatedCia402Drive(self, node_id, eds, counts)

    def drive(self, node_id: int) -> EmulatedCia402Drive:
        """The emulated drive with this node id."""
        return self.drives[node_id]

    def start(self) -> EmulatedCia402Bus:
        """Connect to the bus, boot every drive and start serving. Returns ``self``."""
        if self._thread is not None:
            return self
        self._bus = can.Bus(interface=self.interface, channel=self.channel, **self._bus_kwargs)
        self._stop.clear()
        with self.lock:
            for drive in self.drives.values():
                drive._boot()
        self._thread = threading.Thread(
            target=self._serve, name=f"cia402-emulator-{self.channel}", daemon=True
        )
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving and release the bus. Idempotent."""
        thread, self._thread = self._thread, None
        if thread is not None:
            self._stop.set()
            thread.join(timeout=2.0)
        bus, self._bus = self._bus, None
        if bus is not None:
            bus.shutdown()

    def send(self, can_id: int, data: bytes) -> None:
        """Put one frame on the bus (used by the drives; errors are logged, not raised)."""
        bus = self._bus
        if bus is None:
            return
        try:
            bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))
        except can.CanError as exc:
            logger.warning("emulated CiA 402 bus %s: send failed: %s", self.channel, exc)

    def _serve(self) -> None:
        last = time.monotonic()
        bus = self._bus
        assert bus is not None
        while not self._stop.is_set():
            try:
                msg = bus.recv(timeout=self.tick)
            except can.CanError as exc:
                logger.warning("emulated CiA 402 bus %s: receive failed: %s", self.channel, exc)
                msg = None
            now = time.monotonic()
            with self.lock:
                if msg is not None:
                    for drive in self.drives.values():
                        drive.handle(msg, now)
                if now - last >= self.tick:
                    for drive in self.drives.values():
                        drive.step(now, now - last)
                    last = now

    def __enter__(self) -> EmulatedCia402Bus:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
