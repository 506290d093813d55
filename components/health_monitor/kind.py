"""The health monitor kind: one module's health, from its topics, components and computer."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from components.kinds import ComponentKind, Placement


def check_thresholds(value: Mapping[str, Any]) -> None:
    """Check a module's ``[health]`` table (raises ValueError naming the key at fault)."""
    from components.health_monitor.thresholds import HealthThresholds

    if not isinstance(value, Mapping):
        raise ValueError(f"must be a table, not {value!r}")
    HealthThresholds.from_mapping(value, "[health]")


KIND = ComponentKind(
    name="health_monitor",
    summary="one module's health: topic rates, components, motors, its computer",
    placement=Placement.MODULE,
    builder="components.health_monitor.build:build",
    interface="components.health_monitor.interface:HEALTH_MONITOR",
    healthy_output="health",
    module_facts=("joints", "thresholds"),
    checks={"thresholds": "components.health_monitor.kind:check_thresholds"},
    # Its computer's figures (CPU, memory, temperatures) come from psutil.
    preload=("psutil",),
)
