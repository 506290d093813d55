"""Every level change, newest first: this session's, and a data monitor's history."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

from rich.text import Text
from textual.app import ComposeResult
from textual.binding import Binding
from textual.screen import Screen
from textual.widgets import DataTable, Footer, Static

from components.data_monitor.model import BoardSnapshot, level_name
from msctl.health.cells import (
    BoardView,
    add_columns,
    header_text,
    level_text,
    set_static,
    sync_table,
)

if TYPE_CHECKING:
    from msctl.health.app import HealthApp


class AlarmsScreen(Screen[None], BoardView):
    """Every level change, newest first (this session's, and a data monitor's history)."""

    DEFAULT_CSS = """
    #alarms {
        height: 1fr;
    }
    """

    BINDINGS = [Binding("escape", "app.pop_screen", "Back")]

    def compose(self) -> ComposeResult:
        """Header and the alarm table."""
        yield Static(id="header")
        table: DataTable = DataTable(id="alarms", cursor_type="row", zebra_stripes=True)
        add_columns(table, ("time", "module", "item", "from", "to", "message"))
        yield table
        yield Footer()

    def on_mount(self) -> None:
        """Draw."""
        self.ready = True
        self.call_after_refresh(self.app.draw_now)  # type: ignore[attr-defined]

    def show(self, snapshot: BoardSnapshot) -> None:
        """Draw the alarms, newest first."""
        app: HealthApp = self.app  # type: ignore[assignment]
        set_static(self.query_one("#header", Static), header_text(app, snapshot), layout=False)
        rows = []
        for index, alarm in enumerate(reversed(app.source.alarms())):
            stamp = time.strftime("%H:%M:%S", time.localtime(alarm.at))
            rows.append(
                (
                    f"{alarm.at:.6f}|{alarm.module}|{alarm.item}|{index}",
                    (
                        f"{stamp}.{int(alarm.at % 1 * 1000):03d}",
                        alarm.module,
                        alarm.item,
                        level_text(alarm.before) if alarm.before else level_name(None),
                        level_text(alarm.after),
                        Text(alarm.message),
                    ),
                )
            )
        sync_table(self.query_one("#alarms", DataTable), rows)
