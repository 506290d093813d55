"""A health item as the monitor judges it, before it becomes a DiagnosticStatus."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, NamedTuple

from components.messages import Level


class Item(NamedTuple):
    """One evaluated health item, before it becomes a DiagnosticStatus."""

    name: str
    level: Level
    message: str
    hardware_id: str
    values: Mapping[str, Any]
