"""Injections for the Joint Manager: capabilities any robot may be given by name from data.

``rezero``: a ``msctl_msgs/Rezero`` service that makes the joints' current positions read as
calibrated zero and saves the new offsets to the unit's calibration file. This is the one
place a joint manager touches a file, and only on an explicit operator request, so it is
guarded like every service that writes to disk:

* it refuses while the module moves (a measured speed above ``still_speed``, or a command
  still moving a joint);
* each call shifts a bounded joint's offset by at most ``max_shift`` rad (revolute) or
  ``max_shift_linear`` m (prismatic), from module data, unless the request says ``force``:
  an offset moves the joint's raw limits with it, so an unbounded re-zero could drive it
  past its hardware range (issue 10: 0.56 rad, then a legal ``joint_set`` of 3.0 went
  0.51 rad past the raw limit);
* it keeps a timestamped copy of the unit file beside it before writing (atomic writes);
* it logs who asked: the caller's node, from its request's GID and the graph.

After a re-zero the joint manager also keeps its commands inside the raw range it started
with, which is what the motor interface and simulator enforce until they restart.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from typing import Any

import numpy as np

from components.executor.interface import Serve
from components.executor.registry import injection
from components.joint_manager.calibration_file import CalibrationFileError, write_zero_offsets
from components.joint_manager.core import JointManagerCore, Refusal
from components.messages import JointSample, msg
from components.roles import Role

log = logging.getLogger("msctl.joint_manager")

REZERO = "msctl_msgs/srv/Rezero"
REZERO_RESPONSE = "msctl_msgs/srv/Rezero_Response"

#: Largest offset shift per call of a revolute joint without ``force`` (5 degrees).
DEFAULT_MAX_SHIFT = math.radians(5.0)
#: Largest offset shift per call of a prismatic joint without ``force`` (m).
DEFAULT_MAX_SHIFT_LINEAR = 0.002
#: Measured speed (rad/s or m/s) above which a joint counts as moving.
DEFAULT_STILL_SPEED = 0.02

_REZERO_PARAMS = {
    "joints",
    "calibration_file",
    "service",
    "max_shift",
    "max_shift_linear",
    "still_speed",
}
_NUMBER = (float, int)


def _response(success: bool, message: str, shifts: dict[str, float] | None = None) -> Any:
    shifts = shifts or {}
    return msg(
        REZERO_RESPONSE,
        success=success,
        message=message,
        joints=list(shifts),
        shifts=np.array([float(v) for v in shifts.values()], dtype=np.float64),
    )


def _positive(params: dict[str, Any], key: str, default: float) -> float:
    value = params.get(key, default)
    if isinstance(value, bool) or not isinstance(value, _NUMBER):
        raise ValueError(f"rezero injection: {key} must be a number, not {value!r}")
    value = float(value)
    if not (value >= 0 and math.isfinite(value)):
        raise ValueError(f"rezero injection: {key} must be a finite number >= 0, not {value}")
    return value


@injection(
    "joint_manager",
    "rezero",
    params={
        "joints": (list, str),
        "calibration_file": str,
        "service": str,
        "max_shift": _NUMBER,
        "max_shift_linear": _NUMBER,
        "still_speed": _NUMBER,
    },
    inputs={"rezero": Role.RAW},
)
def rezero(core: JointManagerCore, params: dict[str, Any]) -> None:
    """Re-zero joints at runtime from a service, bounded, and save the offsets to the unit file.

    Adds ``on_<service>`` to the core and a :class:`Serve` to ``core.extra_serve``. On each
    request (``msctl_msgs/Rezero``: ``joints``, ``force``), every targeted joint's zero
    offset becomes its latest raw position (so it reads 0 in calibrated space, direction
    unchanged). Nothing changes when it is refused. The file is written first; if that
    fails, nothing changes at runtime either, so file and manager never disagree.

    Params:
        joints: Joint names (raw ``joint3`` or full ``limb1_joint3``); default all.
        calibration_file: Path of the unit calibration TOML to update; when absent the new
            offsets live only until restart (the response says so).
        service: Service name, default ``rezero``.
        max_shift: Largest offset change per call of a bounded revolute joint without
            ``force`` (rad, default 5 degrees).
        max_shift_linear: The same for a bounded prismatic joint (m, default 0.002).
        still_speed: Measured speed above which a joint counts as moving (default 0.02).

    Raises:
        ValueError: On an unknown parameter, an unknown joint, a bad number, or a service
            already added.
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
    max_shift = _positive(params, "max_shift", DEFAULT_MAX_SHIFT)
    max_shift_linear = _positive(params, "max_shift_linear", DEFAULT_MAX_SHIFT_LINEAR)
    still_speed = _positive(params, "still_speed", DEFAULT_STILL_SPEED)
    guard = _StartRange(core)

    def bound(name: str) -> float:
        spec = core.spec(name)
        if not spec.bounded:
            return math.inf  # no raw limit to be pushed past
        return max_shift_linear if spec.type == "prismatic" else max_shift

    def on_rezero(request: Any, now: float) -> Any:
        caller = _caller()
        force = bool(getattr(request, "force", False))
        try:
            asked = [core.resolve(n) for n in getattr(request, "joints", None) or ()]
        except KeyError as exc:
            return _refused(caller, f"rezero refused: {exc.args[0]}; nothing changed")
        stray = [n for n in asked if n not in targets]
        if stray:
            return _refused(
                caller,
                f"rezero refused: {', '.join(stray)} not re-zeroed by this module "
                f"(it re-zeroes {', '.join(targets)}); nothing changed",
            )
        chosen = asked or targets
        stale = [
            name
            for name in chosen
            if core.latest_raw_position(name) is None
            or core.position_age(name, now) > core.config.stale_timeout
        ]
        if stale:
            return _refused(
                caller,
                f"rezero refused: no fresh joint_states for {', '.join(stale)}; nothing changed",
            )
        moving = _moving(core, still_speed)
        if moving:
            return _refused(
                caller,
                f"rezero refused: the module moves ({', '.join(moving)}); stop it (halt, or "
                "let the motion finish) and ask again; nothing changed",
            )
        new, shifts = {}, {}
        for name in chosen:
            raw = core.latest_raw_position(name)
            assert raw is not None
            old = core.calibration(name)
            new[name] = dataclasses.replace(old, zero_offset=raw)
            shifts[name] = raw - old.zero_offset
        too_far = [
            f"{name} by {shift:+.4g} (bound {bound(name):.4g})"
            for name, shift in shifts.items()
            if abs(shift) > bound(name)
        ]
        if too_far and not force:
            return _refused(
                caller,
                f"rezero refused: it would shift {', '.join(too_far)}, more than the "
                "module allows per call; move the joints nearer their zero, or call again "
                "with force if the calibration really is that far off; nothing changed",
            )
        backup = None
        if path:
            try:
                backup = write_zero_offsets(
                    path,
                    {core.local_name(n): c.zero_offset for n, c in new.items()},
                    {core.local_name(n): c.direction for n, c in new.items()},
                    backup=True,
                )
            except CalibrationFileError as exc:
                return _refused(caller, f"rezero failed, nothing changed: {exc}")
        changes = []
        for name, calibration in new.items():
            old_offset = core.calibration(name).zero_offset
            core.set_calibration(name, calibration)
            changes.append(f"{name} {old_offset:.6g} -> {calibration.zero_offset:.6g}")
        narrowed = guard.protect(new)
        if path:
            saved = f"saved to {path} (the previous file kept as {backup})"
        else:
            saved = "not saved (no calibration_file): lost at restart"
        text = f"re-zeroed {'; '.join(changes)}{' (forced)' if too_far else ''}; {saved}"
        if narrowed:
            text += (
                f"; {', '.join(narrowed)} keep(s) within the raw range the motors started with "
                "until the motor interface restarts"
            )
        level = logging.WARNING if too_far else logging.INFO
        log.log(level, "%s: rezero asked by %s: %s", core.name, caller, text)
        return _response(True, text, shifts)

    setattr(core, handler, on_rezero)
    # Motor-level calibration: only the module's own computer may ask (components.roles).
    core.extra_serve.append(Serve(service, REZERO, handler, role=Role.RAW))


