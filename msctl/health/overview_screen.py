"""The overview: one row per module and station, worst first, and the latest alarms."""

from __future__ import annotations

from typing import TYPE_CHECKING

from rich.text import Text
from textual.app import ComposeResult
from textual.binding import Binding
from textual.screen import Screen
from textual.widgets import DataTable, Footer, Static

from components.data_monitor.model import BoardSnapshot
from components.messages import OK
from msctl.health.cells import (
    BoardView,
    add_columns,
    alarm_text,
    duration,
    header_text,
    level_text,
    number,
    set_static,
    sync_table,
)
from msctl.health.module_screen import ModuleScreen

if TYPE_CHECKING:
    from msctl.health.app import HealthApp


class OverviewScreen(Screen[None], BoardView):
    """One row per module and station, worst first, then by name."""

    DEFAULT_CSS = """
    #overview {
        height: 1fr;
    }

    #alarm-strip {
        height: 5;
        border-top: solid $primary;
        padding: 0 1;
    }
    """

    BINDINGS = [Binding("enter", "open", "Drill down", show=True)]

    def compose(self) -> ComposeResult:
        """Header, the table of rows, the latest alarms."""
        yield Static(id="header")
        table: DataTable = DataTable(id="overview", cursor_type="row", zebra_stripes=True)
        # The message column is bounded, so the numbers stay on screen whatever a module says.
        add_columns(
            table,
            (
                "level",
                "module",
                "host",
                "comps",
                "worst item: message",
                "js Hz",
                "jr Hz",
                "temp",
                "volt",
                "uptime",
            ),
        )
        yield table
        yield Static(id="alarm-strip")
        yield Footer()

    def on_mount(self) -> None:
        """Draw what the app already knows."""
        self.ready = True
        self.call_after_refresh(self.app.draw_now)  # type: ignore[attr-defined]

    def show(self, snapshot: BoardSnapshot) -> None:
        """Draw the header, the rows and the three latest alarms."""
        app: HealthApp = self.app  # type: ignore[assignment]
        set_static(self.query_one("#header", Static), header_text(app, snapshot), layout=False)
        rows = []
        for row in (*snapshot.modules, *snapshot.stations):
            rows.append(
                (
                    row.name,
                    (
                        level_text(row.level),
                        row.name + (" (station)" if row.station else ""),
                        row.host,
                        f"{row.components_ok}/{row.components_expected}",
                        Text(row.message if row.level is not OK else "all OK"),
                        number(row.joint_states_hz, "{:.0f}"),
                        number(row.joint_read_hz, "{:.1f}"),
                        number(row.temperature, "{:.0f}", "°C"),
                        number(row.voltage, "{:.1f}", "V"),
                        duration(row.uptime),
                    ),
                )
            )
        sync_table(self.query_one("#overview", DataTable), rows)
        latest = app.source.alarms()[-3:][::-1]
        strip = Text("alarms (a): ", style="bold")
        if not latest:
            strip.append("none yet")
        for alarm in latest:
            strip.append("\n")
            strip.append_text(alarm_text(alarm))
        set_static(self.query_one("#alarm-strip", Static), strip, layout=False)

    def action_open(self) -> None:
        """Open the drill-down of the row under the cursor."""
        table = self.query_one("#overview", DataTable)
        order = getattr(table, "_msctl_order", [])
        if 0 <= table.cursor_row < len(order):
            self.app.push_screen(ModuleScreen(order[table.cursor_row]))

    def on_data_table_row_selected(self, event: DataTable.RowSelected) -> None:
        """Enter (or a click) on a row opens its drill-down."""
        event.stop()
        if event.row_key.value is not None:
            self.app.push_screen(ModuleScreen(str(event.row_key.value)))
