"""The health board: every module's and ground station's health, aggregated. Pure.

Inputs, each a plain call with ``now`` (monotonic seconds) so tests drive it with fake time:

* :meth:`HealthBoard.on_health`: a module's ``/<slot>/health`` DiagnosticArray (its health
  monitor's summary item, named after the module, then items such as
  ``limb1/components/joint_manager``, ``limb1/topics/joint_states``, ``limb1/motors/...``,
  ``limb1/host/cpu``);
  a ground station's ``/<station>/diagnostics``, where its components (a data archiver)
  report their own status, one DiagnosticStatus each, kept per component as
  ``<station>/status/<component>``;
* :meth:`HealthBoard.on_node`: how many live instances of a node the graph holds (a node
  leaves the graph within the Zenoh lease when its process dies or freezes);
* :meth:`HealthBoard.on_supervisors`: the ``ps`` documents of the supervisors that answered;
  an agent's document may carry ``rejoin``, what it did at its start with the desired state
  it kept (a computer that rebooted brought its part back, or refused to): shown as an item
  ``<row>/agent`` of every row on that computer, and an alarm timed by the agent.

:meth:`HealthBoard.evaluate` turns them into one :class:`BoardSnapshot`: a :class:`Row` per
module and per station, each with its items, and records an :class:`Alarm` for every level
change.

Levels are ranked by :attr:`~components.messages.Level.severity` (ERROR > STALE > WARN > OK)
and STALE stays STALE: a module whose health stops arriving for :data:`STALE_AFTER` seconds
is STALE, and the levels its monitor last reported are kept for display but no longer count
(old news cannot make a module ERROR). A component whose node leaves the graph is ERROR when
its supervisor says its process died, and STALE when the supervisor says the process still
runs (frozen, or its link is down) or the supervisor does not answer.

Everything that comes from the network is bounded here: at most :data:`MAX_ITEMS` items per
module (the rest summed up in one "+N more" item carrying their worst level), strings
truncated, levels diagnostic_msgs does not define shown (``unknown level 7``) and ranked as
ERROR, numbers that are not finite ignored where they would be compared.
"""

from __future__ import annotations

import math
import statistics
from collections import deque
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from components.health.core import TEMPERATURE_KEYS, VOLTAGE_KEYS
from components.messages import ERROR, OK, STALE, WARN, Level, worst

#: Seconds without health after which a module is STALE.
STALE_AFTER = 2.5
#: Seconds after the board starts during which a node not seen yet is STALE, not ERROR
#: (processes start in any order; the graph replays what is up within a moment).
COMPONENT_GRACE = 5.0
#: Seconds a supervisor's answer counts as current.
SUPERVISOR_FRESH = 3.0
#: Items kept per module; the rest become one "+N more" item.
MAX_ITEMS = 48
#: Longest item name, message, hardware id, value key and value kept (characters).
MAX_NAME = 96
MAX_MESSAGE = 160
MAX_KEY = 32
MAX_VALUE = 48
#: Key/value pairs kept per item.
MAX_VALUES = 16
#: Alarms kept in memory.
MAX_ALARMS = 1000
#: Most seconds a row's shown values (ages, uptimes) lag behind when nothing about it changed:
#: a row is evaluated again only when an input about it arrived, a time threshold of its own
#: passed (stale after, grace, supervisor freshness), or this long after its last evaluation.
ROW_REFRESH = 1.0
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
_SPARKS = "▁▂▃▄▅▆▇█"
_CONTROL = {c: " " for c in [*range(32), 127]}


def clip(value: Any, limit: int) -> str:
    """``value`` as one printable line of at most ``limit`` characters (``…`` when cut).

    Control characters (newlines, terminal escapes) become spaces: a sender's text must never
    move the cursor of the operator's terminal.
    """
    text = value if isinstance(value, str) else str(value)
    if len(text) <= limit and text.isprintable():
        return text  # the common case, without building a translated copy
    if len(text) > limit:
        text = text[: limit - 1] + "…"
    return text.translate(_CONTROL)


