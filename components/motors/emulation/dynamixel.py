"""An emulated chain of Dynamixel X-series servos behind a pseudo-terminal.

The emulator speaks Protocol 2.0 byte for byte (header ``FF FF FD 00``, CRC-16 with polynomial
0x8005, byte stuffing, status packets with the alert bit), so the real dynamixel-sdk and the
real :class:`~components.motors.dynamixel.backend.DynamixelBackend` talk to it through pyserial
exactly as to a U2D2 adapter::

    with EmulatedDynamixelChain(ids=[1, 2, 3]) as chain:
        backend = DynamixelBackend(chain.port, motors, {})

Each servo has a control table (the same register map the backend uses), simple motion
physics (position follows the goal at the profile velocity; velocity mode integrates; current
follows speed and tracking error), the Bus Watchdog (register 98, see
:meth:`EmulatedServo.heard`), and fault hooks: :meth:`EmulatedDynamixelChain.silence`,
:meth:`~EmulatedDynamixelChain.resume`, :meth:`~EmulatedDynamixelChain.set_hardware_error`,
:meth:`~EmulatedDynamixelChain.set_temperature`. The baud rate is irrelevant on a pty.

Run ``python -m components.motors.emulation.dynamixel --ids 1,2,3`` to serve a chain for a demo.
"""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import os
import select
import threading
import time
import tty
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

from components.motors.dynamixel.control_table import (
    BUS_WATCHDOG_EXPIRED,
    BUS_WATCHDOG_MAX_UNITS,
    BUS_WATCHDOG_UNIT_MS,
    OPERATING_MODES,
    SIGNED_REGISTERS,
    X_SERIES_REGISTERS,
    to_signed,
)
from components.motors.dynamixel.units import MODELS, DynamixelModel

HEADER = b"\xff\xff\xfd\x00"
BROADCAST_ID = 0xFE

INST_PING = 0x01
INST_READ = 0x02
INST_WRITE = 0x03
INST_REBOOT = 0x08
INST_STATUS = 0x55
INST_SYNC_READ = 0x82
INST_SYNC_WRITE = 0x83

ERR_INSTRUCTION = 0x02
ERR_CRC = 0x03
ERR_DATA_RANGE = 0x04
ERR_DATA_LENGTH = 0x05
ERR_DATA_LIMIT = 0x06
ERR_ACCESS = 0x07
ALERT = 0x80

#: Largest packet a servo accepts; longer "lengths" are line noise, not packets.
MAX_PACKET_LENGTH = 1024

#: Where the RAM area starts: lower addresses are EEPROM and refuse writes with torque on.
RAM_START = 64
#: Where the read-only present-value area starts.
READ_ONLY_START = 120

_REG = X_SERIES_REGISTERS

#: The goal registers a Bus Watchdog expiry makes read-only until the watchdog is cleared.
GOAL_REGISTERS = ("goal_pwm", "goal_current", "goal_velocity", "goal_position")


def _crc_table() -> list[int]:
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else crc << 1
        table.append(crc & 0xFFFF)
    return table


_CRC_TABLE = _crc_table()


def crc16(data: bytes | bytearray, crc: int = 0) -> int:
    """The Dynamixel Protocol 2.0 CRC: CRC-16, polynomial 0x8005, initial 0, no reflection."""
    for byte in data:
        crc = ((crc << 8) ^ _CRC_TABLE[((crc >> 8) ^ byte) & 0xFF]) & 0xFFFF
    return crc


def stuff(body: bytes | bytearray) -> bytes:
    """Byte-stuff an instruction/status body: every ``FF FF FD`` is followed by an extra ``FD``.

    This keeps a header pattern from ever appearing inside a packet.
    """
    out = bytearray()
    for index, byte in enumerate(body):
        out.append(byte)
        if byte == 0xFD and index >= 2 and body[index - 2] == 0xFF and body[index - 1] == 0xFF:
            out.append(0xFD)
    return bytes(out)


def unstuff(body: bytes | bytearray) -> bytes:
    """Undo :func:`stuff`: drop the ``FD`` that follows each ``FF FF FD``."""
    out = bytearray()
    skip = False
    for index, byte in enumerate(body):
        if skip:
            skip = False
            if byte == 0xFD:
                continue
        out.append(byte)
        if byte == 0xFD and index >= 2 and body[index - 2] == 0xFF and body[index - 1] == 0xFF:
            skip = True
    return bytes(out)


