"""How a joint manager sees its operators: the liveliness tokens its computer's router keeps.

An ``on_bound`` hook (:class:`PresenceFeed`) follows, on the executor's own session, the node
tokens of the graph and the claims of the module, and posts into the executor thread:

* ``on_station(name, visible)`` when the first node of a ground station appears or the last
  one vanishes. A station's nodes are those in its namespace (``/gc1/data_monitor``, its
  human operator...) and its computer's supervisor (``/msctl/ground1``, the agent that runs
  on every field computer from boot, so a station is seen before anything is launched);
* ``on_holder(holder)`` when the module's claim holder changes (``None``: its token is gone).

Nothing new crosses the radio: every router already learns the other computers' tokens, and
a cut link makes the robot's router drop the far side's after the session lease. Which
stations exist and where they run comes from the resolved assembly (:func:`watched`).
"""

from __future__ import annotations

import threading
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from components.joint_manager.presence import OperatorPresence, Station

if TYPE_CHECKING:
    from components.assembly import ResolvedAssembly
    from components.build import BuiltComponent
    from components.comm.liveliness import Entity
    from components.executor.executor import Component, Executor


def stations_of(assembly: ResolvedAssembly) -> dict[Station, tuple[str, ...]]:
    """The assembly's ground stations and the node namespaces that show each one alive: its
    own and its computer's supervisor's."""
    from components import kinds
    from components.supervision.contract import host_namespace

    found: dict[Station, tuple[str, ...]] = {}
    for plan in assembly.components:
        # A station kind given to a module (a robot's own recorder) is no station.
        if plan.module is not None or kinds.get(plan.kind).placement is not kinds.Placement.STATION:
            continue
        station = Station(plan.namespace.strip("/"), plan.host)
        found.setdefault(station, (plan.namespace.rstrip("/"), host_namespace(plan.host)))
    return found


def watched(
    assembly: ResolvedAssembly, slot: str, here: str
) -> tuple[OperatorPresence, dict[Station, tuple[str, ...]]] | None:
    """The presence watch of module ``slot`` run on computer ``here``, or ``None`` for none.

    None when the template turned it off (``[safety] operator_timeout = false``; the
    default for an assembly without stations), and off-robot: a computer that is not the
    module's own runs the whole assembly, its stations included, so no radio lies between
    the module and its operators (and a desk simulation run without its station's
    components keeps taking commands).
    """
    timeout = assembly.operator_timeout
    if timeout is None or assembly.module(slot).host != here:
        return None
    stations = stations_of(assembly)
    return OperatorPresence(stations, timeout), stations


class PresenceFeed:
    """Posts a module's operators coming and going to its joint manager (``on_bound`` hook).

    Args:
        built: The built joint manager; the graph watcher joins its resources.
        module: The module's slot (whose claim counts).
        stations: Each station and the namespaces of its nodes (:func:`stations_of`).
    """

    def __init__(
        self,
        built: BuiltComponent,
        module: str,
        stations: Mapping[Station, tuple[str, ...]],
    ) -> None:
        self.built = built
        self.module = module
        self._station_of = {ns: s.name for s, spaces in stations.items() for ns in spaces}
        self._live: dict[str, set[tuple[str, int]]] = {s.name: set() for s in stations}
        self._lock = threading.Lock()
        self._post: Any = None

    def __call__(self, executor: Executor, component: Component) -> None:
        """Start following the graph and the claims of ``executor``'s session."""

        def post(handler: str, *args: Any) -> None:
            executor.call_soon(component, handler, *args)

        self._post = post
        # Nodes already up are reported at once (liveliness history), so a station that was
        # there before this process is seen at its start, well within the grace.
        graph = executor.graph(on_change=self._on_node, nodes_only=True)
        self.built.resources.append(graph)
        executor.claim_guard().claims.on_change(self._on_claim)

    def _on_node(self, entity: Entity, alive: bool) -> None:
        name = self._station_of.get(entity.namespace.rstrip("/"))
        if name is None:
            return
        with self._lock:
            live = self._live[name]
            before = bool(live)
            if alive:
                live.add(entity.node_key)
            else:
                live.discard(entity.node_key)
            if bool(live) != before and self._post is not None:
                # Posted under the lock: appear and vanish reach the core in order.
                self._post("on_station", name, bool(live))

    def _on_claim(self, module: str, holder: Any) -> None:
        if module != self.module or self._post is None:
            return
        with self._lock:
            self._post("on_holder", None if holder is None else holder.holder)
