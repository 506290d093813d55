"""A module's drill-down: its components with their process states, its topics with measured
rates, its motors with a sparkline of recent positions, its computer, its other items; and the
actions on it (restart or stop a component, halt or recover the module, a component's log)."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from rich.text import Text
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import VerticalScroll
from textual.screen import Screen
from textual.widgets import DataTable, Footer, Label, Static

from components.data_monitor.measures import sparkline
from components.data_monitor.model import BoardSnapshot, ComponentView, Row
from components.messages import OK, STALE
from msctl.health.cells import (
    BoardView,
    add_columns,
    duration,
    header_text,
    level_text,
    number,
    set_static,
    sync_table,
)
from msctl.health.confirm_screen import ConfirmScreen
from msctl.health.log_screen import LogScreen
from msctl.health.source import ActionError

if TYPE_CHECKING:
    from msctl.health.app import HealthApp


class ModuleScreen(Screen[None], BoardView):
    """One module (or station): components, topics, motors, its computer, other items.

    Args:
        name: The module slot or station name.
    """

    DEFAULT_CSS = """
    #module-title {
        height: auto;
        padding: 0 1;
        background: $panel;
    }

    #parts {
        height: 1fr;
    }

    DataTable.part {
        height: auto;
        max-height: 24;
    }
    """

    BINDINGS = [
        Binding("escape", "app.pop_screen", "Back"),
        Binding("r", "restart", "Restart component"),
        Binding("s", "stop", "Stop component"),
        Binding("h", "halt", "Halt module"),
        Binding("u", "recover", "Recover module"),
        Binding("l", "logs", "Log tail"),
    ]

    def __init__(self, name: str) -> None:
        super().__init__()
        self.module = name
        self._row: Row | None = None

    def compose(self) -> ComposeResult:
        """Header and one table per part."""
        yield Static(id="header")
        yield Static(id="module-title")
        with VerticalScroll(id="parts"):
            for title, key, columns in (
                (
                    "Components",
                    "components",
                    ("level", "component", "node", "state", "pid", "restarts", "uptime", "why"),
                ),
                (
                    "Topics",
                    "topics",
                    ("topic", "monitor Hz", "rate Hz", "min ms", "max ms", "jitter ms", "age"),
                ),
                (
                    "Motors",
                    "motors",
                    (
                        "level",
                        "joint",
                        "position",
                        "velocity",
                        "effort",
                        "temp",
                        "volt",
                        "recent positions",
                        "message",
                    ),
                ),
                ("Host", "host", ("level", "item", "value", "message")),
                ("Other items", "other", ("level", "item", "message")),
            ):
                yield Label(title, classes="section")
                table: DataTable = DataTable(id=key, cursor_type="row", classes="part")
                add_columns(table, columns)
                yield table
        yield Footer()

    def on_mount(self) -> None:
        """Start measuring this module's topics and joints; draw."""
        self.ready = True
        self.call_after_refresh(self.app.draw_now)  # type: ignore[attr-defined]
        app: HealthApp = self.app  # type: ignore[assignment]
        if app.snapshot is not None:
            row = app.snapshot.row(self.module)
            if row is not None and not row.station:
                app.source.watch_joints(self.module)
        self._watch_topics()
        self.query_one("#components", DataTable).focus()

    def on_unmount(self) -> None:
        """Stop measuring."""
        app: HealthApp = self.app  # type: ignore[assignment]
        app.source.watch_topics([])
        app.source.watch_joints(None)

    def _module_topics(self) -> list[str]:
        app: HealthApp = self.app  # type: ignore[assignment]
        prefix = f"/{self.module}/"
        return [t.name for t in app.source.topics() if t.name.startswith(prefix) and t.publishers]

    def _watch_topics(self) -> None:
        app: HealthApp = self.app  # type: ignore[assignment]
        app.source.watch_topics(self._module_topics())

    def show(self, snapshot: BoardSnapshot) -> None:
        """Draw the module's parts."""
        app: HealthApp = self.app  # type: ignore[assignment]
        set_static(self.query_one("#header", Static), header_text(app, snapshot), layout=False)
        row = snapshot.row(self.module)
        if row is None:
            set_static(
                self.query_one("#module-title", Static), f"{self.module}: not in the assembly"
            )
            return
        self._row = row
        title = Text(f" {row.name} ", style="bold")
        title.append(level_text(row.level))
        title.append(f"  on {row.host}  components {row.components_ok}/{row.components_expected}")
        title.append(f"  {row.message}")
        set_static(self.query_one("#module-title", Static), title)
        sync_table(self.query_one("#components", DataTable), self._component_rows(row))
        sync_table(self.query_one("#topics", DataTable), self._topic_rows(row, app))
        sync_table(self.query_one("#motors", DataTable), self._motor_rows(row, app))
        sync_table(self.query_one("#host", DataTable), self._host_rows(row))
        sync_table(self.query_one("#other", DataTable), self._other_rows(row))
        if app.refreshes % 10 == 0:  # new topics appear: re-check every 2 s
            self._watch_topics()

    @staticmethod
    def _component_rows(row: Row) -> list[tuple[str, tuple[Any, ...]]]:
        rows = []
        for c in row.components:
            rows.append(
                (
                    c.label,
                    (
                        level_text(c.level),
                        c.component or c.label,
                        c.node,
                        c.state or "-",
                        str(c.pid or "-"),
                        str(c.restarts),
                        duration(c.uptime),
                        Text(c.last_error if c.last_error and c.level is OK else c.message),
                    ),
                )
            )
        if not row.components:
            for item in row.group("components"):
                rows.append(
                    (
                        item.name,
                        (
                            level_text(item.level),
                            item.leaf(row.name),
                            item.values.get("node", "-"),
                            "-",
                            "-",
                            "-",
                            "-",
                            Text(item.message),
                        ),
                    )
                )
        return rows

    def _topic_rows(self, row: Row, app: HealthApp) -> list[tuple[str, tuple[Any, ...]]]:
        measured = {t.name: t.stats for t in app.source.topics() if t.stats is not None}
        reported = {
            item.values.get("topic", f"/{row.name}/{item.leaf(row.name)}"): item
            for item in row.group("topics")
        }
        rows = []
        for topic in sorted({*measured, *reported}):
            if not topic.startswith(f"/{row.name}/"):
                continue
            item = reported.get(topic)
            stats = measured.get(topic)
            ms = "{:.1f}"
            rows.append(
                (
                    topic,
                    (
                        topic,
                        _reported_rate(item),
                        number(stats.rate) if stats else "-",
                        number(stats.min_interval * 1e3, ms)
                        if stats and stats.min_interval is not None
                        else "-",
                        number(stats.max_interval * 1e3, ms)
                        if stats and stats.max_interval is not None
                        else "-",
                        number(stats.jitter * 1e3, ms)
                        if stats and stats.jitter is not None
                        else "-",
                        number(stats.age, "{:.1f}", "s")
                        if stats and stats.age is not None
                        else "-",
                    ),
                )
            )
        return rows

    @staticmethod
    def _motor_rows(row: Row, app: HealthApp) -> list[tuple[str, tuple[Any, ...]]]:
        from components.health_monitor.motors import TEMPERATURE_KEYS, VOLTAGE_KEYS

        rows = []
        for item in row.group("motors"):
            joint = item.leaf(row.name)
            values = item.values
            temperature = next((values[k] for k in TEMPERATURE_KEYS if k in values), None)
            voltage = next((values[k] for k in VOLTAGE_KEYS if k in values), None)
            rows.append(
                (
                    item.name,
                    (
                        level_text(item.level),
                        joint,
                        number(values.get("position"), "{:+.3f}"),
                        number(values.get("velocity"), "{:+.3f}"),
                        number(values.get("effort"), "{:+.2f}"),
                        number(temperature, "{:.0f}", "°C"),
                        number(voltage, "{:.1f}", "V"),
                        sparkline(app.source.joint_history(joint)),
                        Text(item.message),
                    ),
                )
            )
        return rows

    @staticmethod
    def _host_rows(row: Row) -> list[tuple[str, tuple[Any, ...]]]:
        rows = []
        for item in row.group("host"):
            value = next(
                (v for k, v in item.values.items() if k not in ("warn_at", "error_at", "sensor")),
                "-",
            )
            if value == item.values.get("hardware_id"):
                value = "-"
            rows.append(
                (
                    item.name,
                    (level_text(item.level), item.leaf(row.name), value, Text(item.message)),
                )
            )
        return rows

    @staticmethod
    def _other_rows(row: Row) -> list[tuple[str, tuple[Any, ...]]]:
        shown = {"components", "topics", "motors", "host"}
        rows = []
        for item in row.items:
            if item.group(row.name) in shown:
                continue
            rows.append(
                (item.name, (level_text(item.level), item.leaf(row.name), Text(item.message)))
            )
        return rows

    # ------------------------------------------------------------------ actions
    def _selected_component(self) -> ComponentView | None:
        table = self.query_one("#components", DataTable)
        if self._row is None or not self._row.components:
            self.app.notify("no component to act on", severity="warning")
            return None
        index = min(max(table.cursor_row, 0), len(self._row.components) - 1)
        order = getattr(table, "_msctl_order", [])
        label = order[index] if index < len(order) else self._row.components[index].label
        return next((c for c in self._row.components if c.label == label), None)

    def _confirm_then(self, question: str, work: Callable[[], str]) -> None:
        app: HealthApp = self.app  # type: ignore[assignment]

        def decided(yes: bool | None) -> None:
            if yes:
                app.run_action_in_thread(work)

        app.push_screen(ConfirmScreen(question), decided)

    def action_restart(self) -> None:
        """Restart the selected component's process, after a confirmation."""
        self._control("restart")

    def action_stop(self) -> None:
        """Stop the selected component's process, after a confirmation."""
        self._control("stop")

    def _control(self, verb: str) -> None:
        view = self._selected_component()
        if view is None:
            return
        app: HealthApp = self.app  # type: ignore[assignment]
        target = view.component or view.label
        where = f" (process {view.process} on {view.host})" if view.host else ""
        self._confirm_then(
            f"{verb.capitalize()} {target}{where}? Every component of its process goes with it.",
            lambda: app.source.control(verb, target, view.host),
        )

    def action_halt(self) -> None:
        """Halt the module (its joint manager's ``halt``), after a confirmation."""
        self._trigger("halt", "Halt {m}: its joint manager stops and holds every joint?")

    def action_recover(self) -> None:
        """Recover the module from a halt (``recover``), after a confirmation."""
        self._trigger("recover", "Recover {m} from its halt: it takes commands again?")

    def _trigger(self, service: str, question: str) -> None:
        if self._row is None or self._row.station:
            self.app.notify(f"{self.module} is a station: it has no {service}", severity="warning")
            return
        app: HealthApp = self.app  # type: ignore[assignment]
        self._confirm_then(
            question.format(m=self.module),
            lambda: app.source.trigger(f"/{self.module}/{service}"),
        )

    def action_logs(self) -> None:
        """Show the last lines of the selected component's log."""
        view = self._selected_component()
        if view is None:
            return
        app: HealthApp = self.app  # type: ignore[assignment]
        target = view.component or view.label

        def fetch() -> None:
            try:
                lines = app.source.log_tail(target, view.host)
            except ActionError as exc:
                app.call_from_thread(app.notify, str(exc), severity="error")
                return
            app.call_from_thread(app.push_screen, LogScreen(target, lines))

        app.run_worker(fetch, thread=True, group="actions")


def _reported_rate(item: Any) -> str:
    """A topic's rate as its module's monitor reported it; ``stale`` once that report is
    old news (the module's health stopped: its last rate says nothing about now)."""
    if item is None:
        return "-"
    if item.level is STALE:
        return "stale"
    return number(item.values.get("rate_hz"))
