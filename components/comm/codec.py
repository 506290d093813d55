"""Per-type CDR codecs, generated as Python source from a type's definition.

``rosbags`` generates a codec per type too, but a nested message costs it a call and a type
lookup, every primitive its own ``struct`` call and every string a bounds-check call: a
6-joint JointState took ~26 us to decode and ~18 us to encode. The codecs made here write
one flat function per type (XCDR1 little-endian, the 4-byte encapsulation header included):

* nested messages inlined, their objects built with positional arguments;
* every run of fixed-size fields between two variable-length ones read or written by one
  precompiled ``struct`` format, alignment padding folded into the format where the
  position's alignment is known when the code is generated;
* numeric arrays as NumPy views of the payload (read-only, no copy), written with
  ``tobytes``;
* a string sequence (JointState's names) compared with the last one seen at that place, and
  its decoded list (or its encoded bytes) reused when equal: names rarely change from one
  sample to the next.

Messages are ``rosbags``' classes of the type store, so what a decoder returns is what
``rosbags`` returns. Every length is checked against the bytes there are: a malformed payload
raises (``ValueError`` or ``struct.error``), never reads past the end or loops on a forged
count. Big-endian payloads, ``wstring`` and ``float128`` go to ``rosbags``' generic codec
(:class:`Unsupported` says so when the code is generated).
"""

from __future__ import annotations

import struct
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
#: Zero bytes of each padding length.
_PADS = tuple(bytes(n) for n in range(8))
_HEADER = b"\x00\x01\x00\x00"


class Unsupported(Exception):
    """A type this generator does not write code for (the caller uses ``rosbags``)."""


# Node types of rosbags' field descriptions (rosbags.interfaces.Nodetype values).
_BASE, _NAME, _ARRAY, _SEQUENCE = 1, 2, 3, 4

Definitions = Callable[[str], list[tuple[str, Any]]]


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

    def emit(self, line: str) -> None:
        self.out.emit(self.indent, line)

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


