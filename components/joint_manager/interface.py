"""How the Joint Manager core meets the data plane (names relative to the module namespace).

``joint_states`` is read best-effort (sensor stream: the newest sample wins); commands and
everything the manager publishes use the reliable default, so a hold is never dropped on our
side. Injections may add services through ``JointManagerCore.extra_serve``; the executor binds
those in addition to this static declaration.
"""

from __future__ import annotations

from components.comm.qos import SENSOR
from components.executor.interface import Every, InterfaceSpec, Publish, Serve, Subscribe
from components.messages import DIAGNOSTIC_ARRAY, JOINT_STATE, TRIGGER
from components.roles import Role

LIST_JOINTS = "msctl_msgs/srv/ListJoints"

JOINT_MANAGER = InterfaceSpec(
    subscribe=(
        # The motors' readings: from the module's own motor interface only.
        Subscribe("joint_states", JOINT_STATE, "on_joint_states", qos=SENSOR, role=Role.FEEDBACK),
        # What operators ask for: from the module's claim holder only while it is claimed.
        Subscribe("joint_set", JOINT_STATE, "on_joint_set", role=Role.COMMAND),
    ),
    publish=(
        Publish("joint_read", JOINT_STATE),
        Publish("joint_commands", JOINT_STATE),
        Publish("diagnostics", DIAGNOSTIC_ARRAY),
    ),
    serve=(
        # Before anything queued: a halt must not wait behind a backlog of joint_states.
        Serve("halt", TRIGGER, "on_halt", urgent=True, role=Role.HALT),
        Serve("recover", TRIGGER, "on_recover", role=Role.CONTROL),
        Serve("joints", LIST_JOINTS, "on_joints", role=Role.QUERY),
    ),
    every=(Every(0.02, "tick"),),
)
"""The Joint Manager's static interface: 50 Hz tick for watchdog, keep-alive and diagnostics."""
