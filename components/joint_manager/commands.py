"""The joint manager's command path: calibrated ``joint_set`` in, raw ``joint_commands`` out.

A part of :class:`~components.joint_manager.core.JointManagerCore` (a mixin on the same
instance state): validation, filters, clamping to the limits, refusals and their notes.
"""

from __future__ import annotations

from typing import Any

from components.joint_manager.config import Refusal
from components.joint_manager.joint import (
    EFFORT,
    HOLD,
    POSITION,
    VELOCITY,
    ManagedJoint,
    finite,
)
from components.messages import JointSample, joint_samples, joint_state_batches
from components.motors.base import refused_whole


class CommandPath:
    """``on_joint_set`` and what it needs (see :class:`JointManagerCore`)."""

    def on_joint_set(self, message: Any, now: float) -> None:
        """Calibrated commands from above: validate, filter, clamp, convert, send raw.

        Each joint of the message is judged on its own: a refused joint (unknown, another
        module's, non-finite value, refused by a filter, halted, velocity with no fresh
        position) is counted and left out; the others go out on ``joint_commands``. An
        accepted command feeds that joint's watchdog.
        """
        refused = refused_whole(message, self._size)
        if refused is not None:
            self._counters[refused] += 1
            self._last_refusal = now
            why = (
                f"the module has {self._size} joints"
                if refused == "refused_oversize"
                else "its arrays do not match its names"
            )
            self._refusal_note = f"joint_set with {len(message.name)} names refused: {why}"
            return
        samples = joint_samples(message)
        if self._halted:
            self._refuse_all(samples, now)
            return
        if self.presence_held:
            self._refuse_all(samples, now, no_operator=True)
            return
        # The last entry per joint wins: one command per joint however often it is named.
        latest = {sample.name: sample for sample in samples}
        if len(latest) != len(samples):
            self._counters["duplicates"] += len(samples) - len(latest)
        out: list[JointSample] = []
        accepted = False
        for sample in latest.values():
            j = self._joints.get(sample.name)
            if j is None:
                self._refuse_name(sample.name, now)
                continue
            command = sample
            if command.position is None and command.velocity is None and command.effort is None:
                continue
            if not finite(command):
                self._refuse(j, "refused_nan", f"{j.spec.name}: NaN or inf in command", now)
                continue
            refused = False
            for command_filter in j.filters:
                result = command_filter(command, now)
                if isinstance(result, Refusal):
                    self._refuse(j, result.counter, result.reason, now)
                    refused = True
                    break
                command = result
            if refused:
                if j.pin is not None:
                    out.append(self._hold_sample(j))
                continue
            sent = self._limit(j, command, now)
            if sent is None:
                continue
            out.append(sent)
            j.last_command = now
            accepted = True
        if accepted:
            # A fresh accepted command is the operator back: the trip is over.
            self._tripped_at = None
            self._tripped_joints = []
        self._send(out, now)

    def _limit(self, j: ManagedJoint, command: JointSample, now: float) -> JointSample | None:
        """Clamp one calibrated command and express it in raw space (None: refused)."""
        spec, cal = j.spec, j.cal
        position, velocity, effort = command.position, command.velocity, command.effort
        clamped = False
        if position is not None:
            limited = j.clamp_position(position)
            clamped |= limited != position
            position = limited
        if velocity is not None:
            limited = min(max(velocity, -spec.max_velocity), spec.max_velocity)
            clamped |= limited != velocity
            velocity = limited
        if effort is not None:
            limited = min(max(effort, -spec.max_effort), spec.max_effort)
            clamped |= limited != effort
            effort = limited
            if position is None and self._too_fast(j, effort):
                self._counters["speed_cuts"] += 1
                self._mark_clamp(
                    j, f"{spec.name}: faster than {spec.max_velocity:g}, effort cut", now
                )
                effort = 0.0 if velocity is None else None
        if position is None and (velocity is not None or effort is not None) and spec.bounded:
            # Velocity or effort mode on a bounded joint drives it toward its limits: only
            # safe while we know where the joint is. The position's own age: velocity-only
            # feedback (an encoder reporting NaN, a motor interface sending positions in
            # another batch) must not make it look fresh.
            seen = j.position_seen
            stale = seen is None or j.position is None or now - seen > self.config.stale_timeout
            if stale:
                mode = "velocity" if velocity is not None else "effort"
                self._refuse(
                    j,
                    "refused_no_state",
                    f"{spec.name}: {mode} command refused, no fresh joint_states "
                    "(is the motor interface running?)",
                    now,
                )
                return None
        if (
            position is None
            and velocity is not None
            and spec.bounded
            and self._heading_past_limit(j, velocity)
        ):
            self._mark_clamp(j, f"{spec.name}: velocity toward a limit, holding", now)
            j.mode = HOLD
            j.target_raw = None
            return self._hold_sample(j)
        if clamped:
            self._mark_clamp(j, f"{spec.name}: command clamped to limits", now)
        j.cmd_effort = effort or 0.0
        if position is not None:
            j.mode = POSITION
            j.target_raw = cal.to_raw(position)
        elif velocity is not None:
            j.mode = VELOCITY
            j.target_raw = None
            j.cmd_velocity = velocity
        else:
            j.mode = EFFORT
            j.target_raw = None
        return JointSample(
            spec.name,
            None if position is None else j.target_raw,
            None if velocity is None else cal.rate_to_raw(velocity),
            None if effort is None else cal.rate_to_raw(effort),
        )

    def _hold_sample(self, j: ManagedJoint) -> JointSample:
        """Raw command holding a joint: at its pin, else where it is; velocity 0.

        Without any known position the only safe thing to send is velocity 0.
        """
        hold = j.pin if j.pin is not None else j.position
        if hold is None:
            return JointSample(j.spec.name, None, 0.0, None)
        # Clamped here too: a pin may have left the limits through a calibration change.
        return JointSample(j.spec.name, j.cal.to_raw(j.clamp_position(hold)), 0.0, None)

    def _send(self, out: list[JointSample], now: float) -> None:
        if out:
            for message in joint_state_batches(out, self.stamp(now)):
                self.publish("joint_commands", message)

    def _refuse_name(self, name: str, now: float) -> None:
        name = name if len(name) <= 64 else name[:64] + "..."  # notes stay small
        head, sep, _ = name.partition("_")
        if sep and head and not name.startswith(self._prefix):
            counter = "refused_other_module"
            reason = (
                f"command for {name!r} refused: it belongs to module {head!r}, not {self.module!r}"
            )
        else:
            counter = "refused_unknown"
            reason = f"command for unknown joint {name!r} refused; known: {sorted(self._joints)}"
        self._counters[counter] += 1
        self._last_refusal = now
        self._refusal_note = reason

    def _refuse_all(
        self, samples: list[JointSample], now: float, no_operator: bool = False
    ) -> None:
        for sample in samples:
            j = self._joints.get(sample.name)
            if j is None:
                self._refuse_name(sample.name, now)
            elif no_operator:
                assert self.presence is not None
                why = f"{j.spec.name}: {self.presence.reason(now)}; held until one is visible"
                self._refuse(j, "refused_no_operator", why, now)
            else:
                self._refuse(j, "refused_halted", f"{j.spec.name}: halted, call recover", now)

    def _refuse(self, j: ManagedJoint, counter: str, reason: str, now: float) -> None:
        self._counters[counter] = self._counters.get(counter, 0) + 1
        j.last_refusal = now
        j.note = reason
        self._last_refusal = now
        self._refusal_note = reason

    def _mark_clamp(self, j: ManagedJoint, note: str, now: float) -> None:
        self._counters["clamped"] += 1
        j.last_clamp = now
        j.note = note
        self._last_clamp = now
