"""The ``msctl health`` screen: every module, component, joint, topic and alarm.

Screens: the overview (one row per module and station, worst first), a module's drill-down
(components with their process states, topics with measured rates, motors with a sparkline
of recent positions, its computer), the alarms, and every topic of the graph. Actions
(restart or stop a component, halt or recover a module) each ask for a confirmation first;
``l`` shows the last lines of a component's log.

Data reaches the screen one way: the app evaluates its source (a
:class:`~msctl.health.live.LiveHealth`, fed on Zenoh's threads under its own lock) at a
bounded rate, :data:`REFRESH_PERIOD`, however fast samples arrive, and only changed cells
are redrawn. Work that blocks (a supervisor request, a data monitor's history) runs in
thread workers, which answer through ``post_message`` / ``call_from_thread``.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any

from rich.text import Text
from textual.app import App, ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical, VerticalScroll
from textual.css.query import NoMatches
from textual.message import Message
from textual.screen import ModalScreen, Screen
from textual.widgets import Button, DataTable, Footer, Label, RichLog, Static

from components.data_monitor.alarms import Alarm
from components.data_monitor.measures import sparkline
from components.data_monitor.model import BoardSnapshot, ComponentView, Row, finite, level_name
from components.messages import ERROR, OK, STALE, WARN, Level
from msctl.health.source import ActionError, HealthSource

#: Seconds between two evaluations of the board (5 Hz), whatever the data rate.
REFRESH_PERIOD = 0.2
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


#: Rich styles of the levels in table cells (widget styles live in health.tcss).
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
    height is fixed in health.tcss pass ``layout=False``.
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


# ---------------------------------------------------------------------------------- overview
class OverviewScreen(Screen[None], BoardView):
    """One row per module and station, worst first, then by name."""

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


def alarm_text(alarm: Alarm) -> Text:
    """``12:03:04 limb1 limb1/host/cpu OK -> ERROR message`` with the levels coloured."""
    text = Text(time.strftime("%H:%M:%S", time.localtime(alarm.at)) + f" {alarm.module} ")
    text.append(alarm.item + " ")
    text.append(level_text(alarm.before) if alarm.before is not None else Text("-"))
    text.append(" -> ")
    text.append(level_text(alarm.after))
    text.append(" " + alarm.message)
    return text


# ---------------------------------------------------------------------------------- drill-down
class ModuleScreen(Screen[None], BoardView):
    """One module (or station): components, topics, motors, its computer, other items.

    Args:
        name: The module slot or station name.
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
        from components.health.core import TEMPERATURE_KEYS, VOLTAGE_KEYS

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


# ---------------------------------------------------------------------------------- other views
class AlarmsScreen(Screen[None], BoardView):
    """Every level change, newest first (this session's, and a data monitor's history)."""

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


class TopicsScreen(Screen[None], BoardView):
    """Every topic on the graph: type, publishers, subscribers and measured rate."""

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


class ConfirmScreen(ModalScreen[bool]):
    """Asks before an action; dismissed with True (y / Yes) or False (n / Escape / No).

    Args:
        question: What is about to happen.
    """

    BINDINGS = [
        Binding("y", "answer(True)", "Yes"),
        Binding("n", "answer(False)", "No"),
        Binding("escape", "answer(False)", "No"),
    ]

    def __init__(self, question: str) -> None:
        super().__init__()
        self.question = question

    def compose(self) -> ComposeResult:
        """The question and two buttons."""
        with Vertical(id="confirm-box"):
            yield Static(self.question, id="confirm-question")
            with Horizontal(id="confirm-buttons"):
                yield Button("Yes (y)", id="yes", variant="error")
                yield Button("No (n)", id="no", variant="primary")

    def on_mount(self) -> None:
        """No is the default."""
        self.query_one("#no", Button).focus()

    def on_button_pressed(self, event: Button.Pressed) -> None:
        """Yes or No."""
        self.dismiss(event.button.id == "yes")

    def action_answer(self, yes: bool) -> None:
        """Answer by key."""
        self.dismiss(yes)


class LogScreen(ModalScreen[None]):
    """The last lines of a component's log.

    Args:
        component: Whose log.
        lines: The lines.
    """

    BINDINGS = [Binding("escape", "dismiss", "Close"), Binding("q", "dismiss", "Close")]

    def __init__(self, component: str, lines: Sequence[str]) -> None:
        super().__init__()
        self.component = component
        self.lines = list(lines)

    def compose(self) -> ComposeResult:
        """A title and the lines."""
        with Vertical(id="log-box"):
            yield Label(f"log of {self.component} (Escape closes)", classes="section")
            yield RichLog(id="log-lines", wrap=False, markup=False, highlight=False)

    def on_mount(self) -> None:
        """Write the lines."""
        log = self.query_one("#log-lines", RichLog)
        for line in self.lines or ["(empty)"]:
            log.write(Text(line))


