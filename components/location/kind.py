"""The location publisher kind: poses of a module's links on tf."""

from components.kinds import ComponentKind, Placement

KIND = ComponentKind(
    name="location_publisher",
    summary="poses of a module's links (tf), from joint_read",
    placement=Placement.MODULE,
    config=("components.location.core:LocationConfig",),
    builder="components.location.build:build",
    interface="components.location.interface:location_interface",
    # Every location publisher writes tf (the root-link one at start, from static edges).
    healthy_output="tf",
    structural=("link", "links"),
)
