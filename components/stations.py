"""Ground-station kinds the assembler plans and the operator tools will run.

Each is a typed entry now, so templates are checked against it at ``msctl assemble``; none
has a builder yet, so the launcher reports them as not built instead of starting a
placeholder. Each moves into its own package (``components/<kind>/kind.py``) when its code
lands.
"""

from components.kinds import ComponentKind, Placement

KINDS = (
    ComponentKind(
        name="human_operator",
        summary="a station's operator: claims, the second deadman (msctl teleop)",
        placement=Placement.STATION,
    ),
    ComponentKind(
        name="autonomous_operator",
        summary="a supervised Python-API script, main(robot)",
        placement=Placement.STATION,
    ),
)
