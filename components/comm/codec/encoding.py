"""The encoding function of a type, as generated source: message -> CDR bytes."""

from __future__ import annotations

import struct
from typing import Any

import numpy

from components.comm.codec.source import (
    _BASE,
    _CODES,
    _DTYPES,
    _NAME,
    _SEQUENCE,
    REMEMBER_AT_MOST,
    Codec,
    Definitions,
    _base,
    _compile,
    _Run,
    _size,
    _Writer,
)


class _Encoder(_Run):
    """Writes the body of one encoding function: ``parts`` (the byte strings to join) and
    ``pos`` (the absolute position of the end of ``parts``, 4 after the header)."""

    def __init__(self, out: _Writer, fields: Definitions) -> None:
        super().__init__(out)
        self.fields = fields
        self.values: list[str] = []
        # The shape path's lines read the message's fields; then what the message must match
        # (strings, string lists, numeric sequences' shapes) and the pieces of values it
        # writes between the remembered bytes. A run of only counts and lengths is shape.
        self.checks: list[str] = []
        self.pieces: list[str] = []
        self.marks: list[str] = []  # the full path's index of each piece in ``parts``
        self.shapes: list[bool] = []  # which of the pending run's values are shape
        self.run_values = False  # whether the pending run holds values, not only shape

    def piece(self, slow: str, fast: str) -> None:
        """Append a piece of values: ``slow`` in the full path, ``fast`` in the shape path."""
        mark = self.out.name("i")
        self.emit(f"{mark} = len(parts)")
        self.emit(f"parts.append({slow})")
        self.marks.append(mark)
        self.pieces.append(fast)

    def align(self, alignment: int) -> None:
        if self.pad_in_run(alignment):
            return
        self.flush_run()
        self.settle()
        if alignment == 8:
            self.emit("pad = (4 - pos) & 7")
        else:
            self.emit(f"pad = -pos & {alignment - 1}")
        self.emit("parts.append(PADS[pad])")
        self.emit("pos += pad")
        self.known = alignment

    def flush_run(self) -> None:
        """Pack the pending scalars (their bytes are already counted in ``off``)."""
        if self.fmt != "<":
            pack = self.out.const("pack", struct.Struct(self.fmt).pack)
            if self.run_values:
                fast = [
                    f"E[{self.slot(value)}]" if shape else value
                    for value, shape in zip(self.values, self.shapes, strict=True)
                ]
                self.piece(f"{pack}({', '.join(self.values)})", f"{pack}({', '.join(fast)})")
            else:  # counts and lengths only: part of the shape
                self.emit(f"parts.append({pack}({', '.join(self.values)}))")
        self.fmt, self.values, self.shapes, self.run_values = "<", [], [], False

    def settle(self) -> None:
        """Add the static offset to ``pos``."""
        if self.off:
            self.emit(f"pos += {self.off}")
        self.off = 0

    def scalar(self, base: str, value: str, shape: bool = False) -> None:
        """One fixed-size value in the pending run; ``shape``: a count or a length, what the
        shape path takes from the memo."""
        size = _size(base)
        self.align(size)
        self.fmt += _CODES[base]
        self.values.append(value)
        self.shapes.append(shape)
        self.run_values = self.run_values or not shape
        self.off += size

    def message(self, type_name: str, value: str) -> None:
        for field, desc in self.fields(type_name):
            self.field(desc, f"{value}.{field}")

    def field(self, desc: Any, expr: str) -> None:
        node = desc[0]
        if node == _NAME:
            local = self.out.name("m")
            self.both(f"{local} = {expr}")
            self.message(desc[1], local)
            return
        if node == _BASE:
            base = _base(desc)
            if base == "string":
                self.string(expr)
            else:
                self.scalar(base, expr)
            return
        inner, count = desc[1]
        local = self.out.name("q")
        if inner[0] == _BASE and _base(inner) != "string":
            self.numbers(inner, count, node == _SEQUENCE, expr, local)
            return
        self.both(f"{local} = {expr}")
        self.variable = True
        if node == _SEQUENCE:
            self.scalar("uint32", f"len({local})", shape=True)
        else:
            self.emit(f"if len({local}) != {count}:")
            self.emit(f"    raise ValueError(f'{{len({local})}} elements, expected {count}')")
        self.flush_run()
        self.settle()
        if inner[0] == _BASE and node == _SEQUENCE:
            self.string_list(local)
            self.checks.append(
                f"{local}.__class__ is list and {local} == E[{self.slot(f'list({local})')}]"
            )
        elif inner[0] == _BASE:
            self.fast_ok = False
            self.emit(f"for item in {local}:")
            self.string_item("item")
        else:
            self.fast_ok = False
            function = self.element_function(inner[1])
            self.emit(f"for item in {local}:")
            self.emit(f"    pos = {function}(item, parts, pos)")
        self.known = 1

    def string(self, expr: str) -> None:
        text, local = self.out.name("t"), self.out.name("b")
        self.both(f"{text} = {expr}")
        self.checks.append(f"{text} == E[{self.slot(text)}]")
        self.variable = True
        self.emit(f"{local} = {text}.encode()")
        self.scalar("uint32", f"len({local}) + 1", shape=True)
        self.flush_run()
        self.emit(f"parts.append({local})")
        self.emit("parts.append(PADS[1])")
        self.emit(f"pos += {self.off} + len({local}) + 1")
        self.off = 0
        self.known = 1

    def string_item(self, item: str) -> None:
        self.emit("    pad = -pos & 3")
        self.emit(f"    b = {item}.encode()")
        self.emit("    parts.append(PADS[pad] + pack_u32(len(b) + 1) + b + PADS[1])")
        self.emit("    pos += pad + 5 + len(b)")

    def string_list(self, local: str) -> None:
        memo = self.out.const("memo", [(None, -1, b"")])
        self.emit(f"mlist, mmod, mraw = {memo}[0]")
        self.emit(f"if {local}.__class__ is list and pos & 3 == mmod and {local} == mlist:")
        self.emit("    parts.append(mraw)")
        self.emit("    pos += len(mraw)")
        self.emit("else:")
        self.emit("    start, mark = pos, len(parts)")
        self.emit(f"    for item in {local}:")
        self.indent += 1
        self.string_item("item")
        self.indent -= 1
        self.emit("    raw = b''.join(parts[mark:])")
        self.emit(f"    if {local}.__class__ is list:")
        self.emit(f"        {memo}[0] = ({local}.copy(), start & 3, raw)")

    def numbers(self, inner: Any, count: int, sequence: bool, expr: str, local: str) -> None:
        base = _base(inner)
        size = _size(base)
        dtype = self.out.const("dt", numpy.dtype(_DTYPES[base]))
        self.emit(f"{local} = asarray({expr}, {dtype})")
        if sequence:
            # The shape path takes an array of the type's own dtype and the last length.
            self.fast.append(f"{local} = {expr}")
            self.checks.append(
                f"{local}.__class__ is ndarray and {local}.dtype is {dtype} and "
                f"{local}.shape == E[{self.slot(f'{local}.shape')}]"
            )
            self.variable = True
            self.emit(f"if {local}.ndim != 1:")
            self.emit(f"    raise ValueError(f'a sequence of {{{local}.ndim}} dimensions')")
            self.scalar("uint32", f"len({local})", shape=True)
            self.flush_run()
            self.settle()
            if size > 4:
                self.emit(f"if len({local}):")
                self.emit("    pad = (4 - pos) & 7")
                self.emit("    parts.append(PADS[pad])")
                self.emit("    pos += pad")
            self.piece(f"{local}.tobytes()", f"{local}.tobytes()")
            self.emit(f"pos += {local}.nbytes")
            self.known = min(4, size)
            return
        self.fast.append(f"{local} = asarray({expr}, {dtype})")
        self.checks.append(f"{local}.shape == ({count},)")
        self.emit(f"if {local}.shape != ({count},):")
        self.emit(f"    raise ValueError(f'shape {{{local}.shape}}, expected ({count},)')")
        self.align(size)
        self.flush_run()
        self.piece(f"{local}.tobytes()", f"{local}.tobytes()")
        self.off += count * size

    ROLE = "encode"

    def nested(self) -> _Encoder:
        return _Encoder(self.out, self.fields)

    def element_body(self, type_name: str) -> tuple[str, str]:
        """Encode one element: ``(message, parts, pos) -> pos``."""
        self.message(type_name, "message")
        self.flush_run()
        self.settle()
        return "(message, parts, pos)", "return pos"