def finite(value: Any) -> float | None:
    """``value`` as a finite float, or ``None`` (absent, not a number, NaN, infinite)."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        return None
    return number if math.isfinite(number) else None


def level_name(level: Level | None) -> str:
    """``OK``/``WARN``/``ERROR``/``STALE``; ``-`` for none (an item seen for the first time)."""
    return "-" if level is None else level.name


def sparkline(values: Iterable[float | None], width: int = 16, resolution: float = 1e-4) -> str:
    """The last ``width`` values as block characters, scaled between their min and max.

    Values that are missing or not finite are blanks; a range narrower than ``resolution``
    (a joint at rest: numerical noise) is drawn flat.
    """
    recent = list(values)[-width:]
    numbers = [v for v in (finite(v) for v in recent) if v is not None]
    if not numbers:
        return ""
    low, high = min(numbers), max(numbers)
    span = high - low
    out = []
    for value in recent:
        number = finite(value)
        if number is None:
            out.append(" ")
        elif span < resolution:
            out.append(_SPARKS[0])
        else:
            out.append(_SPARKS[min(7, int((number - low) / span * 7.999))])
    return "".join(out)


# ---------------------------------------------------------------------------------- what to watch
@dataclass(frozen=True)
class ExpectedNode:
    """A component (or several of one node name) the board expects on the graph.

    Attributes:
        label: Item label (``joint_manager``), as the module's health monitor names it.
        node: Fully qualified node (``/limb1/joint_manager``).
        alternatives: Other nodes that satisfy it (``/sim/simulator`` for a motor interface).
        count: Live instances expected.
        components: Names supervisors list it under (``limb1/joint_manager``,
            ``sim/simulator``), to find its process state.
        kind: Its component kind.
    """

    label: str
    node: str
    alternatives: tuple[str, ...] = ()
    count: int = 1
    components: tuple[str, ...] = ()
    kind: str = ""

    @property
    def nodes(self) -> tuple[str, ...]:
        """Every node that counts towards it."""
        return (self.node, *self.alternatives)


@dataclass(frozen=True)
class WatchedSpec:
    """A module or ground station the board shows as one row.

    Attributes:
        name: Module slot or station name.
        host: Its computer (from the resolved assembly).
        expected: Its components expected on the graph.
        station: A ground station (no health topic of its own).
        planned: ``(component, kind)`` pairs planned but not built yet (shown, never
            expected).
    """

    name: str
    host: str
    expected: tuple[ExpectedNode, ...] = ()
    station: bool = False
    planned: tuple[tuple[str, str], ...] = ()

    @property
    def health_topic(self) -> str:
        """Where its health arrives: a module's health monitor publishes ``/limb1/health``;
        a station's components report their own status on ``/gc1/diagnostics``."""
        return f"/{self.name}/diagnostics" if self.station else f"/{self.name}/health"


# ---------------------------------------------------------------------------------- what it shows
@dataclass(frozen=True)
class Item:
    """One line of a row: a health item, a component, or the board's own judgement.

    Attributes:
        name: Full item name (``limb1/components/joint_manager``).
        level: Its level as it counts now.
        message: What it says (bounded, one line).
        values: Its key/value pairs (bounded).
        reported: The level its source last reported, when that differs from ``level``
            (a stale module's items keep their last level here).
        pending: A first "waiting for ..." state, which raises no alarm.
    """

    name: str
    level: Level
    message: str
    values: Mapping[str, str] = field(default_factory=dict)
    reported: Level | None = None
    pending: bool = False

    def group(self, row: str) -> str:
        """Its group inside row ``row``: ``components``, ``topics``, ``motors``, ``host``..."""
        rest = self.name.removeprefix(row + "/")
        return rest.split("/", 1)[0] if "/" in rest else ""

    def leaf(self, row: str) -> str:
        """Its name inside its group (``joint_manager``), or inside the row."""
        rest = self.name.removeprefix(row + "/")
        return rest.split("/", 1)[1] if "/" in rest else rest


@dataclass(frozen=True)
class ComponentView:
    """A component as the supervisors and the graph see it.

    Attributes:
        label: Item label (``joint_manager``).
        node: The node that runs it.
        level: Its level.
        message: Why.
        live: Live instances on the graph.
        state: Its process state from its supervisor (``running``, ``restarting``,
            ``failed``, ``unresponsive``...), ``""`` if no supervisor listed it.
        process: Its process name.
        host: The host whose supervisor runs it.
        pid: Its process id.
        restarts: Restarts of its process.
        last_error: Its process's last error.
        uptime: Seconds its process has run.
        component: The component name a supervisor knows (for restart, stop and logs).
        waiting: Not seen yet, within the startup grace (raises no alarm).
    """

    label: str
    node: str
    level: Level
    message: str
    live: int = 0
    state: str = ""
    process: str = ""
    host: str = ""
    pid: int | None = None
    restarts: int = 0
    last_error: str = ""
    uptime: float | None = None
    component: str = ""
    waiting: bool = False


@dataclass(frozen=True)
class Row:
    """One module or station in the overview.

    Attributes:
        name: Module slot or station name.
        host: Its computer.
        station: Whether it is a ground station.
        level: Worst level of its items.
        message: The worst item and its message.
        worst_item: Name of the worst item (``""`` when all are OK).
        components_ok: Expected components that are OK.
        components_expected: Expected components.
        joint_states_hz: Rate of ``joint_states`` its monitor measured.
        joint_read_hz: Rate of ``joint_read`` its monitor measured.
        temperature: Hottest motor (°C).
        voltage: Lowest motor supply voltage (V).
        uptime: Seconds its processes have run (the youngest), from its supervisor.
        health_age: Seconds since its health last arrived (``None``: never).
        items: Its items, the board's own first, then its monitor's (bounded).
        components: Its components with their process states.
    """

    name: str
    host: str
    station: bool
    level: Level
    message: str
    worst_item: str = ""
    components_ok: int = 0
    components_expected: int = 0
    joint_states_hz: float | None = None
    joint_read_hz: float | None = None
    temperature: float | None = None
    voltage: float | None = None
    uptime: float | None = None
    health_age: float | None = None
    items: tuple[Item, ...] = ()
    components: tuple[ComponentView, ...] = ()

    def group(self, name: str) -> list[Item]:
        """Its items of one group (``motors``)."""
        return [i for i in self.items if i.group(self.name) == name]

    def to_json(self) -> dict[str, Any]:
        """The row as ``msctl health --once --json`` prints it."""
        return {
            "name": self.name,
            "host": self.host,
            "level": self.level.name,
            "message": self.message,
            "items": [
                {"name": i.name, "level": i.level.name, "message": i.message} for i in self.items
            ],
        }