def build_packet(dxl_id: int, instruction: int, params: bytes | bytearray = b"") -> bytes:
    """A complete Protocol 2.0 packet: header, id, length, stuffed body, CRC (little-endian)."""
    body = stuff(bytes([instruction]) + bytes(params))
    length = len(body) + 2
    packet = HEADER + bytes([dxl_id, length & 0xFF, length >> 8]) + body
    crc = crc16(packet)
    return packet + bytes([crc & 0xFF, crc >> 8])


def build_status(dxl_id: int, error: int, data: bytes | bytearray = b"") -> bytes:
    """A status packet (instruction 0x55) carrying ``error`` and ``data``."""
    return build_packet(dxl_id, INST_STATUS, bytes([error]) + bytes(data))


@dataclass(frozen=True)
class Packet:
    """One received packet, unstuffed. ``crc_ok`` False means only ``dxl_id`` is trustworthy."""

    dxl_id: int
    instruction: int
    params: bytes
    crc_ok: bool = True


class PacketParser:
    """Splits a byte stream into Protocol 2.0 packets, resynchronising on the header."""

    def __init__(self) -> None:
        self._buffer = bytearray()

    def feed(self, data: bytes) -> Iterator[Packet]:
        """Add received bytes and yield every complete packet they finish."""
        self._buffer += data
        while True:
            start = self._buffer.find(HEADER)
            if start < 0:
                # Keep a possible partial header at the end.
                del self._buffer[: max(0, len(self._buffer) - 3)]
                return
            del self._buffer[:start]
            if len(self._buffer) < 7:
                return
            length = self._buffer[5] | self._buffer[6] << 8
            if length < 3 or length > MAX_PACKET_LENGTH:
                del self._buffer[:1]
                continue
            total = 7 + length
            if len(self._buffer) < total:
                return
            raw = bytes(self._buffer[:total])
            del self._buffer[:total]
            crc_ok = crc16(raw[:-2]) == (raw[-2] | raw[-1] << 8)
            body = unstuff(raw[7:-2])
            yield Packet(raw[4], body[0], body[1:], crc_ok)


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

    def __init__(self, dxl_id: int, model: DynamixelModel, now: float):
        self.dxl_id = dxl_id
        self.model = model
        self.table = bytearray(662)  # up to the end of the X-series indirect data area
        self.silenced = False
        self.booting_until = 0.0
        self.heard_at = now
        self.watchdog_expired_at: float | None = None
        self.watchdog_trips = 0
        self._position = float(model.center_tick)
        self._t = now
        self._factory_defaults()
        self._ram_defaults()

    # -- control table --------------------------------------------------------------------

    def get(self, name: str) -> int:
        """A register's value (signed where the register is)."""
        address, size = _REG[name]
        value = int.from_bytes(self.table[address : address + size], "little")
        return to_signed(value, size) if name in SIGNED_REGISTERS else value

    def set(self, name: str, value: int) -> None:
        """Store a register's value without protocol checks (for physics and fault hooks)."""
        address, size = _REG[name]
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
        if end > READ_ONLY_START and address < READ_ONLY_START + 28:
            return ERR_ACCESS
        if address <= _REG["hardware_error_status"][0] < end:
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
        reg_address, size = _REG[name]
        return address < reg_address + size and reg_address < end

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
        current_limit = self.get("current_limit")
        current = round(0.9 * velocity_units + 0.5 * tracking_error)
        self.set("present_current", max(-current_limit, min(current_limit, current)))
        self.set("present_velocity", velocity_units)
        self.set("velocity_trajectory", velocity_units)
        self.set("present_position", round(self._position))
        self.set("position_trajectory", round(self._position))
        self.set("moving", int(velocity_units != 0))
        tick = (self.get("realtime_tick") + round(dt * 1000)) % 32768
        self.set("realtime_tick", tick)


class EmulatedDynamixelChain:
    """A chain of emulated X-series servos served on the master side of a pseudo-terminal.

    Args:
        ids: Servo ids on the chain.
        model: Model key (from :data:`~components.motors.dynamixel.units.MODELS`) for every
            servo, unless ``models`` names another for an id.
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


def main(argv: list[str] | None = None) -> None:
    """Serve an emulated chain until interrupted, printing the device path to use."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ids", default="1,2,3", help="comma-separated servo ids")
    parser.add_argument("--model", default="XM430-W350", choices=sorted(MODELS))
    args = parser.parse_args(argv)
    ids = [int(part) for part in args.ids.split(",") if part.strip()]
    with EmulatedDynamixelChain(ids=ids, model=args.model) as chain:
        print(chain.port, flush=True)
        with contextlib.suppress(KeyboardInterrupt):
            while True:
                time.sleep(1.0)


if __name__ == "__main__":
    main()
