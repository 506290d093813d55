"""The human operator kind: the station's operator process, relaying with a second deadman."""

from components.kinds import ComponentKind, Placement

KIND = ComponentKind(
    name="human_operator",
    summary="a station's operator: claims, the second deadman, relays (msctl teleop)",
    placement=Placement.STATION,
    config=("components.human_operator.core:HumanOperatorConfig",),
    builder="components.human_operator.build:build",
    interface="components.human_operator.interface:human_operator_interface",
    # Its status, on the station's diagnostics (where the data monitor reads stations).
    healthy_output="diagnostics",
    # Its claims and attached screens live in the process: rebuilt alone, a screen would
    # keep relaying into a desk that no longer knows it.
    not_rebuilt_alone="its operators' claims and screens are held by the running process",
)
