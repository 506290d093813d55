"""Data monitor core: the assembly's health as ``/diagnostics_agg``, and its alarm history.

The aggregation is a :class:`~components.data_monitor.board.HealthBoard`; this core feeds it
(every module's ``health``, graph changes and supervisor states, posted into the executor
thread by the builder's hooks) and publishes what it shows the way ROS's
``diagnostic_aggregator`` does, so ``rqt_robot_monitor`` on a ROS machine shows the tree:

* ``/diagnostics_agg``: one DiagnosticArray with hierarchical names: ``/<assembly>`` (the
  worst of everything), ``/<assembly>/<module>``, ``/<assembly>/<module>/<group>`` (each the
  worst of its children) and ``/<assembly>/<module>/<group>/<item>``;
* ``/diagnostics_toplevel_state``: one DiagnosticStatus, the overall level.

Unlike the ROS aggregator, a STALE item never turns the top level ERROR (ros/diagnostics
#297): levels are ranked by severity, and STALE stays STALE.

It publishes once per ``publish_period``, and at once (at most every ``min_period``) when a
level changes. Every level change is an alarm; the newest :data:`board.MAX_ALARMS` are kept
and served on ``~/alarms`` (``msctl_msgs/srv/GetAlarms``), so a ``msctl health`` opened later
shows what happened before it opened.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from components.config import require
from components.data_monitor.alarms import MAX_ALARMS, Alarm
from components.data_monitor.board import MAX_ITEMS, STALE_AFTER, HealthBoard
from components.data_monitor.encoding import AggregateEncoder
from components.data_monitor.model import BoardSnapshot, Item, Row
from components.executor.core import Core, Outbox
from components.messages import (
    OK,
    Level,
    diagnostic_array,
    diagnostic_status,
    msg,
    to_time,
    worst,
)

DIAGNOSTIC_STATUS = "diagnostic_msgs/msg/DiagnosticStatus"
ALARM = "msctl_msgs/msg/Alarm"
GET_ALARMS = "msctl_msgs/srv/GetAlarms"
#: ``from_level`` of an alarm whose item was first seen at its level (the message's NONE).
NO_LEVEL = 255


@dataclass(frozen=True)
class DataMonitorConfig:
    """A data monitor's parameters.

    Attributes:
        publish_period: Seconds between regular publications of ``/diagnostics_agg``.
        min_period: Shortest time (s) between two publications when levels change.
        stale_after: Seconds without a module's health before it is STALE.
        max_items: Items kept per module (the rest summed up in one "+N more" item).
    """

    publish_period: float = 1.0
    min_period: float = 0.2
    stale_after: float = STALE_AFTER
    max_items: int = MAX_ITEMS

    def __post_init__(self) -> None:
        require(self, positive=("publish_period", "min_period", "stale_after", "max_items"))


def health_handler(slot: str) -> str:
    """Name of the core's handler for ``/<slot>/health``."""
    return f"on_health_{slot}"


def alarm_message(alarm: Alarm) -> Any:
    """An :class:`Alarm` as a ``msctl_msgs/Alarm``."""
    return msg(
        ALARM,
        stamp=to_time(alarm.at),
        module=alarm.module,
        item=alarm.item,
        from_level=NO_LEVEL if alarm.before is None else int(alarm.before),
        to_level=int(alarm.after),
        message=alarm.message,
    )


def alarm_from_message(message: Any) -> Alarm:
    """A received ``msctl_msgs/Alarm`` as an :class:`Alarm` (bounded like every input).

    Raises:
        ValueError: If it is not an alarm (a field is missing).
    """
    from components.data_monitor.model import MAX_MESSAGE, MAX_NAME, clip
    from components.messages import from_time

    try:
        before = int(message.from_level)
        return Alarm(
            at=from_time(message.stamp),
            module=clip(message.module, MAX_NAME),
            item=clip(message.item, MAX_NAME),
            before=None if before == NO_LEVEL else Level.of(before),
            after=Level.of(int(message.to_level)),
            message=clip(message.message, MAX_MESSAGE),
        )
    except AttributeError as exc:
        raise ValueError(f"not an alarm: {exc}") from None


def aggregate(snapshot: BoardSnapshot) -> list[tuple[str, Level, str, str, dict[str, str]]]:
    """The ``/diagnostics_agg`` statuses of a snapshot: ``(name, level, message, hardware_id,
    values)``, parents before children, as ROS's aggregator names them."""
    top = f"/{snapshot.assembly}"
    out: list[tuple[str, Level, str, str, dict[str, str]]] = []
    rows = [*snapshot.modules, *snapshot.stations]
    worst_row = next((r for r in rows if r.level is snapshot.level), None)
    out.append(
        (
            top,
            snapshot.level,
            f"{worst_row.name}: {worst_row.message}"
            if worst_row and snapshot.level is not OK
            else "all OK",
            "",
            {"modules": str(len(snapshot.modules)), "stations": str(len(snapshot.stations))},
        )
    )
    for row in rows:
        out.extend(_row_statuses(top, row))
    return out


