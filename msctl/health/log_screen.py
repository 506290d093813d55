"""The last lines of a component's log, over the screen it was asked from."""

from __future__ import annotations

from collections.abc import Sequence

from rich.text import Text
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Vertical
from textual.screen import ModalScreen
from textual.widgets import Label, RichLog


class LogScreen(ModalScreen[None]):
    """The last lines of a component's log.

    Args:
        component: Whose log.
        lines: The lines.
    """

    DEFAULT_CSS = """
    LogScreen {
        align: center middle;
    }

    #log-box {
        width: 90%;
        height: 80%;
        border: thick $primary;
        background: $surface;
    }
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