# ----------------------------------------------------------------------------- decoding
class _Decoder(_Run):
    """Writes the body of one decoding function: ``data``, ``n`` (its length) and ``pos``
    (the absolute position, 4 at the top: CDR aligns from the end of the header)."""

    def __init__(self, out: _Writer, fields: Definitions, classes: Callable[[str], type]):
        self.out, self.fields, self.classes = out, fields, classes
        self.indent = 1
        self.known = 8  # what (pos - 4) is known to be a multiple of
        self.off = 0  # bytes since pos, not yet added to it
        self.fmt = "<"  # the pending run's struct format (from pos)
        self.targets: list[str] = []
        self.after: list[str] = []  # lines that read fixed arrays of the pending run
        self.functions: dict[str, str] = {}  # element type -> its decoding function

    # position bookkeeping
    def align(self, alignment: int) -> None:
        if self.pad_in_run(alignment):
            return
        self.flush()
        if alignment == 8:
            self.emit("pos = ((pos + 3) & -8) + 4")
        else:
            self.emit(f"pos = (pos + {alignment - 1}) & -{alignment}")
        self.known = alignment

    def scalar(self, base: str) -> str:
        size = _size(base)
        self.align(size)
        target = self.out.name("v")
        self.fmt += _CODES[base]
        self.targets.append(target)
        self.off += size
        return target

    def flush(self) -> None:
        """Read the pending run and move ``pos`` past it."""
        if self.targets:
            unpack = self.out.const("unpack", struct.Struct(self.fmt).unpack_from)
            self.emit(f"{', '.join(self.targets)}, = {unpack}(data, pos)")
        for line in self.after:
            self.emit(line)
        if self.off:
            self.emit(f"pos += {self.off}")
        self.fmt, self.targets, self.after, self.off = "<", [], [], 0

    def dynamic(self, known: int) -> None:
        self.known = known

    # fields
    def message(self, type_name: str) -> str:
        values = [self.field(desc) for _, desc in self.fields(type_name)]
        cls = self.out.const("cls", self.classes(type_name))
        target = self.out.name("m")
        # Positional arguments, in the definition's order; built once its fields are read:
        # after the pending run when some are in it (so the run stays one unpack).
        line = f"{target} = {cls}({', '.join(values)})"
        if self.targets or self.after:
            self.after.append(line)
        else:
            self.emit(line)
        return target

    def field(self, desc: Any) -> str:
        node = desc[0]
        if node == _NAME:
            return self.message(desc[1])
        if node == _BASE:
            base = _base(desc)
            return self.string() if base == "string" else self.scalar(base)
        inner, count = desc[1]
        if node == _SEQUENCE:
            length = self.scalar("uint32")
            self.flush()
            self.dynamic(4)
            return self.sequence(inner, length)
        return self.array(inner, count)

    def string(self) -> str:
        length = self.scalar("uint32")
        self.flush()
        self.emit(f"end = pos + {length}")
        self.emit(f"if not {length} or end > n or data[end - 1]:")
        self.emit(f"    raise ValueError(f'bad string of length {{{length}}} at byte {{pos}}')")
        target = self.out.name("s")
        self.emit(f"{target} = data[pos:end - 1].decode()")
        self.emit("pos = end")
        self.dynamic(1)
        return target

    def sequence(self, inner: Any, length: str) -> str:
        """Elements after a count read into ``length`` (``pos`` is past the count)."""
        self.emit(f"if {length} > {MAX_SEQUENCE} or {length} > n - pos:")
        self.emit(f"    raise ValueError(f'sequence of {{{length}}} at byte {{pos}}: too long')")
        target = self.out.name("q")
        if inner[0] == _BASE and _base(inner) != "string":
            base = _base(inner)
            size = _size(base)
            if size > 4:
                self.emit(f"if {length}:")
                self.emit("    pos = ((pos + 3) & -8) + 4")
            dtype = self.out.const("dt", numpy.dtype(_DTYPES[base]))
            self.emit(f"{target} = frombuffer(data, {dtype}, {length}, pos)")
            self.emit(f"pos += {length} * {size}" if size > 1 else f"pos += {length}")
            self.dynamic(min(4, size))
            return target
        if inner[0] == _BASE:
            self.string_list(target, length)
        else:
            self.message_list(target, inner[1], length)
        self.dynamic(1)
        return target

    def string_list(self, target: str, length: str) -> None:
        # The count is part of what must match: the same bytes may follow another count.
        memo = self.out.const("memo", [(-1, -1, b"", 0, [])])
        self.emit(f"mpos, mcount, mraw, mend, mlist = {memo}[0]")
        self.emit(f"if pos == mpos and {length} == mcount and data.startswith(mraw, pos):")
        self.emit(f"    {target} = mlist.copy()")
        self.emit("    pos = mend")
        self.emit("else:")
        self.emit(f"    {target} = []")
        self.emit("    start = pos")
        self.emit(f"    for _ in range({length}):")
        self.emit("        pos = (pos + 3) & -4")
        self.emit("        size, = unpack_u32(data, pos)")
        self.emit("        end = pos + 4 + size")
        self.emit("        if not size or end > n or data[end - 1]:")
        self.emit("            raise ValueError(f'bad string of length {size} at byte {pos}')")
        self.emit(f"        {target}.append(data[pos + 4:end - 1].decode())")
        self.emit("        pos = end")
        self.emit(f"    {memo}[0] = (start, {length}, data[start:pos], pos, {target}.copy())")

    def message_list(self, target: str, type_name: str, length: str) -> None:
        function = self.element_function(type_name)
        self.emit(f"{target} = []")
        self.emit(f"for _ in range({length}):")
        self.emit(f"    item, pos = {function}(data, n, pos)")
        self.emit(f"    {target}.append(item)")

    ROLE = "decode"

    def nested(self) -> _Decoder:
        return _Decoder(self.out, self.fields, self.classes)

    def element_body(self, type_name: str) -> tuple[str, str]:
        """Decode one element: ``(data, n, pos) -> (message, pos)``."""
        result = self.message(type_name)
        self.flush()
        return "(data, n, pos)", f"return {result}, pos"

    def array(self, inner: Any, count: int) -> str:
        target = self.out.name("a")
        if inner[0] == _BASE and _base(inner) != "string":
            base = _base(inner)
            size = _size(base)
            self.align(size)
            dtype = self.out.const("dt", numpy.dtype(_DTYPES[base]))
            self.after.append(f"{target} = frombuffer(data, {dtype}, {count}, pos + {self.off})")
            # Skipped by the run's format (which bounds it); frombuffer checks its own bounds
            # when the run reads nothing else.
            self.fmt += f"{count * size}x"
            self.off += count * size
            return target
        self.flush()
        if inner[0] == _BASE:
            self.emit(f"{target} = []")
            self.emit(f"for _ in range({count}):")
            self.emit("    pos = (pos + 3) & -4")
            self.emit("    size, = unpack_u32(data, pos)")
            self.emit("    end = pos + 4 + size")
            self.emit("    if not size or end > n or data[end - 1]:")
            self.emit("        raise ValueError(f'bad string of length {size} at byte {pos}')")
            self.emit(f"    {target}.append(data[pos + 4:end - 1].decode())")
            self.emit("    pos = end")
        else:
            self.message_list(target, inner[1], str(count))
        self.dynamic(1)
        return target


