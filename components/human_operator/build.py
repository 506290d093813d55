"""Build a human operator from the resolved assembly.

The core relays and keeps the deadman; the desk (its ``on_bound`` hook,
:class:`~components.human_operator.desk.OperatorDesk`) holds the claims of its screens and
opens each relay input to the screen holding its modules. Both are closed with the
component.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from components.assembly import ComponentPlan, ResolvedAssembly
from components.build import BuiltComponent, config_from_params, node_name
from components.human_operator.core import HumanOperatorConfig, HumanOperatorCore
from components.human_operator.desk import OperatorDesk
from components.human_operator.interface import human_operator_interface
from components.human_operator.routes import routes_of


def build(
    plan: ComponentPlan, assembly: ResolvedAssembly, options: Mapping[str, Any]
) -> BuiltComponent:
    """A human operator relaying every command input of ``assembly``.

    Params: :class:`HumanOperatorConfig` fields.

    Raises:
        BuildError: If a parameter is out of range or not a number.
    """
    del options
    config = config_from_params(plan, HumanOperatorConfig)
    node = node_name(plan.name)
    routes = routes_of(assembly, f"{plan.namespace.rstrip('/')}/{node}")
    core = HumanOperatorCore(plan.name, routes, config, hardware_id=plan.host)
    built = BuiltComponent(core, human_operator_interface(routes), plan.namespace, node)
    desk = OperatorDesk([m.slot for m in assembly.modules], routes, config.deadman_timeout)
    built.resources.append(desk)
    built.on_bound = desk
    return built