def _caller() -> str:
    """The node that sent the request being handled, as the transport knows it."""
    from components.comm.services import current_caller

    return current_caller() or "a local call"


def _refused(caller: str, text: str) -> Any:
    log.info("rezero asked by %s: %s", caller, text)
    return _response(False, text)


def _moving(core: JointManagerCore, still_speed: float) -> list[str]:
    """Joints of the module that move: measured faster than ``still_speed``, or commanded."""
    moving = []
    for name in core.joint_names:
        latest = core.latest(name)
        speed = None if latest is None else latest.velocity
        if (speed is not None and abs(speed) > still_speed) or core.in_motion(name):
            moving.append(name)
    return moving


class _StartRange:
    """Keeps a re-zeroed joint's commands inside the raw range it had when the manager was
    built, which is what the motor interface and the simulator enforce until they restart
    (they read the calibration once, at start).

    A filter is added to a joint only when a re-zero first changes its calibration, so
    joints never re-zeroed pay nothing per command.
    """

    def __init__(self, core: JointManagerCore) -> None:
        self._core = core
        self._raw: dict[str, tuple[float, float]] = {}
        for name in core.joint_names:
            if core.spec(name).bounded:
                lo, hi = core.command_range(name)
                cal = core.calibration(name)
                a, b = cal.to_raw(lo), cal.to_raw(hi)
                self._raw[name] = (min(a, b), max(a, b))
        self._guarded: set[str] = set()

    def protect(self, changed: dict[str, Any]) -> list[str]:
        """Guard the joints of ``changed``; return those whose command range shrank."""
        narrowed = []
        for name in changed:
            if name not in self._raw:
                continue
            lo, hi = self._range(name)
            start_lo, start_hi = self._core.command_range(name)
            if lo > start_lo + 1e-12 or hi < start_hi - 1e-12:
                narrowed.append(name)
            if name not in self._guarded:
                self._guarded.add(name)
                self._core.add_command_filter(name, self._filter(name))
        return narrowed

    def _range(self, name: str) -> tuple[float, float]:
        """The start raw range in calibrated space under the joint's current calibration."""
        raw_lo, raw_hi = self._raw[name]
        cal = self._core.calibration(name)
        a, b = cal.to_calibrated(raw_lo), cal.to_calibrated(raw_hi)
        return min(a, b), max(a, b)

    def _filter(self, name: str) -> Any:
        core = self._core

        def keep_start_range(command: JointSample, now: float) -> JointSample | Refusal:
            lo, hi = self._range(name)
            position = command.position
            if position is not None:
                if position < lo or position > hi:
                    return command._replace(position=min(max(position, lo), hi))
                return command
            velocity = command.velocity
            latest = core.latest(name)
            here = None if latest is None else latest.position
            if (
                velocity
                and here is not None
                and ((here >= hi and velocity > 0) or (here <= lo and velocity < 0))
            ):
                return Refusal(
                    "refused_rezero_range",
                    f"{name}: at the edge of the raw range the motors started with "
                    "(re-zeroed since); restart the motor interface to use the new range",
                )
            return command

        return keep_start_range
