"""The onboard computer's items: CPU, memory, disk and temperature against the module's
thresholds (the metrics themselves are read by :mod:`components.health_monitor.host`). Pure."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from components.health_monitor.items import Item
from components.health_monitor.thresholds import HealthThresholds
from components.messages import ERROR, OK, STALE, WARN


def host_items(
    module: str,
    hardware_id: str,
    t: HealthThresholds,
    metrics: Mapping[str, Any] | None,
    error: str | None,
) -> list[Item]:
    """One item per host metric, STALE while never read or when the last read failed.

    Args:
        module: Module slot (items are ``<module>/host/cpu``...).
        hardware_id: Hardware id of the items (the onboard computer's hostname).
        t: The module's thresholds.
        metrics: The last metrics read (``None``: never read).
        error: Why the last read failed (``None``: it did not).
    """
    prefix = f"{module}/host"
    specs = (
        ("cpu", "cpu_percent", "%", t.cpu_warn, t.cpu_error, "CPU load"),
        ("memory", "memory_percent", "%", t.memory_warn, t.memory_error, "memory in use"),
        ("disk", "disk_percent", "%", t.disk_warn, t.disk_error, "disk / in use"),
        (
            "temperature",
            "temperature",
            " °C",
            t.host_temperature_warn,
            t.host_temperature_error,
            "temperature",
        ),
    )
    items = []
    for label, key, unit, warn_at, error_at, what in specs:
        name = f"{prefix}/{label}"
        if metrics is None or error:
            # Never read, or the last read failed: old numbers would be misleading.
            message = f"cannot read host metrics: {error}" if error else "not read yet"
            items.append(Item(name, STALE, message, hardware_id, {}))
            continue
        value = metrics.get(key)
        values: dict[str, Any] = {"warn_at": warn_at, "error_at": error_at}
        if value is None:
            items.append(
                Item(name, OK, f"{what}: not readable on this computer", hardware_id, values)
            )
            continue
        value = float(value)
        values[key] = f"{value:.1f}"
        if key == "temperature" and metrics.get("temperature_sensor"):
            values["sensor"] = metrics["temperature_sensor"]
        if value >= error_at:
            level = ERROR
        elif value >= warn_at:
            level = WARN
        else:
            level = OK
        text = f"{what} {value:.0f}{unit}"
        if level != OK:
            text += f" (warn at {warn_at:g}{unit}, error at {error_at:g}{unit})"
        items.append(Item(name, level, text, hardware_id, values))
    return items
