"""The location publisher kind: poses of a module's links on tf."""

from components.kinds import ComponentKind, Placement

KIND = ComponentKind(
    name="location_publisher",
    summary="poses of a module's links (tf), from joint_read",
    placement=Placement.MODULE,
    config=("components.location_publisher.core:LocationConfig",),
    builder="components.location_publisher.build:build",
    interface="components.location_publisher.interface:location_interface",
    # Every location publisher writes tf (the root-link one at start, from static edges).
    healthy_output="tf",
    structural=("link", "links"),
)
