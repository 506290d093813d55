"""Rates on the health screen decay when nothing arrives (issue 32, case 9): a module whose
health stopped shows no rate rather than its last one, and a measured topic that went quiet
measures 0 Hz. The board and the meter with plain calls and fake time."""

from __future__ import annotations

from typing import Any

import pytest

from components.assembly import ResolvedAssembly, from_document
from components.data_monitor.board import STALE_AFTER
from components.data_monitor.measures import RateMeter
from components.data_monitor.plan import board_for
from components.messages import STALE, diagnostic_array, diagnostic_status
from msctl.assembler import resolve
from msctl.health.module_screen import _reported_rate


@pytest.fixture(scope="module")
def dragon() -> ResolvedAssembly:
    return from_document(resolve("dragon").document)


def _health(slot: str) -> Any:
    statuses = [diagnostic_status(slot, 0, "summary", "unit-1", {})]
    for leaf, rate in (("joint_states", "97.0"), ("joint_read", "99.0")):
        statuses.append(
            diagnostic_status(
                f"{slot}/topics/{leaf}",
                0,
                f"{rate} Hz",
                "unit-1",
                {"rate_hz": rate, "topic": f"/{slot}/{leaf}"},
            )
        )
    return diagnostic_array(statuses)


def test_a_stopped_module_shows_no_rate_eleven_seconds_later(dragon) -> None:
    board = board_for(dragon)
    for t in (0.0, 0.5, 1.0):
        board.on_health("limb1", _health("limb1"), t)
    live = board.evaluate(1.1).row("limb1")
    assert (live.joint_states_hz, live.joint_read_hz) == (97.0, 99.0)
    assert _reported_rate(next(i for i in live.group("topics"))) == "97.0"
    # Everything stopped at 1.0: 11 s later the row is stale and says no rate.
    later = board.evaluate(12.0).row("limb1")
    assert later.level is STALE
    assert (later.joint_states_hz, later.joint_read_hz) == (None, None)
    topics = list(later.group("topics"))
    assert topics and all(i.level is STALE for i in topics)
    assert {_reported_rate(i) for i in topics} == {"stale"}
    # Just before the bound it was still the module's own word.
    board.on_health("limb1", _health("limb1"), 20.0)
    assert board.evaluate(20.0 + STALE_AFTER - 0.01).row("limb1").joint_states_hz == 97.0


def test_a_measured_topic_that_went_quiet_decays_to_zero() -> None:
    meter = RateMeter(window=2.0)
    for i in range(300):
        meter.arrive(i * 0.01)  # 100 Hz for 3 s
    assert meter.stats(3.0).rate == pytest.approx(100.0, rel=0.05)
    quiet = meter.stats(3.0 + 11.0)
    assert quiet.rate == 0.0 and quiet.age == pytest.approx(11.01, abs=0.02)
    assert quiet.min_interval is None and quiet.jitter is None
