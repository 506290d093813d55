"""The health board fed live from the data plane, for ``msctl health`` (screen, ``--once``,
``--watch``).

It reads every module's ``/<slot>/health`` and every station's ``/<station>/diagnostics``
directly (so it works when no data monitor runs), follows the graph for the nodes of every
module and station, and asks the supervisors for their ``ps`` once a second and at once when
a node leaves. Zenoh and the poller call in on
their own threads; everything reaches the board under one lock, and readers take snapshots
(:meth:`LiveHealth.evaluate`) at their own, bounded, pace.

When a data monitor runs, :meth:`LiveHealth.fetch_history` gets the alarms it recorded before
this view opened.
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

from components.assembly import ResolvedAssembly
from components.data_monitor.alarms import Alarm
from components.data_monitor.board import COMPONENT_GRACE, STALE_AFTER
from components.data_monitor.core import GET_ALARMS, alarm_from_message
from components.data_monitor.feeds import NodeFeed, SupervisorPoller
from components.data_monitor.measures import History, RateMeter
from components.data_monitor.model import BoardSnapshot
from components.data_monitor.plan import board_for
from components.messages import DIAGNOSTIC_ARRAY, JOINT_STATE, TRIGGER
from components.supervision.protocol import RunDocument
from msctl.health.source import ActionError, TopicRow

_log = logging.getLogger(__name__)

#: Most topics measured at once (the topics view of a large assembly).
MAX_METERED = 400
#: Seconds between two samples of a joint's position kept for its sparkline.
JOINT_SAMPLE_PERIOD = 0.1


class TopicMeters:
    """Arrival-time rates of a set of topics, measured without decoding a sample.

    Each topic gets one plain Zenoh subscriber on its data keys (any type), whose callback
    only notes the time: it keeps up with fast topics that ``ros2 topic hz`` under-reports.

    Args:
        session: An open Zenoh session.
        domain: ROS domain id.
    """

    def __init__(self, session: Any, domain: int = 0) -> None:
        self.session = session
        self.domain = domain
        self._meters: dict[str, RateMeter] = {}
        self._subscribers: dict[str, Any] = {}
        self._lock = threading.Lock()

    def watch(self, topics: Iterable[str]) -> None:
        """Measure exactly ``topics`` (at most :data:`MAX_METERED`) from now on."""
        from components.comm.names import key_name

        wanted = list(dict.fromkeys(topics))[:MAX_METERED]
        for topic in set(self._subscribers) - set(wanted):
            self._undeclare(self._subscribers.pop(topic))
            with self._lock:
                self._meters.pop(topic, None)
        for topic in wanted:
            if topic in self._subscribers:
                continue
            meter = RateMeter()
            with self._lock:
                self._meters[topic] = meter

            def arrived(_sample: Any, meter: RateMeter = meter, lock: Any = self._lock) -> None:
                with lock:
                    meter.arrive(time.monotonic())

            key = f"{self.domain}/{key_name(topic)}/*/*"
            self._subscribers[topic] = self.session.declare_subscriber(key, arrived)

    def stats(self, now: float | None = None) -> dict[str, Any]:
        """``{topic: RateStats}`` of every measured topic."""
        now = time.monotonic() if now is None else now
        with self._lock:
            return {topic: meter.stats(now) for topic, meter in self._meters.items()}

    @staticmethod
    def _undeclare(subscriber: Any) -> None:
        try:
            subscriber.undeclare()
        except Exception as exc:  # the session may be closed already
            _log.debug("rate meter: subscriber not undeclared: %s", exc)

    def close(self) -> None:
        """Stop measuring (idempotent)."""
        for subscriber in self._subscribers.values():
            self._undeclare(subscriber)
        self._subscribers.clear()


class LiveHealth:
    """A :class:`~components.data_monitor.board.HealthBoard` fed from the data plane.

    Args:
        node: An open node (``msctl.plane.connected``); closed by its owner, not here.
        assembly: The resolved assembly to watch.
        stale_after: Seconds without a module's health before it is STALE.
        grace: Seconds a node may take to show on the graph before it is an error.
        supervisors: Ask the supervisors for process states.
        on_change: Called (from any thread) after each input, e.g. to wake a screen.
    """

    def __init__(
        self,
        node: Any,
        assembly: ResolvedAssembly,
        stale_after: float = STALE_AFTER,
        grace: float = COMPONENT_GRACE,
        supervisors: bool = True,
        on_change: Callable[[], None] | None = None,
    ) -> None:
        self.node = node
        self.assembly = assembly
        self.board = board_for(
            assembly,
            stale_after=stale_after,
            wall_offset=time.time() - time.monotonic(),
            grace=grace,
        )
        self.lock = threading.Lock()
        self._on_change = on_change
        self._want_supervisors = supervisors
        self._subscriptions: list[Any] = []
        self._health_seen: set[str] = set()
        self._arrived = threading.Condition(self.lock)
        self.feed: NodeFeed | None = None
        self.poller: SupervisorPoller | None = None
        self.history_source: str | None = None
        self.meters = TopicMeters(node.session, node.domain)
        self._joints = History()
        self._joint_subscription: Any = None
        self._joint_sampled = 0.0

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> LiveHealth:
        """Subscribe, follow the graph and start asking the supervisors."""
        now = time.monotonic()
        with self.lock:
            self.board.start(now)
        for spec in self.board.watched:
            # A station's components (its data archivers) report on its diagnostics.
            callback = functools.partial(self._on_health, spec.name)
            self._subscriptions.append(
                self.node.subscription(spec.health_topic, DIAGNOSTIC_ARRAY, callback)
            )
        self.feed = NodeFeed(self.board.nodes(), self._on_node)
        graph = self.feed.attach(self.node.session, self.node.domain)
        with self.lock:
            self.board.watch_graph(time.monotonic())
        if self._want_supervisors:
            self.poller = SupervisorPoller(self.node, graph, self._on_supervisors).start()
        return self

    def close(self) -> None:
        """Stop every feed and subscription (idempotent); the node stays open."""
        self.meters.close()
        self.watch_joints(None)
        if self.poller is not None:
            self.poller.close()
        if self.feed is not None:
            self.feed.close()
        for subscription in self._subscriptions:
            subscription.close()
        self._subscriptions.clear()

    def __enter__(self) -> LiveHealth:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ inputs (any thread)
    def _changed(self) -> None:
        if self._on_change is not None:
            self._on_change()

    def _on_health(self, slot: str, message: Any) -> None:
        with self.lock:
            self.board.on_health(slot, message, time.monotonic())
            self._health_seen.add(slot)
            self._arrived.notify_all()
        self._changed()

    def _on_node(self, node: str, count: int) -> None:
        with self.lock:
            self.board.on_node(node, count, time.monotonic())
        if count == 0 and self.poller is not None:
            self.poller.poke()
        self._changed()

    def _on_supervisors(self, documents: list[RunDocument], unanswered: list[str]) -> None:
        with self.lock:
            self.board.on_supervisors(documents, time.monotonic(), unanswered)
            self._arrived.notify_all()
        self._changed()

    # ------------------------------------------------------------------ readers
    @property
    def version(self) -> int:
        """Changes with every input (a screen redraws only when it moved, or time did)."""
        return self.board.version

    def evaluate(self, now: float | None = None) -> BoardSnapshot:
        """The board at ``now`` (default: the current monotonic time)."""
        with self.lock:
            return self.board.evaluate(time.monotonic() if now is None else now)

    def take_alarms(self) -> list[Alarm]:
        """Alarms recorded since the last call (by :meth:`evaluate`)."""
        with self.lock:
            return self.board.take_alarms()

    def alarms(self) -> list[Alarm]:
        """Every alarm kept, oldest first."""
        with self.lock:
            return list(self.board.alarms)

    def wait_first_news(self, timeout: float) -> bool:
        """Wait until every module's health arrived once and the supervisors answered once
        (when asked), or ``timeout`` passes; returns whether everything came."""
        modules = {s.name for s in self.board.watched if not s.station}
        deadline = time.monotonic() + timeout

        def complete() -> bool:
            polled = self.poller is None or self.poller.rounds > 0
            return modules <= self._health_seen and polled

        with self._arrived:
            while not complete():
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                # The poller's first round is not signalled when no supervisor exists.
                self._arrived.wait(min(remaining, 0.1))
        return True

    def router_connected(self) -> bool:
        """Whether this session reaches a Zenoh router."""
        try:
            return bool(list(self.node.session.info.routers_zid()))
        except Exception:
            return False

    def data_monitors(self) -> list[str]:
        """The data monitors' alarm services on the graph (``/gc1/data_monitor/alarms``)."""
        if self.feed is None or self.feed.graph is None:
            return []
        services = self.feed.graph.services()
        return sorted(name for name, info in services.items() if GET_ALARMS in info.types)

    def fetch_history(self, timeout: float = 2.0) -> int:
        """Merge the alarm history of the first data monitor that answers.

        Returns:
            How many alarms were new to this board (0 when no data monitor answered).
        """
        from components.comm.services import ServiceError
        from components.comm.types import registry

        for service in self.data_monitors():
            client = self.node.client(service, GET_ALARMS)
            try:
                request = registry().msg_class(client.parts.request)(max_count=0)
                response = client.call(request, timeout=timeout)
            except ServiceError:
                continue
            finally:
                client.close()
            alarms = []
            for message in list(response.alarms)[-5000:]:
                try:
                    alarms.append(alarm_from_message(message))
                except ValueError:
                    continue
            with self.lock:
                added = self.board.merge_history(alarms)
            self.history_source = str(response.source)[:128] or service
            self._changed()
            return added
        return 0

    # ------------------------------------------------------------------ topics and joints
    def topics(self) -> list[TopicRow]:
        """Every topic on the graph, with the rates of the measured ones."""
        if self.feed is None or self.feed.graph is None:
            return []
        stats = self.meters.stats()
        return [
            TopicRow(
                name, tuple(sorted(info.types)), info.publishers, info.subscribers, stats.get(name)
            )
            for name, info in self.feed.graph.topics().items()
        ]

    def watch_topics(self, names: Iterable[str]) -> None:
        """Measure exactly these topics' rates from now on."""
        self.meters.watch(names)

    def watch_joints(self, module: str | None) -> None:
        """Keep recent joint positions of ``module`` from its ``joint_states`` (``None``: stop)."""
        from components.comm.qos import SENSOR

        if self._joint_subscription is not None:
            self._joint_subscription.close()
            self._joint_subscription = None
        if module is None:
            return
        self._joint_subscription = self.node.subscription(
            f"/{module}/joint_states", JOINT_STATE, self._on_joint_states, SENSOR
        )

    def _on_joint_states(self, message: Any) -> None:
        now = time.monotonic()
        if now - self._joint_sampled < JOINT_SAMPLE_PERIOD:
            return
        self._joint_sampled = now
        names, positions = list(message.name)[:64], message.position
        with self.lock:
            for index, name in enumerate(names):
                self._joints.add(str(name), positions[index] if index < len(positions) else None)

    def joint_history(self, joint: str) -> list[float | None]:
        """Recent positions of ``joint``, oldest first."""
        with self.lock:
            return self._joints.get(joint)

    # ------------------------------------------------------------------ actions
    def control(self, verb: str, component: str, host: str) -> str:
        """``restart``/``stop``/``start`` a component through the supervisor of ``host``, as
        ``msctl restart`` does.

        Raises:
            ActionError: If no supervisor runs it, or the supervisor refused or did not answer.
        """
        from components.comm.services import ServiceError
        from components.supervision.protocol import AnswerError, process_answer
        from msctl.launcher.control import RequestError, call_supervisor

        if not host:
            raise ActionError(f"no supervisor lists {component}: see `msctl ps`")
        try:
            answer = call_supervisor(self.node, host, verb, {"component": component})
            acted = process_answer(answer, verb, f"the supervisor of {host}")
        except (RequestError, AnswerError) as exc:
            raise ActionError(str(exc)) from exc
        except ServiceError as exc:
            raise ActionError(f"the supervisor of {host} did not answer: {exc}") from exc
        if self.poller is not None:
            self.poller.poke()
        return f"{verb} {component} on {host}: process {acted.process} is {acted.state}"

    def trigger(self, service: str) -> str:
        """Call the ``std_srvs/Trigger`` service ``service`` (``/limb1/halt``).

        Raises:
            ActionError: If nobody answers, or the service reports failure.
        """
        from components.comm.services import ServiceError
        from components.comm.types import registry

        client = self.node.client(service, TRIGGER)
        try:
            request = registry().msg_class(client.parts.request)()
            response = client.call(request, timeout=3.0)
        except ServiceError as exc:
            raise ActionError(f"{service}: {exc}") from exc
        finally:
            client.close()
        text = f"{service}: {response.message or ('done' if response.success else 'failed')}"
        if not response.success:
            raise ActionError(text)
        return text

    def log_tail(self, component: str, host: str, lines: int = 40) -> list[str]:
        """The last ``lines`` of ``component``'s log, from the supervisor of ``host``.

        Raises:
            ActionError: If no supervisor runs it, or it did not answer.
        """
        from components.comm.services import ServiceError
        from components.supervision.protocol import AnswerError, logs_answer
        from msctl.launcher.control import RequestError, call_supervisor

        if not host:
            raise ActionError(f"no supervisor lists {component}: see `msctl ps`")
        try:
            answer = call_supervisor(
                self.node, host, "logs", {"component": component, "lines": lines}
            )
            told = logs_answer(answer, f"the supervisor of {host}")
        except (RequestError, ServiceError, AnswerError) as exc:
            raise ActionError(f"logs of {component}: {exc}") from exc
        out: list[str] = []
        for process, text in told.items():
            out.append(f"--- {process} ---")
            out.extend(text[-lines:])
        return out
