"""The joint manager kind: limits, calibration and the command watchdog of one module."""

from components.kinds import ComponentKind, Placement

KIND = ComponentKind(
    name="joint_manager",
    summary="limits, calibration and the command watchdog between operators and motors",
    placement=Placement.MODULE,
    config=("components.joint_manager.core:JointManagerConfig",),
    builder="components.joint_manager.build:build",
    interface="components.joint_manager.interface:JOINT_MANAGER",
    healthy_output="diagnostics",
    module_facts=("joints",),
    extensions=("components.joint_manager.injections", "components.overrides"),
)
