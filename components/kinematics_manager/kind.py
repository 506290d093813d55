"""The kinematics manager kind: forward and inverse kinematics of one limb chain."""

from components.kinds import ComponentKind, Placement

KIND = ComponentKind(
    name="kinematics_manager",
    summary="tip pose and IK targets of one limb chain",
    placement=Placement.MODULE,
    config=(
        "components.kinematics_manager.core:KinematicsConfig",
        "components.kinematics_manager.ik:IkSettings",
    ),
    builder="components.kinematics_manager.build:build",
    interface="components.kinematics_manager.interface:KINEMATICS_MANAGER",
    # Diagnostics go out at start, before any joint_read; tip_pose needs joint angles first.
    healthy_output="diagnostics",
    structural=("chain", "base_link", "tip_link", "joints"),
    # It takes ik_target only from the limb's claim holder and turns it into joint_set.
    claim_relay=True,
    extensions=("components.kinematics_manager.injections",),
    # The IK's random restarts (numpy loads numpy.random on first use).
    preload=("numpy.random",),
)
