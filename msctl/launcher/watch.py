"""Judging components healthy from Zenoh's data plane: their node's liveliness token is seen
and their first output has arrived
(:class:`components.health_monitor.startup_watch.ComponentWatch`)."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

from components.comm.graph import NODE_TOKENS, Graph, snapshot
from components.health_monitor.startup_watch import ComponentWatch
from msctl.launcher.plan import ComponentRun

_log = logging.getLogger(__name__)

#: Seconds a component may have published while its node is missing from the live graph
#: before the router is asked for node tokens directly. Seen in loaded runs of 60
#: components: an operator that ran and published stayed "starting" for minutes, its node's
#: token on the router (a fresh client session found it) but never delivered to the
#: supervisor's peer session, whose direct link to that component's peer was missing. So the
#: router is asked (through a client: see components.comm.session.graph_questions), which
#: has every token. Rare enough to ask about.
RECHECK_AFTER = 2.0
#: Seconds one such query may take.
RECHECK_QUERY = 1.0


class HealthWatch(ComponentWatch):
    """Follows Zenoh's graph and each component's first output topic.

    Args:
        session: An open Zenoh session (the caller closes it after :meth:`close`).
        components: What to follow.
        domain: ROS domain id.
        clock: Monotonic time (tests pass a fake one).
        outputs_session: Where to take the outputs instead (a client of the router: it gets
            a new peer's first samples, which a peer session gets only once linked to it).
    """

    def __init__(
        self,
        session: Any,
        components: Iterable[ComponentRun],
        domain: int = 0,
        clock: Callable[[], float] = time.monotonic,
        outputs_session: Any = None,
    ):
        super().__init__(components, clock)
        self._session, self._domain = session, domain
        self._closed = False
        # Nodes a direct query found (see RECHECK_AFTER), until their process restarts.
        self._queried: set[str] = set()
        self._asked_at = -RECHECK_AFTER
        self._asking: threading.Thread | None = None
        self._graph = Graph(session, domain, tokens=NODE_TOKENS)
        self._subscribers = []
        for topic, names in self.outputs().items():
            key = f"{domain}/{topic.strip('/')}/*/*"
            self._subscribers.append(
                (outputs_session or session).declare_subscriber(
                    key, lambda _s, names=names: self.saw(names)
                )
            )

    def forget(self, names: Iterable[str]) -> None:
        """A process restarted: its components must show themselves again."""
        names = list(names)
        super().forget(names)
        with self._lock:
            for name in names:
                self._queried.discard(self.components[name].node_fqn)

    def node_names(self) -> set[str]:
        """The live graph's nodes, and those a recheck found."""
        nodes = self._graph.node_names()
        with self._lock:
            return nodes | self._queried

    def status(self) -> dict[str, tuple[bool, bool]]:
        """``{component: (node seen, output seen)}``; asks the router about a component
        that has published for :data:`RECHECK_AFTER` with its node missing."""
        result = super().status()
        missing = set()
        for name, (node, output) in result.items():
            if output and not node and (self.output_age(name) or 0.0) >= RECHECK_AFTER:
                missing.add(self.components[name].node_fqn)
        now = self._clock()
        with self._lock:
            if missing and self._asking is None and now - self._asked_at >= RECHECK_AFTER:
                self._asked_at = now
                self._asking = threading.Thread(
                    target=self._ask, args=(missing,), name="health-recheck", daemon=True
                )
                self._asking.start()
        return result

    def _ask(self, missing: set[str]) -> None:
        """Ask the router for node tokens (off the caller's thread: it may take a second).
        A peer's graph question goes through a client of its router
        (:func:`components.comm.session.graph_questions`)."""
        seen: set[str] = set()
        try:
            if self._closed:
                return
            found = snapshot(self._session, self._domain, RECHECK_QUERY, NODE_TOKENS)
            seen = found.node_names() & missing
        except Exception as exc:  # no router now, or closing: the next turn asks again, or nobody
            _log.debug("node tokens not asked: %s: %s", type(exc).__name__, exc)
        finally:
            with self._lock:
                self._queried |= seen
                self._asking = None

    def close(self) -> None:
        """Stop watching (idempotent)."""
        for subscriber in self._subscribers:
            try:
                subscriber.undeclare()
            except Exception as exc:  # the session may be closed already
                _log.debug("start watch: subscriber not undeclared: %s", exc)
        self._subscribers.clear()
        self._graph.close()
        with self._lock:
            self._closed = True
            asking = self._asking
        if asking is not None:
            # Never long: a query still running on a closed session just fails.
            asking.join(timeout=RECHECK_QUERY)
