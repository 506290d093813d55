"""Health monitor core: one module's health as one DiagnosticArray.

The monitor aggregates, for its module:

* **components**: one item per expected component node (``/limb1/joint_manager``). OK while
  the node is on the graph; ERROR as soon as it leaves (the graph watcher reports it within
  the Zenoh lease, about a second after a crash); STALE during a short grace period at
  startup before it is first seen, ERROR if it never appears.
* **topics**: one item per main topic (``joint_states``, ``joint_read``, ``diagnostics``)
  with its measured rate. STALE when silent longer than its threshold, WARN below its
  expected rate.
* **motors**: one item per actuated joint (and the bus once it reports), carrying the worst
  level any source (motor interface, joint manager) published for it on ``diagnostics``,
  with that source's message; module temperature/voltage limits are applied to the values.
* **host**: the onboard computer's CPU, memory, disk and temperature, WARN/ERROR at
  thresholds from module data.

It publishes one DiagnosticArray on ``health`` once per ``publish_period`` and at once when
any item gets worse, preceded by a summary item named after the module.

Everything here is pure: graph changes arrive as :meth:`HealthMonitorCore.on_component_seen`
(or ``on_component_instances``) calls, host metrics through the ``read_host_metrics``
callable, time as ``now``.

Its state is bounded whatever arrives: only the module's own motors and expected nodes are
kept, a ``joint_states`` or ``joint_commands`` message naming more joints than the module
has is refused whole (counted as ``refused_oversize`` in the summary), and each motor keeps
at most :data:`MAX_SOURCES` reporting sources.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from typing import Any, NamedTuple

from components.executor.core import Core
from components.messages import (
    ERROR,
    OK,
    STALE,
    WARN,
    Level,
    diagnostic_array,
    diagnostic_status,
    diagnostic_values,
    joint_samples,
    worst,
)

#: Most diagnostics sources kept per motor (motor interface, joint manager, simulator... are
#: three): status names are free text, and a flood of invented ones must not grow memory.
MAX_SOURCES = 8

#: Keys motor backends use for a motor's temperature (°C) and supply voltage (V).
TEMPERATURE_KEYS = ("temperature", "temperature_c")
VOLTAGE_KEYS = ("input_voltage_v", "voltage")


@dataclass(frozen=True)
class TopicWatch:
    """One topic the monitor listens to.

    Attributes:
        topic: Name relative to the module namespace (``joint_states``).
        stale_after: Seconds of silence after which the item is STALE.
        min_rate: Expected minimum rate in Hz (WARN below it); ``None``: rate not checked
            (topics published on change with a slow keep-alive).
    """

    topic: str
    stale_after: float
    min_rate: float | None = None


@dataclass(frozen=True)
class HealthThresholds:
    """Thresholds of one module's health, from the module's ``[health]`` data.

    Every field is optional in the data; the defaults below apply when a key is absent.

    Attributes:
        stale_after: Silence (s) after which ``joint_states`` is STALE.
        min_rate: Minimum ``joint_states`` rate (Hz) before WARN.
        joint_read_stale_after: Silence (s) after which ``joint_read`` is STALE; the joint
            manager publishes it on change with a 1 Hz keep-alive, so above 1 s.
        diagnostics_stale_after: Silence (s) after which ``diagnostics``, and a motor with
            no fresh diagnostics, are STALE (diagnostics come at 1 Hz).
        rate_window: Seconds over which topic rates are measured.
        component_grace: Seconds after start during which a component not yet seen is STALE
            rather than ERROR (processes start in any order).
        max_temperature: Motor temperature (°C) at which a motor is ERROR; ``None``: the
            motor backends' own limits only.
        temperature_margin: A motor is WARN from ``max_temperature - temperature_margin``.
        min_voltage: Motor supply voltage (V) below which a motor is WARN.
        cpu_warn: Host CPU load (%) for WARN.
        cpu_error: Host CPU load (%) for ERROR.
        memory_warn: Host memory use (%) for WARN.
        memory_error: Host memory use (%) for ERROR.
        disk_warn: Host disk use of ``/`` (%) for WARN.
        disk_error: Host disk use of ``/`` (%) for ERROR.
        host_temperature_warn: Onboard computer temperature (°C) for WARN.
        host_temperature_error: Onboard computer temperature (°C) for ERROR.
        publish_period: Seconds between regular publications of ``health``.
        max_tracking_error: A joint farther than this (rad or m, raw) from its commanded
            position while not moving is WARN: stalled, blocked or too weak for its load.
            ``None``: not checked.
        tracking_grace: Seconds a joint must stay stalled off target before it is WARN (a
            servo settling, or starting a move, is not a fault).
        stall_velocity: Below this speed (rad/s or m/s) a joint counts as not moving.
        topics: Per-topic overrides, ``{"joint_read": {"stale_after": 2.0, "min_rate": 1}}``.
    """

    stale_after: float = 0.5
    min_rate: float = 50.0
    joint_read_stale_after: float = 2.5
    diagnostics_stale_after: float = 3.0
    rate_window: float = 1.0
    component_grace: float = 5.0
    max_temperature: float | None = None
    temperature_margin: float = 10.0
    min_voltage: float | None = None
    cpu_warn: float = 85.0
    cpu_error: float = 98.0
    memory_warn: float = 85.0
    memory_error: float = 95.0
    disk_warn: float = 90.0
    disk_error: float = 97.0
    host_temperature_warn: float = 80.0
    host_temperature_error: float = 90.0
    publish_period: float = 1.0
    max_tracking_error: float | None = None
    tracking_grace: float = 1.0
    stall_velocity: float = 0.05
    topics: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any], where: str = "[health]") -> HealthThresholds:
        """Thresholds from module data; absent keys keep their defaults.

        Keys this monitor does not use are ignored so that module data can serve several
        readers.

        Raises:
            ValueError: If a known key holds something other than a number (the message
                names ``where`` and the key).
        """
        changes: dict[str, Any] = {}
        for f in fields(cls):
            if f.name not in data:
                continue
            value = data[f.name]
            if f.name == "topics":
                if not isinstance(value, Mapping) or not all(
                    isinstance(v, Mapping) for v in value.values()
                ):
                    raise ValueError(f"{where}.topics must be a table of tables, got {value!r}")
                for topic, table in value.items():
                    for key, number in table.items():
                        if key not in ("stale_after", "min_rate"):
                            raise ValueError(
                                f"{where}.topics.{topic}.{key}: unknown key "
                                "(use stale_after or min_rate)"
                            )
                        _number(number, f"{where}.topics.{topic}.{key}")
                changes[f.name] = {k: dict(v) for k, v in value.items()}
                continue
            changes[f.name] = _number(value, f"{where}.{f.name}")
        return replace(cls(), **changes)

    def topic_watches(self) -> tuple[TopicWatch, ...]:
        """The module's main topics with their silence and rate thresholds."""
        watches = (
            TopicWatch("joint_states", self.stale_after, self.min_rate),
            TopicWatch("joint_read", self.joint_read_stale_after),
            TopicWatch("diagnostics", self.diagnostics_stale_after),
        )
        out = []
        for watch in watches:
            extra = self.topics.get(watch.topic, {})
            out.append(
                TopicWatch(
                    watch.topic,
                    float(extra.get("stale_after", watch.stale_after)),
                    float(extra["min_rate"]) if "min_rate" in extra else watch.min_rate,
                )
            )
        return tuple(out)


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or math.isnan(value):
        raise ValueError(f"{where} must be a number, got {value!r}")
    return float(value)


