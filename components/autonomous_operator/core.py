"""The autonomous operator's status: what its script reports, on the station's diagnostics.

The script runs on a thread of its own (:mod:`~components.autonomous_operator.runner`); what
it says (``robot.report(...)``) and what becomes of it (connecting, running, finished,
failed) reach this core through the executor (``call_soon``), and the core publishes it,
one DiagnosticStatus named after the component, every ``status_period`` and at once when
the level changes. Pure: no I/O, time passed in.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from components.config import require
from components.executor.core import Core
from components.messages import ERROR, OK, WARN, Level, diagnostic_array, diagnostic_status

#: What the operator is doing.
STARTING, RUNNING, FINISHED, FAILED = "starting", "running", "finished", "failed"
#: Most values one report may carry (a script reporting in a loop must not grow a message).
MAX_VALUES = 32
#: Longest text kept from a report.
MAX_TEXT = 400


@dataclass(frozen=True)
class OperatorConfig:
    """An autonomous operator's own parameters (its script's are in ``params``).

    Attributes:
        status_period: Seconds between two status reports.
        connect_timeout: Seconds to find the robot's joint managers before giving up (the
            process then exits, and its supervisor starts it again).
        stop_timeout: Seconds the script gets to stop (its motions stopped, what it
            commands held) when the component stops.
    """

    status_period: float = 1.0
    connect_timeout: float = 60.0
    stop_timeout: float = 5.0

    def __post_init__(self) -> None:
        require(self, positive=("status_period", "connect_timeout", "stop_timeout"))


def level_of(name: str) -> Level:
    """``"ok"``, ``"warn"`` or ``"error"`` as a level.

    Raises:
        ValueError: For another word.
    """
    levels = {"ok": OK, "warn": WARN, "error": ERROR}
    try:
        return levels[name.lower()]
    except (KeyError, AttributeError):
        raise ValueError(f"level must be one of {', '.join(levels)}, not {name!r}") from None


class AutonomousOperatorCore(Core):
    """Publishes the operator's status.

    Args:
        name: The component's name (``gc1/steering``).
        script: What it runs (for the status).
        config: Its parameters.
        hardware_id: The station's computer.
        on_stop: Called when the component stops, before its node closes: the runner
            stops the script there, so its last commands still go out.
    """

    def __init__(
        self,
        name: str,
        script: str,
        config: OperatorConfig | None = None,
        hardware_id: str = "",
        on_stop: Callable[[], None] | None = None,
    ) -> None:
        super().__init__(name)
        self.script = script
        self.config = config or OperatorConfig()
        self.hardware_id = hardware_id
        self.on_stop = on_stop
        self.state = STARTING
        self.level: Level = OK
        self.message = f"starting {script}"
        self.values: dict[str, str] = {}
        self._next = 0.0

    def start(self, now: float) -> None:
        """Say it is starting, at once (the launcher waits for this output)."""
        self._publish(now)

    def on_state(self, state: str, level: int, message: str, now: float) -> None:
        """The runner's news: connecting, running, finished, failed."""
        self.state = state
        self._set(Level(level), message, now)

    def on_report(self, level: int, message: str, values: Mapping[str, Any], now: float) -> None:
        """What the script reports (``robot.report``)."""
        self.values = {str(k)[:64]: str(v)[:MAX_TEXT] for k, v in list(values.items())[:MAX_VALUES]}
        self._set(Level(level), message, now)

    def _set(self, level: Level, message: str, now: float) -> None:
        changed = level != self.level
        self.level = level
        self.message = message[:MAX_TEXT]
        if changed:
            self._publish(now)

    def tick(self, now: float) -> None:
        """Publish the status when due."""
        if now >= self._next:
            self._publish(now)

    def _publish(self, now: float) -> None:
        self._next = now + self.config.status_period
        values = {"script": self.script, "state": self.state, **self.values}
        status = diagnostic_status(self.name, self.level, self.message, self.hardware_id, values)
        self.publish("diagnostics", diagnostic_array([status], self.stamp(now)))

    def stop(self, now: float) -> None:
        """Stop the script (its motions end, what it commanded is held)."""
        if self.on_stop is not None:
            self.on_stop()
