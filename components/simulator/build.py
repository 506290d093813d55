"""Build the whole-assembly simulator (the launcher's stand-in for every motor interface).

The assembly's component plan lists one hardware ``motor_interface`` per module; off-robot the
launcher replaces them all by ONE simulator component, e.g.
``ComponentPlan(name="sim", kind="simulator", host=..., module=None, namespace="/sim")``.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any

from components.assembly import ComponentPlan, ResolvedAssembly
from components.build import BuildError, BuiltComponent
from components.simulator.core import SimulatorConfig, SimulatorCore
from components.simulator.interface import simulator_interface
from components.simulator.topics import SIM_NAMESPACE
from components.simulator.world import SimulationError, SimWorld

_CONFIG_OPTIONS = ("speed", "tick_period", "state_period", "pose_period", "diagnostics_period")


def simulator_config(
    options: Mapping[str, Any], params: Mapping[str, Any] | None = None
) -> SimulatorConfig:
    """The timing from plan params, then run-time options (``speed``...), which win.

    Raises:
        BuildError: If a value is not a positive number.
    """
    values: dict[str, float] = {}
    for source in (dict(params or {}), dict(options)):
        for key in _CONFIG_OPTIONS:
            if source.get(key) is not None:
                try:
                    values[key] = float(source[key])
                except (TypeError, ValueError):
                    raise BuildError(
                        f"simulator: {key} must be a number, not {source[key]!r}"
                    ) from None
    try:
        return SimulatorConfig(**values)
    except ValueError as exc:
        raise BuildError(f"simulator: {exc}") from exc


def build(
    plan: ComponentPlan, assembly: ResolvedAssembly, options: Mapping[str, Any]
) -> BuiltComponent:
    """A :class:`SimulatorCore` for the whole assembly.

    Options: ``speed`` (simulated seconds per wall second, default 1), ``viewer`` (open
    MuJoCo's viewer when a display exists), ``mjcf`` (another model file), and the other
    :class:`SimulatorConfig` timings.

    Raises:
        BuildError: If the plan names a module (the simulator is whole-assembly), the timing
            is invalid, or the model does not match the assembly.
    """
    if plan.module is not None:
        raise BuildError(
            f"{plan.name}: the simulator serves the whole assembly; plan it with module=None "
            f"(it was given module {plan.module!r})"
        )
    config = simulator_config(options, plan.params)
    try:
        world = SimWorld.from_assembly(assembly, options.get("mjcf"))
    except SimulationError as exc:
        raise BuildError(f"{plan.name}: {exc}") from exc
    if options.get("viewer"):
        world.attach_viewer()
    core = SimulatorCore(plan.name, world, config, timer=time.perf_counter)
    namespace = plan.namespace or SIM_NAMESPACE
    return BuiltComponent(
        core, simulator_interface(assembly, config), namespace, "simulator", [world]
    )