@dataclass(frozen=True)
class ExpectedComponent:
    """A component (or several of one kind) of the module the monitor expects on the graph.

    Attributes:
        label: Item label (``joint_manager``).
        node: Fully qualified node that runs it (``/limb1/joint_manager``).
        count: How many live instances of ``node`` are expected (two location publishers
            of a module share one node name).
        alternatives: Other nodes that satisfy it as well (the simulator
            ``/sim/simulator`` standing in for the motor interface).
    """

    label: str
    node: str
    count: int = 1
    alternatives: tuple[str, ...] = ()

    @property
    def nodes(self) -> tuple[str, ...]:
        """Every node that counts towards this component."""
        return (self.node, *self.alternatives)


@dataclass(frozen=True)
class MotorWatch:
    """An actuated joint whose motor diagnostics the monitor follows.

    Attributes:
        joint: Assembly joint name (``limb1_joint3``), the item label.
        raw_name: The joint's name inside its module (``joint3``), as some backends say it.
    """

    joint: str
    raw_name: str = ""


class Item(NamedTuple):
    """One evaluated health item, before it becomes a DiagnosticStatus."""

    name: str
    level: Level
    message: str
    hardware_id: str
    values: Mapping[str, Any]


class _ComponentState:
    __slots__ = ("alive", "appearances", "changed_at", "expected", "live", "live_node")

    def __init__(self, expected: ExpectedComponent) -> None:
        self.expected = expected
        self.alive = False
        self.live = 0
        self.live_node = expected.node
        self.appearances = 0
        self.changed_at: float | None = None