@dataclass(frozen=True)
class Alarm:
    """One level change.

    Attributes:
        at: Wall-clock seconds (Unix time) of the change.
        module: Module slot or station name.
        item: Item name, or the module's name for the module's own level.
        before: The level before; ``None`` when the item was first seen at ``after``.
        after: The new level.
        message: The item's message at the change.
    """

    at: float
    module: str
    item: str
    before: Level | None
    after: Level
    message: str

    def to_json(self) -> dict[str, Any]:
        """As stored in the alarm file and printed by ``--json``."""
        return {
            "at": round(self.at, 3),
            "module": self.module,
            "item": self.item,
            "from": level_name(self.before),
            "to": self.after.name,
            "message": self.message,
        }

    @classmethod
    def from_json(cls, data: Any) -> Alarm:
        """An alarm from :meth:`to_json`'s form.

        Raises:
            ValueError: Naming the field that is missing or wrong.
        """
        if not isinstance(data, Mapping):
            raise ValueError(f"an alarm is an object, not {type(data).__name__}")
        at = finite(data.get("at"))
        if at is None:
            raise ValueError(f"alarm field 'at' must be a number, not {data.get('at')!r}")
        levels = {level.name: level for level in Level}
        before = data.get("from")
        after = data.get("to")
        if before != "-" and before not in levels:
            raise ValueError(f"alarm field 'from' must be a level name or '-', not {before!r}")
        if after not in levels:
            raise ValueError(f"alarm field 'to' must be a level name, not {after!r}")
        return cls(
            at=at,
            module=clip(data.get("module", ""), MAX_NAME),
            item=clip(data.get("item", ""), MAX_NAME),
            before=None if before == "-" else levels[before],
            after=levels[after],
            message=clip(data.get("message", ""), MAX_MESSAGE),
        )

    def line(self) -> str:
        """One line for ``--watch`` and ``--alarms``: time, module, item, from -> to, message."""
        import time as _time

        stamp = _time.strftime("%H:%M:%S", _time.localtime(self.at))
        millis = int((self.at % 1) * 1000)
        return (
            f"{stamp}.{millis:03d} {self.module} {self.item} "
            f"{level_name(self.before)} -> {self.after.name} {self.message}"
        )


@dataclass(frozen=True)
class BoardSnapshot:
    """The whole assembly at one moment.

    Attributes:
        assembly: The assembly's template name.
        level: Worst level of every row.
        modules: Module rows, worst first, then by name.
        stations: Station rows, worst first, then by name.
        at: Monotonic seconds of the evaluation.
        hosts: Hosts of the assembly.
        supervisors: Supervisors whose answer is current.
    """

    assembly: str
    level: Level
    modules: tuple[Row, ...]
    stations: tuple[Row, ...]
    at: float = 0.0
    hosts: tuple[str, ...] = ()
    supervisors: int = 0

    def row(self, name: str) -> Row | None:
        """The module or station called ``name``."""
        for row in (*self.modules, *self.stations):
            if row.name == name:
                return row
        return None

    def to_json(self) -> dict[str, Any]:
        """``{"assembly", "level", "modules": [...], "stations": [...]}`` (``--once --json``)."""
        return {
            "assembly": self.assembly,
            "level": self.level.name,
            "modules": [r.to_json() for r in self.modules],
            "stations": [r.to_json() for r in self.stations],
        }


# ---------------------------------------------------------------------------------- the board
@dataclass
class _Supervised:
    name: str
    host: str
    process: str
    state: str
    pid: int | None
    uptime: float
    restarts: int
    last_error: str
    at: float

    def news(self, other: _Supervised) -> bool:
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


@dataclass
class _RowState:
    spec: WatchedSpec
    health_at: float | None = None
    items: list[Item] = field(default_factory=list)
    summary: Item | None = None
    hidden: int = 0
    hidden_level: Level = OK
    # Figures of the items as last reported (computed once per arrival, not per evaluation).
    joint_states_hz: float | None = None
    joint_read_hz: float | None = None
    temperature: float | None = None
    voltage: float | None = None
    # A station's component reports by status name: (item, arrival time).
    reports: dict[str, tuple[Item, float]] = field(default_factory=dict)
    # The last evaluation, reused until an input about the row or a threshold comes.
    row: Row | None = None
    dirty: bool = True
    evaluated_at: float = -math.inf
    deadline: float = math.inf


