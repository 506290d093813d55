"""One emulated CiA 402 drive (one CANopen node): NMT, heartbeat producer and consumer, an
expedited SDO server, four RPDOs and four TPDOs with configurable mapping, SYNC and EMCY."""

from __future__ import annotations

import logging
import struct
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import can
import canopen
from canopen.objectdictionary import ODVariable

from components.motors.emulation.cia402.motion import DriveMotion
from components.motors.emulation.cia402.profile import (
    ABORT_COMMAND,
    ABORT_GENERAL,
    ABORT_LENGTH,
    ABORT_NO_OBJECT,
    ABORT_NO_SUBINDEX,
    ABORT_READ_WRITE_ONLY,
    ABORT_VALUE_RANGE,
    ABORT_WRITE_READ_ONLY,
    EDS_PATH,
    MODE_PROFILE_POSITION,
    MODE_PROFILE_VELOCITY,
    NMT_BOOTUP,
    NMT_OPERATIONAL,
    NMT_PRE_OPERATIONAL,
    NMT_STOPPED,
    SWITCH_ON_DISABLED,
    SdoAbort,
)

if TYPE_CHECKING:
    from components.motors.emulation.cia402.bus import EmulatedCia402Bus

logger = logging.getLogger("components.motors.emulation.cia402")


class EmulatedCia402Drive(DriveMotion):
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
            raise SdoAbort(ABORT_NO_OBJECT)
        obj = self.od[index]
        if isinstance(obj, ODVariable):
            if subindex != 0:
                raise SdoAbort(ABORT_NO_SUBINDEX)
            return obj
        if subindex not in obj:
            raise SdoAbort(ABORT_NO_SUBINDEX)
        return obj[subindex]

    def _write(self, index: int, subindex: int, value: Any) -> None:
        """Store a value written by SDO or RPDO and apply what it means to the drive."""
        if index == 0x6060 and value not in (0, MODE_PROFILE_POSITION, MODE_PROFILE_VELOCITY):
            raise SdoAbort(ABORT_VALUE_RANGE)
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
                    raise SdoAbort(ABORT_READ_WRITE_ONLY)
                raw = var.encode_raw(self._get(index, subindex))
                if len(raw) > 4:
                    raise SdoAbort(ABORT_GENERAL)  # this dictionary has no long objects
                header = 0x43 | ((4 - len(raw)) << 2)
                self._send_sdo(struct.pack("<BHB", header, index, subindex) + raw.ljust(4, b"\0"))
            elif specifier == 1:  # initiate download
                var = self._var(index, subindex)
                if not var.writable:
                    raise SdoAbort(ABORT_WRITE_READ_ONLY)
                if not command & 0x02:
                    raise SdoAbort(ABORT_COMMAND)  # segmented: not needed for <= 4 bytes
                size = 4 - ((command >> 2) & 0x3) if command & 0x01 else 4
                if size != len(var) // 8:
                    raise SdoAbort(ABORT_LENGTH)
                self._write(index, subindex, var.decode_raw(request[4 : 4 + size]))
                self._send_sdo(struct.pack("<BHB", 0x60, index, subindex) + b"\0\0\0\0")
            elif specifier == 4:  # abort from the client: nothing in flight to cancel
                return
            else:
                raise SdoAbort(ABORT_COMMAND)
        except SdoAbort as abort:
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
                    except SdoAbort:
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
