"""The serial port of a chain and the exchanges on it (dynamixel-sdk, Protocol 2.0).

:class:`ChainExchanges` is the part of the backend that talks on the port: one register read
or write, a SYNC_WRITE, the SYNC_READ of the state block (received packet by packet, so one
silent servo neither blinds the chain nor loses the others' alert bits). Every exchange notes
when it went out to each servo, which is what feeds their Bus Watchdog.
"""

from __future__ import annotations

import logging
import time
from typing import Any

from dynamixel_sdk import COMM_SUCCESS, GroupSyncWrite, PacketHandler, PortHandler
from dynamixel_sdk.protocol2_packet_handler import (
    PKT_ERROR,
    PKT_ID,
    PKT_LENGTH_H,
    PKT_LENGTH_L,
    PKT_PARAMETER0,
)

from components.motors.base import MotorError
from components.motors.dynamixel.control_table import (
    READ_BLOCK_LENGTH,
    READ_BLOCK_START,
    SIGNED_REGISTERS,
    X_SERIES_REGISTERS,
    to_signed,
)
from components.motors.dynamixel.servo import Servo

log = logging.getLogger("components.motors.dynamixel")


class NoAnswer(Exception):
    """A servo did not answer (or answered garbage) during a multi-step exchange."""


class LatencyAwarePort(PortHandler):
    """PortHandler whose reply timeout uses the adapter's real latency timer.

    The SDK hard-codes 16 ms (FTDI's default) into every timeout; an adapter set to 1 ms can
    use a much shorter one, which is what keeps a silent servo from stalling the cycle.
    """

    def __init__(self, port_name: str, latency_timer_ms: float):
        super().__init__(port_name)
        self.latency_timer_ms = latency_timer_ms

    def setPacketTimeout(self, packet_length: int) -> None:
        """Start a reply timeout sized for ``packet_length`` bytes plus two latency periods."""
        self.packet_start_time = self.getCurrentTime()
        self.packet_timeout = (
            self.tx_time_per_byte * packet_length + 2.0 * self.latency_timer_ms + 2.0
        )


