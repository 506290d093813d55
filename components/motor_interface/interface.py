"""The motor interface's place on the data plane (module namespace)."""

from components.comm.qos import SENSOR
from components.executor.interface import Every, InterfaceSpec, Publish, Serve, Subscribe
from components.messages import DIAGNOSTIC_ARRAY, JOINT_STATE, TRIGGER

#: The same interface the simulator serves for each module: the joint manager cannot tell
#: a real bus from the simulated one.
MOTOR_INTERFACE = InterfaceSpec(
    subscribe=(Subscribe("joint_commands", JOINT_STATE, "on_joint_commands"),),
    publish=(
        Publish("joint_states", JOINT_STATE, SENSOR),
        Publish("diagnostics", DIAGNOSTIC_ARRAY),
    ),
    serve=(
        Serve("motors/halt", TRIGGER, "on_halt"),
        Serve("motors/recover", TRIGGER, "on_recover"),
    ),
    every=(Every(0.01, "tick"),),
)
