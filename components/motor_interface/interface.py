"""The motor interface's place on the data plane (module namespace)."""

from components.comm.qos import SENSOR
from components.executor.interface import Every, InterfaceSpec, Publish, Serve, Subscribe
from components.messages import DIAGNOSTIC_ARRAY, JOINT_STATE, TRIGGER
from components.motors.base import READ_PERIOD
from components.roles import Role

#: The node whose ``joint_commands`` the motor interface takes, relative to the module's
#: namespace: the module's own joint manager (the builder names it from the assembly).
COMMANDING_NODE = "joint_manager"

#: The same interface the simulator serves for each module: the joint manager cannot tell
#: a real bus from the simulated one. Commands from any other node are refused by the
#: transport, counted and warned about (one WARN per intruding node).
MOTOR_INTERFACE = InterfaceSpec(
    subscribe=(
        Subscribe(
            "joint_commands",
            JOINT_STATE,
            "on_joint_commands",
            senders=(COMMANDING_NODE,),
            role=Role.RAW,
        ),
    ),
    publish=(
        Publish("joint_states", JOINT_STATE, SENSOR),
        Publish("diagnostics", DIAGNOSTIC_ARRAY),
    ),
    serve=(
        # The joint manager's own requests to its motors.
        Serve("motors/halt", TRIGGER, "on_halt", role=Role.RAW),
        Serve("motors/recover", TRIGGER, "on_recover", role=Role.RAW),
    ),
    every=(Every(READ_PERIOD, "tick"),),
)
