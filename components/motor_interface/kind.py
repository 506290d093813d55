"""The motor interface kind: one bus of motors, carried between the data plane and a backend."""

from components.kinds import ComponentKind, Placement

KIND = ComponentKind(
    name="motor_interface",
    summary="carries joint_commands to a module's motors and their readings back",
    placement=Placement.MODULE,
    builder="components.motor_interface.build:build",
    interface="components.motor_interface.interface:MOTOR_INTERFACE",
    healthy_output="joint_states",
    module_facts=("joints", "bus", "channel"),
)
