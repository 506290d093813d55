"""Motor interface: carries ``joint_commands`` to a motor backend and its readings back as
``joint_states`` (raw joint space), with the backend's health as ``diagnostics``.

The backend (CANopen, Dynamixel, ...) is handed in, so this logic is the same for every bus
and is tested with a fake backend. It never lets a backend fault escape: a bus that will not
open is retried and reported, and the process keeps running.
"""

from __future__ import annotations

from collections.abc import Sequence
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
)
from components.motors.base import FAULT_KEY, MotorBackend, MotorCommand, MotorError


@dataclass(frozen=True)
class MotorInterfaceConfig:
    """Timing of the motor interface.

    Attributes:
        diagnostics_period: Seconds between two ``diagnostics`` messages.
        reopen_period: Seconds between two attempts to open a bus that failed to open.
        command_timeout: Seconds without ``joint_commands`` after which every joint last
            commanded with a velocity gets velocity 0. A second line behind the joint
            manager's own watchdog (0.5 s): it covers a joint manager that died or hung.
    """

    diagnostics_period: float = 1.0
    reopen_period: float = 2.0
    command_timeout: float = 1.0


class MotorInterfaceCore(Core):
    """Routes commands to one bus of motors and publishes their states.

    Args:
        name: Component name (``limb1/motor_interface``).
        module: Module slot (``limb1``): joint names on topics are ``<module>_<raw name>``.
        backend: The bus, not yet opened.
        config: Timing.
    """

    def __init__(
        self,
        name: str,
        module: str,
        backend: MotorBackend,
        config: MotorInterfaceConfig | None = None,
    ) -> None:
        super().__init__(name)
        self.module = module
        self.backend = backend
        self.config = config or MotorInterfaceConfig()
        self._to_raw = {f"{module}_{m.joint}": m.joint for m in backend.motors}
        self._to_full = {raw: full for full, raw in self._to_raw.items()}
        self.is_open = False
        self.open_error = ""
        self._next_open = 0.0
        self._next_diagnostics = 0.0
        self.refused_unknown = 0
        self._last_command = 0.0
        self._spinning: set[str] = set()  # raw joints last commanded with a velocity != 0
        self.watchdog_stops = 0

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
        """Forward the commands for this module's joints to the backend."""
        if not self.is_open:
            return
        commands = []
        for sample in joint_samples(message):
            raw = self._to_raw.get(sample.name)
            if raw is None:
                self.refused_unknown += 1
                continue
            commands.append(MotorCommand(raw, sample.position, sample.velocity, sample.effort))
            if sample.position is None and sample.velocity:
                self._spinning.add(raw)
            else:
                self._spinning.discard(raw)
        if commands:
            self._last_command = now
            self.backend.write(commands)

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
            samples = [
                JointSample(self._to_full[s.joint], s.position, s.velocity, s.effort)
                for s in states.values()
                if s.joint in self._to_full
            ]
            for batch in _homogeneous(samples):
                self.publish("joint_states", joint_state(batch, self.stamp(now)))
        if now >= self._next_diagnostics:
            self._next_diagnostics = now + self.config.diagnostics_period
            self.publish("diagnostics", diagnostic_array(self.diagnostics(), self.stamp(now)))

    def diagnostics(self) -> list[Any]:
        """The bus's and every motor's health as DiagnosticStatus messages."""
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
        if self.watchdog_stops:
            statuses.append(
                diagnostic_status(
                    f"{self.module}/motor_interface",
                    WARN,
                    f"velocity set to 0 after {self.config.command_timeout:g} s without "
                    f"joint_commands ({self.watchdog_stops} time(s)); is the joint manager up?",
                    hardware_id=self.backend.channel,
                    values={"watchdog_stops": self.watchdog_stops},
                )
            )
        return statuses

    def on_halt(self, request: Any, now: float) -> Any:
        """Stop all motion on the bus at once."""
        from components.messages import trigger_response

        self.backend.halt()
        return trigger_response(True, f"{self.module}: motors halted")

    def on_recover(self, request: Any, now: float) -> Any:
        """Clear motor faults (fault reset / reboot)."""
        from components.messages import trigger_response

        self.backend.recover()
        return trigger_response(True, f"{self.module}: motor faults cleared")

    def stop(self, now: float) -> None:
        """Leave the motors halted; the builder's resources close the bus."""
        if self.is_open:
            self.backend.halt()


def _homogeneous(samples: list[JointSample]) -> list[list[JointSample]]:
    # One JointState per set of carried fields (a motor that cannot read effort, say).
    groups: dict[tuple[bool, bool, bool], list[JointSample]] = {}
    for s in samples:
        key = (s.position is not None, s.velocity is not None, s.effort is not None)
        groups.setdefault(key, []).append(s)
    return list(groups.values())
