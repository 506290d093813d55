"""Whether each commanded module can move now: the teleop's view of what another shell did.

An operator's screen must never say MOVING when nothing can move. Another shell may have
halted a module (``msctl estop``) or taken its joint manager down (``msctl down``,
``msctl stop``); the claims say nothing of either. :class:`ModuleWatch` follows, per module:

* its joint manager on the graph: the server of the module's ``halt`` (what a halt reaches;
  followed as a liveliness token, so a process that dies is seen gone within the session
  lease). A module seen and then gone is GONE at once; one never seen after
  :data:`FIRST_SEEN_GRACE` seconds is gone too (a graph just joined may lag a moment);
* its joint manager's ``diagnostics`` (the manager's own status says ``halted``), and the
  halts and recovers this teleop itself sent (acknowledged: known before the next report).

:meth:`ModuleWatch.why_not` says, in the operator's words, why a module cannot move ("" when
it can). The screen refuses the keys of such a module and says why (see
:mod:`msctl.teleop.app`). Time is passed in where it matters, so the rules are testable with
plain calls.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable, Mapping
from typing import Any

#: Seconds a module's joint manager may take to show on a graph just joined before it is
#: taken as gone.
FIRST_SEEN_GRACE = 5.0
#: Seconds after this teleop's own recover is acknowledged during which a ``halted`` report
#: is taken as one published before it (the joint manager reports once a second).
RECOVER_GRACE = 2.0


class ModuleStates:
    """The rules, without I/O: what was heard of each module, and why it cannot move.

    Args:
        namespaces: Module -> its namespace (``/limb1``).
        started: When watching began (monotonic seconds).
    """

    def __init__(self, namespaces: Mapping[str, str], started: float) -> None:
        self.namespaces = {slot: ns.rstrip("/") for slot, ns in namespaces.items()}
        self.started = started
        self._present: dict[str, bool] = {}
        self._halted: dict[str, bool] = {}
        self._recovered_at: dict[str, float] = {}

    def presence(self, slot: str, present: bool) -> None:
        """Whether the module's joint manager is on the graph now."""
        self._present[slot] = present

    def report(self, slot: str, halted: bool, now: float) -> None:
        """The joint manager's own report of being halted (or not)."""
        if halted and now - self._recovered_at.get(slot, -RECOVER_GRACE) < RECOVER_GRACE:
            return  # published before our recover, received after it
        self._halted[slot] = halted

    def halted(self, slot: str) -> None:
        """This teleop's halt of ``slot`` was acknowledged."""
        self._halted[slot] = True
        self._recovered_at.pop(slot, None)

    def recovered(self, slot: str, now: float) -> None:
        """This teleop's recover of ``slot`` was acknowledged."""
        self._halted[slot] = False
        self._recovered_at[slot] = now

    def why_not(self, slot: str, now: float) -> str:
        """Why ``slot`` cannot move now ("" when it can)."""
        namespace = self.namespaces.get(slot, f"/{slot}")
        present = self._present.get(slot)
        if present is False or (present is None and now - self.started > FIRST_SEEN_GRACE):
            return (
                f"{slot} is GONE: its joint manager ({namespace}/halt) left the graph "
                "(msctl down or stop from elsewhere?): see `msctl ps`"
            )
        if self._halted.get(slot):
            return f"{slot} is HALTED (an e-stop): nothing moves until ctrl+r recovers it"
        return ""


class ModuleWatch:
    """:class:`ModuleStates` fed from the data plane.

    Args:
        node: An open node (the caller's; closed by it).
        namespaces: Module -> its namespace.
        clock: Monotonic seconds.
    """

    def __init__(
        self,
        node: Any,
        namespaces: Mapping[str, str],
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        from components.comm.graph import Graph
        from components.comm.liveliness import EntityKind
        from components.messages import DIAGNOSTIC_ARRAY

        self.clock = clock
        self.states = ModuleStates(namespaces, clock())
        self._lock = threading.Lock()
        self._halts = {f"{ns.rstrip('/')}/halt": slot for slot, ns in namespaces.items()}
        self._servers: dict[str, set[str]] = {slot: set() for slot in namespaces}
        self._subscriptions: list[Any] = []
        self._kind = EntityKind.SERVICE
        # Only the service servers' tokens: what a halt reaches, and nothing else to parse.
        servers = f"*/*/*/{EntityKind.SERVICE.value}/**"
        self.graph = Graph(node.session, node.domain, self._on_entity, tokens=servers)
        for slot, namespace in namespaces.items():
            self._subscriptions.append(
                node.subscription(
                    f"{namespace.rstrip('/')}/diagnostics",
                    DIAGNOSTIC_ARRAY,
                    lambda message, s=slot: self._on_diagnostics(s, message),
                )
            )

    def _on_entity(self, entity: Any, alive: bool) -> None:
        slot = self._halts.get(entity.topic or "")
        if slot is None or entity.kind is not self._kind:
            return
        key = f"{entity.zid}/{entity.node_fqn}"
        with self._lock:
            servers = self._servers[slot]
            if alive:
                servers.add(key)
            else:
                servers.discard(key)
            self.states.presence(slot, bool(servers))

    def _on_diagnostics(self, slot: str, message: Any) -> None:
        from components.messages import diagnostic_values

        for status in message.status:
            values = diagnostic_values(status)
            if values.get("module") == slot and "halted" in values:
                with self._lock:
                    self.states.report(slot, values["halted"] == "True", self.clock())

    def why_not(self, slot: str) -> str:
        """Why ``slot`` cannot move now ("" when it can)."""
        with self._lock:
            return self.states.why_not(slot, self.clock())

    def acknowledged(self, verb: str, answers: Iterable[Any]) -> None:
        """Note this teleop's own halt or recover answers (``ok`` ones)."""
        with self._lock:
            for answer in answers:
                if not getattr(answer, "ok", False):
                    continue
                if verb == "halt":
                    self.states.halted(answer.module)
                else:
                    self.states.recovered(answer.module, self.clock())

    def close(self) -> None:
        """Stop watching (idempotent); the node stays open."""
        self.graph.close()
        for subscription in self._subscriptions:
            subscription.close()
        self._subscriptions.clear()
