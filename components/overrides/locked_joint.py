"""``locked_joint``: a joint that must not move (broken gearbox, seized bearing, jammed cable).

Named in a unit's calibration file, e.g. ``overrides = [{name = "locked_joint", joint =
"joint3"}]``, so a broken joint gets its override in minutes without touching any code.
"""

from __future__ import annotations

import math
from typing import Any

from components.executor.registry import override
from components.joint_manager.core import JointManagerCore, Refusal
from components.messages import JointSample

_PARAMS = {"joint", "position"}


@override(
    "joint_manager", "locked_joint", params={"joint": str, "position": float}, required=("joint",)
)
def locked_joint(core: JointManagerCore, params: dict[str, Any]) -> None:
    """Hold one joint at a fixed position and refuse every command to it (WARN, counted).

    Uses the Joint Manager's hook points: :meth:`JointManagerCore.pin` keeps the joint held
    (and reported as locked by the ``joints`` service); a command filter refuses commands
    naming it with ``refused_locked``, which puts the joint's diagnostic at WARN.

    Params:
        joint: The joint, raw (``joint3``) or full (``limb1_joint3``) name.
        position: Calibrated position to hold; default where the joint is at the first
            feedback.

    Raises:
        ValueError: On a missing/unknown joint, a non-finite position or unknown parameter.
    """
    unknown = set(params) - _PARAMS
    if unknown:
        raise ValueError(
            f"locked_joint override: unknown parameter(s) {sorted(unknown)}; "
            f"known: {sorted(_PARAMS)}"
        )
    if "joint" not in params:
        raise ValueError("locked_joint override: 'joint' is required (e.g. joint = \"joint3\")")
    try:
        name = core.resolve(str(params["joint"]))
    except KeyError as exc:
        raise ValueError(f"locked_joint override: {exc.args[0]}") from None
    position = params.get("position")
    if position is not None:
        position = float(position)
        if not math.isfinite(position):
            raise ValueError(f"locked_joint override: position for {name} must be finite")
    reason = (
        f"{name} is locked by override locked_joint: command refused "
        "(remove the override from the unit calibration to use it)"
    )

    def refuse(command: JointSample, now: float) -> Refusal:
        return Refusal("refused_locked", reason)

    core.pin(name, position, note="locked by override locked_joint")
    core.add_command_filter(name, refuse)
