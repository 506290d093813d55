"""What the health board watches, read from the resolved assembly (static knowledge only).

One :class:`~components.data_monitor.model.WatchedSpec` per module (its health topic and the
nodes its components run as) and per ground station (its components; kinds with no code yet
listed as planned). A component whose kind something stands in for in simulation (the motor
interface, for the simulator) is satisfied by either node, since the assembly does not say
whether it runs simulated.
"""

from __future__ import annotations

from collections.abc import Iterable

from components import kinds
from components.assembly import ComponentPlan, ResolvedAssembly
from components.build import buildable, node_name
from components.data_monitor.board import HealthBoard
from components.data_monitor.model import ExpectedNode, WatchedSpec


def expected_nodes(plans: Iterable[ComponentPlan]) -> list[ExpectedNode]:
    """The nodes ``plans`` run as; components sharing a node name make one entry."""
    by_node: dict[str, ExpectedNode] = {}
    for plan in plans:
        if not buildable(plan.kind):
            continue
        node = f"{plan.namespace.rstrip('/')}/{node_name(plan.name)}"
        stand_ins = kinds.stand_ins(plan.kind)
        alternatives = tuple(f"{k.namespace.rstrip('/')}/{k.name}" for k in stand_ins)
        names = (plan.name, *(k.component_name for k in stand_ins))
        known = by_node.get(node)
        if known is None:
            by_node[node] = ExpectedNode(
                node_name(plan.name), node, alternatives, 1, names, plan.kind
            )
        else:
            by_node[node] = ExpectedNode(
                known.label,
                node,
                known.alternatives,
                known.count + 1,
                (*known.components, plan.name),
                known.kind,
            )
    return list(by_node.values())


def watched(assembly: ResolvedAssembly) -> list[WatchedSpec]:
    """Every module (in assembly order), then every ground station."""
    specs = []
    for module in assembly.modules:
        plans = [c for c in assembly.components if c.module == module.slot]
        specs.append(WatchedSpec(module.slot, module.host, tuple(expected_nodes(plans))))
    stations: dict[str, list[ComponentPlan]] = {}
    for plan in assembly.components:
        if plan.module is None:
            stations.setdefault(plan.name.split("/", 1)[0], []).append(plan)
    for name, plans in stations.items():
        specs.append(
            WatchedSpec(
                name,
                plans[0].host,
                tuple(expected_nodes(plans)),
                station=True,
                planned=tuple((p.name, p.kind) for p in plans if not buildable(p.kind)),
            )
        )
    return specs


def board_for(assembly: ResolvedAssembly, **options: float) -> HealthBoard:
    """A :class:`HealthBoard` watching ``assembly`` (``options``: its keyword arguments)."""
    return HealthBoard(assembly.template, watched(assembly), assembly.hosts, **options)  # type: ignore[arg-type]
