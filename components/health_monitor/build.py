"""Build a module's health monitor from the resolved assembly, and bind its graph watcher.

The core is pure; what it needs from the outside world comes in two ways:

* host metrics: a :class:`~components.health_monitor.host.HostMetricsReader` whose ``read`` the core
  calls from its timer;
* graph changes: the graph lives on the executor's session, which exists only once the core
  is added to an executor, so the built component carries an ``on_bound`` hook
  (:class:`GraphFeed`). Run through :func:`components.executor.runner.run_built`, the hook
  opens a :class:`~components.comm.graph.Graph` and forwards each expected node's appearance
  and disappearance into the executor thread with ``Executor.call_soon``; the graph is
  closed with the component's other resources.
"""

from __future__ import annotations

import threading
from collections.abc import Iterable, Mapping
from dataclasses import replace
from typing import TYPE_CHECKING, Any

from components import kinds
from components.assembly import ComponentPlan, ResolvedAssembly
from components.build import BuildError, BuiltComponent, buildable
from components.build import node_name as component_node_name
from components.comm.liveliness import Entity, EntityKind
from components.health_monitor.core import ExpectedComponent, HealthMonitorCore
from components.health_monitor.host import HostMetricsReader
from components.health_monitor.interface import HEALTH_MONITOR
from components.health_monitor.motors import MotorWatch
from components.health_monitor.thresholds import HealthThresholds

if TYPE_CHECKING:
    from components.comm.graph import Graph
    from components.executor.executor import Component, Executor


def stand_in_node(kind: kinds.ComponentKind) -> str:
    """The node of an assembly-wide stand-in (``/sim/simulator``)."""
    return f"{kind.namespace.rstrip('/')}/{kind.name}"


def node_name(plan: ComponentPlan) -> str:
    """The node name a planned component runs as (``limb1/joint_manager`` ->
    ``joint_manager``; see :func:`components.build.node_name`)."""
    return component_node_name(plan.name)


def expected_components(
    plan: ComponentPlan, assembly: ResolvedAssembly, options: Mapping[str, Any]
) -> list[ExpectedComponent]:
    """The components of ``plan.module`` the monitor should see on the graph.

    With ``options["launched"]`` (names of the components the launcher started), exactly
    those of the module; otherwise every component of the module whose kind the launcher
    starts (a runnable kind: other kinds are never started, so expecting them would be a
    false alarm). Components sharing a node name make one item expecting that many
    instances.

    A component whose kind something stands in for in simulation (the motor interface, for
    the simulator: see :mod:`components.kinds`) is satisfied by the stand-in's node: only by
    it with ``options["sim"]``; by either otherwise, because the launcher runs the simulator
    in another process than the module's components, whose ``sim`` option cannot tell.
    """
    launched = options.get("launched")
    launched_names = None if launched is None else set(launched)
    sim = bool(options.get("sim"))
    by_node: dict[str, ExpectedComponent] = {}
    for other in assembly.components:
        if other.module != plan.module or other.name == plan.name:
            continue
        if launched_names is not None:
            if other.name not in launched_names:
                continue
        elif not buildable(other.kind):
            continue
        node = f"{other.namespace.rstrip('/')}/{node_name(other)}"
        alternatives: tuple[str, ...] = ()
        stand_ins = tuple(stand_in_node(k) for k in kinds.stand_ins(other.kind))
        if stand_ins:
            if sim:
                node, alternatives = stand_ins[0], stand_ins[1:]
            else:
                alternatives = stand_ins
        known = by_node.get(node)
        if known is not None:
            by_node[node] = replace(known, count=known.count + 1)
        else:
            by_node[node] = ExpectedComponent(node_name(other), node, 1, alternatives)
    return list(by_node.values())


class GraphFeed:
    """Forwards graph changes of the expected nodes to the health core (an ``on_bound`` hook).

    Zenoh delivers liveliness changes on its own threads; this keeps, per node name, the set
    of live node tokens (a restarted process briefly overlaps its predecessor; two location
    publishers share a name) and posts ``on_component_instances(node, count)`` into the
    executor thread when that number changes.

    Args:
        built: The built health monitor; the graph is added to its resources.
        nodes: Fully qualified names of the nodes to follow.
    """

    def __init__(self, built: BuiltComponent, nodes: Iterable[str]) -> None:
        self.built = built
        self.nodes = frozenset(nodes)
        self.graph: Graph | None = None
        self._live: dict[str, set[tuple[str, int]]] = {}
        self._lock = threading.Lock()
        self._post: Any = None

    def __call__(self, executor: Executor, component: Component) -> None:
        """Start following the graph of ``executor``'s data plane (called once, before run)."""

        def post(node: str, count: int) -> None:
            executor.call_soon(component, "on_component_instances", node, count)

        self._post = post
        # The graph reports the nodes already up at once (Zenoh's liveliness history, rclpy's
        # first read), so a component that started before the monitor is seen at once.
        self.graph = executor.graph(on_change=self._on_change, nodes_only=True)
        self.built.resources.append(self.graph)

    def _on_change(self, entity: Entity, alive: bool) -> None:
        if entity.kind is not EntityKind.NODE or entity.node_fqn not in self.nodes:
            return
        node = entity.node_fqn
        with self._lock:
            live = self._live.setdefault(node, set())
            before = len(live)
            if alive:
                live.add(entity.node_key)
            else:
                live.discard(entity.node_key)
            if len(live) != before and self._post is not None:
                # Posted under the lock so that appear/vanish reach the core in order.
                self._post(node, len(live))


def build(
    plan: ComponentPlan, assembly: ResolvedAssembly, options: Mapping[str, Any]
) -> BuiltComponent:
    """A health monitor for ``plan.module``, thresholds from the module's ``[health]`` data.

    Raises:
        BuildError: If the plan has no module, or a threshold is not a number.
    """
    if plan.module is None:
        raise BuildError(f"{plan.name}: a health monitor needs a module")
    module = assembly.module(plan.module)
    data = plan.params.get("thresholds", module.health)
    where = f"[health] of module {module.slot} ({module.module_type}, unit {module.unit})"
    try:
        thresholds = HealthThresholds.from_mapping(data, where)
    except ValueError as exc:
        raise BuildError(f"{plan.name}: {exc}") from exc
    expected = expected_components(plan, assembly, options)
    reader = HostMetricsReader()
    core = HealthMonitorCore(
        plan.name,
        module=module.slot,
        components=expected,
        motors=[MotorWatch(j.spec.name, j.raw_name) for j in module.actuated_joints],
        thresholds=thresholds,
        read_host_metrics=reader.read,
        unit=module.unit,
        host=module.host,
    )
    built = BuiltComponent(core, HEALTH_MONITOR, module.namespace, node_name(plan), [reader])
    built.on_bound = GraphFeed(built, {n for c in expected for n in c.nodes})
    return built
