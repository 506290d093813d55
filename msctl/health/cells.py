"""What every ``msctl health`` screen draws with: fixed column widths, coloured level cells,
numbers and durations for cells, a table redrawn only where it changed, and the header line.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from rich.text import Text
from textual.widgets import DataTable, Static

from components.data_monitor.alarms import Alarm
from components.data_monitor.model import BoardSnapshot, finite
from components.messages import ERROR, OK, STALE, WARN, Level

if TYPE_CHECKING:
    from msctl.health.app import HealthApp

#: Width of the overview's message column (characters).
MESSAGE_WIDTH = 72
#: Column widths (characters), fixed so the layout does not jump as values change.
WIDTHS: dict[str, int] = {
    "level": 5,
    "module": 16,
    "host": 14,
    "comps": 5,
    "worst item: message": MESSAGE_WIDTH,
    "js Hz": 5,
    "jr Hz": 5,
    "temp": 5,
    "volt": 6,
    "uptime": 7,
    "component": 28,
    "node": 28,
    "state": 12,
    "pid": 7,
    "restarts": 8,
    "why": 56,
    "topic": 36,
    "monitor Hz": 10,
    "rate Hz": 8,
    "min ms": 8,
    "max ms": 8,
    "jitter ms": 9,
    "jitter": 8,
    "age": 6,
    "joint": 20,
    "position": 9,
    "velocity": 9,
    "effort": 8,
    "recent positions": 16,
    "message": 56,
    "item": 30,
    "value": 8,
    "time": 12,
    "from": 5,
    "to": 5,
    "type": 32,
    "pubs": 4,
    "subs": 4,
}


def add_columns(table: DataTable, labels: Sequence[str]) -> None:
    """Add columns keyed by their label, each at its fixed width."""
    for label in labels:
        table.add_column(label, key=label, width=WIDTHS.get(label))


#: Rich styles of the levels in table cells (widget styles: health.tcss and each screen).
LEVEL_STYLES: dict[Level, str] = {
    OK: "bold green",
    WARN: "bold yellow",
    ERROR: "bold white on red",
    STALE: "bold magenta",
}


def level_text(level: Level | None) -> Text:
    """A level as a coloured cell."""
    if level is None:
        return Text("-")
    return Text(level.name, style=LEVEL_STYLES[level])


def number(value: Any, fmt: str = "{:.1f}", unit: str = "") -> str:
    """A number for a cell (``-`` when absent or not finite)."""
    parsed = finite(value)
    return "-" if parsed is None else fmt.format(parsed) + unit


def duration(seconds: float | None) -> str:
    """``42s``, ``12m03s``, ``3h07m`` (``-`` when unknown)."""
    if seconds is None:
        return "-"
    seconds = int(seconds)
    if seconds < 60:
        return f"{seconds}s"
    if seconds < 3600:
        return f"{seconds // 60}m{seconds % 60:02d}s"
    return f"{seconds // 3600}h{seconds % 3600 // 60:02d}m"


def sync_table(table: DataTable, rows: Sequence[tuple[str, tuple[Any, ...]]]) -> None:
    """Make ``table`` show ``rows`` (``(key, cells)``), redrawing only what changed.

    Rows keep their keys, so the cursor stays on the same row when rows are reordered.
    """
    keys = [key for key, _ in rows]
    previous: dict[str, tuple[Any, ...]] = getattr(table, "_msctl_cells", {})
    order: list[str] = getattr(table, "_msctl_order", [])
    columns = list(table.columns)
    if keys != order:
        selected = None
        if table.row_count and 0 <= table.cursor_row < len(order):
            selected = order[table.cursor_row]
        table.clear()
        for key, cells in rows:
            table.add_row(*cells, key=key)
        if selected in keys:
            table.move_cursor(row=keys.index(selected))
    else:
        for key, cells in rows:
            old = previous.get(key, ())
            for index, cell in enumerate(cells):
                if index >= len(old) or old[index] != cell:
                    table.update_cell(key, columns[index], cell)
    table._msctl_cells = dict(rows)  # type: ignore[attr-defined]
    table._msctl_order = keys  # type: ignore[attr-defined]


def set_static(widget: Static, content: Text | str, layout: bool = True) -> None:
    """Show ``content`` in ``widget`` if it differs from what it shows.

    ``Static.update`` repaints, and with ``layout`` lays the whole screen out again: at the
    refresh rate, over a 40-module overview, that was most of the screen's CPU. Widgets whose
    height is fixed in their CSS pass ``layout=False``.
    """
    if getattr(widget, "_msctl_content", None) == content:
        return
    widget._msctl_content = content  # type: ignore[attr-defined]
    widget.update(content, layout=layout)


def header_text(app: HealthApp, snapshot: BoardSnapshot) -> Text:
    """The header line: assembly, hosts, supervisors, router link, data monitor, clock."""
    text = Text()
    text.append(f" {snapshot.assembly} ", style="bold")
    text.append(level_text(snapshot.level))
    text.append(f"  hosts {len(snapshot.hosts)}  supervisors {snapshot.supervisors}  router ")
    text.append(
        "linked" if app.router_linked else "NOT LINKED",
        style="green" if app.router_linked else "bold red",
    )
    monitor = app.source.history_source
    text.append(f"  data monitor {monitor or 'none (reading modules directly)'}")
    text.append("  " + time.strftime("%H:%M:%S", time.localtime(app.clock())))
    return text


class BoardView:
    """A screen that shows snapshots (the app calls :meth:`show` at each refresh, once the
    screen is :attr:`ready`: composed and mounted)."""

    ready = False

    def show(self, snapshot: BoardSnapshot) -> None:
        """Draw ``snapshot``."""


def alarm_text(alarm: Alarm) -> Text:
    """``12:03:04 limb1 limb1/host/cpu OK -> ERROR message`` with the levels coloured."""
    text = Text(time.strftime("%H:%M:%S", time.localtime(alarm.at)) + f" {alarm.module} ")
    text.append(alarm.item + " ")
    text.append(level_text(alarm.before) if alarm.before is not None else Text("-"))
    text.append(" -> ")
    text.append(level_text(alarm.after))
    text.append(" " + alarm.message)
    return text
