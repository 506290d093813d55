"""Where output goes: data to stdout, human messages to stderr.

``out`` and ``err`` are rich consoles made when first used: importing rich costs about 70 ms,
which a command that prints only JSON or plain lines (``msctl ps --json``, ``msctl topic
list``) does not pay.
"""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Sequence
from typing import Any

_consoles: dict[str, Any] = {}


def _console(name: str) -> Any:
    from rich.console import Console

    if name == "out":
        # Data (tables, JSON documents, echoed messages) goes to stdout. Piped into another
        # tool (no terminal to measure), tables get room instead of rich's 80 columns.
        return Console(soft_wrap=True, width=None if sys.stdout.isatty() else 160)
    # Progress, warnings and errors go to stderr so that stdout stays parseable.
    return Console(stderr=True, soft_wrap=True)


def __getattr__(name: str) -> Any:
    """``out`` (stdout) and ``err`` (stderr): the rich consoles, made on first use."""
    if name not in ("out", "err"):
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    if name not in _consoles:
        _consoles[name] = _console(name)
    return _consoles[name]


def print_json(document: Any) -> None:
    """Print exactly one JSON document on stdout (for ``--json``)."""
    sys.stdout.write(json.dumps(document, indent=2, sort_keys=False, default=_default) + "\n")
    sys.stdout.flush()


def print_line(text: str) -> None:
    """Print one line of data on stdout as it is (no markup, no highlighting, no wrapping):
    what ``out.print(text, markup=False, highlight=False)`` prints, without loading rich."""
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


#: ANSI colours :func:`print_table` may give a cell (the names rich uses).
_ANSI = {"green": "32", "red": "31", "yellow": "33", "dim": "2"}


def print_table(columns: Sequence[str], rows: Sequence[Sequence[tuple[str, str]]]) -> None:
    """Print a table on stdout as aligned plain columns, without loading rich.

    For the listings typed all day (``msctl ps``): importing rich and laying a table out
    through it cost about 80 ms a run, twice the time of opening the Zenoh session. Cells
    are one line each. The last column is not padded; on a terminal it is cut (``…``) to the
    terminal's width, so a long error does not wrap into the next rows, and piped it stays
    whole (``--json`` has it whole too). Colours appear only on a terminal and never with
    ``NO_COLOR`` set.

    Args:
        columns: The header of each column.
        rows: Each row's cells as ``(text, colour)``; colour is ``""`` or one of green, red,
            yellow, dim.
    """
    terminal = sys.stdout.isatty()
    colour = terminal and not os.environ.get("NO_COLOR")
    rows = [[(" ".join(text.splitlines()), style) for text, style in row] for row in rows]
    widths = [max([len(c), *(len(row[i][0]) for row in rows)]) for i, c in enumerate(columns)]
    room = None  # characters the last column may take (None: whole)
    if terminal:
        import shutil

        left = shutil.get_terminal_size().columns - sum(widths[:-1]) - 2 * (len(widths) - 1)
        room = left if left >= 10 else None  # narrower than that, wrapping reads better
    last = len(columns) - 1

    def line(cells: Sequence[tuple[str, str]]) -> str:
        parts = []
        for i, (text, style) in enumerate(cells):
            if i < last:
                padded = text.ljust(widths[i])
            elif room is not None and len(text) > room:
                padded = text = text[: room - 1] + "…"
            else:
                padded = text
            if colour and style in _ANSI:
                padded = f"\x1b[{_ANSI[style]}m{text}\x1b[0m" + padded[len(text) :]
            parts.append(padded)
        return "  ".join(parts).rstrip()

    header = line([(c, "") for c in columns])
    text = [f"\x1b[1m{header}\x1b[0m" if colour else header]
    text += [line(row) for row in rows]
    sys.stdout.write("\n".join(text) + "\n")
    sys.stdout.flush()


def _default(value: Any) -> Any:
    # numpy arrays and scalars, dataclasses, paths: make them JSON without surprises.
    if hasattr(value, "tolist"):
        return value.tolist()
    if hasattr(value, "__dataclass_fields__"):
        return {k: getattr(value, k) for k in value.__dataclass_fields__}
    return str(value)
