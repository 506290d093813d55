"""An emulated chain of X-series servos served on the master side of a pseudo-terminal."""

from __future__ import annotations

import contextlib
import fcntl
import os
import select
import threading
import time
import tty
from collections.abc import Iterable

from components.motors.emulation.dynamixel.datasheet import MODELS
from components.motors.emulation.dynamixel.protocol import (
    BROADCAST_ID,
    ERR_CRC,
    ERR_DATA_LENGTH,
    ERR_DATA_RANGE,
    ERR_INSTRUCTION,
    INST_PING,
    INST_READ,
    INST_REBOOT,
    INST_SYNC_READ,
    INST_SYNC_WRITE,
    INST_WRITE,
    Packet,
    PacketParser,
    build_status,
)
from components.motors.emulation.dynamixel.servo import EmulatedServo


class EmulatedDynamixelChain:
    """A chain of emulated X-series servos served on the master side of a pseudo-terminal.

    Args:
        ids: Servo ids on the chain.
        model: Model key (from
            :data:`~components.motors.emulation.dynamixel.datasheet.MODELS`) for every servo,
            unless ``models`` names another for an id.
        models: Per-id model keys.
        boot_time_s: How long a servo stays silent after REBOOT.
        gap_stops_sync_read: In a SYNC_READ each servo waits for the status packet of the one
            listed before it; when True, a silent servo also silences every servo after it in
            that reply (as some firmware does), instead of just leaving a gap.

    The serving thread starts on construction; :meth:`close` (or leaving the ``with`` block)
    stops it and closes both ends of the pty.
    """

    def __init__(
        self,
        ids: Iterable[int] = (1,),
        model: str = "XM430-W350",
        models: dict[int, str] | None = None,
        boot_time_s: float = 0.05,
        gap_stops_sync_read: bool = False,
    ):
        now = time.monotonic()
        models = models or {}
        self.boot_time = boot_time_s
        self.gap_stops_sync_read = gap_stops_sync_read
        self.servos: dict[int, EmulatedServo] = {
            dxl_id: EmulatedServo(dxl_id, MODELS[models.get(dxl_id, model)], now)
            for dxl_id in sorted(ids)
        }
        self._lock = threading.Lock()
        self._master, self._slave = os.openpty()
        # Raw mode on both ends: no echo, no CR/LF translation, no flow-control bytes eaten.
        tty.setraw(self._master)
        tty.setraw(self._slave)
        flags = fcntl.fcntl(self._master, fcntl.F_GETFL)
        fcntl.fcntl(self._master, fcntl.F_SETFL, flags | os.O_NONBLOCK)
        self.port = os.ttyname(self._slave)
        self._wake_r, self._wake_w = os.pipe()
        self._stop = threading.Event()
        self._closed = False
        self.packets_seen = 0
        self._thread = threading.Thread(
            target=self._serve, name=f"dynamixel-emulator {self.port}", daemon=True
        )
        self._thread.start()

    # -- lifecycle ------------------------------------------------------------------------

    def close(self) -> None:
        """Stop serving and close the pty (the bus "goes away" for any open backend)."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        with contextlib.suppress(OSError):
            os.write(self._wake_w, b"x")
        self._thread.join(timeout=2.0)
        for fd in (self._master, self._slave, self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)

    def __enter__(self) -> EmulatedDynamixelChain:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- fault hooks and inspection -------------------------------------------------------

    def silence(self, dxl_id: int) -> None:
        """The servo stops answering (and hearing): a cut cable or a brown-out."""
        with self._lock:
            self.servos[dxl_id].silenced = True

    def resume(self, dxl_id: int, power_cycled: bool = True) -> None:
        """The servo answers again; by default it lost power meanwhile (RAM reset, torque off)."""
        with self._lock:
            servo = self.servos[dxl_id]
            servo.silenced = False
            if power_cycled:
                servo.reboot(time.monotonic(), 0.0)

    def set_hardware_error(self, dxl_id: int, bits: int) -> None:
        """Raise Hardware Error Status bits (0 input voltage, 2 overheating, 3 encoder,
        4 electrical shock, 5 overload); shutdown bits drop torque as the firmware does."""
        with self._lock:
            self.servos[dxl_id].raise_hardware_error(bits)

    def set_temperature(self, dxl_id: int, celsius: int) -> None:
        """Set Present Temperature; above Temperature Limit the servo flags overheating."""
        with self._lock:
            servo = self.servos[dxl_id]
            servo.set("present_temperature", celsius)
            servo.step(time.monotonic())

    def register(self, dxl_id: int, name: str) -> int:
        """A register's current value, e.g. ``chain.register(3, "torque_enable")``."""
        with self._lock:
            servo = self.servos[dxl_id]
            servo.step(time.monotonic())
            return servo.get(name)

    def watchdog(self, dxl_id: int) -> tuple[float, float | None, int]:
        """Bus Watchdog bookkeeping of one servo: (last packet heard, last expiry, expiries).

        Times are ``time.monotonic()``; the expiry is None if it never expired.
        """
        with self._lock:
            servo = self.servos[dxl_id]
            servo.step(time.monotonic())
            return servo.heard_at, servo.watchdog_expired_at, servo.watchdog_trips

    def set_register(self, dxl_id: int, name: str, value: int) -> None:
        """Set a register directly, bypassing protocol checks (test and demo setup)."""
        with self._lock:
            self.servos[dxl_id].set(name, value)

    # -- serving --------------------------------------------------------------------------

    def _serve(self) -> None:
        parser = PacketParser()
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._master, self._wake_r], [], [], 0.005)
            except (OSError, ValueError):
                return
            now = time.monotonic()
            with self._lock:
                for servo in self.servos.values():
                    servo.step(now)
            if self._master not in ready:
                continue
            try:
                data = os.read(self._master, 4096)
            except BlockingIOError:
                continue
            except OSError:
                return
            for packet in parser.feed(data):
                self.packets_seen += 1
                with self._lock:
                    reply = self._handle(packet, time.monotonic())
                if reply:
                    with contextlib.suppress(BlockingIOError):
                        os.write(self._master, reply)

    def _handle(self, packet: Packet, now: float) -> bytes:
        live = {i: s for i, s in self.servos.items() if s.answering(now)}
        if packet.dxl_id != BROADCAST_ID and packet.dxl_id not in live:
            return b""
        if not packet.crc_ok:
            if packet.dxl_id == BROADCAST_ID:
                return b""
            return build_status(packet.dxl_id, ERR_CRC | live[packet.dxl_id].status_error())
        for servo in self._addressed(packet, live):
            servo.heard(now)
        handler = {
            INST_PING: self._ping,
            INST_READ: self._read,
            INST_WRITE: self._write,
            INST_REBOOT: self._reboot,
            INST_SYNC_READ: self._sync_read,
            INST_SYNC_WRITE: self._sync_write,
        }.get(packet.instruction)
        if handler is None:
            if packet.dxl_id == BROADCAST_ID:
                return b""
            return build_status(packet.dxl_id, ERR_INSTRUCTION)
        return handler(packet, live, now)

    def _addressed(self, packet: Packet, live: dict[int, EmulatedServo]) -> list[EmulatedServo]:
        """The servos an instruction is for: its id, or every one a broadcast reaches.

        A SYNC_READ or SYNC_WRITE reaches only the ids it lists.
        """
        if packet.dxl_id != BROADCAST_ID:
            return [live[packet.dxl_id]]
        params = packet.params
        if packet.instruction == INST_SYNC_READ:
            ids: Iterable[int] = params[4:]
        elif packet.instruction == INST_SYNC_WRITE and len(params) >= 4:
            length = params[2] | params[3] << 8
            ids = params[4 :: length + 1] if length else ()
        else:
            return list(live.values())
        return [live[i] for i in dict.fromkeys(ids) if i in live]

    def _targets(self, packet: Packet, live: dict[int, EmulatedServo]) -> list[EmulatedServo]:
        if packet.dxl_id == BROADCAST_ID:
            return list(live.values())
        return [live[packet.dxl_id]]

    def _ping(self, packet: Packet, live: dict[int, EmulatedServo], now: float) -> bytes:
        replies = b""
        for servo in self._targets(packet, live):
            data = servo.get("model_number").to_bytes(2, "little") + bytes(
                [servo.get("firmware_version")]
            )
            replies += build_status(servo.dxl_id, servo.status_error(), data)
        return replies

    def _read(self, packet: Packet, live: dict[int, EmulatedServo], now: float) -> bytes:
        if packet.dxl_id == BROADCAST_ID:
            return b""
        servo = live[packet.dxl_id]
        if len(packet.params) != 4:
            return build_status(servo.dxl_id, ERR_DATA_LENGTH | servo.status_error())
        address = packet.params[0] | packet.params[1] << 8
        length = packet.params[2] | packet.params[3] << 8
        if address + length > len(servo.table):
            return build_status(servo.dxl_id, ERR_DATA_RANGE | servo.status_error())
        if servo.get("status_return_level") < 1:
            return b""
        data = servo.table[address : address + length]
        return build_status(servo.dxl_id, servo.status_error(), data)

    def _write(self, packet: Packet, live: dict[int, EmulatedServo], now: float) -> bytes:
        if len(packet.params) < 3:
            return (
                b""
                if packet.dxl_id == BROADCAST_ID
                else build_status(packet.dxl_id, ERR_DATA_LENGTH)
            )
        address = packet.params[0] | packet.params[1] << 8
        data = packet.params[2:]
        replies = b""
        for servo in self._targets(packet, live):
            error = servo.write(address, data)
            if packet.dxl_id != BROADCAST_ID and servo.get("status_return_level") >= 2:
                replies += build_status(servo.dxl_id, error | servo.status_error())
        return replies

    def _reboot(self, packet: Packet, live: dict[int, EmulatedServo], now: float) -> bytes:
        replies = b""
        for servo in self._targets(packet, live):
            if packet.dxl_id != BROADCAST_ID:
                replies += build_status(servo.dxl_id, servo.status_error())
            servo.reboot(now, self.boot_time)
        return replies

    def _sync_read(self, packet: Packet, live: dict[int, EmulatedServo], now: float) -> bytes:
        if packet.dxl_id != BROADCAST_ID or len(packet.params) < 5:
            return b""
        address = packet.params[0] | packet.params[1] << 8
        length = packet.params[2] | packet.params[3] << 8
        replies = b""
        # Servos answer in the order the instruction lists them; a silent one leaves a gap.
        for dxl_id in packet.params[4:]:
            servo = live.get(dxl_id)
            if servo is None and dxl_id in self.servos and self.gap_stops_sync_read:
                break
            if servo is None or address + length > len(servo.table):
                continue
            data = servo.table[address : address + length]
            replies += build_status(dxl_id, servo.status_error(), data)
        return replies

    def _sync_write(self, packet: Packet, live: dict[int, EmulatedServo], now: float) -> bytes:
        if packet.dxl_id != BROADCAST_ID or len(packet.params) < 4:
            return b""
        address = packet.params[0] | packet.params[1] << 8
        length = packet.params[2] | packet.params[3] << 8
        if length == 0:
            return b""
        entries = packet.params[4:]
        for offset in range(0, len(entries) - length, length + 1):
            servo = live.get(entries[offset])
            if servo is not None:
                servo.write(address, entries[offset + 1 : offset + 1 + length])
        return b""
