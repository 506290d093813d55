"""The ``msctl health`` screen: every module, component, joint, topic and alarm.

Screens, one module each: the overview (:mod:`~msctl.health.overview_screen`: one row per
module and station, worst first), a module's drill-down (:mod:`~msctl.health.module_screen`:
components with their process states, topics with measured rates, motors with a sparkline
of recent positions, its computer), the alarms (:mod:`~msctl.health.alarms_screen`), and
every topic of the graph (:mod:`~msctl.health.topics_screen`). Actions (restart or stop a
component, halt or recover a module) each ask for a confirmation first
(:mod:`~msctl.health.confirm_screen`); ``l`` shows the last lines of a component's log
(:mod:`~msctl.health.log_screen`). App styles are in ``health.tcss``; each screen's own
styles are its ``DEFAULT_CSS``.

Data reaches the screen one way: the app evaluates its source (a
:class:`~msctl.health.live.LiveHealth`, fed on Zenoh's threads under its own lock) at a
bounded rate, :data:`REFRESH_PERIOD`, however fast samples arrive, and only changed cells
are redrawn. Work that blocks (a supervisor request, a data monitor's history) runs in
thread workers, which answer through ``post_message`` / ``call_from_thread``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from textual.app import App
from textual.binding import Binding
from textual.css.query import NoMatches
from textual.message import Message

from components.data_monitor.model import BoardSnapshot
from msctl.health.alarms_screen import AlarmsScreen
from msctl.health.cells import BoardView
from msctl.health.overview_screen import OverviewScreen
from msctl.health.source import ActionError, HealthSource
from msctl.health.topics_screen import TopicsScreen

#: Seconds between two evaluations of the board (5 Hz), whatever the data rate.
REFRESH_PERIOD = 0.2


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

    with connected("health") as node, LiveHealth(node, assembly) as live:
        # The session is recorded once it can watch: one that never connected would stand,
        # empty, as the last session `health --alarms` shows, hiding the one before.
        log = AlarmLog(assembly.template, "msctl health")
        HealthApp(live, alarm_log=log, duration=duration).run()
