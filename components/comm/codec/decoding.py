"""The decoding function of a type, as generated source: CDR bytes -> message."""

from __future__ import annotations

import struct
from collections.abc import Callable
from typing import Any

import numpy

from components.comm.codec.source import (
    _BASE,
    _CODES,
    _DTYPES,
    _NAME,
    _SEQUENCE,
    MAX_SEQUENCE,
    REMEMBER_AT_MOST,
    Codec,
    Definitions,
    _base,
    _compile,
    _Run,
    _size,
    _Writer,
)


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
) -> Codec:
    """The decoding codec of one type: CDR bytes (with header) -> message.

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
        "def decode(memo, data):",
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
    return Codec(_compile(main, out.consts, {"fallback": fallback})["decode"])
