"""Where output goes: data to stdout, human messages to stderr.

``out`` and ``err`` are rich consoles made when first used: importing rich costs about 70 ms,
which a command that prints only JSON or plain lines (``msctl ps --json``, ``msctl topic
list``) does not pay.
"""

from __future__ import annotations

import json
import sys
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


def _default(value: Any) -> Any:
    # numpy arrays and scalars, dataclasses, paths: make them JSON without surprises.
    if hasattr(value, "tolist"):
        return value.tolist()
    if hasattr(value, "__dataclass_fields__"):
        return {k: getattr(value, k) for k in value.__dataclass_fields__}
    return str(value)
