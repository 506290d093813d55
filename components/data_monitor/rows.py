"""What the board keeps of each row between inputs, and the items it shows from what the row's
sources reported (a module's health monitor, a station's components). Pure.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

from components.data_monitor.model import Item, Row, WatchedSpec
from components.messages import OK, STALE, Level


@dataclass
class RowState:
    """One row between evaluations: what its sources last reported, and its last judgement."""

    spec: WatchedSpec
    health_at: float | None = None
    items: list[Item] = field(default_factory=list)
    summary: Item | None = None
    hidden: int = 0
    hidden_level: Level = OK
    # Figures of the items as last reported (computed once per arrival, not per evaluation).
    joint_states_hz: float | None = None
    joint_read_hz: float | None = None
    temperature: float | None = None
    voltage: float | None = None
    # A station's component reports by status name: (item, arrival time).
    reports: dict[str, tuple[Item, float]] = field(default_factory=dict)
    # The last evaluation, reused until an input about the row or a threshold comes.
    row: Row | None = None
    dirty: bool = True
    evaluated_at: float = -math.inf
    deadline: float = math.inf


def report_items(state: RowState, now: float, stale_after: float) -> tuple[list[Item], list[Level]]:
    """A station's component reports, each STALE once its reporter went quiet."""
    items: list[Item] = []
    counted: list[Level] = []
    for item, at in state.reports.values():
        age = now - at
        if age > stale_after:
            # Its reporter went quiet: what it said last is old news.
            items.append(
                Item(
                    item.name,
                    STALE,
                    f"no report for {age:.1f} s; last {item.level.name}: {item.message}",
                    item.values,
                )
            )
            counted.append(STALE)
        else:
            items.append(item)
            counted.append(item.level)
    return items, counted


def monitor_items(
    state: RowState, stale: bool, now: float, graph: bool
) -> tuple[list[Item], list[Level]]:
    """The items a module's health monitor reported, its "+N more" item and its summary's
    level; when its health is stale they show their last level and count no more."""
    spec = state.spec
    judged = {f"{spec.name}/components/{e.label}" for e in spec.expected} if graph else set()
    items: list[Item] = []
    counted: list[Level] = []
    for item in state.items:
        if item.name in judged:
            continue
        if stale:
            items.append(
                Item(
                    item.name,
                    STALE,
                    f"last {item.level.name} {health_age(state, now)}: {item.message}",
                    item.values,
                    reported=item.level,
                )
            )
        else:
            items.append(item)
            counted.append(item.level)
    if state.hidden:
        items.append(
            Item(
                f"{spec.name}/+{state.hidden} more",
                STALE if stale else state.hidden_level,
                f"{state.hidden} more items not shown (worst {state.hidden_level.name})",
                reported=state.hidden_level if stale else None,
            )
        )
        if not stale:
            counted.append(state.hidden_level)
    if state.summary is not None and not stale:
        counted.append(state.summary.level)
    return items, counted


def health_age(state: RowState, now: float) -> str:
    """How long ago its health last arrived (``never``), for an item's message."""
    if state.health_at is None:
        return "never"
    return f"{now - state.health_at:.1f} s ago"


def row_message(
    state: RowState, items: Sequence[Item], worst_item: Item | None, level: Level
) -> str:
    """A row's message: its worst item and what it says (its monitor's summary when only
    the summary is bad)."""
    if worst_item is None and state.summary is not None and level is not OK:
        return f"{state.summary.name}: {state.summary.message}"
    if worst_item is None:
        return "all OK" if items else "nothing to watch"
    return f"{worst_item.name}: {worst_item.message}"


def worst_of(items: Sequence[Item]) -> Item | None:
    """The first of the worst items that are not OK, or ``None``."""
    bad = [i for i in items if i.level is not OK and not (i.pending and i.level is OK)]
    if not bad:
        return None
    return max(bad, key=lambda i: i.level.severity)  # the first of the worst
