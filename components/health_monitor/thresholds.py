"""A module's health thresholds, from its ``[health]`` data, and the topics they watch."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from typing import Any


@dataclass(frozen=True)
class TopicWatch:
    """One topic the monitor listens to.

    Attributes:
        topic: Name relative to the module namespace (``joint_states``).
        stale_after: Seconds of silence after which the item is STALE.
        min_rate: Expected minimum rate in Hz (WARN below it); ``None``: rate not checked
            (topics published on change with a slow keep-alive).
    """

    topic: str
    stale_after: float
    min_rate: float | None = None


@dataclass(frozen=True)
class HealthThresholds:
    """Thresholds of one module's health, from the module's ``[health]`` data.

    Every field is optional in the data; the defaults below apply when a key is absent.

    Attributes:
        stale_after: Silence (s) after which ``joint_states`` is STALE.
        min_rate: Minimum ``joint_states`` rate (Hz) before WARN.
        joint_read_stale_after: Silence (s) after which ``joint_read`` is STALE; the joint
            manager publishes it on change with a 1 Hz keep-alive, so above 1 s.
        diagnostics_stale_after: Silence (s) after which ``diagnostics``, and a motor with
            no fresh diagnostics, are STALE (diagnostics come at 1 Hz).
        rate_window: Seconds over which topic rates are measured.
        component_grace: Seconds after start during which a component not yet seen is STALE
            rather than ERROR (processes start in any order).
        max_temperature: Motor temperature (°C) at which a motor is ERROR; ``None``: the
            motor backends' own limits only.
        temperature_margin: A motor is WARN from ``max_temperature - temperature_margin``.
        min_voltage: Motor supply voltage (V) below which a motor is WARN.
        cpu_warn: Host CPU load (%) for WARN.
        cpu_error: Host CPU load (%) for ERROR.
        memory_warn: Host memory use (%) for WARN.
        memory_error: Host memory use (%) for ERROR.
        disk_warn: Host disk use of ``/`` (%) for WARN.
        disk_error: Host disk use of ``/`` (%) for ERROR.
        host_temperature_warn: Onboard computer temperature (°C) for WARN.
        host_temperature_error: Onboard computer temperature (°C) for ERROR.
        publish_period: Seconds between regular publications of ``health``.
        max_tracking_error: A joint farther than this (rad or m, raw) from its commanded
            position while not moving is WARN: stalled, blocked or too weak for its load.
            ``None``: not checked.
        tracking_grace: Seconds a joint must stay stalled off target before it is WARN (a
            servo settling, or starting a move, is not a fault).
        stall_velocity: Below this speed (rad/s or m/s) a joint counts as not moving.
        topics: Per-topic overrides, ``{"joint_read": {"stale_after": 2.0, "min_rate": 1}}``.
    """

    stale_after: float = 0.5
    min_rate: float = 50.0
    joint_read_stale_after: float = 2.5
    diagnostics_stale_after: float = 3.0
    rate_window: float = 1.0
    component_grace: float = 5.0
    max_temperature: float | None = None
    temperature_margin: float = 10.0
    min_voltage: float | None = None
    cpu_warn: float = 85.0
    cpu_error: float = 98.0
    memory_warn: float = 85.0
    memory_error: float = 95.0
    disk_warn: float = 90.0
    disk_error: float = 97.0
    host_temperature_warn: float = 80.0
    host_temperature_error: float = 90.0
    publish_period: float = 1.0
    max_tracking_error: float | None = None
    tracking_grace: float = 1.0
    stall_velocity: float = 0.05
    topics: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any], where: str = "[health]") -> HealthThresholds:
        """Thresholds from module data; absent keys keep their defaults.

        Keys this monitor does not use are ignored so that module data can serve several
        readers.

        Raises:
            ValueError: If a known key holds something other than a number (the message
                names ``where`` and the key).
        """
        changes: dict[str, Any] = {}
        for f in fields(cls):
            if f.name not in data:
                continue
            value = data[f.name]
            if f.name == "topics":
                if not isinstance(value, Mapping) or not all(
                    isinstance(v, Mapping) for v in value.values()
                ):
                    raise ValueError(f"{where}.topics must be a table of tables, got {value!r}")
                for topic, table in value.items():
                    for key, number in table.items():
                        if key not in ("stale_after", "min_rate"):
                            raise ValueError(
                                f"{where}.topics.{topic}.{key}: unknown key "
                                "(use stale_after or min_rate)"
                            )
                        _number(number, f"{where}.topics.{topic}.{key}")
                changes[f.name] = {k: dict(v) for k, v in value.items()}
                continue
            changes[f.name] = _number(value, f"{where}.{f.name}")
        return replace(cls(), **changes)

    def topic_watches(self) -> tuple[TopicWatch, ...]:
        """The module's main topics with their silence and rate thresholds."""
        watches = (
            TopicWatch("joint_states", self.stale_after, self.min_rate),
            TopicWatch("joint_read", self.joint_read_stale_after),
            TopicWatch("diagnostics", self.diagnostics_stale_after),
        )
        out = []
        for watch in watches:
            extra = self.topics.get(watch.topic, {})
            out.append(
                TopicWatch(
                    watch.topic,
                    float(extra.get("stale_after", watch.stale_after)),
                    float(extra["min_rate"]) if "min_rate" in extra else watch.min_rate,
                )
            )
        return tuple(out)


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or math.isnan(value):
        raise ValueError(f"{where} must be a number, got {value!r}")
    return float(value)