class HealthBoard:
    """Aggregates the assembly's health (see the module docstring).

    Args:
        assembly: The assembly's template name.
        watched: Its modules and stations.
        hosts: Its hosts (for the header).
        stale_after: Seconds without health before a module is STALE.
        wall_offset: Added to ``now`` for the wall-clock time of alarms.
        max_items: Items kept per module.
        grace: Seconds after the start during which a node not seen yet is STALE (waiting)
            rather than ERROR.
    """

    def __init__(
        self,
        assembly: str,
        watched: Sequence[WatchedSpec],
        hosts: Sequence[str] = (),
        stale_after: float = STALE_AFTER,
        wall_offset: float = 0.0,
        max_items: int = MAX_ITEMS,
        grace: float = COMPONENT_GRACE,
    ) -> None:
        if not stale_after > 0:
            raise ValueError(f"stale_after must be > 0, not {stale_after}")
        if max_items < 1:
            raise ValueError(f"max_items must be at least 1, not {max_items}")
        self.assembly = assembly
        self.hosts = tuple(hosts)
        self.stale_after = stale_after
        self.wall_offset = wall_offset
        self.max_items = max_items
        self.grace = grace
        self._rows = {spec.name: _RowState(spec) for spec in watched}
        # Which rows a node's coming and going concerns.
        self._rows_of_node: dict[str, list[_RowState]] = {}
        for state in self._rows.values():
            for expected in state.spec.expected:
                for node in expected.nodes:
                    self._rows_of_node.setdefault(node, []).append(state)
        self._live: dict[str, int] = {}
        self._seen: dict[str, float] = {}
        self._gone_at: dict[str, float] = {}
        self._graph = False
        self._started: float | None = None
        self._supervised: dict[str, _Supervised] = {}
        self._supervisors_at: dict[str, float] = {}
        # host -> (level, message, agent's time) of its agent's rejoin report.
        self._rejoins: dict[str, tuple[Level, str, float]] = {}
        self._levels: dict[tuple[str, str], Level] = {}
        self.alarms: deque[Alarm] = deque(maxlen=MAX_ALARMS)
        self._new: list[Alarm] = []
        #: Health arrays for no watched module (a stray publisher), counted.
        self.unknown = 0
        #: Incremented by every input, so a screen redraws only when something changed.
        self.version = 0

    # ------------------------------------------------------------------ inputs
    @property
    def watched(self) -> list[WatchedSpec]:
        """The modules and stations, in assembly order."""
        return [state.spec for state in self._rows.values()]

    def nodes(self) -> set[str]:
        """Every node the board follows on the graph."""
        return {n for s in self._rows.values() for e in s.spec.expected for n in e.nodes}

    def start(self, now: float) -> None:
        """Start the clock of the startup grace (called once; inputs call it if needed)."""
        if self._started is None:
            self._started = now
            self._all_dirty()

    def _all_dirty(self) -> None:
        for state in self._rows.values():
            state.dirty = True

    def watch_graph(self, now: float) -> None:
        """The graph is followed from now on: components are judged from it (and their
        supervisors), no longer from their module's health alone."""
        self.start(now)
        self._graph = True
        self._all_dirty()
        self.version += 1

    def on_health(self, module: str, message: Any, now: float) -> None:
        """A module's health arrived (a DiagnosticArray, or anything with ``status``).

        Args:
            module: The module slot whose ``health`` topic it came on.
            message: The DiagnosticArray.
            now: Monotonic seconds.
        """
        self.start(now)
        state = self._rows.get(module)
        if state is None:
            self.unknown += 1
            return
        statuses = getattr(message, "status", None)
        if not isinstance(statuses, Sequence):
            statuses = []
        if state.spec.station:
            self._on_reports(state, statuses, now)
            return
        summary: Item | None = None
        candidates: list[tuple[int, Level, Any]] = []
        for index, status in enumerate(statuses):
            if summary is None and getattr(status, "name", None) == module:
                summary = _parse(status)
                continue
            candidates.append((index, _level_of(status), status))
        kept = candidates
        hidden: list[Level] = []
        if len(candidates) > self.max_items:
            # Keep the worst ones visible, then fill with the others in their order.
            ranked = sorted(candidates, key=lambda c: (-c[1].severity, c[0]))
            keep = {c[0] for c in ranked[: self.max_items - 1]}
            kept = [c for c in candidates if c[0] in keep]
            hidden = [c[1] for c in candidates if c[0] not in keep]
        items: list[Item] = []
        names: set[str] = set()
        for _, _, status in kept:
            item = _parse(status)
            if item.name in names or item.name == module:
                hidden.append(item.level)  # a duplicate name: counted, not shown twice
                continue
            names.add(item.name)
            items.append(item)
        state.items = items
        state.summary = summary
        state.hidden = len(hidden)
        state.hidden_level = worst(hidden)
        state.health_at = now
        name = state.spec.name
        state.joint_states_hz = _rate(items, f"{name}/topics/joint_states")
        state.joint_read_hz = _rate(items, f"{name}/topics/joint_read")
        state.temperature = _extreme(items, name, TEMPERATURE_KEYS, max)
        state.voltage = _extreme(items, name, VOLTAGE_KEYS, min)
        state.dirty = True
        self.version += 1

    def _on_reports(self, state: _RowState, statuses: Sequence[Any], now: float) -> None:
        """A station's components reported (each its own status, each array a few)."""
        prefix = state.spec.name + "/"
        for status in statuses[: self.max_items]:
            parsed = _parse(status)
            leaf = parsed.name.removeprefix(prefix).replace("/", "_")
            name = f"{prefix}status/{clip(leaf, MAX_NAME)}"
            if name not in state.reports and len(state.reports) >= self.max_items:
                self.unknown += 1  # bounded: a flood of names is counted, not kept
                continue
            item = Item(name, parsed.level, parsed.message, parsed.values)
            state.reports[name] = (item, now)
        state.dirty = True
        self.version += 1

    def on_node(self, node: str, count: int, now: float) -> None:
        """The graph holds ``count`` live instances of ``node`` now (0: it left).

        Args:
            node: Fully qualified node name (``/limb1/joint_manager``).
            count: Live instances (distinct node tokens).
            now: Monotonic seconds.
        """
        self.start(now)
        before = self._live.get(node, 0)
        self._live[node] = max(0, int(count))
        if count > 0:
            self._seen[node] = now
        elif before > 0:
            self._gone_at[node] = now
        for state in self._rows_of_node.get(node, ()):
            state.dirty = True
        self.version += 1

    def on_supervisors(
        self, documents: Iterable[Any], now: float, unanswered: Iterable[str] = ()
    ) -> None:
        """The ``ps`` documents of the supervisors that answered just now.

        Malformed entries (a document is data from the network) are skipped.

        Args:
            documents: ``{"host": ..., "components": [{"name", "state", "process", "pid",
                "uptime", "restarts", "last_error"}, ...]}`` per supervisor.
            now: Monotonic seconds.
            unanswered: Supervisors (by host or namespace) that did not answer (informative).
        """
        self.start(now)
        del unanswered  # their entries simply stop being current
        changed = False
        for document in documents:
            if not isinstance(document, Mapping):
                continue
            host = clip(document.get("host", ""), MAX_NAME)
            self._supervisors_at[host] = now
            self._on_rejoin(host, document.get("rejoin"))
            components = document.get("components", [])
            if not isinstance(components, list):
                continue
            for entry in components:
                if not isinstance(entry, Mapping) or not isinstance(entry.get("name"), str):
                    continue
                pid = entry.get("pid")
                known = self._supervised.get(entry["name"])
                supervised = self._supervised[entry["name"]] = _Supervised(
                    name=entry["name"],
                    host=clip(entry.get("host", host), MAX_NAME),
                    process=clip(entry.get("process", ""), MAX_NAME),
                    state=clip(entry.get("state", ""), 40),
                    pid=pid if isinstance(pid, int) and not isinstance(pid, bool) else None,
                    uptime=finite(entry.get("uptime")) or 0.0,
                    restarts=_int(entry.get("restarts")),
                    last_error=clip(entry.get("last_error") or "", MAX_MESSAGE),
                    at=now,
                )
                # Rows are judged again when a process changed, not at every answer (its
                # freshness is a deadline of the rows, its uptime is extrapolated).
                if known is None or known.news(supervised):
                    changed = True
        if changed:
            self._all_dirty()
        self.version += 1

    def _on_rejoin(self, host: str, report: Any) -> None:
        """An agent's ``rejoin`` report (``{"outcome": "rejoined" | "refused", "at",
        "message"}``), or its absence (cleared by the next ``up`` or ``down``).

        A new report is an alarm of every row on ``host`` at once, stamped with the agent's
        time (each board that sees it records the same alarm, which merges as one).
        """
        known = self._rejoins.get(host)
        at = finite(report.get("at")) if isinstance(report, Mapping) else None
        if at is None:  # none, or malformed: nothing to show
            if known is not None:
                del self._rejoins[host]
                self._all_dirty()
            return
        level = OK if report.get("outcome") == "rejoined" else ERROR
        entry = (level, clip(report.get("message") or "", MAX_MESSAGE), at)
        if entry == known:
            return
        self._rejoins[host] = entry
        for state in self._rows.values():
            if state.spec.host != host:
                continue
            state.dirty = True
            key = (state.spec.name, f"{state.spec.name}/agent")
            alarm = Alarm(at, key[0], key[1], self._levels.get(key), level, entry[1])
            self._levels[key] = level
            self.alarms.append(alarm)
            self._new.append(alarm)

    # ------------------------------------------------------------------ alarms
    def take_alarms(self) -> list[Alarm]:
        """The alarms recorded since the last call, oldest first."""
        taken, self._new = self._new, []
        return taken

    def merge_history(self, alarms: Iterable[Alarm]) -> int:
        """Add alarms recorded before this board started (a data monitor's history).

        Returns:
            How many were new to this board.
        """
        known = {(a.at, a.module, a.item, a.after) for a in self.alarms}
        older = [a for a in alarms if (a.at, a.module, a.item, a.after) not in known]
        if not older:
            return 0
        merged = sorted([*older, *self.alarms], key=lambda a: a.at)
        self.alarms = deque(merged[-MAX_ALARMS:], maxlen=MAX_ALARMS)
        self.version += 1
        return len(older)

    def _record(self, row: str, item: str, level: Level, message: str, now: float) -> None:
        key = (row, item)
        before = self._levels.get(key)
        if before is level:
            return
        self._levels[key] = level
        if before is None and level is OK:
            return  # first seen, and fine: not news
        alarm = Alarm(now + self.wall_offset, row, item, before, level, message)
        self.alarms.append(alarm)
        self._new.append(alarm)

    # ------------------------------------------------------------------ evaluation
    def evaluate(self, now: float) -> BoardSnapshot:
        """Every row at ``now``; records an alarm for every level that changed."""
        self.start(now)
        modules, stations = [], []
        for state in self._rows.values():
            row = state.row
            if (
                row is None
                or state.dirty
                or now >= state.deadline
                or now - state.evaluated_at >= ROW_REFRESH
                or now < state.evaluated_at  # a clock that went back: trust nothing kept
            ):
                row = state.row = self._row(state, now)
                state.dirty = False
                state.evaluated_at = now
                state.deadline = self._deadline(state, now)
            (stations if row.station else modules).append(row)
        order = lambda r: (-r.level.severity, r.name)  # noqa: E731
        modules.sort(key=order)
        stations.sort(key=order)
        fresh = sum(now - at <= SUPERVISOR_FRESH for at in self._supervisors_at.values())
        return BoardSnapshot(
            assembly=self.assembly,
            level=worst(r.level for r in (*modules, *stations)),
            modules=tuple(modules),
            stations=tuple(stations),
            at=now,
            hosts=self.hosts,
            supervisors=fresh,
        )

    def _row(self, state: _RowState, now: float) -> Row:
        spec = state.spec
        components = [self._component(spec, e, now) for e in spec.expected]
        items: list[Item] = []
        counted: list[Level] = []
        stale = False
        if not spec.station:
            health = self._health_item(state, now)
            stale = health.level is STALE
            items.append(health)
            counted.append(health.level)
        judged = {f"{spec.name}/components/{c.label}" for c in components} if self._graph else set()
        if self._graph:
            for view in components:
                items.append(_component_item(f"{spec.name}/components/{view.label}", view))
                counted.append(view.level)
        rejoin = self._rejoins.get(spec.host)
        if rejoin is not None:
            said, told, _ = rejoin
            items.append(Item(f"{spec.name}/agent", said, told, {"host": spec.host}))
            counted.append(said)
        for component, kind in spec.planned:
            items.append(
                Item(
                    f"{spec.name}/components/{component.rsplit('/', 1)[-1]}",
                    OK,
                    f"planned, not built yet ({kind})",
                    pending=True,
                )
            )
        for item, at in state.reports.values():
            age = now - at
            if age > self.stale_after:
                # Its reporter went quiet: what it said last is old news.
                items.append(
                    Item(
                        item.name,
                        STALE,
                        f"no report for {age:.1f} s; last {item.level.name}: {item.message}",
                        item.values,
                    )
                )
                counted.append(STALE)
            else:
                items.append(item)
                counted.append(item.level)
        for item in state.items:
            if item.name in judged:
                continue
            if stale:
                items.append(
                    Item(
                        item.name,
                        STALE,
                        f"last {item.level.name} {_age(state, now)}: {item.message}",
                        item.values,
                        reported=item.level,
                    )
                )
            else:
                items.append(item)
                counted.append(item.level)
        if state.hidden:
            items.append(
                Item(
                    f"{spec.name}/+{state.hidden} more",
                    STALE if stale else state.hidden_level,
                    f"{state.hidden} more items not shown (worst {state.hidden_level.name})",
                    reported=state.hidden_level if stale else None,
                )
            )
            if not stale:
                counted.append(state.hidden_level)
        if state.summary is not None and not stale:
            counted.append(state.summary.level)
        level = worst(counted)
        # Alarms: items as their source reported them (a stale module's items keep theirs).
        for item in items:
            if not item.pending:
                reported = item.level if item.reported is None else item.reported
                self._record(spec.name, item.name, reported, item.message, now)
        worst_item = _worst_item(items)
        if worst_item is None and state.summary is not None and level is not OK:
            message = f"{state.summary.name}: {state.summary.message}"
        elif worst_item is None:
            message = "all OK" if items else "nothing to watch"
        else:
            message = f"{worst_item.name}: {worst_item.message}"
        # A row whose only bad news is "waiting for ..." has no news yet: no alarm.
        bad = [i for i in items if i.level is not OK]
        pending = bool(bad) and all(i.pending for i in bad)
        if not pending:  # a row still waiting for its first news raises no alarm
            self._record(spec.name, spec.name, level, message, now)
        if self._graph:
            ok, total = sum(c.level is OK for c in components), len(components)
        else:
            reported = [
                i for i in state.items if i.group(spec.name) == "components" and not i.pending
            ]
            ok, total = sum(i.level is OK for i in reported), len(reported)
        return Row(
            name=spec.name,
            host=spec.host,
            station=spec.station,
            level=level,
            message=clip(message, MAX_NAME + MAX_MESSAGE),
            worst_item=worst_item.name if worst_item is not None else "",
            components_ok=ok,
            components_expected=total,
            # A stale module's last measured rates are no rates at all: its topics may have
            # stopped with it (shown as 93-99 Hz 11 s after everything stopped).
            joint_states_hz=None if stale else state.joint_states_hz,
            joint_read_hz=None if stale else state.joint_read_hz,
            temperature=state.temperature,
            voltage=state.voltage,
            uptime=self._uptime(spec, now),
            health_age=None if state.health_at is None else now - state.health_at,
            items=tuple(items),
            components=tuple(components),
        )

    def _deadline(self, state: _RowState, now: float) -> float:
        """The first time after ``now`` at which ``state``'s levels may change by themselves
        (its health goes stale, a startup grace ends, a supervisor's answer gets old)."""
        times = []
        if state.health_at is not None:
            times.append(state.health_at + self.stale_after)
        times.extend(at + self.stale_after for _, at in state.reports.values())
        if self._started is not None:
            times.append(self._started + self.grace)
        for expected in state.spec.expected:
            entry, _ = self._supervisor_of(expected, now)
            if entry is not None:
                times.append(entry.at + SUPERVISOR_FRESH)
        # A threshold crossed at this very instant is judged "not yet" (strict comparisons):
        # it is checked again at the next evaluation.
        later = [t for t in times if t >= now]
        return min(later, default=math.inf)

    def _health_item(self, state: _RowState, now: float) -> Item:
        spec = state.spec
        name = f"{spec.name}/health"
        topic = spec.health_topic
        if state.health_at is None:
            return Item(name, STALE, f"waiting for {topic}", {"topic": topic}, pending=True)
        age = now - state.health_at
        values = {"topic": topic, "age": f"{age:.1f}"}
        if age > self.stale_after:
            return Item(
                name,
                STALE,
                f"no health for {age:.1f} s (stale after {self.stale_after:g} s): its monitor "
                "stopped, or the link to it is down",
                values,
            )
        return Item(name, OK, f"{topic} arriving", values)

    def _supervisor_of(self, expected: ExpectedNode, now: float) -> tuple[_Supervised | None, bool]:
        for name in expected.components:
            entry = self._supervised.get(name)
            if entry is not None:
                return entry, now - entry.at <= SUPERVISOR_FRESH
        return None, False

    def _component(self, spec: WatchedSpec, expected: ExpectedNode, now: float) -> ComponentView:
        live = {n: self._live.get(n, 0) for n in expected.nodes}
        total = sum(live.values())
        node = max(expected.nodes, key=lambda n: live[n]) if total else expected.node
        seen = [self._seen[n] for n in expected.nodes if n in self._seen]
        entry, fresh = self._supervisor_of(expected, now)
        extra: dict[str, Any] = {}
        if entry is not None:
            extra = {
                "state": entry.state if fresh else f"{entry.state}?",
                "process": entry.process,
                "host": entry.host,
                "pid": entry.pid,
                "restarts": entry.restarts,
                "last_error": entry.last_error,
                "uptime": entry.uptime + (now - entry.at),
                "component": entry.name,
            }
        else:
            extra = {"component": expected.components[0] if expected.components else ""}

        def view(level: Level, message: str, waiting: bool = False) -> ComponentView:
            return ComponentView(
                expected.label, node, level, message, total, waiting=waiting, **extra
            )

        if not self._graph:
            state = entry.state if entry is not None and fresh else ""
            level = STATE_LEVELS.get(state, WARN) if state else OK
            return view(level, f"process {state}" if state else "")
        if total >= expected.count:
            if entry is not None and fresh and entry.state in ("unresponsive", "restarting"):
                return view(
                    STATE_LEVELS[entry.state],
                    f"{node} on the graph, but its process {entry.process} is {entry.state}",
                )
            return view(OK, f"{node} running")
        if total:
            return view(ERROR, f"only {total} of {expected.count} instances of {node} on the graph")
        started = self._started if self._started is not None else now
        if not seen and now - started < self.grace:
            return view(STALE, f"waiting for {node} on the graph", waiting=True)
        gone = [self._gone_at[n] for n in expected.nodes if n in self._gone_at]
        where = (
            f"{node} left the graph {now - max(gone):.1f} s ago"
            if seen and gone
            else f"{node} is not on the graph"
        )
        if entry is not None and fresh:
            if entry.state in ALIVE_STATES:
                return view(
                    STALE,
                    f"{where}, but its process {entry.process} is {entry.state}: frozen, or "
                    "its link is down",
                )
            error = f" ({entry.last_error})" if entry.last_error else ""
            return view(ERROR, f"{where}: process {entry.process} {entry.state}{error}")
        if entry is not None:
            return view(
                STALE, f"{where}, and the supervisor of {entry.host} does not answer: link down?"
            )
        return view(ERROR, where)

    def _uptime(self, spec: WatchedSpec, now: float) -> float | None:
        ages = []
        for expected in spec.expected:
            entry, fresh = self._supervisor_of(expected, now)
            if entry is not None and fresh and entry.state in ("running", "starting"):
                ages.append(entry.uptime + (now - entry.at))
        return min(ages) if ages else None


