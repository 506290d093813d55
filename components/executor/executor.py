"""The Executor: runs one or many cores in one process.

One thread (the caller of :meth:`Executor.run`) calls every handler of every core, so a core
never sees two callbacks at once and cores need no locks. Zenoh threads only decode samples
and queue them; each subscription keeps at most ``depth`` pending samples (keep-last), so a
slow core sees the newest data rather than an ever-growing backlog.

An exception in a core's handler is logged with the component's name and counted; the other
cores keep running. SIGINT/SIGTERM stop the loop; every core's ``stop`` runs, then every
node and the session are closed, so the process exits promptly.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import queue
import signal
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from components.claim_guard import ClaimGuard
from components.claims import Claims
from components.comm.node import Node
from components.comm.services import PendingRequest
from components.comm.session import SessionSettings, open_session
from components.executor.core import Core
from components.executor.heartbeat import Heartbeat
from components.executor.interface import InterfaceSpec, Serve, Subscribe

log = logging.getLogger("msctl.executor")

_STOP = object()
_WAKE = object()  # an urgent request is waiting (Executor._urgent)


@dataclass
class Component:
    """A core bound to the data plane: its node, publishers and counters."""

    name: str
    core: Core
    spec: InterfaceSpec
    node: Node
    publishers: dict[str, Any] = field(default_factory=dict)
    errors: int = 0
    handled: int = 0
    removed: bool = False
    guarded: list[Any] = field(default_factory=list)

    def publish(self, topic: str, message: Any) -> None:
        """The core's outbox: publish on a declared output."""
        try:
            publisher = self.publishers[topic]
        except KeyError:
            raise KeyError(
                f"{self.name} published on {topic!r}, which its interface does not declare "
                f"(declared: {sorted(self.publishers)})"
            ) from None
        publisher.publish(message)


class _Inbox:
    """Pending samples of one subscription (bounded for keep-last)."""

    __slots__ = ("component", "handler", "items", "lock", "scheduled")

    def __init__(self, component: Component, handler: Callable, depth: int | None) -> None:
        self.component = component
        self.handler = handler
        self.items: deque[Any] = deque(maxlen=depth)
        self.lock = threading.Lock()
        self.scheduled = False


class _Call:
    """A call posted from another thread with :meth:`Executor.call_soon`."""

    __slots__ = ("args", "component", "handler")

    def __init__(self, component: Component, handler: Callable, args: tuple[Any, ...]) -> None:
        self.component = component
        self.handler = handler
        self.args = args


class _Task:
    """Work for the executor itself, posted with :meth:`Executor.post`."""

    __slots__ = ("work",)

    def __init__(self, work: Callable[[], Any]) -> None:
        self.work = work


