"""The joint manager's diagnostics: one status for the manager, one per joint.

A part of :class:`~components.joint_manager.core.JointManagerCore` (a mixin on the same
instance state).
"""

from __future__ import annotations

from typing import Any

from components.joint_manager.joint import ManagedJoint, fmt
from components.joint_manager.presence import OperatorPresence
from components.messages import (
    ERROR,
    OK,
    STALE,
    WARN,
    diagnostic_array,
    diagnostic_status,
    worst,
)


class ManagerStatus:
    """``diagnostics`` (see :class:`JointManagerCore`)."""

    def diagnostics(self, now: float) -> Any:
        """The DiagnosticArray ``tick`` publishes: one status for the manager, one per joint."""
        statuses = [self._manager_status(now)]
        statuses.extend(self._joint_status(j, now) for j in self._joints.values())
        return diagnostic_array(statuses, self.stamp(now))

    def _manager_status(self, now: float) -> Any:
        cfg = self.config
        levels, notes = [OK], []
        if self._halted:
            levels.append(ERROR)
            notes.append("halted: commands refused until recover")
        if self._tripped_at is not None:
            levels.append(ERROR)
            notes.append(
                f"watchdog stopped {', '.join(self._tripped_joints)}: no command for "
                f"{cfg.watchdog_timeout} s; send a command or recover"
            )
        if self.presence is not None:
            if self.presence.held:
                levels.append(ERROR)
                notes.append(
                    f"{self.presence.reason(now)}: motors held, commands refused until an "
                    "operator is visible again"
                )
            else:
                # Said at OK: the robot is fine again, and "back to OK" after an outage
                # must not wait for a warning window.
                back = self.presence.lifted(now, cfg.warn_window)
                if back is not None:
                    notes.append(back)
        age = None if self._last_feedback is None else now - self._last_feedback
        if age is None or age > cfg.stale_timeout:
            # Below ERROR: "no news" must not hide a halt or a watchdog trip.
            levels.append(STALE)
            notes.append(
                "no joint_states yet" if age is None else f"no joint_states for {age:.1f} s"
            )
        if now - self._last_refusal <= cfg.warn_window:
            levels.append(WARN)
            notes.append(self._refusal_note)
        if now - self._last_clamp <= cfg.warn_window:
            levels.append(WARN)
            notes.append("commands clamped to limits")
        level = worst(levels)
        values: dict[str, Any] = {
            "module": self.module,
            "halted": self._halted,
            "operators": _operators(self.presence),
            "joints": len(self._joints),
            "feedback_age": "never" if age is None else f"{age:.3f}",
        }
        values.update(self._counters)
        return diagnostic_status(
            self.name, level, "; ".join(notes) or "OK", hardware_id=self.module, values=values
        )

    def _joint_status(self, j: ManagedJoint, now: float) -> Any:
        cfg = self.config
        levels, notes = [OK], []
        if j.seen is None or now - j.seen > cfg.stale_timeout:
            levels.append(STALE)
            notes.append("no joint_states" if j.seen is None else f"stale {now - j.seen:.1f} s")
        if j.pin_note is not None:
            levels.append(WARN)
            where = "current position" if j.pin is None else f"{j.pin:.4f}"
            notes.append(f"{j.pin_note}, held at {where}")
        if max(j.last_refusal, j.last_clamp) >= now - cfg.warn_window:
            levels.append(WARN)
            notes.append(j.note)
        if self.presence is not None:
            # On every joint too: the module's health monitor reads the joints' statuses,
            # so the module's own health says why its motors hold, and when they may move
            # again (at OK: the alarm history keeps that message with the change to OK).
            if self.presence.held:
                levels.append(ERROR)
                notes.insert(0, f"held: {self.presence.reason(now)}")
            else:
                back = self.presence.lifted(now, cfg.warn_window)
                if back is not None:
                    notes.append(back)
        level = worst(levels)
        values = {
            "position": fmt(j.position),
            "velocity": fmt(j.velocity),
            "effort": fmt(j.effort),
            "age": "never" if j.seen is None else f"{now - j.seen:.3f}",
            "mode": j.mode,
            "locked": j.pin_note is not None,
        }
        return diagnostic_status(
            f"{self.name}/{j.spec.name}",
            level,
            "; ".join(notes) or "OK",
            hardware_id=self.module,
            values=values,
        )


def _operators(presence: OperatorPresence | None) -> str:
    """The ``operators`` diagnostic value: who attends the module now."""
    if presence is None:
        return "not watched"
    if presence.held:
        return "none: held"
    seen = presence.visible()
    if presence.holder is not None:
        seen.insert(0, presence.holder)
    return ", ".join(seen) or "none"
