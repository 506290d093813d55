"""The simulator kind: one MuJoCo world standing in for every motor interface off-robot."""

from components.kinds import ComponentKind, Placement

KIND = ComponentKind(
    name="simulator",
    summary="one MuJoCo world for the whole assembly, speaking the motor interfaces' topics",
    placement=Placement.ASSEMBLY,
    config=("components.simulator.core:SimulatorConfig",),
    builder="components.simulator.build:build",
    interface="components.simulator.interface:simulator_interface",
    healthy_output="/sim/diagnostics",
    stands_in_for=("motor_interface",),
    namespace="/sim",
    # A new world starts from the initial pose: the robot would jump, and every motor with it.
    not_rebuilt_alone="a new MuJoCo world would start the robot again from its initial pose",
)