class Executor:
    """Runs cores. Use as a context manager or call :meth:`close`.

    Args:
        settings: Session settings (default: from the environment).
        session: An already open session to use instead (the caller closes it).
        clock: Monotonic clock giving ``now`` to handlers (tests may pass a fake).
        heartbeat: Beaten from the loop and between handler calls, so the supervisor can
            tell a frozen or stuck process from a quiet one
            (:mod:`components.executor.heartbeat`).
    """

    def __init__(
        self,
        settings: SessionSettings | None = None,
        session: Any = None,
        clock: Callable[[], float] = time.monotonic,
        heartbeat: Heartbeat | None = None,
    ) -> None:
        self._settings = settings or SessionSettings.from_env()
        self._owns_session = session is None
        self._session = self._open_plane(session)
        self.clock = clock
        self.components: list[Component] = []
        self._work: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._timers: list[tuple[float, int, Component, Callable, float]] = []
        self._timer_seq = itertools.count()
        self._stopping = threading.Event()
        self._closed = False
        self._wall_offset = time.time() - time.monotonic()
        self._heartbeat = heartbeat
        self._claim_guard: ClaimGuard | None = None
        # Urgent service requests (Serve.urgent): handled before any queued item, between
        # the messages of an inbox and between timers. The work queue only wakes the loop.
        self._urgent: deque[Any] = deque()

    # ------------------------------------------------------------------ the plane
    #: The data plane the components' nodes are on (``rclpy`` for the RclpyExecutor).
    transport = "zenoh"

    def _open_plane(self, session: Any) -> Any:
        """Open the data plane; returns the Zenoh session (the given one, or a new one)."""
        return session if session is not None else open_session(self._settings)

    @property
    def session(self) -> Any:
        """The Zenoh session: msctl's data plane here; on rclpy, its control plane (claims,
        supervisors), opened when first asked for."""
        return self._session

    @property
    def domain(self) -> int:
        """The ROS domain id of the data plane."""
        return self._settings.domain

    def _node(self, name: str, namespace: str) -> Any:
        """A node on the data plane (the Zenoh one here)."""
        return Node(self.session, name, namespace, domain=self._settings.domain)

    def graph(
        self, on_change: Callable[[Any, bool], None] | None = None, nodes_only: bool = False
    ) -> Any:
        """A live view of the data plane's graph, the caller closes it.

        Args:
            on_change: Called with ``(entity, alive)`` for every change, from another thread
                (nodes already up are reported at once).
            nodes_only: Follow the nodes alone, not their endpoints (less work, where only
                nodes matter).
        """
        from components.comm.graph import NODE_TOKENS, Graph

        tokens = NODE_TOKENS if nodes_only else "**"
        return Graph(self.session, self._settings.domain, on_change=on_change, tokens=tokens)

    # ------------------------------------------------------------------ building
    def add(
        self,
        core: Core,
        spec: InterfaceSpec,
        namespace: str = "/",
        node_name: str | None = None,
    ) -> Component:
        """Bind ``core`` to the data plane under ``namespace`` as node ``node_name``."""
        node = self._node(node_name or core.name.replace("/", "_").replace("-", "_"), namespace)
        component = Component(core.name, core, spec, node)
        try:
            for output in spec.publish:
                component.publishers[output.topic] = node.publisher(
                    output.topic, output.msg_type, output.qos
                )
            for extra in getattr(core, "extra_publish", ()):
                component.publishers[extra.topic] = node.publisher(
                    extra.topic, extra.msg_type, extra.qos
                )
            core.bind(component, self._wall_offset)
            for sub in (*spec.subscribe, *getattr(core, "extra_subscribe", ())):
                self._bind_subscription(component, sub)
            for serve in (*spec.serve, *getattr(core, "extra_serve", ())):
                self._bind_service(component, serve)
            now = self.clock()
            for every in spec.every:
                handler = self._handler(core, every.handler)
                heapq.heappush(
                    self._timers,
                    (now + every.period, next(self._timer_seq), component, handler, every.period),
                )
        except Exception:
            node.close()
            raise
        self.components.append(component)
        return component

    def _handler(self, core: Core, name: str) -> Callable:
        handler = getattr(core, name, None)
        if not callable(handler):
            raise AttributeError(
                f"{core.name}: the interface names handler {name!r}, which the core lacks"
            )
        return handler

    def _bind_subscription(self, component: Component, sub: Subscribe) -> None:
        handler = self._handler(component.core, sub.handler)
        depth = sub.qos.depth if sub.qos.history == "keep_last" else None
        inbox = _Inbox(component, handler, depth)

        def on_message(message: Any) -> None:
            with inbox.lock:
                inbox.items.append(message)
                if inbox.scheduled:
                    return
                inbox.scheduled = True
            self._work.put(inbox)

        subscription = component.node.subscription(
            sub.topic,
            sub.msg_type,
            on_message,
            sub.qos,
            senders=sub.senders,
            guarded=sub.claim is not None,
        )
        if sub.claim is not None:
            self.claim_guard().add(subscription, sub.claim)
            component.guarded.append(subscription)

    def claim_guard(self) -> ClaimGuard:
        """The one claims watcher of this process (made on first use), which keeps every
        claim-guarded subscription on its module's holder (:mod:`components.claims`)."""
        if self._claim_guard is None:
            self._claim_guard = ClaimGuard(Claims(self.session, self._settings.domain))
        return self._claim_guard

    def _bind_service(self, component: Component, serve: Serve) -> None:
        handler = self._handler(component.core, serve.handler)

        def on_request(pending: PendingRequest) -> None:
            if serve.urgent:
                self._urgent.append((component, handler, pending))
                self._work.put(_WAKE)
            else:
                self._work.put((component, handler, pending))

        component.node.service(
            serve.service,
            serve.srv_type,
            on_request,
            deferred=True,
            queue_only=True,
            urgent=serve.urgent,
        )

    def call_soon(self, component: Component, handler: str | Callable, *args: Any) -> None:
        """Have the executor thread call ``handler(*args, now)`` for ``component``.

        Thread-safe: this is how I/O outside the data plane (a graph watcher, a file
        watcher) reaches a core without the core needing locks. Calls run in the order
        posted, interleaved with samples and timers, and only while :meth:`run` (or
        :meth:`spin_once`) is running; ``now`` is appended as for every other handler.

        Args:
            component: The component (as returned by :meth:`add`) the call is counted for.
            handler: A method name of the component's core, or any callable.
            *args: Positional arguments before ``now``.

        Raises:
            AttributeError: If ``handler`` names a method the core lacks.
        """
        if isinstance(handler, str):
            handler = self._handler(component.core, handler)
        self._work.put(_Call(component, handler, args))

    def post(self, work: Callable[[], Any]) -> None:
        """Have the executor thread call ``work()`` between handlers (thread-safe).

        For work on the executor itself rather than on one core (rebuilding a component);
        what it raises is logged, and the loop goes on.
        """
        self._work.put(_Task(work))

    def start_component(self, component: Component) -> None:
        """Call the core's ``start`` now: for a component added while the loop runs (those
        added before :meth:`run` are started by it)."""
        self._call(component, component.core.start, self.clock())

    def remove(self, component: Component) -> None:
        """Stop one component and take it off the data plane; the others run on.

        Its core's ``stop`` is called, its node (publishers, subscriptions, services,
        liveliness) is closed, its timers are dropped, and samples or calls already queued
        for it are discarded. Call from the executor thread (a :meth:`post`), or before
        :meth:`run`.
        """
        if component.removed:
            return
        self._call(component, component.core.stop, self.clock())
        component.removed = True
        if self._claim_guard is not None:
            for subscription in component.guarded:
                self._claim_guard.discard(subscription)
        component.node.close()
        self._timers = [t for t in self._timers if t[2] is not component]
        heapq.heapify(self._timers)
        self.components.remove(component)

    # ------------------------------------------------------------------ running
    def run(self, duration: float | None = None) -> None:
        """Run until :meth:`stop`, a signal, or ``duration`` seconds; then shut down cleanly."""
        restore = self._install_signals()
        try:
            start = self.clock()
            for component in self.components:
                self._call(component, component.core.start, start)
            deadline = None if duration is None else time.monotonic() + duration
            while not self._stopping.is_set():
                if self._heartbeat is not None:
                    self._heartbeat.beat()
                timeout = self._next_timeout(deadline)
                try:
                    item = (
                        self._work.get(timeout=timeout) if timeout > 0 else self._work.get_nowait()
                    )
                except queue.Empty:
                    item = None
                if item is _STOP:
                    break
                if item is not None:
                    self._dispatch(item)
                self._run_due_timers()
                if deadline is not None and time.monotonic() >= deadline:
                    break
        finally:
            self._shutdown_cores()
            restore()
            self.close()

    def spin_once(self, timeout: float = 0.0) -> None:
        """Handle what is pending (for tests and embedding in another loop)."""
        try:
            item = self._work.get(timeout=timeout) if timeout > 0 else self._work.get_nowait()
        except queue.Empty:
            item = None
        if item is not None and item is not _STOP:
            self._dispatch(item)
        self._run_due_timers()

    def stop(self) -> None:
        """Ask the loop to finish (safe from any thread or a signal handler)."""
        self._stopping.set()
        self._work.put(_STOP)

    def _next_timeout(self, deadline: float | None) -> float:
        now = self.clock()
        wait = 0.5
        if self._timers:
            wait = min(wait, self._timers[0][0] - now)
        if deadline is not None:
            wait = min(wait, deadline - time.monotonic())
        if self._heartbeat is not None:
            wait = min(wait, self._heartbeat.period)
        return max(wait, 0.0)

    def _serve_urgent(self) -> None:
        """Handle every urgent request waiting (see :class:`Serve`'s ``urgent``)."""
        while self._urgent:
            try:
                request = self._urgent.popleft()
            except IndexError:
                return
            self._answer(*request)

    def _dispatch(self, item: Any) -> None:
        self._serve_urgent()
        if item is _WAKE:
            return
        if isinstance(item, _Task):
            try:
                item.work()
            except Exception:
                log.exception("executor task %s failed", getattr(item.work, "__name__", item))
            return
        if isinstance(item, _Inbox):
            while True:
                with item.lock:
                    if not item.items:
                        item.scheduled = False
                        return
                    message = item.items.popleft()
                self._call(item.component, item.handler, message, self.clock())
                self._serve_urgent()
            return
        if isinstance(item, _Call):
            self._call(item.component, item.handler, *item.args, self.clock())
            return
        self._answer(*item)

    def _answer(self, component: Component, handler: Callable, pending: PendingRequest) -> None:
        """Call a service handler and reply with what it returned."""
        with pending.handling():  # the handler may ask who called (current_caller)
            response = self._call(component, handler, pending.request, self.clock())
        if response is None:
            pending.fail(f"{component.name} could not answer (see its log)")
        else:
            try:
                pending.reply(response)
            except Exception:
                component.errors += 1
                log.exception("%s: replying to a service request failed", component.name)

    def _run_due_timers(self) -> None:
        now = self.clock()
        while self._timers and self._timers[0][0] <= now:
            self._serve_urgent()
            due, seq, component, handler, period = heapq.heappop(self._timers)
            self._call(component, handler, now)
            following = due + period
            if following <= now:  # fell behind (a slow handler): skip, never burst
                following = now + period
            heapq.heappush(self._timers, (following, seq, component, handler, period))

    def _call(self, component: Component, handler: Callable, *args: Any) -> Any:
        if self._heartbeat is not None:
            # A loop kept busy by a flood of samples is alive; one stuck in a handler is not.
            self._heartbeat.beat()
        if component.removed:
            return None  # queued before it was removed: its core is stopped
        component.handled += 1
        try:
            return handler(*args)
        except Exception:
            component.errors += 1
            log.exception(
                "component %s: %s failed", component.name, getattr(handler, "__name__", handler)
            )
            return None

    def _shutdown_cores(self) -> None:
        now = self.clock()
        for component in self.components:
            self._call(component, component.core.stop, now)

    def _install_signals(self) -> Callable[[], None]:
        if threading.current_thread() is not threading.main_thread():
            return lambda: None
        previous = {}
        for signum in (signal.SIGINT, signal.SIGTERM):
            previous[signum] = signal.getsignal(signum)
            signal.signal(signum, lambda *_: self.stop())

        def restore() -> None:
            for signum, handler in previous.items():
                signal.signal(signum, handler)

        return restore

    # ------------------------------------------------------------------ closing
    def close(self) -> None:
        """Close every node and, if the executor opened it, the session (idempotent)."""
        if self._closed:
            return
        self._closed = True
        if self._claim_guard is not None:
            self._claim_guard.claims.close()
        for component in reversed(self.components):
            component.node.close()
        if self._owns_session and self._session is not None:
            self._session.close()

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
