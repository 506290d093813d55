"""Build a motor interface from its module's plan: the backend comes from the bus kind."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from components.assembly import ComponentPlan, ResolvedAssembly
from components.build import BuildError, BuiltComponent
from components.motor_interface.core import MotorInterfaceCore
from components.motor_interface.interface import MOTOR_INTERFACE
from components.motors.base import MotorError, backend_class


def build(
    plan: ComponentPlan, assembly: ResolvedAssembly, options: Mapping[str, Any]
) -> BuiltComponent:
    """A MotorInterfaceCore on the module's bus (CANopen, Dynamixel...)."""
    if plan.module is None:
        raise BuildError(f"{plan.name}: a motor interface needs a module")
    module = assembly.module(plan.module)
    bus = module.bus
    bus_options: dict[str, Any] = dict(bus.options)
    if bus.bitrate is not None:
        bus_options.setdefault("bitrate", bus.bitrate)
    if bus.baudrate is not None:
        bus_options.setdefault("baudrate", bus.baudrate)
    bus_options.update(options.get("bus_options", {}))
    channel = options.get("channel", bus.channel)
    try:
        backend = backend_class(bus.kind)(channel, module.motor_specs(), bus_options)
    except MotorError as exc:
        raise BuildError(f"{plan.name}: {exc}") from exc
    core = MotorInterfaceCore(plan.name, module.slot, backend)
    return BuiltComponent(core, MOTOR_INTERFACE, module.namespace, "motor_interface", [backend])
