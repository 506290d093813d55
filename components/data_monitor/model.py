"""What the health board shows, and the bounds on everything it takes from the network.

:class:`WatchedSpec` and :class:`ExpectedNode` say what to watch; :class:`Item`,
:class:`ComponentView`, :class:`Row` and :class:`BoardSnapshot` are what the board shows.
Everything that comes from the network is bounded here: strings truncated and made printable
(:func:`clip`), numbers that are not finite ignored (:func:`finite`), and a DiagnosticStatus
turned into an :class:`Item` with its level, names and values bounded (:func:`parse_status`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from components.messages import ERROR, Level

#: Longest item name, message, hardware id, value key and value kept (characters).
MAX_NAME = 96
MAX_MESSAGE = 160
MAX_KEY = 32
MAX_VALUE = 48
#: Key/value pairs kept per item.
MAX_VALUES = 16
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


# ---------------------------------------------------------------------------------- from the wire
def level_of(status: Any) -> Level:
    """A DiagnosticStatus's level (ERROR when it is not a number)."""
    raw = getattr(status, "level", None)
    try:
        return Level.of(int(raw))  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return ERROR


def parse_status(status: Any) -> Item:
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


def bounded_items(
    statuses: Sequence[Any], module: str, max_items: int
) -> tuple[Item | None, list[Item], list[Level]]:
    """A module's health array as bounded items.

    Args:
        statuses: Its DiagnosticStatus entries.
        module: The module's slot: its monitor's summary is the first entry of that name.
        max_items: Items kept: when there are more, the worst stay visible (then the others
            in their order) and the rest are only counted.

    Returns:
        The summary item (``None`` if there was none), the items kept, and the levels of those
        not shown (over the bound, or a name seen twice).
    """
    summary: Item | None = None
    candidates: list[tuple[int, Level, Any]] = []
    for index, status in enumerate(statuses):
        if summary is None and getattr(status, "name", None) == module:
            summary = parse_status(status)
            continue
        candidates.append((index, level_of(status), status))
    kept = candidates
    hidden: list[Level] = []
    if len(candidates) > max_items:
        # Keep the worst ones visible, then fill with the others in their order.
        ranked = sorted(candidates, key=lambda c: (-c[1].severity, c[0]))
        keep = {c[0] for c in ranked[: max_items - 1]}
        kept = [c for c in candidates if c[0] in keep]
        hidden = [c[1] for c in candidates if c[0] not in keep]
    items: list[Item] = []
    names: set[str] = set()
    for _, _, status in kept:
        item = parse_status(status)
        if item.name in names or item.name == module:
            hidden.append(item.level)  # a duplicate name: counted, not shown twice
            continue
        names.add(item.name)
        items.append(item)
    return summary, items, hidden


def reported_rate(items: Sequence[Item], name: str) -> float | None:
    """The ``rate_hz`` value of item ``name`` (a topic its monitor measured), if any."""
    for item in items:
        if item.name == name:
            return finite(item.values.get("rate_hz"))
    return None


def motor_extreme(items: Sequence[Item], row: str, keys: Sequence[str], pick: Any) -> float | None:
    """``pick`` (``max``, ``min``) of the motors' first value among ``keys`` (a temperature,
    a voltage) in row ``row``, or ``None`` when no motor reports one."""
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
