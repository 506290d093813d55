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
  sample to the next;
* a *shape path* beside the full one: a topic's messages are laid out alike from one sample
  to the next (the same frame, names and array lengths), so each codec remembers the last
  layout it went through, the bytes between the values and where the values are. A payload
  of the same length whose bytes between values are all equal is read at the remembered
  places with no lengths parsed or checked (it is what the full path would read); a message
  with the same strings, string lists and array shapes is written as the remembered bytes
  around its packed values. Anything else takes the full path, which remembers anew. Where
  the codec runs, between two waits for the network, this took a JointState's decoding from
  ~11 to ~9 us and its encoding from ~6 to ~3 us.

Messages are ``rosbags``' classes of the type store, so what a decoder returns is what
``rosbags`` returns. Every length is checked against the bytes there are: a malformed payload
raises (``ValueError`` or ``struct.error``), never reads past the end or loops on a forged
count. Big-endian payloads, ``wstring`` and ``float128`` go to ``rosbags``' generic codec
(:class:`Unsupported` says so when the code is generated).
"""

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


# ----------------------------------------------------------------------------- decoding
class _Decoder(_Run):
    """Writes the body of one decoding function: ``data``, ``n`` (its length) and ``pos``
    (the absolute position, 4 at the top: CDR aligns from the end of the header).

    Beside it, the same walk writes the *shape path*: for a payload laid out like the last
    one decoded, it reads only the values. A payload's shape is every byte but its values
    (numbers in runs, numeric sequences' elements): counts, string bytes, padding, and its
    length. The full path ends by remembering the last good payload's shape (its gaps
    between values, as bytes, and where each value starts) with what it decoded from them
    (strings, string lists); the shape path runs when the length and every gap are equal,
    so it reads exactly what the full path would, checks included. Types with sequences
    or arrays of messages or fixed arrays of strings have no shape path (``fast_ok``).
    """

    def __init__(self, out: _Writer, fields: Definitions, classes: Callable[[str], type]):
        super().__init__(out)
        self.fields, self.classes = fields, classes
        self.targets: list[str] = []
        self.after: list[str] = []  # lines that read fixed arrays of the pending run
        # The shape path's runs of values (start, end), and the counts it takes from its memo.
        self.spans: list[tuple[str, str]] = []
        self.counts: dict[str, str] = {}  # a count's local -> its memo slot, when not read
        self.trailing = False  # whether shape (a count, a string) follows the last values

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

    def flush(self, tail: int = 0) -> None:
        """Read the pending run and move ``pos`` past it. ``tail``: the bytes of a count or
        length that ends the run, part of the shape, not of the values."""
        size = self.off - tail
        if size > 0:
            # Values: the shape path reads them where the last payload had them.
            start = self.out.name("a")
            self.emit(f"{start} = pos")
            self.spans.append((start, f"{start} + {size}"))
            self.fast.append(f"pos = S[{self.slot(start)}]")
        if self.targets:
            unpack = self.out.const("unpack", struct.Struct(self.fmt).unpack_from)
            line = f"{', '.join(self.targets)}, = {unpack}(data, pos)"
            self.emit(line)
            if size > 0:
                self.fast.append(line)
            else:  # only a count or a length: the last payload's, for what reads it
                self.counts.update((t, f"S[{self.slot(t)}]") for t in self.targets)
        for line in self.after:
            self.both(line)
        if self.off:
            self.emit(f"pos += {self.off}")
        if tail or size > 0:
            self.trailing = tail > 0
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
            self.both(line)
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
            self.flush(tail=4)
            self.dynamic(4)
            self.variable = True
            return self.sequence(inner, length)
        return self.array(inner, count)

    def string(self) -> str:
        length = self.scalar("uint32")
        self.flush(tail=4)
        self.variable = True
        self.emit(f"end = pos + {length}")
        self.emit(f"if not {length} or end > n or data[end - 1]:")
        self.emit(f"    raise ValueError(f'bad string of length {{{length}}} at byte {{pos}}')")
        target = self.out.name("s")
        self.emit(f"{target} = data[pos:end - 1].decode()")
        self.fast.append(f"{target} = S[{self.slot(target)}]")
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
            start = self.out.name("d")
            self.emit(f"{start} = pos")
            self.emit(f"{target} = frombuffer(data, {dtype}, {length}, pos)")
            self.emit(f"pos += {length} * {size}" if size > 1 else f"pos += {length}")
            self.spans.append((start, f"{start} + {length} * {size}"))
            count, at = self.counts.get(length, length), f"S[{self.slot(start)}]"
            self.fast.append(f"{target} = frombuffer(data, {dtype}, {count}, {at})")
            self.trailing = False
            self.dynamic(min(4, size))
            return target
        if inner[0] == _BASE:
            self.string_list(target, length)
            self.fast.append(f"{target} = S[{self.slot(f'{target}.copy()')}].copy()")
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
        self.fast_ok = False  # the shape of each element would be its own
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
        self.variable = True
        if inner[0] == _BASE:
            self.fast_ok = False
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
    result = body.message(type_name)
    body.flush()
    fast: list[str] = []
    remember: list[str] = []
    if body.fast_ok and body.variable:
        # The gaps between runs of values, from the header to the end of the last field
        # (the up to 3 bytes after it are never read: the same length, the same count);
        # none after values that end the message.
        ends = ["0", *(end for _, end in body.spans)]
        starts = [*(start for start, _ in body.spans), "pos"]
        if not body.trailing:
            ends, starts = ends[:-1], starts[:-1]
        gaps = [f"data[{a}:{b}], {a}" for a, b in zip(ends, starts, strict=True)]
        first = len(body.memo) + 1
        same = " and ".join(
            f"data.startswith(S[{first + 2 * i}], S[{first + 2 * i + 1}])" for i in range(len(gaps))
        )
        memo = "memo"
        fast = [
            f"    S = {memo}[0]",
            f"    if n == S[0] and {same}:",
            *(f"        {line}" for line in body.fast),
            f"        return {result}",
        ]
        remember = [
            f"    if n <= {REMEMBER_AT_MOST}:",
            f"        {memo}[0] = (n, {', '.join([*body.memo, *gaps])})",
        ]
    main = [
        *out.defs,
        f"def decode(data{', memo=MEMO' if fast else ''}):",
        "    if data.__class__ is not bytes:",
        "        data = bytes(data)",
        "    n = len(data)",
        *fast,
        "    if n < 4 or data[0] or data[1] != 1:",
        "        if n >= 4 and data[0] == 0 and data[1] == 0:",
        "            return fallback(data)",
        "        raise ValueError('invalid or unsupported CDR encapsulation')",
        "    pos = 4",
        *out.lines,
        "    if pos + 3 < n:",
        f"        raise ValueError(f'{{n - pos}} trailing bytes after a {type_name}')",
        *remember,
        f"    return {result}",
    ]
    return _compile(main, out.consts, {"fallback": fallback, "MEMO": [(None,)]})["decode"]


def own(function: Callable[[Any], Any]) -> Callable[[Any], Any]:
    """A copy of a generated codec with a memory of the last shape of its own, for one
    stream (a publisher, a subscription): the shared codec would keep forgetting between
    two streams of one type laid out differently (two limbs' JointStates). Anything else
    is returned as it is."""
    code = getattr(function, "__code__", None)
    if code is None or code.co_varnames[code.co_argcount - 1 : code.co_argcount] != ("memo",):
        return function  # no shape path: nothing of its own to remember
    copy = types.FunctionType(
        function.__code__, function.__globals__, function.__name__, ([(None,)],)
    )
    copy.__qualname__ = function.__qualname__
    return copy


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


def encoder(type_name: str, fields: Definitions) -> Callable[[Any], bytes]:
    """The encoding function of one type: message -> CDR bytes (with header).

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
        f"def encode(message{', memo=MEMO' if fast else ''}):",
        *fast,
        "    parts = [HEADER]",
        "    pos = 4",
        *out.lines,
        *end,
    ]
    return _compile(main, out.consts, {"ndarray": numpy.ndarray, "MEMO": [(None,)]})["encode"]
