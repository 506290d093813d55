"""The joint manager's feedback path: raw ``joint_states`` in, calibrated ``joint_read`` out.

A part of :class:`~components.joint_manager.core.JointManagerCore` (a mixin on the same
instance state), kept apart from its command path and its diagnostics.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

from components.joint_manager.joint import EFFORT, HOLD, VELOCITY, ManagedJoint, moved
from components.messages import JointSample, joint_samples, joint_state_batches


class FeedbackPath:
    """``on_joint_states`` and what it needs (see :class:`JointManagerCore`)."""

    def on_joint_states(self, message: Any, now: float) -> None:
        """Raw feedback from the motor interface: update state, publish ``joint_read``.

        Joints that changed by more than the read thresholds go out at once in one batch;
        every fresh joint goes out at the keep-alive period. Names this manager does not
        control and non-finite values are ignored (counted as ``feedback_rejected``).
        """
        if len(message.name) > self._size:
            # A flood (or a bug): dropped before it costs anything per name.
            self._counters["feedback_oversize"] += 1
            return
        changed: dict[str, ManagedJoint] = {}
        holds: list[JointSample] = []
        for name, raw_pos, raw_vel, raw_eff in joint_samples(message):
            j = self._joints.get(name)
            if j is None:
                self._counters["feedback_rejected"] += 1
                continue
            updated = False
            cal = j.cal
            if raw_pos is not None:
                if math.isfinite(raw_pos):
                    j.raw_position = raw_pos
                    j.position = cal.to_calibrated(raw_pos)
                    j.position_seen = now
                    updated = True
                else:
                    self._counters["feedback_rejected"] += 1
            if raw_vel is not None:
                if math.isfinite(raw_vel):
                    j.velocity = cal.rate_to_calibrated(raw_vel)
                    updated = True
                else:
                    self._counters["feedback_rejected"] += 1
            if raw_eff is not None:
                if math.isfinite(raw_eff):
                    j.effort = cal.rate_to_calibrated(raw_eff)
                    updated = True
                else:
                    self._counters["feedback_rejected"] += 1
            if not updated:
                continue
            j.seen = now
            self._last_feedback = now
            if j.pin_note is not None and j.pin is None and j.position is not None:
                # A pin "where it is" takes effect at the first measured position.
                j.pin = j.clamp_position(j.position)
                holds.append(self._hold_sample(j))
            elif j.mode in (VELOCITY, EFFORT) and self._heading_past_limit(j):
                # Between two commands a joint keeps its velocity: check it on every
                # feedback, not only when a command arrives, or it could run through a limit
                # for a whole watchdog timeout.
                self._mark_clamp(j, f"{j.spec.name}: reached a limit, holding", now)
                holds.append(self._hold_sample(j))
                j.mode = HOLD
            elif j.cmd_effort and j.mode in (VELOCITY, EFFORT) and self._too_fast(j, j.cmd_effort):
                holds.append(self._cut_effort(j, now))
            if self._changed(j):
                changed[name] = j
        self._send(holds, now)
        if not self._keepalive_if_due(now) and changed:
            self._publish_read(changed.values(), now)

    def _too_fast(self, j: ManagedJoint, effort: float) -> bool:
        """Whether ``effort`` pushes a joint already above its max velocity on (effort mode
        has no speed bound of its own; an effort that brakes is never cut)."""
        speed = j.velocity
        return speed is not None and abs(speed) > j.spec.max_velocity and effort * speed > 0

    def _cut_effort(self, j: ManagedJoint, now: float) -> JointSample:
        """The raw command that takes a too-fast joint's effort away (counted)."""
        self._counters["speed_cuts"] += 1
        self._mark_clamp(j, f"{j.spec.name}: faster than {j.spec.max_velocity:g}, effort cut", now)
        j.cmd_effort = 0.0
        if j.mode == VELOCITY:
            return JointSample(j.spec.name, None, j.cal.rate_to_raw(j.cmd_velocity), None)
        return JointSample(j.spec.name, None, None, 0.0)

    def _heading_past_limit(self, j: ManagedJoint, velocity: float | None = None) -> bool:
        """Whether a bounded joint would cross ``lo``/``hi`` within the lookahead.

        ``velocity`` defaults to the commanded one in velocity mode and the measured one in
        effort mode (an effort command has no velocity of its own).
        """
        if not j.spec.bounded or j.position is None:
            return False
        if velocity is None:
            velocity = j.cmd_velocity if j.mode == VELOCITY else (j.velocity or 0.0)
        ahead = j.position + velocity * self.config.velocity_limit_lookahead
        return (velocity > 0 and ahead >= j.hi) or (velocity < 0 and ahead <= j.lo)

    def _changed(self, j: ManagedJoint) -> bool:
        cfg = self.config
        return (
            moved(j.position, j.pub_position, cfg.read_position_threshold)
            or moved(j.velocity, j.pub_velocity, cfg.read_velocity_threshold)
            or moved(j.effort, j.pub_effort, cfg.read_effort_threshold)
        )

    def _keepalive_if_due(self, now: float) -> bool:
        if self._last_keepalive is not None and (
            now - self._last_keepalive < self.config.keepalive_period
        ):
            return False
        self._last_keepalive = now
        stale = self.config.stale_timeout
        fresh = [j for j in self._joints.values() if j.seen is not None and now - j.seen <= stale]
        if fresh:
            self._publish_read(fresh, now)
        return True

    def _publish_read(self, joints: Iterable[ManagedJoint], now: float) -> None:
        samples = []
        for j in joints:
            samples.append(JointSample(j.spec.name, j.position, j.velocity, j.effort))
            j.pub_position, j.pub_velocity, j.pub_effort = j.position, j.velocity, j.effort
        for message in joint_state_batches(samples, self.stamp(now)):
            self.publish("joint_read", message)
