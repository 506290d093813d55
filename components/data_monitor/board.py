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

:meth:`HealthBoard.evaluate` turns them into one
:class:`~components.data_monitor.model.BoardSnapshot`: a
:class:`~components.data_monitor.model.Row` per module and per station, each with its items.
Judging a row records nothing; each row judged again is then handed to the board's
:class:`~components.data_monitor.alarms.AlarmRecorder`, which records an
:class:`~components.data_monitor.alarms.Alarm` for every level change.

Levels are ranked by :attr:`~components.messages.Level.severity` (ERROR > STALE > WARN > OK)
and STALE stays STALE: a module whose health stops arriving for :data:`STALE_AFTER` seconds
is STALE, and the levels its monitor last reported are kept for display but no longer count
(old news cannot make a module ERROR). A component whose node leaves the graph is ERROR when
its supervisor says its process died, and STALE when the supervisor says the process still
runs (frozen, or its link is down) or the supervisor does not answer.

Everything that comes from the network is bounded (:mod:`components.data_monitor.model`): at
most :data:`MAX_ITEMS` items per module (the rest summed up in one "+N more" item carrying their
worst level), strings truncated, levels diagnostic_msgs does not define shown (``unknown level
7``) and ranked as ERROR, numbers that are not finite ignored where they would be compared.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from msgspec import UnsetType

from components.data_monitor.alarms import Alarm, AlarmRecorder
from components.data_monitor.judgement import (
    SUPERVISOR_FRESH,
    Supervised,
    before_graph,
    component_item,
    off_graph,
    on_graph,
    process_facts,
)
from components.data_monitor.model import (
    MAX_MESSAGE,
    MAX_NAME,
    BoardSnapshot,
    ComponentView,
    ExpectedNode,
    Item,
    Row,
    WatchedSpec,
    bounded_items,
    clip,
    finite,
    motor_extreme,
    parse_status,
    reported_rate,
)
from components.data_monitor.rows import (
    RowState,
    monitor_items,
    report_items,
    row_message,
    worst_of,
)
from components.health_monitor.motors import TEMPERATURE_KEYS, VOLTAGE_KEYS
from components.messages import ERROR, OK, STALE, Level, worst
from components.supervision.protocol import Rejoin, RunDocument, run_document

