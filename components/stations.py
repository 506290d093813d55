"""Ground-station kinds the assembler plans and no code runs yet (the autonomous operator).

Each is a typed entry now, so templates are checked against it at ``msctl assemble``; none
has a builder yet, so the launcher reports them as not built instead of starting a
placeholder. Each moves into its own package (``components/<kind>/kind.py``) when its code
lands.
"""

from components.kinds import ComponentKind, Placement

KINDS = (
    ComponentKind(
        name="autonomous_operator",
        summary="a supervised Python-API script, main(robot)",
        placement=Placement.STATION,
    ),
)