def _row_statuses(top: str, row: Row) -> list[tuple[str, Level, str, str, dict[str, str]]]:
    base = f"{top}/{row.name}"
    values = {
        "host": row.host,
        "components": f"{row.components_ok}/{row.components_expected}",
    }
    out = [(base, row.level, row.message, row.host, values)]
    groups: dict[str, list[Item]] = {}
    for item in row.items:
        groups.setdefault(item.group(row.name), []).append(item)
    for group, items in groups.items():
        if group:
            level = worst(i.level for i in items)
            bad = [i for i in items if i.level is level and level is not OK]
            message = f"{bad[0].leaf(row.name)}: {bad[0].message}" if bad else "OK"
            out.append((f"{base}/{group}", level, message, row.host, {"items": str(len(items))}))
            prefix = f"{base}/{group}"
        else:
            prefix = base
        for item in items:
            hardware = item.values.get("hardware_id", row.host)
            out.append(
                (f"{prefix}/{item.leaf(row.name)}", item.level, item.message, hardware, item.values)
            )
    return out


class DataMonitorCore(Core):
    """Feeds a :class:`HealthBoard` and publishes it (see the module docstring).

    Handlers: ``on_health_<slot>`` per module (see :func:`health_handler`),
    :meth:`on_node_instances`, :meth:`on_graph_ready` and :meth:`on_supervisors` (posted by
    the builder's hooks), :meth:`tick`, :meth:`on_get_alarms`.

    Args:
        name: Component name (``gc1/data_monitor``).
        board: The board, watching the assembly.
        config: Parameters.
        on_supervisor_needed: Called (in the executor thread) when a node leaves the graph,
            so supervisors are asked at once whether its process died; ``None``: nobody to ask.
    """

    def __init__(
        self,
        name: str,
        board: HealthBoard,
        config: DataMonitorConfig | None = None,
        on_supervisor_needed: Callable[[], None] | None = None,
    ) -> None:
        super().__init__(name)
        self.board = board
        self.config = config or DataMonitorConfig()
        self._poke = on_supervisor_needed
        self._last_publish: float | None = None
        self._last_level: Level | None = None
        self._changed = False
        self.publications = 0
        self._encoder = AggregateEncoder()
        self._publish_encoded: Callable[[bytes], None] | None = None
        for spec in board.watched:
            handler = functools.partial(self.on_health, spec.name)
            setattr(self, health_handler(spec.name), handler)

    def bind(self, outbox: Outbox, wall_offset: float = 0.0) -> None:
        """Attach the outputs; the board stamps its alarms with the executor's wall clock
        (built without one, it stamped them in monotonic seconds: a history merged into
        `msctl health` showed 1970 times, sorted before every local alarm)."""
        super().bind(outbox, wall_offset)
        self.board.wall_offset = wall_offset

    def publish_encoded(self, publish_raw: Callable[[bytes], None]) -> None:
        """Publish ``/diagnostics_agg`` as CDR bytes through ``publish_raw`` (the bound
        publisher's), encoded by :class:`AggregateEncoder`, instead of as a message through
        the outbox: at 40 modules, building and serialising the tree's messages every second
        was a third of the data monitor's CPU. Subscribers receive the same bytes."""
        self._publish_encoded = publish_raw

    # ------------------------------------------------------------------ inputs
    def start(self, now: float) -> None:
        """Start the board's clock and publish a first picture."""
        self.board.start(now)
        self._publish(now, self.board.evaluate(now))

    def on_health(self, slot: str, message: Any, now: float) -> None:
        """A module's ``health`` (or a station's ``diagnostics``) arrived."""
        self.board.on_health(slot, message, now)

    def on_node_instances(self, node: str, count: int, now: float) -> None:
        """The graph holds ``count`` live instances of ``node``."""
        self.board.on_node(node, count, now)
        if count == 0 and self._poke is not None:
            self._poke()

    def on_graph_ready(self, now: float) -> None:
        """The graph is followed from now on."""
        self.board.watch_graph(now)

    def on_supervisors(
        self, documents: Sequence[Any], unanswered: Iterable[str], now: float
    ) -> None:
        """The supervisors' ``ps`` documents."""
        self.board.on_supervisors(documents, now, unanswered)

    def tick(self, now: float) -> None:
        """Evaluate; publish when a level changed (bounded) or the period is due."""
        snapshot = self.board.evaluate(now)
        if self.board.take_alarms() or snapshot.level is not self._last_level:
            self._changed = True
        since = None if self._last_publish is None else now - self._last_publish
        due = since is None or since >= self.config.publish_period
        if due or (self._changed and since >= self.config.min_period):
            self._publish(now, snapshot)

    def on_get_alarms(self, request: Any, now: float) -> Any:
        """Serve the alarm history (the newest ``max_count``, 0: all), oldest first."""
        alarms = list(self.board.alarms)
        count = int(getattr(request, "max_count", 0) or 0)
        if 0 < count < len(alarms):
            alarms = alarms[-count:]
        return msg(
            f"{GET_ALARMS}_Response",
            source=self.name,
            alarms=[alarm_message(a) for a in alarms[-MAX_ALARMS:]],
        )

    # ------------------------------------------------------------------ output
    def _publish(self, now: float, snapshot: BoardSnapshot) -> None:
        self.board.take_alarms()
        self._changed = False
        self._last_publish = now
        self._last_level = snapshot.level
        self.publications += 1
        stamp = self.stamp(now)
        entries = aggregate(snapshot)
        if self._publish_encoded is not None:
            self._publish_encoded(self._encoder.encode(entries, stamp))
        else:
            statuses = [diagnostic_status(*entry) for entry in entries]
            self.publish("/diagnostics_agg", diagnostic_array(statuses, stamp))
        _, level, message, _, _ = entries[0]
        self.publish(
            "/diagnostics_toplevel_state",
            diagnostic_status("toplevel_state", level, message, "", {}),
        )
