"""The bridge kind: a ground station's relay between msctl's Zenoh data plane and a DDS ROS 2
graph (``msctl bridge`` as a supervised component), so a team on ROS 2's default rmw sees the
robot's topics and services."""

from components.kinds import ComponentKind, Placement

KIND = ComponentKind(
    name="bridge",
    summary="relays topics and services between msctl's Zenoh plane and a DDS ROS 2 graph",
    placement=Placement.STATION,
    config=("components.bridge.core:BridgeConfig",),
    builder="components.bridge.build:build",
    interface="components.bridge.interface:BRIDGE",
    healthy_output="diagnostics",
)
