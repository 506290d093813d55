"""The contract every motor backend fulfils, and the registry that picks one by name.

A backend owns one bus (a CAN channel, a serial port, a simulated world) and the motors on
it. It speaks SI units in *raw* joint space (no calibration: that is the joint manager's
job): radians, rad/s, N·m. Conversion from ticks and raw register values happens in exactly
one place per backend.

Faults never raise out of :meth:`MotorBackend.read` or :meth:`MotorBackend.write`: a motor
that stops answering, a bus that goes away, an over-temperature flag are reported through
:meth:`MotorBackend.diagnostics` (ERROR naming the joint) and the backend keeps trying to pick
the motor up again. Only :meth:`MotorBackend.open` may raise, with a :class:`MotorError` that
says which channel and what to do.
"""

from __future__ import annotations

import importlib
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any

#: Backend name -> "module:Class", imported lazily so a missing SDK breaks only that backend.
BACKENDS: dict[str, str] = {
    "canopen": "components.motors.canopen_drive:CanopenBackend",
    "dynamixel": "components.motors.dynamixel_chain:DynamixelBackend",
}


class MotorError(Exception):
    """A motor bus could not be opened or used; the message names the channel and the fix."""


@dataclass(frozen=True)
class MotorSpec:
    """One motor on a bus, as the resolved assembly describes it.

    Attributes:
        joint: Raw joint name (module-scoped, as in the module's URDF).
        motor_id: CANopen node id or Dynamixel id.
        model: Motor model key (e.g. ``"XM430-W350"``, ``"cia402"``): selects conversion
            constants in the backend.
        params: Extra per-motor parameters from module data (gear ratio, counts per rev...).
    """

    joint: str
    motor_id: int
    model: str
    params: dict[str, Any] = field(default_factory=dict)


@dataclass
class MotorState:
    """Latest reading of one motor in raw joint space (SI units).

    ``None`` where the backend cannot read that quantity.
    """

    joint: str
    position: float | None = None
    velocity: float | None = None
    effort: float | None = None
    temperature: float | None = None
    stamp: float = 0.0


@dataclass(frozen=True)
class MotorCommand:
    """A command for one motor in raw joint space.

    Exactly one of position/velocity is the control target (position wins if both); effort,
    when given, is a limit or feed-forward depending on the backend.
    """

    joint: str
    position: float | None = None
    velocity: float | None = None
    effort: float | None = None


@dataclass(frozen=True)
class MotorDiagnostic:
    """Health of one motor (or of the bus when ``joint`` is empty).

    Attributes:
        level: 0 OK, 1 WARN, 2 ERROR, 3 STALE (diagnostic_msgs levels).
    """

    joint: str
    level: int
    message: str
    values: dict[str, str] = field(default_factory=dict)


class MotorBackend(ABC):
    """One bus of motors.

    Lifecycle: ``open()`` once, then ``read``/``write``/``diagnostics`` from one thread,
    ``close()`` once (idempotent). Also a context manager.
    """

    def __init__(self, channel: str, motors: list[MotorSpec], options: dict[str, Any]):
        self.channel = channel
        self.motors = list(motors)
        self.options = dict(options)

    @abstractmethod
    def open(self) -> None:
        """Connect to the bus and bring every motor to a safe, enabled-but-holding state.

        Raises:
            MotorError: If the bus itself cannot be opened (motors that do not answer are
                reported by diagnostics instead).
        """

    @abstractmethod
    def close(self) -> None:
        """Stop every motor (hold / torque off as the hardware prefers) and release the bus."""

    @abstractmethod
    def read(self) -> dict[str, MotorState]:
        """The latest state of each motor that answered, keyed by joint name. Never raises."""

    @abstractmethod
    def write(self, commands: list[MotorCommand]) -> None:
        """Send commands; unknown joints are ignored (the caller validated). Never raises."""

    @abstractmethod
    def diagnostics(self) -> list[MotorDiagnostic]:
        """Health of each motor and of the bus, as of the latest read/write."""

    def halt(self) -> None:
        """Stop all motion now (velocity zero, hold position). Never raises."""

    def recover(self) -> None:
        """Clear faults (fault reset, reboot) and re-enable. Never raises."""

    def __enter__(self) -> MotorBackend:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def backend_class(name: str) -> type[MotorBackend]:
    """The backend class registered under ``name``.

    Raises:
        MotorError: If the name is unknown or its module cannot be imported (with the pip hint).
    """
    try:
        target = BACKENDS[name]
    except KeyError:
        raise MotorError(
            f"unknown motor backend {name!r}; known: {', '.join(sorted(BACKENDS))}"
        ) from None
    module_name, _, class_name = target.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise MotorError(
            f"motor backend {name!r} cannot load ({exc}); reinstall msctl with `pip install .`"
        ) from exc
    return getattr(module, class_name)
