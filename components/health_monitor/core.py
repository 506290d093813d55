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
from dataclasses import dataclass
from typing import Any

from components.executor.core import Core
from components.health_monitor.host_items import host_items
from components.health_monitor.items import Item
from components.health_monitor.motors import MAX_SOURCES, MotorWatch, SourceReport, motor_item
from components.health_monitor.thresholds import HealthThresholds, TopicWatch
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
        self._motor_reports: dict[str, dict[str, SourceReport]] = {
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
            reports[status.name] = SourceReport(
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
            items.extend(
                host_items(self.module, self.host, self.thresholds, self._host, self._host_error)
            )
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
        return motor_item(name, self._motor_reports[label], now, self.thresholds, self.unit)
