"""The one diagnostic ``Level`` of the runtime: wire bytes, severity order, and ``worst``."""

from __future__ import annotations

import itertools

import pytest

from components.comm.types import registry
from components.messages import (
    ERROR,
    LEVEL_NAMES,
    OK,
    STALE,
    WARN,
    Level,
    diagnostic_array,
    diagnostic_status,
    worst,
)


def test_values_are_the_diagnostic_msgs_bytes_and_the_old_names_are_aliases() -> None:
    assert [(level.name, int(level)) for level in Level] == [
        ("OK", 0),
        ("WARN", 1),
        ("ERROR", 2),
        ("STALE", 3),
    ]
    assert (OK, WARN, ERROR, STALE) == (Level.OK, Level.WARN, Level.ERROR, Level.STALE)
    assert OK is Level.OK and STALE is Level.STALE
    assert LEVEL_NAMES == {OK: "OK", WARN: "WARN", ERROR: "ERROR", STALE: "STALE"}


def test_severity_puts_a_known_failure_above_no_news() -> None:
    assert sorted(Level, key=lambda level: level.severity) == [OK, WARN, STALE, ERROR]
    assert ERROR.severity > STALE.severity  # whereas the bytes say 2 < 3


@pytest.mark.parametrize(
    ("levels", "expected"),
    [
        ((), OK),
        ((OK,), OK),
        ((OK, WARN), WARN),
        ((WARN, STALE), STALE),
        ((STALE, ERROR), ERROR),
        ((ERROR, STALE), ERROR),
        ((ERROR, STALE, WARN, OK), ERROR),
    ],
)
def test_worst(levels: tuple[Level, ...], expected: Level) -> None:
    assert worst(levels) is expected
    assert worst(iter(levels)) is expected  # any iterable, read once


def test_worst_is_independent_of_order() -> None:
    for combo in itertools.product(Level, repeat=3):
        ranked = max(combo, key=lambda level: level.severity)
        assert all(worst(p) is ranked for p in itertools.permutations(combo))


def test_received_ints_become_levels_and_undefined_bytes_are_errors() -> None:
    assert worst([0, 3]) is STALE and worst([3, 2]) is ERROR
    assert isinstance(worst([1]), Level)
    assert Level.of(2) is ERROR
    assert Level.of(7) is ERROR  # a sender inventing levels is broken: show it
    assert worst([STALE, 200]) is ERROR


def test_a_level_serializes_as_the_byte() -> None:
    status = diagnostic_status("limb1/joint_manager", STALE, "no news")
    data = registry().serialize(diagnostic_array([status]), "diagnostic_msgs/msg/DiagnosticArray")
    (back,) = registry().deserialize(data, "diagnostic_msgs/msg/DiagnosticArray").status
    assert back.level == 3 and Level.of(back.level) is STALE
