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

Each generated function takes the memory of its stream first (``memo``: a one-item list
holding the last shape, ``(None,)`` before any); a :class:`Codec` is one type's function in one
direction, and :meth:`Codec.stream` binds it to a fresh memory for one stream (a publisher, a
subscription), so two streams of one type laid out differently (two limbs' JointStates) do not
make each other forget. The source is written by :mod:`.decoding` and :mod:`.encoding`, from
the pieces both share in :mod:`.source`.
"""

from __future__ import annotations

import types
from collections.abc import Callable
from typing import Any

from components.comm.codec.decoding import decoder
from components.comm.codec.encoding import encoder
from components.comm.codec.source import MAX_SEQUENCE, REMEMBER_AT_MOST, Codec, Unsupported

__all__ = [
    "MAX_SEQUENCE",
    "REMEMBER_AT_MOST",
    "Codec",
    "Unsupported",
    "decoder",
    "encoder",
    "memory",
]


def memory(stream: Callable[[Any], Any]) -> list[Any]:
    """The memory of the last shape of a stream's codec (from :meth:`Codec.stream`): a
    one-item list, ``[(None,)]`` before the first value it remembered."""
    if not isinstance(stream, types.MethodType):
        raise TypeError(f"{stream!r} is not a stream's codec (see Codec.stream)")
    return stream.__self__
