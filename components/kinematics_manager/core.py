"""The Kinematics Manager core: one limb chain's forward and inverse kinematics.

It reads the limb's calibrated joint angles (``joint_read``), publishes where the tip is
(``tip_pose``, in the chain's base frame), and turns a tip target (``ik_target``) into joint
position targets (``joint_set``) for the joint manager. Pure: no clock, no I/O; ``now`` is
passed in and outputs go through the outbox.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pinocchio as pin

from components.config import require
from components.executor.core import Core
from components.kinematics_manager.ik import IkResult, IkSettings, IkSolver
from components.kinematics_manager.model import ChainModel
from components.kinematics_manager.poses import apart, partial_target, pose_stamped
from components.messages import (
    OK,
    STALE,
    WARN,
    JointSample,
    diagnostic_array,
    diagnostic_status,
    joint_state,
    worst,
)


@dataclass(frozen=True)
class KinematicsConfig:
    """Tuning of one kinematics manager.

    Attributes:
        ik: The solver's tuning (tolerances, budget, jump bound, limit margin).
        tip_position_threshold: Tip movement (m) that publishes ``tip_pose`` at once.
        tip_angle_threshold: Tip rotation (rad) that publishes ``tip_pose`` at once.
        min_period: Shortest time between two ``tip_pose`` publications (rate limit); a
            change held back goes out on the next tick.
        keepalive_period: ``tip_pose`` is republished this often when nothing moves.
        diagnostics_period: Seconds between ``diagnostics`` publications.
        stale_timeout: No ``joint_read`` for this long makes the manager STALE and refuses
            targets (it would solve from angles it no longer knows).
        warn_window: An unreachable or refused target keeps the manager at WARN this long.
    """

    ik: IkSettings = field(default_factory=IkSettings)
    tip_position_threshold: float = 1e-4
    tip_angle_threshold: float = 1e-3
    min_period: float = 0.01
    keepalive_period: float = 1.0
    diagnostics_period: float = 1.0
    stale_timeout: float = 1.5
    warn_window: float = 5.0

    def __post_init__(self) -> None:
        require(
            self,
            positive=("keepalive_period", "diagnostics_period", "stale_timeout"),
            non_negative=(
                "tip_position_threshold",
                "tip_angle_threshold",
                "min_period",
                "warn_window",
            ),
        )

    @classmethod
    def from_params(cls, params: Mapping[str, Any]) -> KinematicsConfig:
        """A config from plan params: top-level fields of this class, IkSettings fields too.

        Unknown keys (``chain``, ``joints``... which the builder reads) are ignored.
        """
        ik_fields = IkSettings.__dataclass_fields__
        own = {k: params[k] for k in cls.__dataclass_fields__ if k != "ik" and k in params}
        ik = {k: params[k] for k in ik_fields if k in params}
        return cls(ik=IkSettings(**ik), **own)


class KinematicsCore(Core):
    """Forward and inverse kinematics of one limb chain.

    Args:
        name: Component name (``limb1/kinematics_manager``).
        module: The module's slot (``limb1``), as ``hardware_id`` in diagnostics.
        chain: The chain's model.
        config: Tuning.
        seed: Seed of the IK restarts (reproducible solves).
    """

    def __init__(
        self,
        name: str,
        module: str,
        chain: ChainModel,
        config: KinematicsConfig | None = None,
        seed: int = 0,
    ) -> None:
        super().__init__(name)
        self.module = module
        self.chain = chain
        self.config = config or KinematicsConfig()
        self.solver = IkSolver(chain, self.config.ik, seed=seed)
        self.frame = chain.base_link
        self.q = np.zeros(chain.nq)
        self._seen = np.zeros(chain.nq, dtype=bool)
        self._last_read: float | None = None
        self._tip: pin.SE3 | None = None
        self._published_tip: pin.SE3 | None = None
        self._published_at: float | None = None
        self._last_diagnostics: float | None = None
        self._last_warn = -np.inf
        self._warn_note = ""
        self.last_result: IkResult | None = None
        self.counters: dict[str, int] = {
            "targets": 0,
            "solved": 0,
            "unreachable": 0,
            "refused": 0,
        }

    # ------------------------------------------------------------------ state
    @property
    def ready(self) -> bool:
        """Whether every chain joint's angle is known."""
        return bool(self._seen.all())

    @property
    def tip(self) -> pin.SE3 | None:
        """The tip's placement in the base frame, from the latest angles (None: unknown)."""
        return self._tip

    def start(self, now: float) -> None:
        """Publish the first diagnostics at once (STALE until joint_read arrives)."""
        self._publish_diagnostics(now)

    # ------------------------------------------------------------------ inputs
    def on_joint_read(self, message: Any, now: float) -> None:
        """Keep the chain's current angles; publish ``tip_pose`` when the tip moved."""
        # A finger or another chain's joint is skipped.
        if not self.chain.take_positions(message, self.q, self._seen):
            return
        self._last_read = now
        if self.ready:
            self._tip = self.chain.tip(self.q)
            self._publish_tip_if_due(now)

    def on_ik_target(self, message: Any, now: float) -> None:
        """Solve for a tip target and send the joint targets, or the closest reachable ones.

        The target is a PoseStamped in the chain's base frame (``frame_id`` empty or the base
        link). NaN parts keep the current tip's value (see
        :func:`~components.kinematics_manager.poses.partial_target`).
        """
        self.counters["targets"] += 1
        frame = message.header.frame_id
        if frame not in ("", self.frame):
            self._refuse(f"ik_target in frame {frame!r}; send it in {self.frame!r}", now)
            return
        if not self.ready or self._tip is None:
            missing = [
                n for n, seen in zip(self.chain.joint_names, self._seen, strict=True) if not seen
            ]
            self._refuse(f"ik_target before joint_read of {', '.join(missing)}", now)
            return
        if self._last_read is None or now - self._last_read > self.config.stale_timeout:
            self._refuse("ik_target refused: joint_read is stale", now)
            return
        target = partial_target(message.pose, self._tip)
        if target is None:
            self._refuse("ik_target has a zero-length quaternion", now)
            return
        if not np.isfinite(target.translation).all():
            self._refuse("ik_target has an infinite coordinate; send metres (NaN keeps one)", now)
            return
        result = self.solver.solve(target, self.q)
        self.last_result = result
        if result.reachable:
            self.counters["solved"] += 1
        else:
            self.counters["unreachable"] += 1
            self._warn(
                f"target unreachable: moving to the closest pose, "
                f"{result.position_error * 1000:.1f} mm / "
                f"{np.degrees(result.orientation_error):.1f} deg away",
                now,
            )
        samples = [
            JointSample(name, float(value), None, None)
            for name, value in zip(self.chain.joint_names, result.q, strict=True)
        ]
        self.publish("joint_set", joint_state(samples, self.stamp(now)))

    def tick(self, now: float) -> None:
        """Held-back and keep-alive ``tip_pose``; periodic diagnostics."""
        if self._tip is not None:
            self._publish_tip_if_due(now)
        last = self._last_diagnostics
        if last is None or now - last >= self.config.diagnostics_period:
            self._publish_diagnostics(now)

    # ------------------------------------------------------------------ outputs
    def _publish_tip_if_due(self, now: float) -> None:
        cfg = self.config
        tip = self._tip
        assert tip is not None
        last = self._published_at
        if last is not None and now - last < cfg.min_period:
            return
        due = last is None or now - last >= cfg.keepalive_period
        if not due and self._published_tip is not None:
            distance, angle = apart(tip, self._published_tip)
            due = distance > cfg.tip_position_threshold or angle > cfg.tip_angle_threshold
        if due:
            self.publish("tip_pose", pose_stamped(tip, self.stamp(now), self.frame))
            self._published_tip = tip
            self._published_at = now

    def _refuse(self, note: str, now: float) -> None:
        self.counters["refused"] += 1
        self._warn(note, now)

    def _warn(self, note: str, now: float) -> None:
        # Published at once, not at the next period: the operator should see why the limb
        # did not go where asked while it matters.
        self._last_warn = now
        self._warn_note = note
        self._publish_diagnostics(now)

    def _publish_diagnostics(self, now: float) -> None:
        self._last_diagnostics = now
        self.publish("diagnostics", diagnostic_array([self.status(now)], self.stamp(now)))

    def status(self, now: float) -> Any:
        """The manager's DiagnosticStatus at ``now``."""
        levels, notes = [OK], []
        age = None if self._last_read is None else now - self._last_read
        if not self.ready:
            levels.append(STALE)
            notes.append("waiting for joint_read of every chain joint")
        elif age is not None and age > self.config.stale_timeout:
            levels.append(STALE)
            notes.append(f"no joint_read for {age:.1f} s")
        if now - self._last_warn <= self.config.warn_window:
            levels.append(WARN)
            notes.append(self._warn_note)
        level = worst(levels)
        values: dict[str, Any] = {
            "module": self.module,
            "chain": f"{self.chain.base_link} -> {self.chain.tip_link}",
            "joints": self.chain.nq,
            "position_only": self.solver.position_only,
            "joint_read_age": "never" if age is None else f"{age:.3f}",
        }
        values.update(self.counters)
        result = self.last_result
        if result is not None:
            values["last_position_error_m"] = f"{result.position_error:.6f}"
            values["last_orientation_error_rad"] = f"{result.orientation_error:.6f}"
            values["last_jump"] = f"{result.jump:.4f}"
            values["last_iterations"] = result.iterations
        return diagnostic_status(
            self.name, level, "; ".join(notes) or "OK", hardware_id=self.module, values=values
        )