def encoder(type_name: str, fields: Definitions) -> Codec:
    """The encoding codec of one type: message -> CDR bytes (with header).

    Raises:
        Unsupported: If the type holds what the generator does not write.
    """
    out = _Writer()
    body = _Encoder(out, fields)
    body.message(type_name, "message")
    body.flush_run()
    fast: list[str] = []
    end = ["    return b''.join(parts)"]
    if body.fast_ok and body.variable:
        # The bytes between the pieces of values, as the full path wrote them.
        bounds = ["", *(f"{mark} + 1" for mark in body.marks)]
        stops = [*body.marks, ""]
        gaps = [f"b''.join(parts[{a}:{b}])" for a, b in zip(bounds, stops, strict=True)]
        first = len(body.memo) + 1
        pieces = [f"E[{first}]"]
        for i, piece in enumerate(body.pieces):
            pieces += [piece, f"E[{first + i + 1}]"]
        memo = "memo"
        fast = [
            f"    E = {memo}[0]",
            *(f"    {line}" for line in body.fast),
            f"    if E[0] and {' and '.join(body.checks)}:",
            f"        return b''.join(({', '.join(pieces)},))",
        ]
        end = [
            "    data = b''.join(parts)",
            f"    if len(data) <= {REMEMBER_AT_MOST}:",
            f"        {memo}[0] = (True, {', '.join([*body.memo, *gaps])})",
            "    return data",
        ]
    main = [
        *out.defs,
        "def encode(memo, message):",
        *fast,
        "    parts = [HEADER]",
        "    pos = 4",
        *out.lines,
        *end,
    ]
    return Codec(_compile(main, out.consts, {"ndarray": numpy.ndarray})["encode"])