class ChainExchanges:
    """The backend's exchanges on its serial port (a mixin of
    :class:`~components.motors.dynamixel.backend.DynamixelBackend`, run on its I/O thread).
    """

    channel: str
    baudrate: int
    latency_timer_ms: float
    _port: PortHandler | None
    _packet: PacketHandler
    _by_id: dict[int, Servo]
    _bus_error: str

    def _port_error_text(self, exc: object) -> str:
        return (
            f"cannot open Dynamixel port {self.channel} at {self.baudrate} baud ({exc}); check "
            f"that the U2D2/USB adapter is plugged in and the path exists (ls -l {self.channel}), "
            "and that your user may open it (sudo usermod -aG dialout $USER, then log in again)"
        )

    def _open_port(self) -> None:
        port = LatencyAwarePort(self.channel, self.latency_timer_ms)
        if not port.setBaudRate(self.baudrate):
            raise MotorError(
                f"cannot open Dynamixel port {self.channel}: baud rate {self.baudrate} is not one "
                "the SDK supports; use 57600, 115200, 1000000, 2000000, 3000000 or 4000000"
            )
        self._port = port
        self._bus_error = ""

    def _close_port(self) -> None:
        port, self._port = self._port, None
        if port is not None and port.ser is not None:
            try:
                port.closePort()
            except Exception as exc:
                log.debug("%s: close failed: %s", self.channel, exc)

    def _mark_sent(self, ids: Any) -> None:
        """Note that an instruction including these servo ids goes out now (feeds watchdogs)."""
        now = time.monotonic()
        for sid in ids:
            servo = self._by_id.get(sid)
            if servo is not None:
                servo.sent_at = now

    def _release(self) -> None:
        # The SDK marks the port busy per transaction and clears it on the happy paths only;
        # an exception mid-transaction would otherwise leave every later call COMM_PORT_BUSY.
        if self._port is not None:
            self._port.is_using = False

    def _read_register(self, servo: Servo, name: str) -> tuple[int, int]:
        """(value, status error byte) of one register; raises NoAnswer when silent."""
        address, size = servo.model.registers[name]
        servo.sent_at = time.monotonic()
        data, result, error = self._packet.readTxRx(self._port, servo.sid, address, size)
        self._release()
        if result != COMM_SUCCESS or len(data) != size:
            raise NoAnswer(self._packet.getTxRxResult(result))
        value = int.from_bytes(bytes(data), "little")
        if name in SIGNED_REGISTERS:
            value = to_signed(value, size)
        return value, error

    def _write_register(self, servo: Servo, name: str, value: int) -> int:
        """Write one register and return the status error byte; raises NoAnswer when silent."""
        address, size = servo.model.registers[name]
        data = list((value & ((1 << (8 * size)) - 1)).to_bytes(size, "little"))
        servo.sent_at = time.monotonic()
        result, error = self._packet.writeTxRx(self._port, servo.sid, address, size, data)
        self._release()
        if result != COMM_SUCCESS:
            raise NoAnswer(self._packet.getTxRxResult(result))
        if error & 0x7F:
            servo.note = f"write {name}={value}: {self._packet.getRxPacketError(error & 0x7F)}"
            log.warning("%s: servo id %d %s", servo.joint, servo.sid, servo.note)
        return error

    def _sync_write(self, name: str, values: dict[int, int]) -> None:
        if not values or self._port is None:
            return
        address, size = X_SERIES_REGISTERS[name]
        group = GroupSyncWrite(self._port, self._packet, address, size)
        mask = (1 << (8 * size)) - 1
        for sid, value in values.items():
            group.addParam(sid, list((value & mask).to_bytes(size, "little")))
        self._mark_sent(values)
        result = group.txPacket()
        self._release()
        if result != COMM_SUCCESS:
            raise OSError(f"sync write {name} failed: {self._packet.getTxRxResult(result)}")

    def _sync_read_block(self, servos: list[Servo]) -> dict[int, tuple[bytes, int]]:
        """SYNC_READ the state block; servo id -> (data, status error byte) for each reply."""
        if not servos:
            return {}
        ids = [s.sid for s in servos]
        self._mark_sent(ids)
        result = self._packet.syncReadTx(
            self._port, READ_BLOCK_START, READ_BLOCK_LENGTH, ids, len(ids), False
        )
        if result != COMM_SUCCESS:
            self._release()
            raise OSError(f"sync read failed: {self._packet.getTxRxResult(result)}")
        replies: dict[int, tuple[bytes, int]] = {}
        wanted = set(ids)
        # Replies come back in id order. A silent servo leaves a gap (later replies still come
        # within the group timeout) or, on some firmware, ends the reply; either way keep what
        # arrived, and the caller reads the missing servos one by one.
        while len(replies) < len(ids):
            packet, result = self._packet.rxPacket(self._port, False)
            if result != COMM_SUCCESS:
                break
            sid = packet[PKT_ID]
            length = (packet[PKT_LENGTH_L] | packet[PKT_LENGTH_H] << 8) - 4
            if sid in wanted and length == READ_BLOCK_LENGTH:
                start = PKT_PARAMETER0 + 1
                replies[sid] = (bytes(packet[start : start + length]), packet[PKT_ERROR])
        self._release()
        return replies

    def _read_block_single(self, servo: Servo) -> tuple[bytes, int] | None:
        servo.sent_at = time.monotonic()
        data, result, error = self._packet.readTxRx(
            self._port, servo.sid, READ_BLOCK_START, READ_BLOCK_LENGTH
        )
        self._release()
        if result != COMM_SUCCESS or len(data) != READ_BLOCK_LENGTH:
            return None
        return bytes(data), error
