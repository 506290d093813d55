"""How the board judges a component: from the graph and from its supervisor's answer. Pure.

A component whose node is on the graph is OK unless its supervisor says its process is
unresponsive or restarting; one whose node left the graph is ERROR when its supervisor says
the process died, and STALE when the supervisor says it still runs (frozen, or its link is
down) or the supervisor does not answer. Before the board follows the graph, the supervisor's
state alone counts.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from components.data_monitor.model import (
    MAX_MESSAGE,
    MAX_NAME,
    ComponentView,
    ExpectedNode,
    Item,
    clip,
    finite,
)
from components.messages import ERROR, OK, STALE, WARN, Level

if TYPE_CHECKING:
    from components.supervision.protocol import ComponentRow

#: Seconds a supervisor's answer counts as current.
SUPERVISOR_FRESH = 3.0
#: Supervisor states of a process whose node may be off the graph without it having died.
ALIVE_STATES = ("running", "unresponsive")
#: Level of a component by its supervisor's state, when its node is on the graph.
STATE_LEVELS: Mapping[str, Level] = {
    "running": OK,
    "starting": OK,
    "restarting": WARN,
    "unresponsive": STALE,
    "failed": ERROR,
    "stopped": ERROR,
}


@dataclass
class Supervised:
    """A process as its supervisor last listed it (bounded by the board when it arrived).

    Attributes:
        name: The component name the supervisor knows (``limb1/joint_manager``).
        host: The host whose supervisor runs it.
        process: Its process name.
        state: Its process state (``running``, ``failed``...).
        pid: Its process id.
        uptime: Seconds its process had run at ``at``.
        restarts: Restarts of its process.
        last_error: Its process's last error.
        at: Monotonic seconds of the answer.
    """

    name: str
    host: str
    process: str
    state: str
    pid: int | None
    uptime: float
    restarts: int
    last_error: str
    at: float

    @classmethod
    def from_entry(cls, entry: ComponentRow, host: str, now: float) -> Supervised:
        """One component of a supervisor's ``ps`` answer (data from the network: its types
        checked when it was decoded, its lengths bounded here).

        Args:
            entry: The component's row.
            host: The answering supervisor's host (the process's unless the entry says).
            now: Monotonic seconds of the answer.
        """
        return cls(
            name=entry.name,
            host=clip(entry.host or host, MAX_NAME),
            process=clip(entry.process, MAX_NAME),
            state=clip(entry.state, 40),
            pid=entry.pid,
            uptime=finite(entry.uptime) or 0.0,
            restarts=entry.restarts,
            last_error=clip(entry.last_error or "", MAX_MESSAGE),
            at=now,
        )

    def news(self, other: Supervised) -> bool:
        """Whether ``other`` (a later answer) says something else about the process than
        this one does, besides its time and its uptime (which grows by itself)."""
        return (self.host, self.process, self.state, self.pid, self.restarts, self.last_error) != (
            other.host,
            other.process,
            other.state,
            other.pid,
            other.restarts,
            other.last_error,
        )


def process_facts(
    expected: ExpectedNode, entry: Supervised | None, fresh: bool, now: float
) -> dict[str, Any]:
    """What a component's view says about its process (``?`` after a state no longer fresh)."""
    if entry is None:
        return {"component": expected.components[0] if expected.components else ""}
    return {
        "state": entry.state if fresh else f"{entry.state}?",
        "process": entry.process,
        "host": entry.host,
        "pid": entry.pid,
        "restarts": entry.restarts,
        "last_error": entry.last_error,
        "uptime": entry.uptime + (now - entry.at),
        "component": entry.name,
    }


def before_graph(entry: Supervised | None, fresh: bool) -> tuple[Level, str]:
    """Level and message of a component while the graph is not followed yet: its supervisor's
    state alone (OK when no supervisor answered)."""
    state = entry.state if entry is not None and fresh else ""
    level = STATE_LEVELS.get(state, WARN) if state else OK
    return level, f"process {state}" if state else ""


def on_graph(node: str, entry: Supervised | None, fresh: bool) -> tuple[Level, str]:
    """Level and message of a component whose instances are all on the graph."""
    if entry is not None and fresh and entry.state in ("unresponsive", "restarting"):
        return (
            STATE_LEVELS[entry.state],
            f"{node} on the graph, but its process {entry.process} is {entry.state}",
        )
    return OK, f"{node} running"


def off_graph(where: str, entry: Supervised | None, fresh: bool) -> tuple[Level, str]:
    """Level and message of a component whose node is not on the graph (``where`` says since
    when), by what its supervisor says of its process."""
    if entry is not None and fresh:
        if entry.state in ALIVE_STATES:
            return (
                STALE,
                f"{where}, but its process {entry.process} is {entry.state}: frozen, or "
                "its link is down",
            )
        error = f" ({entry.last_error})" if entry.last_error else ""
        return ERROR, f"{where}: process {entry.process} {entry.state}{error}"
    if entry is not None:
        return STALE, f"{where}, and the supervisor of {entry.host} does not answer: link down?"
    return ERROR, where


def component_item(name: str, view: ComponentView) -> Item:
    """A component's view as an item of its row (its node, live instances, process)."""
    values: dict[str, str] = {"node": view.node, "live": str(view.live)}
    if view.state:
        values.update(
            state=view.state,
            process=view.process,
            pid=str(view.pid or "-"),
            restarts=str(view.restarts),
        )
    return Item(name, view.level, view.message, values, pending=view.waiting)
