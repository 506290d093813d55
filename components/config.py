"""Checks shared by the components' configuration dataclasses."""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any


def require(config: Any, positive: Iterable[str] = (), non_negative: Iterable[str] = ()) -> None:
    """Refuse a configuration whose named fields are out of range.

    Raises:
        ValueError: Naming the class and field at fault, and the value given.
    """
    kind = type(config).__name__
    for name in positive:
        if not getattr(config, name) > 0:
            raise ValueError(f"{kind}.{name} must be > 0, not {getattr(config, name)}")
    for name in non_negative:
        if not getattr(config, name) >= 0:
            raise ValueError(f"{kind}.{name} must be >= 0, not {getattr(config, name)}")


def positive_numbers(owner: str, **values: float) -> None:
    """Refuse any of ``values`` that is not a finite number above zero (a script's keyword
    arguments, which have no config class).

    Raises:
        ValueError: ``owner: name must be a positive number, not value``.
    """
    for name, value in values.items():
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"{owner}: {name} must be a positive number, not {value}")
