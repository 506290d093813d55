"""Dynamixel Protocol 2.0 framing as a servo sees it: header ``FF FF FD 00``, CRC-16 with
polynomial 0x8005, byte stuffing, status packets with the alert bit, and a parser that splits
a byte stream into packets."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

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
