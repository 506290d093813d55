"""Motor interface: carries ``joint_commands`` to a motor backend and its readings back as
``joint_states`` (raw joint space), with the backend's health as ``diagnostics``.

The backend (CANopen, Dynamixel, ...) is handed in, so this logic is the same for every bus
and is tested with a fake backend. It never lets a backend fault escape: a bus that will not
open is retried and reported, and the process keeps running.

It is the last stage before the bus, so it checks every command itself, whoever published it
(the joint manager stays the main gate; this is the layer behind it):

* a message naming more joints than the bus has, or whose arrays do not match its names, is
  refused whole;
* a name the bus does not drive, a NaN or inf, a position, speed or effort outside the unit's
  raw limits (:class:`~components.motors.base.RawLimits`) is refused;
* a joint named twice gets its last entry only (one command per joint per message);
* after ``motors/halt`` every command is refused until ``motors/recover``;
* a joint in effort mode turning faster than its max velocity gets its effort cut to 0.

Every refusal is counted by reason (:attr:`MotorInterfaceCore.counters`, also in diagnostics).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from components.executor.core import Core
from components.messages import (
    ERROR,
    OK,
    WARN,
    JointSample,
    diagnostic_array,
    diagnostic_status,
    joint_samples,
    joint_state,
    worst,
)
from components.motors.base import (
    FAULT_KEY,
    MotorBackend,
    MotorCommand,
    MotorError,
    RawLimits,
    check_command,
    refused_whole,
)

#: Counters of the motor interface. ``refused_oversize`` and ``refused_malformed`` count
#: messages (refused whole); the other ``refused_*`` count command entries; ``duplicates``
#: counts entries superseded by a later entry for the same joint in the same message;
#: ``speed_cuts`` counts effort commands cut to 0 because the joint turned too fast.
COUNTERS = (
    "refused_oversize",
    "refused_malformed",
    "refused_not_open",
    "refused_halted",
    "refused_unknown",
    "refused_nan",
    "refused_position",
    "refused_velocity",
    "refused_effort",
    "duplicates",
    "speed_cuts",
)


@dataclass(frozen=True)
class MotorInterfaceConfig:
    """Timing of the motor interface.

    Attributes:
        diagnostics_period: Seconds between two ``diagnostics`` messages.
        reopen_period: Seconds between two attempts to open a bus that failed to open.
        command_timeout: Seconds without ``joint_commands`` after which every joint last
            commanded with a velocity gets velocity 0. A second line behind the joint
            manager's own watchdog (0.5 s): it covers a joint manager that died or hung.
        warn_window: A refused command keeps the motor interface's status at WARN for this
            many seconds.
    """

    diagnostics_period: float = 1.0
    reopen_period: float = 2.0
    command_timeout: float = 1.0
    warn_window: float = 5.0


class _Motor:
    """Per-motor state of the last stage (slots: touched at every command)."""

    __slots__ = ("checks", "effort", "full", "limits", "raw", "speed")

    def __init__(self, raw: str, full: str, limits: RawLimits) -> None:
        self.raw = raw
        self.full = full
        self.limits = limits
        self.checks = limits.checks()
        # Effort of the latest effort-mode command (None: the motor is not in effort mode).
        self.effort: float | None = None
        # Latest measured speed (None until read).
        self.speed: float | None = None


class MotorInterfaceCore(Core):
    """Routes commands to one bus of motors and publishes their states.

    Args:
        name: Component name (``limb1/motor_interface``).
        module: Module slot (``limb1``): joint names on topics are ``<module>_<raw name>``.
        backend: The bus, not yet opened.
        config: Timing.
        limits: Raw limits per motor, keyed by raw joint name (``joint3``); see
            :meth:`RawLimits.of_joint`. A motor left out is checked for NaN/inf only (its
            diagnostics say so): the builder passes every motor's limits.

    Attributes:
        halted: Whether ``motors/halt`` was called and ``motors/recover`` not since.
    """

    def __init__(
        self,
        name: str,
        module: str,
        backend: MotorBackend,
        config: MotorInterfaceConfig | None = None,
        limits: Mapping[str, RawLimits] | None = None,
    ) -> None:
        super().__init__(name)
        self.module = module
        self.backend = backend
        self.config = config or MotorInterfaceConfig()
        self._to_raw = {f"{module}_{m.joint}": m.joint for m in backend.motors}
        self._to_full = {raw: full for full, raw in self._to_raw.items()}
        limits = dict(limits or {})
        self.unlimited = sorted(raw for raw in self._to_full if raw not in limits)
        self._motors = {
            full: _Motor(raw, full, limits.get(raw, RawLimits()))
            for full, raw in self._to_raw.items()
        }
        self._by_raw = {m.raw: m for m in self._motors.values()}
        self._size = len(self._motors)
        self._counters = dict.fromkeys(COUNTERS, 0)
        self._last_refusal = -math.inf
        self._refusal_note = ""
        self.halted = False
        self.is_open = False
        self.open_error = ""
        self._next_open = 0.0
        self._next_diagnostics = 0.0
        self._last_command = 0.0
        self._spinning: set[str] = set()  # raw joints last commanded with a velocity != 0
        self._efforts: set[str] = set()  # raw joints in effort mode (watched for speed)
        self.watchdog_stops = 0

    @property
    def counters(self) -> dict[str, int]:
        """A copy of the refusal counters (cumulative since construction); see COUNTERS."""
        return dict(self._counters)

    @property
    def refused_unknown(self) -> int:
        """Command entries naming a joint this bus does not drive."""
        return self._counters["refused_unknown"]

    def raw_limits(self, raw: str) -> RawLimits:
        """The limits a motor's commands are checked against (raw joint name)."""
        return self._by_raw[raw].limits

    @property
    def joint_names(self) -> Sequence[str]:
        """The full joint names this interface drives."""
        return list(self._to_raw)

    def start(self, now: float) -> None:
        """Open the bus (a failure is reported and retried, never raised)."""
        self._try_open(now)

    def _try_open(self, now: float) -> None:
        try:
            self.backend.open()
        except MotorError as exc:
            self.is_open = False
            self.open_error = str(exc)
            self._next_open = now + self.config.reopen_period
            return
        self.is_open = True
        self.open_error = ""

    def on_joint_commands(self, message: Any, now: float) -> None:
        """Check the commands for this module's joints and forward what passes to the bus."""
        count = len(message.name)
        refused = refused_whole(message, self._size)
        if refused:
            self._refuse(refused, 1, f"{refused.removeprefix('refused_')} message", now)
            return
        if not self.is_open:
            self._refuse("refused_not_open", count, "bus not open", now)
            return
        if self.halted:
            self._refuse("refused_halted", count, "halted, call motors/recover", now)
            return
        # Last entry per joint wins: one command per joint however often it is named.
        latest = {sample.name: sample for sample in joint_samples(message)}
        if len(latest) != count:
            self._counters["duplicates"] += count - len(latest)
        commands = []
        for name, position, velocity, effort in latest.values():
            motor = self._motors.get(name)
            if motor is None:
                self._refuse("refused_unknown", 1, f"unknown joint {name[:64]!r}", now)
                continue
            reason = check_command(motor.checks, position, velocity, effort)
            if reason is not None:
                self._refuse(reason, 1, f"{name}: {reason.removeprefix('refused_')}", now)
                continue
            raw = motor.raw
            if position is None and velocity is None and effort is not None:
                self._efforts.add(raw)
                if _too_fast(motor, effort):
                    effort = 0.0
                    self._counters["speed_cuts"] += 1
                motor.effort = effort
            else:
                self._efforts.discard(raw)
                motor.effort = None
            commands.append(MotorCommand(raw, position, velocity, effort))
            if position is None and velocity:
                self._spinning.add(raw)
            else:
                self._spinning.discard(raw)
        if commands:
            self._last_command = now
            self.backend.write(commands)

    def _refuse(self, counter: str, count: int, note: str, now: float) -> None:
        self._counters[counter] += count
        self._last_refusal = now
        self._refusal_note = note

    def tick(self, now: float) -> None:
        """Read the motors, publish ``joint_states``; publish diagnostics when due."""
        if not self.is_open and now >= self._next_open:
            self._try_open(now)
        if self._spinning and now - self._last_command > self.config.command_timeout:
            # Commands stopped while joints were turning: never keep the last velocity.
            self.backend.write([MotorCommand(raw, velocity=0.0) for raw in sorted(self._spinning)])
            self._spinning.clear()
            self.watchdog_stops += 1
        if self.is_open:
            states = self.backend.read()
            samples = []
            for s in states.values():
                motor = self._by_raw.get(s.joint)
                if motor is None:
                    continue
                motor.speed = s.velocity
                samples.append(JointSample(motor.full, s.position, s.velocity, s.effort))
            if self._efforts:
                self._cut_fast_efforts()
            for batch in _homogeneous(samples):
                self.publish("joint_states", joint_state(batch, self.stamp(now)))
        if now >= self._next_diagnostics:
            self._next_diagnostics = now + self.config.diagnostics_period
            self.publish("diagnostics", diagnostic_array(self.diagnostics(now), self.stamp(now)))

    def _cut_fast_efforts(self) -> None:
        """Effort mode has no speed bound of its own: a motor turning faster than its max
        velocity with its effort pushing it on gets effort 0 (an effort that brakes stays)."""
        cuts = []
        for raw in sorted(self._efforts):
            motor = self._by_raw[raw]
            if motor.effort and _too_fast(motor, motor.effort):
                motor.effort = 0.0
                cuts.append(MotorCommand(raw, effort=0.0))
        if cuts:
            self._counters["speed_cuts"] += len(cuts)
            self.backend.write(cuts)

    def diagnostics(self, now: float | None = None) -> list[Any]:
        """The bus's and every motor's health as DiagnosticStatus messages.

        ``now`` (when given) ages refusals out of the status after the warn window.
        """
        if not self.is_open:
            return [
                diagnostic_status(
                    f"{self.module}/bus",
                    ERROR,
                    f"motor bus {self.backend.channel} is not open: {self.open_error}",
                    hardware_id=self.backend.channel,
                )
            ]
        statuses = []
        reported = set()
        for diag in self.backend.diagnostics():
            full = self._to_full.get(diag.joint, diag.joint)
            if not full:
                # The bus itself, or exceptions the backend let out (a status of their own,
                # so they do not hide the bus's).
                backend = FAULT_KEY in diag.values
                full = f"{self.module}/{'motor_backend' if backend else 'bus'}"
            reported.add(full)
            statuses.append(
                diagnostic_status(
                    full,
                    diag.level,
                    diag.message,
                    hardware_id=self.backend.channel,
                    values=diag.values,
                )
            )
        if f"{self.module}/bus" not in reported:
            # The bus always has a status of its own: a backend fault must not stand in for it.
            statuses.append(
                diagnostic_status(f"{self.module}/bus", OK, "ok", hardware_id=self.backend.channel)
            )
        statuses.append(self._own_status(now))
        return statuses

    def _own_status(self, now: float | None = None) -> Any:
        """The last stage's own status: halt latch, watchdog, refusals (counters as values)."""
        levels, notes = [OK], []
        if self.halted:
            levels.append(ERROR)
            notes.append("halted: commands refused until motors/recover")
        if self.watchdog_stops:
            levels.append(WARN)
            notes.append(
                f"velocity set to 0 after {self.config.command_timeout:g} s without "
                f"joint_commands ({self.watchdog_stops} time(s)); is the joint manager up?"
            )
        recent = now is None or now - self._last_refusal <= self.config.warn_window
        if recent and self._last_refusal > -math.inf:
            levels.append(WARN)
            notes.append(f"commands refused (latest: {self._refusal_note})")
        if self.unlimited:
            levels.append(WARN)
            notes.append(f"no raw limits for {', '.join(self.unlimited)}")
        values: dict[str, Any] = {"watchdog_stops": self.watchdog_stops, "halted": self.halted}
        values.update(self._counters)
        return diagnostic_status(
            f"{self.module}/motor_interface",
            worst(levels),
            "; ".join(notes) or "OK",
            hardware_id=self.backend.channel,
            values=values,
        )

    def on_halt(self, request: Any, now: float) -> Any:
        """Stop all motion on the bus at once; refuse every command until recover."""
        from components.messages import trigger_response

        self.backend.halt()
        self.halted = True
        self._spinning.clear()
        self._efforts.clear()
        return trigger_response(
            True, f"{self.module}: motors halted; commands refused until motors/recover"
        )

    def on_recover(self, request: Any, now: float) -> Any:
        """Clear motor faults (fault reset / reboot) and accept commands again."""
        from components.messages import trigger_response

        self.backend.recover()
        self.halted = False
        return trigger_response(
            True, f"{self.module}: motor faults cleared, commands accepted again"
        )

    def stop(self, now: float) -> None:
        """Leave the motors halted; the builder's resources close the bus."""
        if self.is_open:
            self.backend.halt()


def _too_fast(motor: _Motor, effort: float) -> bool:
    """Whether ``effort`` pushes a motor already above its max velocity on."""
    speed = motor.speed
    return speed is not None and abs(speed) > motor.checks[2] and effort * speed > 0


def _homogeneous(samples: list[JointSample]) -> list[list[JointSample]]:
    # One JointState per set of carried fields (a motor that cannot read effort, say).
    groups: dict[tuple[bool, bool, bool], list[JointSample]] = {}
    for s in samples:
        key = (s.position is not None, s.velocity is not None, s.effort is not None)
        groups.setdefault(key, []).append(s)
    return list(groups.values())
