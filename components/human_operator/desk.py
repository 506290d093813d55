"""The human operator's desk: its screens' claims, and who may publish on which relay.

A screen (``msctl teleop`` on the station) attaches with a request on the human operator's
``~/request`` service (``msctl_msgs/srv/AgentRequest``, verb ``attach``, JSON args naming the
operator ``user@host``, the screen's node and session, the modules and whether to take them
over). The desk claims the modules for that operator, as the human operator's node (the one
that sends the commands: joint managers and the steering operator then take its commands as
the holder's), all of them or none. Each relay input then takes samples from that screen's
node alone (:meth:`Subscription.allow <components.comm.topics.Subscription.allow>`); a
``cmd_vel`` relay, only from the one screen holding every module of the robot this desk holds.

A screen lets go by detaching (verb ``detach``), by its node leaving the graph (it quit or
crashed: the desk follows node tokens), or by another operator taking a module over. Each
time, its streams get their one stop (:meth:`HumanOperatorCore.end`) and its relays close.

Claims block for up to seconds (they ask the network who holds a module), so requests are
answered on a thread of the desk, never on the executor's, whose deadman must keep ticking.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from components.errors import ConfigError
from components.human_operator.routes import Route
from components.messages import msg

if TYPE_CHECKING:
    from components.executor.executor import Component, Executor

log = logging.getLogger(__name__)

#: The service type of ``~/request`` (verb + JSON args -> success, message, JSON payload).
REQUEST_SRV = "msctl_msgs/srv/AgentRequest"
#: The service's name, private to the human operator's node.
REQUEST = "~/request"
#: Verbs the desk answers.
ATTACH, DETACH = "attach", "detach"
#: Seconds the desk waits for a stop to be sent before it releases the claims.
STOP_WAIT = 1.0


class RequestError(ConfigError):
    """A request the desk refuses; the message says why."""


@dataclass
class Screen:
    """One attached screen.

    Attributes:
        holder: Its operator, ``user@host``.
        node: Its node (fully qualified).
        zid: Its Zenoh session id.
        claims: Slot -> the claim the desk holds for it.
    """

    holder: str
    node: str
    zid: str
    claims: dict[str, Any] = field(default_factory=dict)

    @property
    def sender(self) -> str:
        """How a subscription names it: ``<node>@<zid>``."""
        return f"{self.node}@{self.zid}"


def _claim(info: Any) -> dict[str, Any]:
    """A claim as a reply carries it (its token key says it all)."""
    return {**info.as_dict(), "key": info.key}


def response(success: bool, message: str, payload: Any = None) -> Any:
    """An ``AgentRequest`` response."""
    return msg(
        f"{REQUEST_SRV}_Response",
        success=success,
        message=message,
        payload="" if payload is None else json.dumps(payload),
    )


class OperatorDesk:
    """The human operator's ``on_bound`` hook and what it opens (closed with the component).

    Args:
        modules: The assembly's module slots (a claim for another name is refused).
        routes: What the component relays.
        deadman_timeout: The relay's deadman (told to screens as they attach).
    """

    def __init__(
        self, modules: Sequence[str], routes: Sequence[Route], deadman_timeout: float
    ) -> None:
        self.modules = tuple(modules)
        self.routes = tuple(routes)
        self.deadman_timeout = deadman_timeout
        self._lock = threading.Lock()
        self._screens: dict[tuple[str, str], Screen] = {}
        self._subscriptions: dict[str, Any] = {}  # target -> the relay input
        self._requests: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._thread: threading.Thread | None = None
        self._closed = False
        self.executor: Executor | None = None
        self.component: Component | None = None
        self.claims: Any = None
        self._graph: Any = None

    # ------------------------------------------------------------------ binding
    def __call__(self, executor: Executor, component: Component) -> None:
        """Open the claims watcher, the relay inputs, the graph watch and ``~/request``."""
        from components.claims import Claims
        from components.comm.graph import NODE_TOKENS, Graph

        self.executor, self.component = executor, component
        node = component.node
        self.claims = Claims(executor.session, node.domain, self.modules)
        for route in self.routes:

            def relay(message: Any, target: str = route.target) -> None:
                executor.call_soon(component, "on_relay", target, message)

            # Nobody until a screen attaches and holds the route's modules.
            self._subscriptions[route.target] = node.subscription(
                route.relay, route.msg_type, relay, senders=(), guarded=True
            )
        self._reallow()
        self._graph = Graph(
            executor.session, node.domain, on_change=self._on_graph, tokens=NODE_TOKENS
        )
        self._thread = threading.Thread(target=self._serve, name="operator-desk", daemon=True)
        self._thread.start()
        node.service(REQUEST, REQUEST_SRV, self._requests.put, deferred=True)

    # ------------------------------------------------------------------ requests
    def _serve(self) -> None:
        while True:
            pending = self._requests.get()
            if pending is None:
                return
            if callable(pending):  # work of the desk's own (a screen's node left)
                self._guarded(pending)
                continue
            try:
                reply = self.answer(str(pending.request.verb), str(pending.request.args))
            except RequestError as exc:
                reply = response(False, str(exc))
            except Exception as exc:  # the desk must answer, and go on answering
                log.exception("human operator request failed")
                reply = response(False, f"{type(exc).__name__}: {exc}")
            try:
                pending.reply(reply)
            except Exception:
                log.debug("could not reply to a request", exc_info=True)

    def _guarded(self, work: Any) -> None:
        try:
            work()
        except Exception:
            log.exception("human operator desk work failed")

    def answer(self, verb: str, args_text: str) -> Any:
        """Answer one request (on the desk's thread).

        Raises:
            RequestError: For a malformed request, naming what is wrong.
        """
        try:
            args = json.loads(args_text or "{}")
        except ValueError as exc:
            raise RequestError(f"args must be a JSON object: {exc}") from None
        if not isinstance(args, dict):
            raise RequestError("args must be a JSON object")
        node, zid = args.get("node"), args.get("zid")
        if not isinstance(node, str) or not isinstance(zid, str) or not node or not zid:
            raise RequestError("args must name the screen's node and zid")
        if verb == ATTACH:
            holder, modules = args.get("holder"), args.get("modules")
            if not isinstance(holder, str) or not holder:
                raise RequestError("attach: args must name the holder (user@host)")
            if not isinstance(modules, list) or not all(isinstance(m, str) for m in modules):
                raise RequestError("attach: args.modules must be a list of module slots")
            return self.attach(holder, node, zid, modules, bool(args.get("take")))
        if verb == DETACH:
            self.detach(node, zid)
            return response(True, f"{node} detached")
        raise RequestError(f"unknown verb {verb!r}; known: {ATTACH}, {DETACH}")

    def attach(self, holder: str, node: str, zid: str, modules: list[str], take: bool) -> Any:
        """Claim ``modules`` for the screen (all or none) and open its relays."""
        from components.claims import ClaimError, ClaimRefused

        assert self.component is not None
        with self._lock:
            screen = self._screens.setdefault((node, zid), Screen(holder, node, zid))
            screen.holder = holder
        new: list[str] = []
        try:
            for slot in modules:
                if slot in screen.claims and screen.claims[slot].held:
                    continue
                other = self._holder_here(slot, screen)
                if other is not None:
                    if not take:
                        info = other.claims[slot].info
                        raise RequestError(
                            f"module {slot} is claimed by {other.holder} (through this station's "
                            f"human operator {info.node}) since {info.since_text()}; take it "
                            "over with --take, or ask them to release it"
                        )
                    self._let_go(other, [slot])
                claim = self.claims.claim(slot, holder, self.component.node, take=take)
                with self._lock:
                    screen.claims[slot] = claim
                new.append(slot)
                claim.on_lost(lambda taker, s=screen, m=slot: self._lost(s, m, taker))
        except (ClaimRefused, ClaimError, RequestError) as exc:
            self._let_go(screen, new)  # all or none
            with self._lock:
                if not screen.claims:
                    self._screens.pop((node, zid), None)
            payload = {"holder": _claim(exc.holder)} if isinstance(exc, ClaimRefused) else None
            self._reallow()
            return response(False, str(exc), payload)
        self._reallow()
        held = sorted(screen.claims)
        relays = {r.target: r.relay for r in self.routes if set(r.modules) & set(screen.claims)}
        return response(
            True,
            f"{holder} holds {', '.join(held)} through {self.component.node.fqn}",
            {
                "operator": self.component.node.fqn,
                "claimed": held,
                "relays": relays,
                "deadman_timeout": self.deadman_timeout,
                "claims": {s: _claim(c.info) for s, c in screen.claims.items()},
            },
        )

    def detach(self, node: str, zid: str) -> None:
        """The screen lets go of everything it holds (idempotent)."""
        with self._lock:
            screen = self._screens.pop((node, zid), None)
        if screen is not None:
            self._let_go(screen, list(screen.claims))
            self._reallow()

    # ------------------------------------------------------------------ letting go
    def _holder_here(self, slot: str, asking: Screen) -> Screen | None:
        """Another screen of this desk holding ``slot``."""
        with self._lock:
            for screen in self._screens.values():
                if screen is not asking and slot in screen.claims and screen.claims[slot].held:
                    return screen
        return None

    def _let_go(self, screen: Screen, slots: Sequence[str]) -> None:
        """Release ``slots`` of ``screen``: their moving streams get their one stop first
        (sent while the claims still name this node, so the modules take it)."""
        if not slots:
            return
        self._end(slots, wait=True)
        with self._lock:
            claims = [screen.claims.pop(s) for s in slots if s in screen.claims]
        for claim in claims:
            claim.release()

    def _lost(self, screen: Screen, slot: str, taker: Any) -> None:
        """Another operator took ``slot`` over from ``screen`` (on a Zenoh thread)."""
        log.warning("%s: module %s taken over by %s", screen.holder, slot, taker.holder)
        with self._lock:
            screen.claims.pop(slot, None)
        self._end([slot])
        self._reallow()

    def _end(self, slots: Sequence[str], wait: bool = False) -> None:
        """Post the one stop of ``slots``' moving streams; with ``wait``, until it is out
        (at most :data:`STOP_WAIT` seconds: the executor may be stopping)."""
        if self.executor is None or self.component is None:
            return
        self.executor.call_soon(self.component, "end", list(slots))
        if wait:
            done = threading.Event()
            self.executor.call_soon(self.component, lambda now: done.set())
            done.wait(STOP_WAIT)

    def _on_graph(self, entity: Any, alive: bool) -> None:
        """A screen's node left the graph (it quit or crashed): it lets go."""
        from components.comm.liveliness import EntityKind

        if alive or entity.kind is not EntityKind.NODE:
            return
        key = (entity.node_fqn, entity.zid)
        with self._lock:
            attached = key in self._screens
        if attached:
            self._requests.put(lambda: self.detach(*key))

    def _reallow(self) -> None:
        """Each relay input takes samples from the one screen holding its modules here."""
        with self._lock:
            holders: dict[str, Screen] = {}
            for screen in self._screens.values():
                for slot, claim in screen.claims.items():
                    if claim.held:
                        holders[slot] = screen
            operators = {}
            for screen in self._screens.values():
                held = tuple(sorted(s for s, c in screen.claims.items() if c.held))
                operators[screen.holder] = held
        for route in self.routes:
            subscription = self._subscriptions.get(route.target)
            if subscription is None:
                continue
            screens = {id(holders[m]): holders[m] for m in route.modules if m in holders}
            if len(screens) == 1:
                (screen,) = screens.values()
                subscription.allow(
                    {screen.sender},
                    f"only {screen.holder}'s screen ({screen.node}), which holds "
                    f"{', '.join(route.modules)} here, may relay on {route.relay}",
                )
            else:
                subscription.allow(
                    set(),
                    f"no screen holds {', '.join(route.modules)} through this human operator"
                    if not screens
                    else f"{', '.join(route.modules)} are held by several screens here",
                )
        if self.executor is not None and self.component is not None:
            self.executor.call_soon(self.component, "on_operators", operators)

    # ------------------------------------------------------------------ closing
    def held(self) -> dict[str, str]:
        """Slot -> the operator holding it through this desk (a snapshot)."""
        with self._lock:
            return {
                slot: screen.holder
                for screen in self._screens.values()
                for slot, claim in screen.claims.items()
                if claim.held
            }

    def close(self) -> None:
        """Release every claim, stop watching, stop the desk's thread (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self._requests.put(None)
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        if self._graph is not None:
            self._graph.close()
        for subscription in self._subscriptions.values():
            subscription.close()
        if self.claims is not None:
            self.claims.close()  # releases every claim it made
