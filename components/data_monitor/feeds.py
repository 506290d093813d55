"""What a health board learns from outside the data it subscribes to: the graph and the
supervisors. Both run on Zenoh's or their own threads and hand what they learn to a ``post``
callable, which the data monitor binds to ``Executor.call_soon`` and ``msctl health`` to its
board's lock, so the board itself stays single-threaded and pure.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any

from components.comm.graph import Graph, GraphView
from components.comm.liveliness import Entity, EntityKind
from components.comm.services import ServiceError

if TYPE_CHECKING:
    from components.supervision.protocol import RunDocument

_log = logging.getLogger(__name__)

#: Seconds between two ``ps`` requests to every supervisor.
POLL_PERIOD = 1.0
#: Seconds a supervisor has to answer one ``ps``.
POLL_TIMEOUT = 1.0
#: After a node leaves the graph, supervisors are asked again at these delays (s): the
#: supervisor needs a moment to notice its child died.
POKE_DELAYS = (0.05, 0.3, 0.8)


class NodeFeed:
    """Counts live instances of some nodes on the graph; posts each change.

    Args:
        nodes: Fully qualified node names to follow.
        post: Called as ``post(node, count)`` (on a Zenoh thread) when a count changes.
    """

    def __init__(self, nodes: Iterable[str], post: Callable[[str, int], None]) -> None:
        self.nodes = frozenset(nodes)
        self._post = post
        self._live: dict[str, set[tuple[str, int]]] = {}
        self._lock = threading.Lock()
        self.graph: Graph | None = None

    def attach(self, session: Any, domain: int = 0) -> Graph:
        """Start following the graph of ``session`` (nodes already up are replayed)."""
        self.graph = Graph(session, domain, on_change=self._on_change)
        return self.graph

    def follow(self, open_graph: Callable[..., Any]) -> Any:
        """Start following the graph ``open_graph(on_change=...)`` opens (an executor's
        :meth:`~components.executor.executor.Executor.graph`, whatever its data plane)."""
        self.graph = open_graph(on_change=self._on_change)
        return self.graph

    def _on_change(self, entity: Entity, alive: bool) -> None:
        if entity.kind is not EntityKind.NODE or entity.node_fqn not in self.nodes:
            return
        with self._lock:
            live = self._live.setdefault(entity.node_fqn, set())
            before = len(live)
            if alive:
                live.add(entity.node_key)
            else:
                live.discard(entity.node_key)
            if len(live) != before:
                # Under the lock, so appear/vanish are posted in order.
                self._post(entity.node_fqn, len(live))

    def close(self) -> None:
        """Stop following the graph (idempotent)."""
        if self.graph is not None:
            self.graph.close()


def supervisor_services(graph: GraphView) -> list[str]:
    """Every supervisor's request service on the graph (``/msctl/<host>/request``)."""
    from components.supervision.contract import AGENT_SRV

    return [
        name
        for name, info in graph.services().items()
        if name.startswith("/msctl/") and name.endswith("/request") and AGENT_SRV in info.types
    ]


class SupervisorPoller:
    """Asks every supervisor on the graph for ``ps``, once a period and when poked.

    One thread; a client per supervisor, kept while the supervisor is on the graph.

    Args:
        node: The node to make clients on.
        graph: A live graph view (to find the supervisors).
        post: Called as ``post(documents, unanswered)`` after each round, from the poller's
            thread: the ``ps`` answers that came back, typed, and the services that did not
            answer.
        period: Seconds between rounds.
        timeout: Seconds each supervisor has to answer.
    """

    def __init__(
        self,
        node: Any,
        graph: GraphView,
        post: Callable[[list[RunDocument], list[str]], None],
        period: float = POLL_PERIOD,
        timeout: float = POLL_TIMEOUT,
    ) -> None:
        self.node = node
        self.graph = graph
        self._post = post
        self.period = period
        self.timeout = timeout
        self._clients: dict[str, Any] = {}
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._extra: list[float] = []
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="supervisor-poller", daemon=True)
        self.rounds = 0

    def start(self) -> SupervisorPoller:
        """Start polling."""
        self._thread.start()
        return self

    def poke(self) -> None:
        """Ask again soon (a node left the graph: did its process die?)."""
        now = time.monotonic()
        with self._lock:
            self._extra = sorted({*self._extra, *(now + d for d in POKE_DELAYS)})
        self._wake.set()

    def _next_wait(self) -> float:
        now = time.monotonic()
        with self._lock:
            self._extra = [t for t in self._extra if t > now]
            upcoming = self._extra[0] - now if self._extra else self.period
        return max(0.0, min(self.period, upcoming))

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.poll_once()
            except Exception as exc:  # a broken reply must not end the polling
                _log.debug("supervisor poll failed: %s: %s", type(exc).__name__, exc)
            self._wake.wait(self._next_wait())
            self._wake.clear()

    def poll_once(self) -> tuple[list[RunDocument], list[str]]:
        """One round: ask every supervisor, post and return what came back (an answer that
        is not a :class:`~components.supervision.protocol.RunDocument` counts as none)."""
        from components.supervision.protocol import run_document
        from components.supervision.wire import SupervisorClient

        services = supervisor_services(self.graph)
        for gone in set(self._clients) - set(services):
            self._clients.pop(gone).close()
        documents: list[RunDocument] = []
        unanswered: list[str] = []
        for service in services:
            if self._stop.is_set():
                break
            client = self._clients.get(service)
            if client is None:
                client = self._clients[service] = SupervisorClient(self.node, service)
            try:
                response = client.ask("ps", "{}", timeout=self.timeout)
                document = run_document(response.payload) if response.success else None
            except ServiceError:
                document = None
            if document is not None:
                documents.append(document)
            else:
                unanswered.append(service)
        self.rounds += 1
        if not self._stop.is_set():
            self._post(documents, unanswered)
        return documents, unanswered

    def close(self) -> None:
        """Stop polling and close the clients (idempotent)."""
        self._stop.set()
        self._wake.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=self.timeout + 2.0)
        for client in self._clients.values():
            client.close()
        self._clients.clear()
