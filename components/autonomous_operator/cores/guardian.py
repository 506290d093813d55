"""The guardian's judgement: when to halt a robot, when to arm again, what to say.

Pure: it is told the body's attitude, the joint managers' commands, the measured positions
and the time, and answers with the halt to send (a reason) and the status to report. The
script (``operators/guardian.py``) subscribes, sends the e-stop and reports.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from components.safety import SafetyLimits

#: The fraction of its threshold the tilt must fall under before the guardian arms again.
REARM = 0.8


def tilt_of(w: float, x: float, y: float, z: float) -> float:
    """The angle (rad) between a body's up axis and the vertical, from its orientation."""
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    if not math.isfinite(norm) or norm < 1e-9:
        return math.nan
    x, y = x / norm, y / norm
    cos = 1.0 - 2.0 * (x * x + y * y)  # the z component of the body's up axis
    return math.acos(max(-1.0, min(1.0, cos)))


@dataclass(frozen=True)
class Status:
    """A status for the operator's diagnostics: its message, level and key-values."""

    message: str
    level: str
    values: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Step:
    """What one check asks for: a halt (its reason), a status, and whether it armed again."""

    halt: str = ""
    status: Status | None = None
    armed_again: bool = False


@dataclass(frozen=True)
class Answer:
    """One module's answer to an e-stop (as :mod:`components.estop` gives it)."""

    module: str
    ok: bool
    seconds: float | None = None


class GuardianCore:
    """Watches one robot's tilt and tracking errors; trips once beyond its limits.

    Args:
        robot: The robot's name (for the statuses).
        limits: Its safety limits (``None`` where a limit is not watched).
        calibrations: Position joint -> its calibration (``to_calibrated(raw)``): the
            commands to the motors are raw, the measurements calibrated.
        attitude: The attitude topic watched ("" when none).
        stale_after: Seconds without an attitude after which the status warns.
        report_period: Seconds between two statuses.
    """

    def __init__(
        self,
        robot: str,
        limits: SafetyLimits,
        calibrations: Mapping[str, Any],
        attitude: str,
        stale_after: float,
        report_period: float,
    ) -> None:
        self.robot = robot
        self.limits = limits
        self.calibrations = dict(calibrations)
        self.attitude = attitude
        self.stale_after = stale_after
        self.report_period = report_period
        self.tilt = math.nan
        self.tilt_at = -math.inf
        self.worst_tilt = 0.0
        #: Why it halted, while it has not armed again ("" when armed).
        self.tripped = ""
        self.halts = 0
        self.commanded: dict[str, float] = {}  # joint -> its latest command (calibrated)
        self.astray: dict[str, float] = {}  # joint -> since when it is astray
        self._next_report = 0.0

    @property
    def watching_tilt(self) -> bool:
        """Whether it watches an attitude topic against a tilt limit."""
        return bool(self.attitude) and self.limits.max_tilt is not None

    @property
    def watching_tracking(self) -> bool:
        """Whether it watches the joints' tracking errors."""
        return self.limits.max_tracking_error is not None

    def trip(self, why: str) -> str:
        """Trip for ``why`` unless tripped already: the halt to send, or ""."""
        if self.tripped:
            return ""
        self.tripped = why
        return why

    def orientation(self, w: float, x: float, y: float, z: float, now: float) -> str:
        """A new attitude of the body: the halt it calls for, or ""."""
        tilt = tilt_of(w, x, y, z)
        if math.isnan(tilt):
            return ""
        self.tilt, self.tilt_at = tilt, now
        self.worst_tilt = max(self.worst_tilt, tilt)
        limit = self.limits.max_tilt
        if limit is None or tilt <= limit:
            return ""
        return self.trip(
            f"body tilt {tilt:.3f} rad ({math.degrees(tilt):.1f} deg) > {limit:g}"
            " rad (module data [safety] max_tilt)"
        )

    def commands(self, samples: Iterable[tuple[str, float | None]]) -> None:
        """The joint managers' commands to the motors: (joint, raw position) pairs."""
        for name, position in samples:
            calibration = self.calibrations.get(name)
            if calibration is not None and position is not None:
                self.commanded[name] = calibration.to_calibrated(position)

    def step(self, now: float, measured: Mapping[str, float]) -> Step:
        """One check at ``now`` with the measured positions (calibrated)."""
        worst_joint, worst, halt = "", 0.0, ""
        if self.watching_tracking:
            worst_joint, worst, halt = self._tracking(now, measured)
        armed_again = self._rearm()
        status = None
        if now >= self._next_report and not self.tripped:
            self._next_report = now + self.report_period
            status = self._watching(now, worst_joint, worst)
        return Step(halt=halt, status=status, armed_again=armed_again)

    def _tracking(self, now: float, measured: Mapping[str, float]) -> tuple[str, float, str]:
        limit, grace = self.limits.max_tracking_error, self.limits.tracking_grace
        worst_joint, worst, halt = "", 0.0, ""
        for joint, command in self.commanded.items():
            at = measured.get(joint)
            if at is None:
                continue
            off = abs(at - command)
            if off > worst:
                worst_joint, worst = joint, off
            if off > limit:
                since = self.astray.setdefault(joint, now)
                if now - since >= grace and not self.tripped:
                    halt = self.trip(
                        f"{joint} {off:.2f} away from its command for "
                        f"{now - since:.1f} s > {limit:g} "
                        "(module data [safety] max_tracking_error)"
                    )
            else:
                self.astray.pop(joint, None)
        return worst_joint, worst, halt

    def _rearm(self) -> bool:
        """Arm again once level and no joint astray (the halt stays until a recover)."""
        if not self.tripped:
            return False
        tilt, limit = self.tilt, self.limits.max_tilt
        level = limit is None or (not math.isnan(tilt) and tilt < REARM * limit)
        if level and not self.astray:
            self.tripped = ""
            return True
        return False

    def _watching(self, now: float, worst_joint: str, worst: float) -> Status:
        stale = self.watching_tilt and now - self.tilt_at > self.stale_after
        tilt = self.tilt
        return Status(
            f"watching {self.robot}: tilt "
            + ("?" if math.isnan(tilt) else f"{math.degrees(tilt):.1f} deg")
            + f", worst tracking {worst_joint or '-'} {worst:.3f}"
            + (f"; no attitude on {self.attitude} for {self.stale_after:g} s" if stale else ""),
            "warn" if stale else "ok",
            {
                "attitude": self.attitude or "none",
                "max_tilt": self.limits.max_tilt,
                "max_tracking_error": self.limits.max_tracking_error,
                "tracking_grace": self.limits.tracking_grace,
                "worst_tilt": f"{self.worst_tilt:.3f}",
                "halts": self.halts,
            },
        )

    def halted(self, why: str, answers: Iterable[Answer]) -> Status:
        """The status after the halt for ``why`` was sent, from the modules' answers."""
        answers = list(answers)
        failed = [a.module for a in answers if not a.ok]
        self.halts += 1
        return Status(
            f"HALTED {self.robot}: {why}; acknowledged: {acknowledged(answers)}"
            + (f"; NO ANSWER from {', '.join(failed)}" if failed else "")
            + " (msctl recover undoes it)",
            "error",
            {"halts": self.halts},
        )


def acknowledged(answers: Iterable[Answer]) -> str:
    """The modules that acknowledged an e-stop, each with its time ("none" if none did)."""
    timing = ", ".join(
        f"{a.module} {a.seconds * 1e3:.0f} ms" if a.seconds is not None else a.module
        for a in answers
        if a.ok
    )
    return timing or "none"