def decoder(
    type_name: str,
    fields: Definitions,
    classes: Callable[[str], type],
    fallback: Callable[[bytes], Any],
) -> Callable[[bytes], Any]:
    """The decoding function of one type: CDR bytes (with header) -> message.

    Args:
        type_name: The canonical type name.
        fields: ``rosbags`` field descriptions of a type name.
        classes: The message class of a type name.
        fallback: Decodes what the generated code does not take (big-endian payloads).

    Raises:
        Unsupported: If the type holds what the generator does not write.
    """
    out = _Writer()
    body = _Decoder(out, fields, classes)
    body.indent = 1
    result = body.message(type_name)
    body.flush()
    main = [
        *out.defs,
        "def decode(data):",
        "    if data.__class__ is not bytes:",
        "        data = bytes(data)",
        "    n = len(data)",
        "    if n < 4 or data[0] or data[1] != 1:",
        "        if n >= 4 and data[0] == 0 and data[1] == 0:",
        "            return fallback(data)",
        "        raise ValueError('invalid or unsupported CDR encapsulation')",
        "    pos = 4",
        *out.lines,
        "    if pos + 3 < n:",
        f"        raise ValueError(f'{{n - pos}} trailing bytes after a {type_name}')",
        f"    return {result}",
    ]
    return _compile(main, out.consts, {"fallback": fallback})["decode"]


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


# ----------------------------------------------------------------------------- encoding
class _Encoder(_Run):
    """Writes the body of one encoding function: ``parts`` (the byte strings to join) and
    ``pos`` (the absolute position of the end of ``parts``, 4 after the header)."""

    def __init__(self, out: _Writer, fields: Definitions) -> None:
        self.out, self.fields = out, fields
        self.indent = 1
        self.known = 8
        self.off = 0
        self.fmt = "<"
        self.values: list[str] = []
        self.functions: dict[str, str] = {}

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
            self.emit(f"parts.append({pack}({', '.join(self.values)}))")
        self.fmt, self.values = "<", []

    def settle(self) -> None:
        """Add the static offset to ``pos``."""
        if self.off:
            self.emit(f"pos += {self.off}")
        self.off = 0

    def scalar(self, base: str, value: str) -> None:
        size = _size(base)
        self.align(size)
        self.fmt += _CODES[base]
        self.values.append(value)
        self.off += size

    def message(self, type_name: str, value: str) -> None:
        for field, desc in self.fields(type_name):
            self.field(desc, f"{value}.{field}")

    def field(self, desc: Any, expr: str) -> None:
        node = desc[0]
        if node == _NAME:
            local = self.out.name("m")
            self.emit(f"{local} = {expr}")
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
        self.emit(f"{local} = {expr}")
        if node == _SEQUENCE:
            self.scalar("uint32", f"len({local})")
        else:
            self.emit(f"if len({local}) != {count}:")
            self.emit(f"    raise ValueError(f'{{len({local})}} elements, expected {count}')")
        self.flush_run()
        self.settle()
        if inner[0] == _BASE and node == _SEQUENCE:
            self.string_list(local)
        elif inner[0] == _BASE:
            self.emit(f"for item in {local}:")
            self.string_item("item")
        else:
            function = self.element_function(inner[1])
            self.emit(f"for item in {local}:")
            self.emit(f"    pos = {function}(item, parts, pos)")
        self.known = 1

    def string(self, expr: str) -> None:
        local = self.out.name("b")
        self.emit(f"{local} = {expr}.encode()")
        self.scalar("uint32", f"len({local}) + 1")
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
            self.emit(f"if {local}.ndim != 1:")
            self.emit(f"    raise ValueError(f'a sequence of {{{local}.ndim}} dimensions')")
            self.scalar("uint32", f"len({local})")
            self.flush_run()
            self.settle()
            if size > 4:
                self.emit(f"if len({local}):")
                self.emit("    pad = (4 - pos) & 7")
                self.emit("    parts.append(PADS[pad])")
                self.emit("    pos += pad")
            self.emit(f"parts.append({local}.tobytes())")
            self.emit(f"pos += {local}.nbytes")
            self.known = min(4, size)
            return
        self.emit(f"if {local}.shape != ({count},):")
        self.emit(f"    raise ValueError(f'shape {{{local}.shape}}, expected ({count},)')")
        self.align(size)
        self.flush_run()
        self.emit(f"parts.append({local}.tobytes())")
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


def encoder(type_name: str, fields: Definitions) -> Callable[[Any], bytes]:
    """The encoding function of one type: message -> CDR bytes (with header).

    Raises:
        Unsupported: If the type holds what the generator does not write.
    """
    out = _Writer()
    body = _Encoder(out, fields)
    body.message(type_name, "message")
    body.flush_run()
    main = [
        *out.defs,
        "def encode(message):",
        "    parts = [HEADER]",
        "    pos = 4",
        *out.lines,
        "    return b''.join(parts)",
    ]
    return _compile(main, out.consts, {})["encode"]