def _age(state: _RowState, now: float) -> str:
    if state.health_at is None:
        return "never"
    return f"{now - state.health_at:.1f} s ago"


def _component_item(name: str, view: ComponentView) -> Item:
    values: dict[str, str] = {"node": view.node, "live": str(view.live)}
    if view.state:
        values.update(
            state=view.state,
            process=view.process,
            pid=str(view.pid or "-"),
            restarts=str(view.restarts),
        )
    return Item(name, view.level, view.message, values, pending=view.waiting)


def _int(value: Any) -> int:
    return value if isinstance(value, int) and not isinstance(value, bool) else 0


def _level_of(status: Any) -> Level:
    raw = getattr(status, "level", None)
    try:
        return Level.of(int(raw))  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return ERROR


def _parse(status: Any) -> Item:
    """One DiagnosticStatus as a bounded :class:`Item`."""
    raw = getattr(status, "level", None)
    try:
        number = int(raw)  # type: ignore[arg-type]
    except (TypeError, ValueError, OverflowError):
        number = None
    level = ERROR if number is None else Level.of(number)
    message = clip(getattr(status, "message", ""), MAX_MESSAGE)
    if number is None or number not in Level._value2member_map_:
        message = clip(f"unknown level {clip(raw, 12)}: {message}", MAX_MESSAGE)
    name = clip(getattr(status, "name", ""), MAX_NAME) or "(unnamed)"
    values: dict[str, str] = {}
    pairs = getattr(status, "values", None) or []
    for pair in pairs[:MAX_VALUES]:
        key = clip(getattr(pair, "key", ""), MAX_KEY)
        values[key] = clip(getattr(pair, "value", ""), MAX_VALUE)
    if len(pairs) > MAX_VALUES:
        values["…"] = f"+{len(pairs) - MAX_VALUES} more values"
    hardware = clip(getattr(status, "hardware_id", ""), MAX_NAME)
    if hardware:
        values.setdefault("hardware_id", hardware)
    return Item(name, level, message, values)


