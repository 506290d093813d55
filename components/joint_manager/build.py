"""Build a joint manager from its module's plan (and, on its robot computer, the watch of its
operators' presence: :mod:`components.joint_manager.presence_feed`)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from components.assembly import ComponentPlan, ResolvedAssembly
from components.build import BuildError, BuiltComponent
from components.joint_manager.core import JointManagerConfig, JointManagerCore
from components.joint_manager.interface import JOINT_MANAGER
from components.joint_manager.presence_feed import PresenceFeed, watched
from components.roles import bind


def build(
    plan: ComponentPlan, assembly: ResolvedAssembly, options: Mapping[str, Any]
) -> BuiltComponent:
    """A JointManagerCore for ``plan.module``: unit calibration, injections, overrides; on
    the module's own computer, held while its operators are gone (the template's
    ``[safety] operator_timeout``)."""
    if plan.module is None:
        raise BuildError(f"{plan.name}: a joint manager needs a module")
    module = assembly.module(plan.module)
    joints = module.actuated_joints
    from components.supervision.contract import this_host

    presence = watched(assembly, module.slot, this_host())
    config_fields = {}
    for key, value in plan.params.items():
        if key in JointManagerConfig.__dataclass_fields__:
            try:
                config_fields[key] = float(value)
            except (TypeError, ValueError):
                raise BuildError(
                    f"{plan.name}: param {key} must be a number, not {value!r}"
                ) from None
    try:
        core = JointManagerCore(
            plan.name,
            module=module.slot,
            joints=[j.spec for j in joints],
            calibration={j.spec.name: j.calibration for j in joints},
            config=JointManagerConfig(**config_fields),
            presence=None if presence is None else presence[0],
        )
    except ValueError as exc:
        raise BuildError(f"{plan.name}: {exc}") from exc
    # Its inputs' rules from their roles: joint_set (a command) only from the module's claim
    # holder while it is claimed, joint_states (feedback) only from its own motor interface.
    spec = bind(JOINT_MANAGER, assembly, module.slot)
    built = BuiltComponent(core, spec, module.namespace, "joint_manager")
    if presence is not None:
        built.on_bound = PresenceFeed(built, module.slot, presence[1])
    # The rezero injection saves new offsets back to the unit's own calibration file.
    if module.calibration_file:
        built.extension_defaults = {"rezero": {"calibration_file": module.calibration_file}}
    return built