# ---------------------------------------------------------------------------------- the app
class HealthApp(App[None]):
    """``msctl health``.

    Args:
        source: Where the board, topics and actions come from.
        clock: Wall clock for the header (tests pass a fixed one).
        refresh_period: Seconds between two evaluations (bounded rate).
        alarm_log: Where new alarms are appended (``None``: nowhere).
        fetch_history: Ask a running data monitor for its alarms at start.
        duration: Quit after this many seconds (``None``: when asked).
    """

    CSS_PATH = "health.tcss"
    TITLE = "msctl health"
    BINDINGS = [
        Binding("q", "quit", "Quit"),
        Binding("a", "alarms", "Alarms"),
        Binding("t", "topics", "Topics"),
    ]

    class HistoryLoaded(Message):
        """A data monitor's alarm history was merged (from a worker thread)."""

        def __init__(self, added: int, source: str | None) -> None:
            super().__init__()
            self.added = added
            self.source = source

    class ActionDone(Message):
        """An action finished (from a worker thread)."""

        def __init__(self, text: str, ok: bool) -> None:
            super().__init__()
            self.text = text
            self.ok = ok

    def __init__(
        self,
        source: HealthSource,
        clock: Callable[[], float] = time.time,
        refresh_period: float = REFRESH_PERIOD,
        alarm_log: Any = None,
        fetch_history: bool = True,
        duration: float | None = None,
    ) -> None:
        super().__init__()
        self.source = source
        self.clock = clock
        self.refresh_period = refresh_period
        self.alarm_log = alarm_log
        self._fetch = fetch_history
        self._duration = duration
        #: The latest snapshot (``None`` before the first refresh).
        self.snapshot: BoardSnapshot | None = None
        #: Refreshes so far (screens do slower work every few).
        self.refreshes = 0
        #: Whether the session reaches a router (checked once a second).
        self.router_linked = True
        #: Messages of the actions carried out, newest last.
        self.action_results: list[tuple[str, bool]] = []

    def on_mount(self) -> None:
        """Evaluate once, show the overview, start the bounded refresh."""
        self.refresh_board()
        self.push_screen(OverviewScreen())
        self.set_interval(self.refresh_period, self.refresh_board)
        if self._fetch:
            self.run_worker(self._load_history, thread=True, group="history")
        if self._duration:
            self.set_timer(self._duration, self.exit)

    def _load_history(self) -> None:
        added = self.source.fetch_history()
        self.post_message(self.HistoryLoaded(added, self.source.history_source))

    def on_health_app_history_loaded(self, message: HistoryLoaded) -> None:
        """Say where the older alarms came from."""
        if message.source:
            self.notify(f"{message.added} earlier alarms from {message.source}")

    def on_health_app_action_done(self, message: ActionDone) -> None:
        """Show an action's outcome."""
        self.action_results.append((message.text, message.ok))
        self.notify(message.text, severity="information" if message.ok else "error", timeout=6)

    def draw_now(self) -> None:
        """Draw the screen on top with the latest snapshot (a screen just mounted)."""
        screen = self.screen
        if self.snapshot is not None and isinstance(screen, BoardView) and screen.ready:
            try:
                screen.show(self.snapshot)
            except NoMatches:
                pass

    def refresh_board(self) -> None:
        """Evaluate the board and redraw the screen on top (called at the bounded rate)."""
        self.refreshes += 1
        if self.refreshes % 5 == 1:
            self.router_linked = self.source.router_connected()
        self.snapshot = self.source.evaluate()
        fresh = self.source.take_alarms()
        if fresh and self.alarm_log is not None:
            self.alarm_log.append(fresh)
        screen = self.screen
        if isinstance(screen, BoardView) and screen.ready:
            try:
                screen.show(self.snapshot)
            except NoMatches:
                pass  # its widgets are still being mounted: the next refresh draws it

    def run_action_in_thread(self, work: Callable[[], str]) -> None:
        """Run a confirmed action off the UI thread; its outcome comes back as a message."""

        def run() -> None:
            try:
                text, ok = work(), True
            except ActionError as exc:
                text, ok = str(exc), False
            self.post_message(self.ActionDone(text, ok))

        self.run_worker(run, thread=True, group="actions")

    def action_alarms(self) -> None:
        """Open the alarms."""
        if not isinstance(self.screen, AlarmsScreen):
            self.push_screen(AlarmsScreen())

    def action_topics(self) -> None:
        """Open the topics view."""
        if not isinstance(self.screen, TopicsScreen):
            self.push_screen(TopicsScreen())


def run_app(assembly: Any, duration: float | None = None) -> None:
    """Run the screen on the data plane until the operator quits (or ``duration`` passes)."""
    from msctl.health.alarms import AlarmLog
    from msctl.health.live import LiveHealth
    from msctl.plane import connected

    log = AlarmLog(assembly.template, "msctl health")
    with connected("health") as node, LiveHealth(node, assembly) as live:
        HealthApp(live, alarm_log=log, duration=duration).run()


def _reported_rate(item: Any) -> str:
    """A topic's rate as its module's monitor reported it; ``stale`` once that report is
    old news (the module's health stopped: its last rate says nothing about now)."""
    if item is None:
        return "-"
    if item.level is STALE:
        return "stale"
    return number(item.values.get("rate_hz"))
