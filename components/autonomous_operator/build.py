"""Build an autonomous operator from the resolved assembly.

The core reports the operator's status; the runner (its ``on_bound`` hook and a resource,
:class:`~components.autonomous_operator.runner.ScriptRunner`) runs the script on the
component's node, over the modules of the robot the data names (``robot``: its root module;
default: the assembly's first robot, or every module when the assembly has several).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from components.assembly import ComponentPlan, ResolvedAssembly
from components.autonomous_operator.core import AutonomousOperatorCore, OperatorConfig
from components.autonomous_operator.interface import AUTONOMOUS_OPERATOR
from components.autonomous_operator.runner import ScriptRunner, load_main, where_it_failed
from components.autonomous_operator.script import check_arguments, locate, read_main
from components.build import BuildError, BuiltComponent, node_name
from components.robots import modules_of, robot_names, root_link


def build(
    plan: ComponentPlan, assembly: ResolvedAssembly, options: Mapping[str, Any]
) -> BuiltComponent:
    """An autonomous operator running ``plan``'s script.

    Params: ``script``, ``robot``, ``params`` (``main``'s keyword arguments) and
    :class:`OperatorConfig` fields.

    Raises:
        BuildError: If the script is gone or no longer takes its params, or a parameter is
            out of range.
    """
    del options
    names = {f.name for f in dataclasses.fields(OperatorConfig)}
    try:
        config = OperatorConfig(**{k: v for k, v in plan.params.items() if k in names})
        path = locate(plan.params.get("script", ""))
        params = dict(plan.params.get("params", {}))
        # Checked at assemble; checked again here, as the script may have changed since.
        check_arguments(read_main(path), params)
        robots = robot_names(assembly)
        robot = plan.params.get("robot") or robots[0]
        slots = modules_of(assembly, robot) if len(robots) > 1 or robot != robots[0] else []
        slots = slots or [m.slot for m in assembly.modules]
    except (TypeError, ValueError, KeyError) as exc:
        raise BuildError(f"{plan.name}: {exc}") from exc
    try:
        # Imported here, before the executor beats its heartbeat: see the runner's docstring.
        main = load_main(path, plan.name.replace("/", "_"))
    except Exception as exc:
        raise BuildError(f"{plan.name}: {where_it_failed(path, exc)}") from exc
    core = AutonomousOperatorCore(plan.name, path.stem, config, hardware_id=plan.host)
    built = BuiltComponent(core, AUTONOMOUS_OPERATOR, plan.namespace, node_name(plan.name))
    runner = ScriptRunner(
        built,
        assembly,
        path,
        main,
        params,
        slots,
        robot,
        root_link(assembly, robot),
        config.connect_timeout,
        config.stop_timeout,
    )
    core.on_stop = runner.stop
    built.resources.append(runner)
    built.on_bound = runner
    return built
