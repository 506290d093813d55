"""Injections for the Joint Manager: capabilities any robot may be given by name from data.

``rezero``: a ``std_srvs/Trigger`` service that makes the joints' current positions read as
calibrated zero and saves the new offsets to the unit's calibration file. This is the one
place a joint manager touches a file, and only on an explicit operator request.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from components.executor.interface import Serve
from components.executor.registry import injection
from components.joint_manager.calibration_file import CalibrationFileError, write_zero_offsets
from components.joint_manager.core import JointManagerCore
from components.messages import TRIGGER, trigger_response

_REZERO_PARAMS = {"joints", "calibration_file", "service"}


@injection(
    "joint_manager",
    "rezero",
    params={"joints": (list, str), "calibration_file": str, "service": str},
)
def rezero(core: JointManagerCore, params: dict[str, Any]) -> None:
    """Re-zero joints at runtime from a Trigger service and save the offsets to the unit file.

    Adds ``on_<service>`` to the core and a :class:`Serve` to ``core.extra_serve``. On each
    request, every targeted joint's zero offset becomes its latest raw position (so it reads
    0 in calibrated space, direction unchanged). The file is written first; if that fails,
    nothing changes at runtime either, so file and manager never disagree.

    Params:
        joints: Joint names (raw ``joint3`` or full ``limb1_joint3``); default all.
        calibration_file: Path of the unit calibration TOML to update; when absent the new
            offsets live only until restart (the response says so).
        service: Service name, default ``rezero``.

    Raises:
        ValueError: On an unknown parameter, an unknown joint, or a service already added.
    """
    unknown = set(params) - _REZERO_PARAMS
    if unknown:
        raise ValueError(
            f"rezero injection: unknown parameter(s) {sorted(unknown)}; "
            f"known: {sorted(_REZERO_PARAMS)}"
        )
    names = params.get("joints") or core.joint_names
    if isinstance(names, str):
        names = [names]
    try:
        targets = [core.resolve(name) for name in names]
    except KeyError as exc:
        raise ValueError(f"rezero injection: {exc.args[0]}") from None
    path = params.get("calibration_file")
    service = str(params.get("service", "rezero"))
    handler = f"on_{service}"
    if any(s.service == service for s in core.extra_serve) or hasattr(core, handler):
        raise ValueError(f"rezero injection: {core.name} already serves {service!r}")

    def on_rezero(request: Any, now: float) -> Any:
        stale = [
            name
            for name in targets
            if core.latest_raw_position(name) is None
            or core.position_age(name, now) > core.config.stale_timeout
        ]
        if stale:
            return trigger_response(
                False,
                f"rezero refused: no fresh joint_states for {', '.join(stale)}; nothing changed",
            )
        new = {}
        for name in targets:
            raw = core.latest_raw_position(name)
            assert raw is not None
            new[name] = dataclasses.replace(core.calibration(name), zero_offset=raw)
        if path:
            try:
                write_zero_offsets(
                    path,
                    {core.local_name(n): c.zero_offset for n, c in new.items()},
                    {core.local_name(n): c.direction for n, c in new.items()},
                )
            except CalibrationFileError as exc:
                return trigger_response(False, f"rezero failed, nothing changed: {exc}")
        changes = []
        for name, calibration in new.items():
            old = core.calibration(name).zero_offset
            core.set_calibration(name, calibration)
            changes.append(f"{name} {old:.6g} -> {calibration.zero_offset:.6g}")
        saved = f"saved to {path}" if path else "not saved (no calibration_file): lost at restart"
        return trigger_response(True, f"re-zeroed {'; '.join(changes)}; {saved}")

    setattr(core, handler, on_rezero)
    core.extra_serve.append(Serve(service, TRIGGER, handler))
