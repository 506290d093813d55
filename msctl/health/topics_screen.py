"""Every topic on the graph: its types, publishers, subscribers and measured rate."""

from __future__ import annotations

from typing import TYPE_CHECKING

from textual.app import ComposeResult
from textual.binding import Binding
from textual.screen import Screen
from textual.widgets import DataTable, Footer, Static

from components.data_monitor.model import BoardSnapshot
from msctl.health.cells import BoardView, add_columns, header_text, number, set_static, sync_table

if TYPE_CHECKING:
    from msctl.health.app import HealthApp


class TopicsScreen(Screen[None], BoardView):
    """Every topic on the graph: type, publishers, subscribers and measured rate."""

    DEFAULT_CSS = """
    #topics-all {
        height: 1fr;
    }
    """

    BINDINGS = [Binding("escape", "app.pop_screen", "Back")]

    def compose(self) -> ComposeResult:
        """Header and the topic table."""
        yield Static(id="header")
        table: DataTable = DataTable(id="topics-all", cursor_type="row", zebra_stripes=True)
        add_columns(
            table, ("topic", "type", "pubs", "subs", "rate Hz", "min ms", "max ms", "jitter")
        )
        yield table
        yield Footer()

    def on_mount(self) -> None:
        """Measure every published topic while this view is open."""
        self.ready = True
        self.call_after_refresh(self.app.draw_now)  # type: ignore[attr-defined]
        app: HealthApp = self.app  # type: ignore[assignment]
        app.source.watch_topics([t.name for t in app.source.topics() if t.publishers])

    def on_unmount(self) -> None:
        """Stop measuring."""
        self.app.source.watch_topics([])  # type: ignore[attr-defined]

    def show(self, snapshot: BoardSnapshot) -> None:
        """Draw the topics."""
        app: HealthApp = self.app  # type: ignore[assignment]
        set_static(self.query_one("#header", Static), header_text(app, snapshot), layout=False)
        topics = app.source.topics()
        if app.refreshes % 10 == 0:
            app.source.watch_topics([t.name for t in topics if t.publishers])
        rows = []
        for t in topics:
            s = t.stats
            ms = "{:.1f}"
            rows.append(
                (
                    t.name,
                    (
                        t.name,
                        ", ".join(t.types),
                        str(t.publishers),
                        str(t.subscribers),
                        number(s.rate) if s else "-",
                        number(s.min_interval * 1e3, ms) if s and s.min_interval else "-",
                        number(s.max_interval * 1e3, ms) if s and s.max_interval else "-",
                        number(s.jitter * 1e3, ms) if s and s.jitter is not None else "-",
                    ),
                )
            )
        sync_table(self.query_one("#topics-all", DataTable), rows)
