"""Where output goes: data to stdout, human messages to stderr."""

from __future__ import annotations

import json
import sys
from typing import Any

from rich.console import Console

#: Data (tables, JSON documents, echoed messages) goes to stdout. Piped into another tool
#: (no terminal to measure), tables get room instead of rich's 80 columns.
out = Console(soft_wrap=True, width=None if sys.stdout.isatty() else 160)
#: Progress, warnings and errors go to stderr so that stdout stays parseable.
err = Console(stderr=True, soft_wrap=True)


def print_json(document: Any) -> None:
    """Print exactly one JSON document on stdout (for ``--json``)."""
    sys.stdout.write(json.dumps(document, indent=2, sort_keys=False, default=_default) + "\n")
    sys.stdout.flush()


def _default(value: Any) -> Any:
    # numpy arrays and scalars, dataclasses, paths: make them JSON without surprises.
    if hasattr(value, "tolist"):
        return value.tolist()
    if hasattr(value, "__dataclass_fields__"):
        return {k: getattr(value, k) for k in value.__dataclass_fields__}
    return str(value)