class _TopicState:
    __slots__ = ("arrivals", "count", "first", "last", "watch")

    def __init__(self, watch: TopicWatch) -> None:
        self.watch = watch
        self.arrivals: deque[float] = deque()
        self.count = 0
        self.first: float | None = None
        self.last: float | None = None


class _SourceReport(NamedTuple):
    level: Level
    message: str
    values: dict[str, str]
    at: float


class HealthMonitorCore(Core):
    """Aggregates one module's health into a DiagnosticArray on ``health``.

    Args:
        name: Component name (``limb1/health_monitor``).
        module: Module slot (``limb1``): item names start with it.
        components: The module's components to watch on the graph.
        motors: The module's actuated joints.
        thresholds: Thresholds from module data.
        read_host_metrics: Returns the onboard computer's metrics as a mapping with
            ``cpu_percent``, ``memory_percent``, ``disk_percent`` and ``temperature`` (°C,
            or ``None`` when no sensor is readable); ``None``: no host items.
        unit: Hardware id of module items (the unit's serial).
        host: Hardware id of host items (the onboard computer's hostname).
    """

    def __init__(
        self,
        name: str,
        module: str,
        components: Sequence[ExpectedComponent],
        motors: Sequence[MotorWatch] = (),
        thresholds: HealthThresholds | None = None,
        read_host_metrics: Callable[[], Mapping[str, Any]] | None = None,
        unit: str = "",
        host: str = "",
    ) -> None:
        super().__init__(name)
        self.module = module
        self.thresholds = thresholds or HealthThresholds()
        self.unit = unit or module
        self.host = host
        self._read_host_metrics = read_host_metrics
        self._components = {c.label: _ComponentState(c) for c in components}
        self._watched_nodes = frozenset(n for c in components for n in c.nodes)
        self._instances: dict[str, int] = {}
        self._topics = {w.topic: _TopicState(w) for w in self.thresholds.topic_watches()}
        self._motors = list(motors)
        self._joints = frozenset(m.joint for m in self._motors)
        self._size = len(self._joints)
        #: Messages refused whole (more joint names than the module has motors); reports
        #: dropped because a motor already had MAX_SOURCES live sources.
        self.counters = {"refused_oversize": 0, "dropped_sources": 0}
        self._motor_names: dict[str, str] = {}
        for motor in self._motors:
            self._motor_names[motor.joint] = motor.joint
            if motor.raw_name:
                self._motor_names.setdefault(motor.raw_name, motor.joint)
        # label -> source status name -> latest report; "bus" appears once something reports it.
        self._motor_reports: dict[str, dict[str, _SourceReport]] = {
            m.joint: {} for m in self._motors
        }
        self._host: Mapping[str, Any] | None = None
        self._host_error: str | None = None
        # joint -> commanded raw position (position mode only) and since when it is stalled
        # off that target.
        self._targets: dict[str, float] = {}
        self._stalled_since: dict[str, float] = {}
        self._tracking_errors: dict[str, float] = {}
        self._started: float | None = None
        self._last_publish: float | None = None
        self._levels: dict[str, Level] = {}
        self.publications = 0

    # ------------------------------------------------------------------ lifecycle
    def start(self, now: float) -> None:
        """Read the host once and publish a first picture (components STALE until seen)."""
        self._started = now
        self.on_host_timer(now)
        self._publish(now, self.evaluate(now))

    # ------------------------------------------------------------------ inputs
    def on_component_seen(self, node: str, alive: bool, now: float) -> None:
        """A node of the graph appeared (``alive``) or vanished (one instance of it).

        Args:
            node: Fully qualified node name (``/limb1/joint_manager``).
            alive: Whether the node is on the graph now.
            now: Monotonic seconds.
        """
        self.on_component_instances(node, 1 if alive else 0, now)

    def on_component_instances(self, node: str, count: int, now: float) -> None:
        """How many live instances of ``node`` the graph holds now (0: it is gone).

        Args:
            node: Fully qualified node name (``/limb1/location_publisher``).
            count: Live instances (distinct node tokens) with that name.
            now: Monotonic seconds.
        """
        if node not in self._watched_nodes:
            return  # only expected nodes are kept
        self._instances[node] = count
        changed = False
        for state in self._components.values():
            expected = state.expected
            if node not in expected.nodes:
                continue
            live = {n: self._instances.get(n, 0) for n in expected.nodes}
            total = sum(live.values())
            alive = total >= expected.count
            if total == state.live and alive == state.alive:
                continue
            if alive != state.alive:
                state.changed_at = now
                if alive:
                    state.appearances += 1
            state.alive, state.live = alive, total
            state.live_node = max(expected.nodes, key=lambda n: live[n])
            changed = True
        if changed:
            self._check(now)

    def on_joint_states(self, message: Any, now: float) -> None:
        """A ``joint_states`` sample arrived: its rate, and how far joints are from target.

        A message naming more joints than the module has is refused whole (no motor
        interface sends one): it is neither a sample nor read.
        """
        if len(message.name) > self._size:
            self.counters["refused_oversize"] += 1
            return
        self._arrived("joint_states", now)
        limit = self.thresholds.max_tracking_error
        if limit is None or not self._targets:
            return
        for sample in joint_samples(message):
            target = self._targets.get(sample.name)
            if target is None or sample.position is None or not math.isfinite(sample.position):
                continue
            error = abs(sample.position - target)
            self._tracking_errors[sample.name] = error
            moving = sample.velocity is not None and abs(sample.velocity) > (
                self.thresholds.stall_velocity
            )
            if error > limit and not moving:
                self._stalled_since.setdefault(sample.name, now)
            else:
                self._stalled_since.pop(sample.name, None)

    def on_joint_commands(self, message: Any, now: float) -> None:
        """What the joint manager asked the motors for: position targets are tracked.

        Only the module's own motors are tracked; a message naming more joints than it has is
        refused whole.
        """
        if len(message.name) > self._size:
            self.counters["refused_oversize"] += 1
            return
        for sample in joint_samples(message):
            if sample.name not in self._joints:
                continue
            if sample.position is not None and math.isfinite(sample.position):
                if self._targets.get(sample.name) != sample.position:
                    self._stalled_since.pop(sample.name, None)  # a new target: a new chance
                self._targets[sample.name] = sample.position
            else:  # velocity or effort mode: there is no position to track
                self._targets.pop(sample.name, None)
                self._stalled_since.pop(sample.name, None)
                self._tracking_errors.pop(sample.name, None)

    def on_joint_read(self, message: Any, now: float) -> None:
        """A ``joint_read`` sample arrived."""
        self._arrived("joint_read", now)

    def on_diagnostics(self, message: Any, now: float) -> None:
        """A DiagnosticArray on the module's ``diagnostics``: keep what concerns a motor."""
        self._arrived("diagnostics", now)
        touched = False
        for status in message.status:
            label = self._motor_label(status.name)
            if label is None:
                continue
            reports = self._motor_reports.setdefault(label, {})
            if status.name not in reports and len(reports) >= MAX_SOURCES:
                # Full: a silent (stale) source makes room; live ones are never pushed out.
                oldest = min(reports, key=lambda source: reports[source].at)
                if now - reports[oldest].at <= self.thresholds.diagnostics_stale_after:
                    self.counters["dropped_sources"] += 1
                    continue
                del reports[oldest]
            reports[status.name] = _SourceReport(
                Level.of(status.level), status.message, diagnostic_values(status), now
            )
            touched = True
        if touched:
            self._check(now)

    def on_host_timer(self, now: float) -> None:
        """Read the onboard computer's metrics (timer handler)."""
        if self._read_host_metrics is None:
            return
        try:
            self._host = dict(self._read_host_metrics())
            self._host_error = None
        except Exception as exc:  # a sensor driver failing must not take the monitor down
            self._host_error = f"{type(exc).__name__}: {exc}"

    def tick(self, now: float) -> None:
        """Periodic check (timer handler): silences, then the regular publication."""
        self._check(now)

    # ------------------------------------------------------------------ evaluation
    def evaluate(self, now: float) -> list[Item]:
        """Every item at ``now``, summary first."""
        items = [self._component_item(s, now) for s in self._components.values()]
        items.extend(self._topic_item(s, now) for s in self._topics.values())
        items.extend(self._motor_item(label, now) for label in self._motor_reports)
        if self.thresholds.max_tracking_error is not None:
            items.append(self._tracking_item(now))
        if self._read_host_metrics is not None:
            items.extend(self._host_items())
        bad = [i for i in items if i.level != OK]
        level = worst([i.level for i in items])
        if bad:
            shown = sorted(bad, key=lambda i: -i.level.severity)[:3]
            message = "; ".join(
                f"{i.name.removeprefix(self.module + '/')} {i.level.name}" for i in shown
            )
            if len(bad) > len(shown):
                message += f" (+{len(bad) - len(shown)} more)"
        else:
            message = f"all {len(items)} items OK"
        summary = Item(
            self.module,
            level,
            message,
            self.unit,
            {
                "items": len(items),
                "ok": len(items) - len(bad),
                "warn": sum(i.level == WARN for i in items),
                "error": sum(i.level == ERROR for i in items),
                "stale": sum(i.level == STALE for i in items),
                **{k: v for k, v in self.counters.items() if v},
            },
        )
        return [summary, *items]

    def _check(self, now: float) -> None:
        items = self.evaluate(now)
        worse = any(i.level.severity > self._levels.get(i.name, OK).severity for i in items)
        self._levels = {i.name: i.level for i in items}
        due = (
            self._last_publish is None or now - self._last_publish >= self.thresholds.publish_period
        )
        if worse or due:
            self._publish(now, items)

    def _publish(self, now: float, items: list[Item]) -> None:
        self._levels = {i.name: i.level for i in items}
        self._last_publish = now
        self.publications += 1
        statuses = [
            diagnostic_status(i.name, i.level, i.message, i.hardware_id, i.values) for i in items
        ]
        self.publish("health", diagnostic_array(statuses, self.stamp(now)))

    def _tracking_item(self, now: float) -> Item:
        limit = self.thresholds.max_tracking_error
        grace = self.thresholds.tracking_grace
        stalled = sorted(n for n, since in self._stalled_since.items() if now - since >= grace)
        values = {
            "max_tracking_error": limit,
            **{n: f"{e:.3f}" for n, e in sorted(self._tracking_errors.items())},
        }
        name = f"{self.module}/tracking"
        if stalled:
            worst_joint = max(stalled, key=lambda n: self._tracking_errors.get(n, 0.0))
            return Item(
                name,
                WARN,
                f"{', '.join(stalled)} not moving, {self._tracking_errors[worst_joint]:.3f} "
                f"from target (limit {limit:g}): blocked, stalled or overloaded?",
                self.unit,
                values,
            )
        return Item(name, OK, "every joint tracks its target", self.unit, values)

    def _component_item(self, state: _ComponentState, now: float) -> Item:
        expected = state.expected
        node = state.live_node if state.live else expected.node
        name = f"{self.module}/components/{expected.label}"
        values: dict[str, Any] = {"node": node, "appearances": state.appearances}
        if expected.count != 1:
            values["instances"] = f"{state.live}/{expected.count}"
        if state.alive:
            values["up_for"] = f"{now - (state.changed_at or now):.1f}"
            return Item(name, OK, f"{node} running", self.unit, values)
        waited = now - (self._started if self._started is not None else now)
        if not state.appearances and waited < self.thresholds.component_grace:
            # Processes start in any order: not an error yet.
            return Item(name, STALE, f"waiting for {node} to start", self.unit, values)
        if state.live:
            return Item(
                name,
                ERROR,
                f"only {state.live} of {expected.count} instances of {node} running: "
                "see `msctl ps`",
                self.unit,
                values,
            )
        if state.appearances:
            gone = now - (state.changed_at or now)
            values["gone_for"] = f"{gone:.1f}"
            return Item(
                name,
                ERROR,
                f"{node} disappeared {gone:.1f} s ago: see `msctl ps` and `msctl logs`",
                self.unit,
                values,
            )
        return Item(
            name,
            ERROR,
            f"{node} has not appeared in {waited:.0f} s: is it launched? (`msctl ps`)",
            self.unit,
            values,
        )

    def _arrived(self, topic: str, now: float) -> None:
        state = self._topics[topic]
        state.count += 1
        if state.first is None:
            state.first = now
        state.last = now
        state.arrivals.append(now)
        self._forget_old(state, now)

    def _forget_old(self, state: _TopicState, now: float) -> None:
        horizon = now - self.thresholds.rate_window
        while state.arrivals and state.arrivals[0] <= horizon:
            state.arrivals.popleft()

    def _topic_item(self, state: _TopicState, now: float) -> Item:
        watch = state.watch
        name = f"{self.module}/topics/{watch.topic}"
        self._forget_old(state, now)
        window = self.thresholds.rate_window
        # Until a full window has passed since the first sample, measure over what was seen.
        span = min(window, now - state.first) if state.first is not None else 0.0
        rate = len(state.arrivals) / span if span > 0 else 0.0
        values: dict[str, Any] = {
            "topic": f"/{self.module}/{watch.topic}",
            "rate_hz": f"{rate:.1f}",
            "samples": state.count,
            "stale_after": watch.stale_after,
        }
        if watch.min_rate is not None:
            values["min_rate_hz"] = watch.min_rate
        if state.last is None:
            return Item(name, STALE, "no samples yet", self.unit, values)
        silent = now - state.last
        values["age"] = f"{silent:.3f}"
        if silent > watch.stale_after:
            return Item(
                name,
                STALE,
                f"silent for {silent:.1f} s (stale after {watch.stale_after:g} s)",
                self.unit,
                values,
            )
        # A rate is only meaningful once a full window has been observed.
        if (
            watch.min_rate is not None
            and state.first is not None
            and now - state.first >= window
            and rate < watch.min_rate
        ):
            return Item(
                name,
                WARN,
                f"{rate:.1f} Hz, expected at least {watch.min_rate:g} Hz",
                self.unit,
                values,
            )
        return Item(name, OK, f"{rate:.1f} Hz", self.unit, values)

    def _motor_label(self, status_name: str) -> str | None:
        # Sources name a motor's status by joint: "limb1_joint3" (motor interface),
        # "limb1/joint_manager/limb1_joint3" (joint manager), or the bus as "limb1/bus".
        last = status_name.rsplit("/", 1)[-1]
        if last in self._motor_names:
            return self._motor_names[last]
        if last == "bus":
            return "bus"
        return None

    def _motor_item(self, label: str, now: float) -> Item:
        name = f"{self.module}/motors/{label}"
        limit = self.thresholds.diagnostics_stale_after
        reports = self._motor_reports[label]
        fresh = {src: r for src, r in reports.items() if now - r.at <= limit}
        if not fresh:
            message = (
                "no diagnostics yet"
                if not reports
                else f"no diagnostics for {now - max(r.at for r in reports.values()):.1f} s"
            )
            return Item(name, STALE, message, self.unit, {"sources": len(reports)})
        checked = [(src, r, *self._motor_limits(r)) for src, r in sorted(fresh.items())]
        source, report, level, message = max(checked, key=lambda c: c[2].severity)
        values: dict[str, Any] = {"source": source, **report.values}
        values["sources"] = len(fresh)
        return Item(name, level, message, self.unit, values)

    def _motor_limits(self, report: _SourceReport) -> tuple[Level, str]:
        """A source's level and message, made worse by the module's temperature/voltage limits."""
        level, message = report.level, report.message
        t = self.thresholds
        temperature = _first_float(report.values, TEMPERATURE_KEYS)
        if t.max_temperature is not None and temperature is not None:
            limit = f"the module limit {t.max_temperature:g} °C"
            extra = None
            if temperature >= t.max_temperature:
                extra = (ERROR, f"{temperature:.0f} °C reaches {limit}: let it cool")
            elif temperature >= t.max_temperature - t.temperature_margin:
                extra = (WARN, f"{temperature:.0f} °C near {limit}")
            if extra is not None and extra[0].severity > level.severity:
                level, message = extra
        voltage = _first_float(report.values, VOLTAGE_KEYS)
        low = t.min_voltage is not None and voltage is not None and voltage < t.min_voltage
        if low and WARN.severity > level.severity:
            level = WARN
            message = f"supply {voltage:.1f} V below {t.min_voltage:g} V: charge the battery"
        return level, message

    def _host_items(self) -> list[Item]:
        t = self.thresholds
        prefix = f"{self.module}/host"
        specs = (
            ("cpu", "cpu_percent", "%", t.cpu_warn, t.cpu_error, "CPU load"),
            ("memory", "memory_percent", "%", t.memory_warn, t.memory_error, "memory in use"),
            ("disk", "disk_percent", "%", t.disk_warn, t.disk_error, "disk / in use"),
            (
                "temperature",
                "temperature",
                " °C",
                t.host_temperature_warn,
                t.host_temperature_error,
                "temperature",
            ),
        )
        items = []
        for label, key, unit, warn_at, error_at, what in specs:
            name = f"{prefix}/{label}"
            if self._host is None or self._host_error:
                # Never read, or the last read failed: old numbers would be misleading.
                message = (
                    f"cannot read host metrics: {self._host_error}"
                    if self._host_error
                    else "not read yet"
                )
                items.append(Item(name, STALE, message, self.host, {}))
                continue
            value = self._host.get(key)
            values: dict[str, Any] = {"warn_at": warn_at, "error_at": error_at}
            if value is None:
                items.append(
                    Item(name, OK, f"{what}: not readable on this computer", self.host, values)
                )
                continue
            value = float(value)
            values[key] = f"{value:.1f}"
            if key == "temperature" and self._host.get("temperature_sensor"):
                values["sensor"] = self._host["temperature_sensor"]
            if value >= error_at:
                level = ERROR
            elif value >= warn_at:
                level = WARN
            else:
                level = OK
            text = f"{what} {value:.0f}{unit}"
            if level != OK:
                text += f" (warn at {warn_at:g}{unit}, error at {error_at:g}{unit})"
            items.append(Item(name, level, text, self.host, values))
        return items


def _first_float(values: Mapping[str, str], keys: Sequence[str]) -> float | None:
    for key in keys:
        if key in values:
            try:
                return float(values[key])
            except ValueError:
                return None
    return None