def _worst_item(items: Sequence[Item]) -> Item | None:
    bad = [i for i in items if i.level is not OK and not (i.pending and i.level is OK)]
    if not bad:
        return None
    return max(bad, key=lambda i: i.level.severity)  # the first of the worst


def _rate(items: Sequence[Item], name: str) -> float | None:
    for item in items:
        if item.name == name:
            return finite(item.values.get("rate_hz"))
    return None


def _extreme(items: Sequence[Item], row: str, keys: Sequence[str], pick: Any) -> float | None:
    found = []
    for item in items:
        if item.group(row) != "motors":
            continue
        for key in keys:
            number = finite(item.values.get(key))
            if number is not None:
                found.append(number)
                break
    return pick(found) if found else None


# ---------------------------------------------------------------------------------- live measures
@dataclass(frozen=True)
class RateStats:
    """A topic's rate, measured from arrival times.

    Attributes:
        rate: Samples per second over the window.
        min_interval: Shortest gap between samples (s).
        max_interval: Longest gap between samples (s).
        jitter: Standard deviation of the gaps (s).
        count: Samples ever seen.
        age: Seconds since the last sample (``None``: never).
    """

    rate: float
    min_interval: float | None
    max_interval: float | None
    jitter: float | None
    count: int
    age: float | None


