"""``/diagnostics_agg`` straight to CDR bytes, each status encoded once while it is unchanged.

The data monitor publishes its whole tree (about 1,000 statuses for 40 modules) every second.
Building that many message objects and serialising them through the generic serializer was a
third of its CPU at that scale, though most statuses are the same from one second to the
next. :class:`AggregateEncoder` writes a ``diagnostic_msgs/DiagnosticArray`` itself and keeps
each status's bytes until its content changes. The bytes are exactly what the registry's
serializer writes (a test compares them), so subscribers see no difference.

Why a status's bytes can be kept: in CDR (XCDR1, little endian) a ``DiagnosticStatus`` is a
``byte`` (the level, never aligned) and then strings and a sequence, which align to 4. After
the level, padding to the next multiple of 4 depends on where the status starts; everything
after that padding (the "body") depends only on the status itself. So the body is kept, and
the level and padding are written for each array.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterable, Mapping
from typing import Any

#: Encapsulation header of little-endian plain CDR (what rmw_zenoh and rosbags write).
CDR_LE = b"\x00\x01\x00\x00"
_U32 = struct.Struct("<I")
_TIME = struct.Struct("<iI")

#: ``(name, level, message, hardware_id, values)``, as
#: :func:`components.data_monitor.core.aggregate` lists them.
StatusTuple = tuple[str, int, str, str, Mapping[str, Any]]


def _string(out: bytearray, text: str) -> None:
    """Append a CDR string at a 4-aligned position of ``out``'s body (length, bytes, NUL)."""
    data = text.encode()
    out += _U32.pack(len(data) + 1)
    out += data
    out += b"\x00"


def _align(out: bytearray) -> None:
    out += b"\x00" * (-len(out) % 4)


def status_body(name: str, message: str, hardware_id: str, values: Mapping[str, Any]) -> bytes:
    """A status's bytes after its level and padding (to be placed at a 4-aligned offset)."""
    out = bytearray()
    _string(out, name)
    _align(out)
    _string(out, message)
    _align(out)
    _string(out, hardware_id)
    _align(out)
    out += _U32.pack(len(values))
    for key, value in values.items():
        _align(out)
        _string(out, str(key))
        _align(out)
        _string(out, str(value))
    return bytes(out)


class AggregateEncoder:
    """Encodes DiagnosticArrays, reusing the bytes of statuses seen in the previous array."""

    def __init__(self) -> None:
        self._bodies: dict[str, tuple[tuple[Any, ...], bytes]] = {}
        #: Statuses encoded anew (not reused) by the last :meth:`encode`.
        self.encoded = 0

    def encode(self, statuses: Iterable[StatusTuple], stamp: float, frame_id: str = "") -> bytes:
        """The CDR bytes (with encapsulation header) of a ``diagnostic_msgs/DiagnosticArray``.

        Args:
            statuses: ``(name, level, message, hardware_id, values)`` per status, in order.
            stamp: Wall-clock seconds for the header.
            frame_id: The header's frame.
        """
        seconds = math.floor(stamp)
        out = bytearray(_TIME.pack(int(seconds), int((stamp - seconds) * 1e9)))
        _string(out, frame_id)
        listed = list(statuses)
        _align(out)
        out += _U32.pack(len(listed))
        kept = self._bodies
        fresh: dict[str, tuple[tuple[Any, ...], bytes]] = {}
        self.encoded = 0
        for name, level, message, hardware_id, values in listed:
            key = (message, hardware_id, tuple(values.items()))
            known = kept.get(name)
            if known is not None and known[0] == key:
                body = known[1]
            else:
                body = status_body(name, message, hardware_id, values)
                self.encoded += 1
            fresh[name] = (key, body)
            out.append(int(level) & 0xFF)
            _align(out)
            out += body
        self._bodies = fresh
        return CDR_LE + bytes(out)
