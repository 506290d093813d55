"""A module's motors as their diagnostics sources report them: each motor's item carries the worst
level a fresh source published for it, made worse by the module's temperature and voltage
limits. Pure.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

from components.health_monitor.items import Item
from components.health_monitor.thresholds import HealthThresholds
from components.messages import ERROR, STALE, WARN, Level

#: Most diagnostics sources kept per motor (motor interface, joint manager, simulator... are
#: three): status names are free text, and a flood of invented ones must not grow memory.
MAX_SOURCES = 8

#: Keys motor backends use for a motor's temperature (°C) and supply voltage (V).
TEMPERATURE_KEYS = ("temperature", "temperature_c")
VOLTAGE_KEYS = ("input_voltage_v", "voltage")


@dataclass(frozen=True)
class MotorWatch:
    """An actuated joint whose motor diagnostics the monitor follows.

    Attributes:
        joint: Assembly joint name (``limb1_joint3``), the item label.
        raw_name: The joint's name inside its module (``joint3``), as some backends say it.
    """

    joint: str
    raw_name: str = ""


class SourceReport(NamedTuple):
    """What one diagnostics source last said of a motor, and when (monotonic seconds)."""

    level: Level
    message: str
    values: dict[str, str]
    at: float


def motor_item(
    name: str,
    reports: Mapping[str, SourceReport],
    now: float,
    thresholds: HealthThresholds,
    unit: str,
) -> Item:
    """A motor's item: the worst of its fresh sources (STALE when none is fresh).

    Args:
        name: Item name (``limb1/motors/limb1_joint3``).
        reports: Its sources' latest reports, by status name.
        now: Monotonic seconds.
        thresholds: The module's thresholds (diagnostics silence, temperature, voltage).
        unit: Hardware id of the item.
    """
    limit = thresholds.diagnostics_stale_after
    fresh = {src: r for src, r in reports.items() if now - r.at <= limit}
    if not fresh:
        message = (
            "no diagnostics yet"
            if not reports
            else f"no diagnostics for {now - max(r.at for r in reports.values()):.1f} s"
        )
        return Item(name, STALE, message, unit, {"sources": len(reports)})
    checked = [(src, r, *motor_limits(r, thresholds)) for src, r in sorted(fresh.items())]
    source, report, level, message = max(checked, key=lambda c: c[2].severity)
    values: dict[str, Any] = {"source": source, **report.values}
    values["sources"] = len(fresh)
    return Item(name, level, message, unit, values)


def motor_limits(report: SourceReport, t: HealthThresholds) -> tuple[Level, str]:
    """A source's level and message, made worse by the module's temperature/voltage limits."""
    level, message = report.level, report.message
    temperature = first_float(report.values, TEMPERATURE_KEYS)
    if t.max_temperature is not None and temperature is not None:
        limit = f"the module limit {t.max_temperature:g} °C"
        extra = None
        if temperature >= t.max_temperature:
            extra = (ERROR, f"{temperature:.0f} °C reaches {limit}: let it cool")
        elif temperature >= t.max_temperature - t.temperature_margin:
            extra = (WARN, f"{temperature:.0f} °C near {limit}")
        if extra is not None and extra[0].severity > level.severity:
            level, message = extra
    voltage = first_float(report.values, VOLTAGE_KEYS)
    low = t.min_voltage is not None and voltage is not None and voltage < t.min_voltage
    if low and WARN.severity > level.severity:
        level = WARN
        message = f"supply {voltage:.1f} V below {t.min_voltage:g} V: charge the battery"
    return level, message


def first_float(values: Mapping[str, str], keys: Sequence[str]) -> float | None:
    """The first of ``keys`` in ``values`` as a float (``None``: absent or not a number)."""
    for key in keys:
        if key in values:
            try:
                return float(values[key])
            except ValueError:
                return None
    return None
