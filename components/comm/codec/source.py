"""What the decoding and encoding source writers share: the primitives' codes, the
generated lines and constants, the pending run of fixed-size fields, and the compilation."""

from __future__ import annotations

import struct
import types
from collections.abc import Callable
from typing import Any

import numpy

# struct codes and NumPy dtypes of the primitives (little-endian).
_CODES = {
    "bool": "?",
    "byte": "b",  # as rosbags reads it (NumPy's byte is int8)
    "octet": "B",
    "char": "B",
    "uint8": "B",
    "int8": "b",
    "uint16": "H",
    "int16": "h",
    "uint32": "I",
    "int32": "i",
    "uint64": "Q",
    "int64": "q",
    "float32": "f",
    "float64": "d",
}
_DTYPES = {
    "bool": "?",
    "byte": "i1",
    "octet": "u1",
    "char": "u1",
    "uint8": "u1",
    "int8": "i1",
    "uint16": "<u2",
    "int16": "<i2",
    "uint32": "<u4",
    "int32": "<i4",
    "uint64": "<u8",
    "int64": "<i8",
    "float32": "<f4",
    "float64": "<f8",
}
#: Most elements a sequence may declare (``rosbags``' own bound, for the same answers).
MAX_SEQUENCE = 1 << 30
#: The largest payload whose shape a codec remembers: the bytes between values are kept and
#: copied once more (a long string is all shape), and a large payload's values dominate.
REMEMBER_AT_MOST = 1 << 16
#: Zero bytes of each padding length.
_PADS = tuple(bytes(n) for n in range(8))
_HEADER = b"\x00\x01\x00\x00"


class Unsupported(Exception):
    """A type this generator does not write code for (the caller uses ``rosbags``)."""


# Node types of rosbags' field descriptions (rosbags.interfaces.Nodetype values).
_BASE, _NAME, _ARRAY, _SEQUENCE = 1, 2, 3, 4

Definitions = Callable[[str], list[tuple[str, Any]]]


class Codec:
    """One type's generated codec in one direction, made once per type.

    The generated function takes the stream's memory of the last shape first; each stream
    (a publisher, a subscription, or the type registry's shared use) calls :meth:`stream` for
    a codec of its own, so the shape path remembers that stream's layout alone.
    """

    __slots__ = ("generated",)

    def __init__(self, generated: Callable[[list[Any], Any], Any]) -> None:
        self.generated = generated

    def stream(self) -> Callable[[Any], Any]:
        """The codec of one stream: value -> result, with a memory of its own.

        A bound method (the memory its ``__self__``): calling it costs what calling the
        function does, not a Python-level ``__call__`` on the hot paths.
        """
        return types.MethodType(self.generated, [(None,)])


def _size(base: str) -> int:
    return struct.calcsize("<" + _CODES[base])


def _base(desc: Any) -> str:
    name = desc[1][0]
    if name not in _CODES and name != "string":
        raise Unsupported(f"primitive {name}")
    return name


class _Writer:
    """Lines of generated source, with unique local names and module-level constants."""

    def __init__(self) -> None:
        self.lines: list[str] = []
        #: Module-level functions (for elements of sequences), before the main one.
        self.defs: list[str] = []
        self.consts: dict[str, Any] = {}
        self._count = 0

    def name(self, stem: str) -> str:
        self._count += 1
        return f"{stem}{self._count}"

    def const(self, stem: str, value: Any) -> str:
        name = self.name(f"_{stem}")
        self.consts[name] = value
        return name

    def emit(self, indent: int, line: str) -> None:
        self.lines.append("    " * indent + line)


class _Run:
    """What a decoder and an encoder share: where generated lines go, and the pending run of
    fixed-size fields as one ``struct`` format, whose padding is folded in while the
    position's alignment is known (``known``: what ``pos - 4`` is a multiple of; ``off``:
    bytes since ``pos`` not yet added to it)."""

    out: _Writer
    indent: int
    known: int
    off: int
    fmt: str

    def __init__(self, out: _Writer) -> None:
        self.out = out
        self.indent = 1
        self.known = 8  # what (pos - 4) is known to be a multiple of
        self.off = 0  # bytes since pos, not yet added to it
        self.fmt = "<"  # the pending run's struct format (from pos)
        self.functions: dict[str, str] = {}  # element type -> its function
        # The shape path (see the module docstring): its lines, the full path's expressions
        # it remembers (memo slot i + 1; slot 0 is the decoder's length, the encoder's
        # "remembered"), whether the type has one, and whether its layout varies at all.
        self.fast: list[str] = []
        self.memo: list[str] = []
        self.fast_ok = True
        self.variable = False

    def emit(self, line: str) -> None:
        self.out.emit(self.indent, line)

    def slot(self, expr: str) -> int:
        """Remember ``expr`` (evaluated at the end of the full path); its memo index."""
        self.memo.append(expr)
        return len(self.memo)

    def both(self, line: str) -> None:
        """A line of both paths."""
        self.emit(line)
        self.fast.append(line)

    def pad_in_run(self, alignment: int) -> bool:
        """Fold the padding to ``alignment`` into the run if its position is known there;
        ``False`` when the caller must align in generated code."""
        if alignment > self.known:
            return False
        pad = -self.off % alignment
        if pad:
            self.fmt += f"{pad}x"
            self.off += pad
        return True

    #: ``decode`` or ``encode``: the stem of the element functions' names.
    ROLE = ""
    #: Element type -> the name of its function, shared by every nested writer of a type.
    functions: dict[str, str]

    def nested(self) -> _Run:
        """A writer of the same kind, on the same output."""
        raise NotImplementedError

    def element_body(self, type_name: str) -> tuple[str, str]:
        """Write the body of one element's function here; its parameters and last line."""
        raise NotImplementedError

    def element_function(self, type_name: str) -> str:
        """A module-level function for elements of that type (of a sequence or an array),
        written once per type, before the main function."""
        known = self.functions.get(type_name)
        if known is not None:
            return known
        out = self.out
        name = f"_{self.ROLE}_{len(self.functions)}_{type_name.replace('/', '_')}"
        self.functions[type_name] = name
        saved, out.lines = out.lines, []
        inner = self.nested()
        inner.known = 1  # an element may start anywhere
        inner.functions = self.functions
        parameters, last = inner.element_body(type_name)
        out.defs += [f"def {name}{parameters}:", *out.lines, f"    {last}", ""]
        out.lines = saved
        return name


def _compile(lines: list[str], consts: dict[str, Any], extra: dict[str, Any]) -> dict[str, Any]:
    namespace: dict[str, Any] = {
        "frombuffer": numpy.frombuffer,
        "asarray": numpy.asarray,
        "unpack_u32": struct.Struct("<I").unpack_from,
        "pack_u32": struct.Struct("<I").pack,
        "PADS": _PADS,
        "HEADER": _HEADER,
        **consts,
        **extra,
    }
    exec(compile("\n".join(lines) + "\n", "<msctl cdr codec>", "exec"), namespace)
    return namespace
