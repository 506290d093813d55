"""How the Kinematics Manager core meets the data plane (names relative to the limb's namespace).

``joint_read`` is the joint manager's calibrated feedback; ``joint_set`` goes back to it as
position targets, so the joint manager's limits, watchdog and halt still apply to IK motion.
"""

from __future__ import annotations

from components.executor.interface import Every, InterfaceSpec, Publish, Subscribe
from components.messages import DIAGNOSTIC_ARRAY, JOINT_STATE, POSE_STAMPED
from components.roles import Role

KINEMATICS_MANAGER = InterfaceSpec(
    subscribe=(
        Subscribe("joint_read", JOINT_STATE, "on_joint_read", role=Role.TELEMETRY),
        Subscribe("ik_target", POSE_STAMPED, "on_ik_target", role=Role.COMMAND),
    ),
    publish=(
        Publish("tip_pose", POSE_STAMPED),
        Publish("joint_set", JOINT_STATE),
        Publish("diagnostics", DIAGNOSTIC_ARRAY),
    ),
    every=(Every(0.05, "tick"),),
)
"""The Kinematics Manager's interface: a 20 Hz tick for held-back and keep-alive tip poses."""
