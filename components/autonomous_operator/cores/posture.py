"""The posture holder's judgement: which pose to hold while driving, when to correct it.

Pure: it is told whether a wheel turns, the measured positions, whether the last correction
is still under way, and the time; it answers with the pose to move the limbs back to (a
correction) and the status to report. The script (``operators/posture.py``) reads the robot,
starts the corrections (``JointSyncer.lerp``) and reports.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class Step:
    """What one check asks for: a pose to bring the limbs back to, and a status."""

    correct_to: dict[str, float] | None = None
    status: tuple[str, dict[str, Any]] | None = None


@dataclass
class PostureCore:
    """Holds the limbs' pose from the start of a drive to its end.

    Args:
        joints: The limbs' position joints it holds (unlocked).
        tolerance: Radians (metres) a joint may stray before it is brought back.
        settle: Seconds it must stay astray first.
        still_after: Seconds every wheel must stay slow before the drive is over.
        report_period: Seconds between two statuses.
    """

    joints: Sequence[str]
    tolerance: float
    settle: float
    still_after: float
    report_period: float
    #: The pose held while driving (None while the limbs are free).
    posture: dict[str, float] | None = None
    astray_since: float | None = None
    corrections: int = 0
    moved_at: float = -math.inf  # when a wheel last turned
    worst_seen: float = 0.0
    _next_report: float = field(default=0.0, repr=False)

    def step(
        self, now: float, measured: Mapping[str, float], driving: bool, correcting: bool
    ) -> Step:
        """One check at ``now``.

        Args:
            now: The time (s).
            measured: The joints' measured positions.
            driving: Whether a wheel turns faster than the moving speed.
            correcting: Whether the last correction is still under way.
        """
        worst_joint, worst, correct_to = "", 0.0, None
        if driving:
            self.moved_at = now
        if now - self.moved_at < self.still_after:
            worst_joint, worst, correct_to = self._hold(now, measured, correcting)
        else:
            self.posture = None  # standing still: the limbs are free
            self.astray_since = None
        status = None
        if now >= self._next_report:
            self._next_report = now + self.report_period
            status = self._status(worst_joint, worst)
        return Step(correct_to=correct_to, status=status)

    def _hold(
        self, now: float, measured: Mapping[str, float], correcting: bool
    ) -> tuple[str, float, dict[str, float] | None]:
        if self.posture is None:
            self.posture = {j: measured[j] for j in self.joints if j in measured}
            self.astray_since = None
        worst_joint, worst = "", 0.0
        for joint, held in self.posture.items():
            off = abs(measured.get(joint, held) - held)
            if off > worst:
                worst_joint, worst = joint, off
        self.worst_seen = max(self.worst_seen, worst)
        correct_to = None
        if worst > self.tolerance and not correcting:
            self.astray_since = now if self.astray_since is None else self.astray_since
            if now - self.astray_since >= self.settle:
                correct_to = self.posture
                self.corrections += 1
                self.astray_since = None
        elif worst <= self.tolerance:
            self.astray_since = None
        return worst_joint, worst, correct_to

    def _status(self, worst_joint: str, worst: float) -> tuple[str, dict[str, Any]]:
        state = (
            f"holding {len(self.posture)} joints; worst {worst_joint or '-'} {worst:.3f} rad off"
            if self.posture is not None
            else "not driving: limbs free"
        )
        return state, {
            "corrections": self.corrections,
            "tolerance": self.tolerance,
            "worst_seen": f"{self.worst_seen:.3f}",
            "holding": self.posture is not None,
        }