class RateMeter:
    """Rate, min/max interval and jitter of one topic from arrival times (no decoding).

    ``ros2 topic hz`` decodes every sample on one thread and under-reports fast topics; this
    only notes the arrival time, so it keeps up with anything Zenoh delivers.

    Args:
        window: Seconds over which statistics are computed.
        max_samples: Arrival times kept (bounds memory for very fast topics).
    """

    def __init__(self, window: float = 2.0, max_samples: int = 4000) -> None:
        self.window = window
        self._times: deque[float] = deque(maxlen=max_samples)
        self._first: float | None = None
        self._last: float | None = None
        self.count = 0

    def arrive(self, t: float) -> None:
        """One sample arrived at monotonic ``t``."""
        if self._first is None:
            self._first = t
        self._times.append(t)
        self._last = t
        self.count += 1

    def stats(self, now: float) -> RateStats:
        """Statistics over the last ``window`` seconds at ``now``."""
        horizon = now - self.window
        times = self._times
        while times and times[0] < horizon:
            times.popleft()
        age = None if self._last is None else now - self._last
        if self._first is None:
            return RateStats(0.0, None, None, None, 0, None)
        span = min(self.window, now - self._first)
        rate = len(times) / span if span > 0 else 0.0
        gaps = [b - a for a, b in zip(times, list(times)[1:], strict=False)]
        if not gaps:
            return RateStats(rate, None, None, None, self.count, age)
        jitter = statistics.pstdev(gaps) if len(gaps) > 1 else 0.0
        return RateStats(rate, min(gaps), max(gaps), jitter, self.count, age)


class History:
    """Recent values per name (joint positions for sparklines), bounded.

    Args:
        length: Values kept per name.
    """

    def __init__(self, length: int = 32) -> None:
        self.length = length
        self._values: dict[str, deque[float | None]] = {}

    def add(self, name: str, value: float | None) -> None:
        """Append one value (``None`` or NaN shows as a gap)."""
        series = self._values.get(name)
        if series is None:
            if len(self._values) >= 512:
                return  # bounded: a flood of names cannot grow this without end
            series = self._values[name] = deque(maxlen=self.length)
        series.append(finite(value))

    def get(self, name: str) -> list[float | None]:
        """The values of ``name``, oldest first."""
        return list(self._values.get(name, ()))
