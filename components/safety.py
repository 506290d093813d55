"""Safety limits from module data: beyond them the robot is halted, not merely warned about.

A module type (and a unit, to tighten them) may carry a ``[safety]`` table::

    [safety]
    max_tilt = 0.35            # rad: the robot's body off level
    max_tracking_error = 0.5   # rad (m): a position joint this far from its command...
    tracking_grace = 0.5       # s: ...for this long

The health monitor's ``[health]`` thresholds say when something is worth a WARN; these say
when a watcher (the guardian operator) e-stops the whole robot. A robot's limits are the
tightest of its modules' (:func:`robot_limits`): the most fragile module decides.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, fields, replace
from typing import Any


@dataclass(frozen=True)
class SafetyLimits:
    """One module's (or robot's) safety limits; ``None``: not watched.

    Attributes:
        max_tilt: Largest angle (rad) between the body's up axis and the vertical.
        max_tracking_error: Largest distance (rad or m) between a position joint's command
            and its measurement, held for ``tracking_grace``.
        tracking_grace: Seconds a tracking error must last before it counts (a joint
            starting a move lags its command for a moment).
    """

    max_tilt: float | None = None
    max_tracking_error: float | None = None
    tracking_grace: float = 0.5

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any], where: str = "[safety]") -> SafetyLimits:
        """Limits from module data.

        Raises:
            ValueError: For an unknown key, or a value that is not a positive finite number
                (the message names ``where`` and the key).
        """
        known = {f.name for f in fields(cls)}
        changes: dict[str, float] = {}
        for key, value in data.items():
            if key not in known:
                raise ValueError(f"{where}.{key}: unknown key (known: {', '.join(sorted(known))})")
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(f"{where}.{key} is {value!r}: give a number")
            if not math.isfinite(value) or value <= 0:
                raise ValueError(f"{where}.{key} is {value}: give a positive finite number")
            changes[key] = float(value)
        if changes.get("max_tilt", 0.0) >= math.pi:
            raise ValueError(f"{where}.max_tilt is {changes['max_tilt']}: give less than pi rad")
        return replace(cls(), **changes)


def robot_limits(tables: Iterable[Mapping[str, Any]]) -> SafetyLimits:
    """The tightest limits of several modules' ``[safety]`` tables (each already checked)."""
    limits = [SafetyLimits.from_mapping(t) for t in tables]

    def smallest(name: str) -> float | None:
        given = [getattr(x, name) for x in limits if getattr(x, name) is not None]
        return min(given) if given else None

    grace = [x.tracking_grace for x in limits if x.max_tracking_error is not None]
    return SafetyLimits(
        max_tilt=smallest("max_tilt"),
        max_tracking_error=smallest("max_tracking_error"),
        tracking_grace=min(grace) if grace else SafetyLimits.tracking_grace,
    )