#: Seconds without health after which a module is STALE.
STALE_AFTER = 2.5
#: Seconds after the board starts during which a node not seen yet is STALE, not ERROR
#: (processes start in any order; the graph replays what is up within a moment).
COMPONENT_GRACE = 5.0
#: Items kept per module; the rest become one "+N more" item.
MAX_ITEMS = 48
#: Most seconds a row's shown values (ages, uptimes) lag behind when nothing about it changed:
#: a row is evaluated again only when an input about it arrived, a time threshold of its own
#: passed (stale after, grace, supervisor freshness), or this long after its last evaluation.
ROW_REFRESH = 1.0


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
        self._rows = {spec.name: RowState(spec) for spec in watched}
        # Which rows a node's coming and going concerns.
        self._rows_of_node: dict[str, list[RowState]] = {}
        for state in self._rows.values():
            for expected in state.spec.expected:
                for node in expected.nodes:
                    self._rows_of_node.setdefault(node, []).append(state)
        self._live: dict[str, int] = {}
        self._seen: dict[str, float] = {}
        self._gone_at: dict[str, float] = {}
        self._graph = False
        self._started: float | None = None
        self._supervised: dict[str, Supervised] = {}
        self._supervisors_at: dict[str, float] = {}
        # host -> (level, message, agent's time) of its agent's rejoin report.
        self._rejoins: dict[str, tuple[Level, str, float]] = {}
        self._alarms = AlarmRecorder()
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
        summary, items, hidden = bounded_items(statuses, module, self.max_items)
        state.items = items
        state.summary = summary
        state.hidden = len(hidden)
        state.hidden_level = worst(hidden)
        state.health_at = now
        name = state.spec.name
        state.joint_states_hz = reported_rate(items, f"{name}/topics/joint_states")
        state.joint_read_hz = reported_rate(items, f"{name}/topics/joint_read")
        state.temperature = motor_extreme(items, name, TEMPERATURE_KEYS, max)
        state.voltage = motor_extreme(items, name, VOLTAGE_KEYS, min)
        state.dirty = True
        self.version += 1

    def _on_reports(self, state: RowState, statuses: Sequence[Any], now: float) -> None:
        """A station's components reported (each its own status, each array a few)."""
        prefix = state.spec.name + "/"
        for status in statuses[: self.max_items]:
            parsed = parse_status(status)
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
        self,
        documents: Iterable[RunDocument | Mapping[str, Any] | bytes | str],
        now: float,
        unanswered: Iterable[str] = (),
    ) -> None:
        """The ``ps`` documents of the supervisors that answered just now.

        An answer that is not a :class:`~components.supervision.protocol.RunDocument` (data
        from the network) is skipped whole.

        Args:
            documents: Each supervisor's answer: a :class:`RunDocument`, or its JSON payload
                or that parsed (:func:`~components.supervision.protocol.run_document`).
            now: Monotonic seconds.
            unanswered: Supervisors (by host or namespace) that did not answer (informative).
        """
        self.start(now)
        del unanswered  # their entries simply stop being current
        changed = False
        for answer in documents:
            document = run_document(answer)
            if document is None:  # not a ps answer: nothing of it is kept
                continue
            host = clip(document.host, MAX_NAME)
            self._supervisors_at[host] = now
            self._on_rejoin(host, document.rejoin)
            for entry in document.components:
                known = self._supervised.get(entry.name)
                supervised = Supervised.from_entry(entry, host, now)
                self._supervised[entry.name] = supervised
                # Rows are judged again when a process changed, not at every answer (its
                # freshness is a deadline of the rows, its uptime is extrapolated).
                if known is None or known.news(supervised):
                    changed = True
        if changed:
            self._all_dirty()
        self.version += 1

    def _on_rejoin(self, host: str, report: Rejoin | UnsetType) -> None:
        """An agent's ``rejoin`` report (``rejoined`` or ``refused``), or its absence (unset:
        cleared by the next ``up`` or ``down``).

        A new report is an alarm of every row on ``host`` at once, stamped with the agent's
        time (each board that sees it records the same alarm, which merges as one).
        """
        known = self._rejoins.get(host)
        at = finite(report.at) if isinstance(report, Rejoin) else None
        if at is None:  # none, or malformed: nothing to show
            if known is not None:
                del self._rejoins[host]
                self._all_dirty()
            return
        level = OK if report.outcome == "rejoined" else ERROR
        entry = (level, clip(report.message, MAX_MESSAGE), at)
        if entry == known:
            return
        self._rejoins[host] = entry
        for state in self._rows.values():
            if state.spec.host != host:
                continue
            state.dirty = True
            self._alarms.announce(state.spec.name, f"{state.spec.name}/agent", level, entry[1], at)

    # ------------------------------------------------------------------ alarms
    @property
    def alarms(self) -> Sequence[Alarm]:
        """Every alarm kept (the last :data:`~components.data_monitor.alarms.MAX_ALARMS`),
        oldest first."""
        return self._alarms.alarms

    def take_alarms(self) -> list[Alarm]:
        """The alarms recorded since the last call, oldest first."""
        return self._alarms.take()

    def merge_history(self, alarms: Iterable[Alarm]) -> int:
        """Add alarms recorded before this board started (a data monitor's history).

        Returns:
            How many were new to this board.
        """
        added = self._alarms.merge_history(alarms)
        if added:
            self.version += 1
        return added

    # ------------------------------------------------------------------ evaluation
    def evaluate(self, now: float) -> BoardSnapshot:
        """Every row at ``now``; records an alarm for every level that changed (rows are
        judged first, then their changes recorded: see :meth:`_row`)."""
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
                row, message = self._row(state, now)
                state.row = row
                self._alarms.observe(row, message, now + self.wall_offset)
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

    def _row(self, state: RowState, now: float) -> tuple[Row, str]:
        """Judge one row at ``now``. Records nothing: :meth:`evaluate` hands the row to the
        alarm recorder afterwards.

        Returns:
            The row, and its message as judged (the row's own is clipped; its alarm is not).
        """
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
        for found, counts in (
            self._board_items(state, components),
            report_items(state, now, self.stale_after),
            monitor_items(state, stale, now, self._graph),
        ):
            items.extend(found)
            counted.extend(counts)
        level = worst(counted)
        worst_item = worst_of(items)
        message = row_message(state, items, worst_item, level)
        ok, total = self._components_ok(state, components)
        row = Row(
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
        return row, message

    def _board_items(
        self, state: RowState, components: Sequence[ComponentView]
    ) -> tuple[list[Item], list[Level]]:
        """The board's own items of a row (its components as judged from the graph, its
        agent's rejoin report, its planned components) and the levels among them that count."""
        spec = state.spec
        items: list[Item] = []
        counted: list[Level] = []
        if self._graph:
            for view in components:
                items.append(component_item(f"{spec.name}/components/{view.label}", view))
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
        return items, counted

    def _components_ok(
        self, state: RowState, components: Sequence[ComponentView]
    ) -> tuple[int, int]:
        """Components OK and expected: judged from the graph once it is followed, else as
        the module's monitor reported them."""
        if self._graph:
            return sum(c.level is OK for c in components), len(components)
        name = state.spec.name
        reported = [i for i in state.items if i.group(name) == "components" and not i.pending]
        return sum(i.level is OK for i in reported), len(reported)

    def _deadline(self, state: RowState, now: float) -> float:
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

    def _health_item(self, state: RowState, now: float) -> Item:
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

    def _supervisor_of(self, expected: ExpectedNode, now: float) -> tuple[Supervised | None, bool]:
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
        extra = process_facts(expected, entry, fresh, now)

        def view(level: Level, message: str, waiting: bool = False) -> ComponentView:
            return ComponentView(
                expected.label, node, level, message, total, waiting=waiting, **extra
            )

        if not self._graph:
            return view(*before_graph(entry, fresh))
        if total >= expected.count:
            return view(*on_graph(node, entry, fresh))
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
        return view(*off_graph(where, entry, fresh))

    def _uptime(self, spec: WatchedSpec, now: float) -> float | None:
        ages = []
        for expected in spec.expected:
            entry, fresh = self._supervisor_of(expected, now)
            if entry is not None and fresh and entry.state in ("running", "starting"):
                ages.append(entry.uptime + (now - entry.at))
        return min(ages) if ages else None
