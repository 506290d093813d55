"""Build a motor interface from its module's plan: the backend comes from the bus kind."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from components.assembly import ComponentPlan, ResolvedAssembly
from components.build import BuildError, BuiltComponent
from components.executor.interface import InterfaceSpec
from components.motor_interface.core import MotorInterfaceCore
from components.motor_interface.interface import MOTOR_INTERFACE
from components.motors.base import MotorError, RawLimits
from components.motors.options import backend_info, parse_options


def build(
    plan: ComponentPlan, assembly: ResolvedAssembly, options: Mapping[str, Any]
) -> BuiltComponent:
    """A MotorInterfaceCore on the module's bus (CANopen, Dynamixel...).

    ``options`` may override the bus for this run: ``channel`` (e.g. an emulator's) and
    ``bus_options`` (keys of the backend's options type, over the module data's). With
    ``emulate`` set (``MSCTL_EMULATE_HARDWARE=1``, as ``msctl rehearse`` runs a robot
    computer), the bus's emulated hardware starts first in this process and the real backend
    opens its channel: the motor loop is the robot's own, only the drives are emulated.

    Raises:
        BuildError: If the bus kind is unknown, an option or the channel is invalid for it,
            or the backend cannot be loaded; the message names the component and the key.
    """
    if plan.module is None:
        raise BuildError(f"{plan.name}: a motor interface needs a module")
    module = assembly.module(plan.module)
    bus = module.bus
    overrides: dict[str, Any] = dict(options.get("bus_options", {}))
    channel = options.get("channel", bus.channel)
    emulated = None
    try:
        info = backend_info(bus.kind)
        if options.get("emulate"):
            emulated = info.load_emulator()(channel, module.motor_specs())
            channel = emulated.channel
            overrides = {**emulated.bus_options, **overrides}
        # bus.bitrate / bus.baudrate go through the same typed options as the rest, unless
        # this run overrides them.
        typed = parse_options(
            bus.kind,
            {**bus.options, **overrides},
            bitrate=None if "bitrate" in overrides else bus.bitrate,
            baudrate=None if "baudrate" in overrides else bus.baudrate,
        )
        info.check_channel(channel)
        backend = info.load_class()(channel, module.motor_specs(), typed)
    except MotorError as exc:
        if emulated is not None:
            emulated.close()
        raise BuildError(f"{plan.name}: bus of module {plan.module}: {exc}") from exc
    # The last stage checks commands against the unit's raw limits itself (defence in depth).
    limits = {j.raw_name: RawLimits.of_joint(j.spec, j.calibration) for j in module.actuated_joints}
    core = MotorInterfaceCore(plan.name, module.slot, backend, limits=limits)
    # Closed in reverse: the backend leaves its bus before the emulated drives go.
    resources: list[Any] = [emulated, backend] if emulated is not None else [backend]
    return BuiltComponent(
        core, interface_for(assembly, module.slot), module.namespace, "motor_interface", resources
    )


def interface_for(assembly: ResolvedAssembly, slot: str) -> InterfaceSpec:
    """:data:`MOTOR_INTERFACE` taking ``joint_commands`` (raw commands, by their role) from
    the module's own joint manager only, named from the assembly."""
    from components.roles import bind

    return bind(MOTOR_INTERFACE, assembly, slot)
