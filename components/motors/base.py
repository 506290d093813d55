"""The contract every motor backend fulfils, written once, and the lookup of a backend by name.

A backend owns one bus (a CAN channel, a serial port, a simulated world) and the motors on
it. It speaks SI units in *raw* joint space (no calibration: that is the joint manager's
job): radians, rad/s, N·m. Conversion from ticks and raw register values happens in exactly
one place per backend.

:class:`MotorBackend` is a template method (python-can's ``BusABC.recv`` /
``_recv_internal`` is the model): the public ``open``, ``read``, ``write``, ``halt``,
``recover``, ``diagnostics`` and ``close`` are written here, once; a backend implements the
protected ``_open``, ``_read``, ``_write``, ``_halt``, ``_recover``, ``_diagnostics`` and
``_close``. The base keeps the lifecycle (before ``open`` and after ``close``, reads are empty
and commands do nothing), makes ``close`` idempotent, warns when a backend is dropped while
open, and turns any exception a backend lets out of ``read``/``write``/``halt``/``recover``/
``diagnostics`` into an ERROR diagnostic: faults never raise out of those. A motor that stops
answering, a bus that goes away, an over-temperature flag are the backend's own diagnostics
(ERROR naming the joint) and the backend keeps trying to pick the motor up again. Only
:meth:`MotorBackend.open` may raise, and only a :class:`MotorError` that says which channel
and what to do.
"""

from __future__ import annotations

import logging
import math
import threading
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, TypeVar

from components.joints import JointCalibration, JointSpec
from components.motors.options import (
    BACKENDS,
    MotorError,
    MotorOptionsError,
    backend_info,
    parse_options,
)

__all__ = [
    "BACKENDS",
    "ERROR",
    "FAULT_KEY",
    "OK",
    "STALE",
    "WARN",
    "MotorBackend",
    "MotorCommand",
    "MotorDiagnostic",
    "MotorError",
    "MotorOptionsError",
    "MotorSpec",
    "MotorState",
    "RawLimits",
    "backend_class",
    "check_command",
    "refused_whole",
]

log = logging.getLogger(__name__)

#: Diagnostic levels (diagnostic_msgs/DiagnosticStatus).
OK, WARN, ERROR, STALE = 0, 1, 2, 3

#: Key of :attr:`MotorDiagnostic.values` that marks the entry reporting exceptions a backend
#: let out (its value names the operations: ``"read,write"``).
FAULT_KEY = "failed_operations"


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


#: Seconds between two reads of a bus by the motor interface (its tick), hence between two
#: ``joint_states`` of a module: 100 Hz. The simulator publishes at the same rate, so a
#: simulated module loads the data plane (and its joint manager) as a real one does.
READ_PERIOD = 0.01

#: Relative slack of :meth:`RawLimits.admits`: a command this close past a limit is float
#: noise (calibration round trips; the simulator's model stores limits to 6 digits), not a
#: command out of limits. 1e-5 of 3.14 rad is 31 µrad.
LIMIT_TOLERANCE = 1e-5


@dataclass(frozen=True)
class RawLimits:
    """What one motor may be commanded to, in raw joint space: the last stage's own limits.

    The module's joint limits (calibrated, URDF space) mapped through the unit's calibration,
    with no margin: the joint manager clamps inside them with its own margin, so everything it
    sends passes, and anything else (another publisher, a bug) is refused before the bus.

    Attributes:
        lower: Lowest raw position (``-inf`` for a continuous joint).
        upper: Highest raw position (``inf`` for a continuous joint).
        max_velocity: Largest speed magnitude (rad/s or m/s).
        max_effort: Largest effort magnitude (N·m or N).
    """

    lower: float = -math.inf
    upper: float = math.inf
    max_velocity: float = math.inf
    max_effort: float = math.inf

    @classmethod
    def of_joint(cls, spec: JointSpec, calibration: JointCalibration) -> RawLimits:
        """The raw limits of a joint: ``spec``'s limits through ``calibration``."""
        lower, upper = -math.inf, math.inf
        if spec.bounded:
            a, b = calibration.to_raw(spec.lower), calibration.to_raw(spec.upper)
            lower, upper = min(a, b), max(a, b)
        return cls(lower, upper, float(spec.max_velocity), float(spec.max_effort))

    def checks(self) -> tuple[float, float, float, float]:
        """``(lowest, highest, max speed, max effort)`` with :data:`LIMIT_TOLERANCE` applied:
        precomputed once, so a per-command check is four comparisons."""

        def slack(value: float) -> float:
            return LIMIT_TOLERANCE * max(1.0, abs(value)) if math.isfinite(value) else 0.0

        return (
            self.lower - slack(self.lower),
            self.upper + slack(self.upper),
            self.max_velocity + slack(self.max_velocity),
            self.max_effort + slack(self.max_effort),
        )

    def admits(
        self, position: float | None, velocity: float | None, effort: float | None
    ) -> str | None:
        """Why a command breaks these limits (a counter name), or ``None`` if it does not.

        Reasons: ``refused_nan`` (NaN or inf anywhere), ``refused_position``,
        ``refused_velocity``, ``refused_effort``.
        """
        return check_command(self.checks(), position, velocity, effort)


def check_command(
    checks: tuple[float, float, float, float],
    position: float | None,
    velocity: float | None,
    effort: float | None,
) -> str | None:
    """:meth:`RawLimits.admits` with the limits precomputed by :meth:`RawLimits.checks`."""
    lo, hi, vmax, emax = checks
    if position is not None:
        if not math.isfinite(position):
            return "refused_nan"
        if not lo <= position <= hi:
            return "refused_position"
    if velocity is not None:
        if not math.isfinite(velocity):
            return "refused_nan"
        if not -vmax <= velocity <= vmax:
            return "refused_velocity"
    if effort is not None:
        if not math.isfinite(effort):
            return "refused_nan"
        if not -emax <= effort <= emax:
            return "refused_effort"
    return None


def refused_whole(message: Any, size: int) -> str | None:
    """Why a whole command JointState is refused (a counter name), or ``None``.

    ``refused_oversize``: more names than the ``size`` joints it may command; a flood or a
    bug, dropped before it costs anything per entry. ``refused_malformed``: a non-empty
    position, velocity or effort array whose length is not the names' (which value belongs to
    which joint would be a guess).
    """
    count = len(message.name)
    if count > size:
        return "refused_oversize"
    for values in (message.position, message.velocity, message.effort):
        length = len(values)
        if length and length != count:
            return "refused_malformed"
    return None


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


_Result = TypeVar("_Result")


class MotorBackend(ABC):
    """One bus of motors, with the lifecycle and the never-raise rule written once.

    Lifecycle: ``open()``, then ``read``/``write``/``halt``/``recover``/``diagnostics`` from
    one thread, then ``close()`` (idempotent; also a context manager). Subclasses set
    :attr:`backend_name` (the registry name, which selects the options type) and implement
    the protected methods; each may raise anything, the public method reports it.

    Args:
        channel: The bus (``can0``, ``/dev/ttyUSB0``...).
        motors: One :class:`MotorSpec` per motor.
        options: The backend's typed options, or a mapping parsed with
            :func:`~components.motors.options.parse_options` (unknown keys and bad values
            raise :class:`MotorOptionsError`, a :class:`MotorError`).
    """

    #: Registry name of the backend (``"canopen"``); selects its options type.
    backend_name: ClassVar[str] = ""

    def __init__(
        self, channel: str, motors: list[MotorSpec], options: Mapping[str, Any] | Any = None
    ) -> None:
        self.channel = channel
        self.motors = list(motors)
        self.options = self._typed_options(options)
        self._open_now = False
        self._fault_lock = threading.Lock()
        #: (operation, exception text) -> [count, first exception]: faults to report.
        self._faults: dict[tuple[str, str], list[Any]] = {}
        # Faults already logged: a fault repeating every cycle is logged once, until a report
        # comes back clean.
        self._logged: set[tuple[str, str]] = set()

    def _typed_options(self, options: Mapping[str, Any] | Any) -> Any:
        if not self.backend_name:
            return dict(options or {})  # a backend outside the registry (a test double)
        return parse_options(self.backend_name, options)

    @property
    def name(self) -> str:
        """What messages call this backend (its registry name, else its class)."""
        return self.backend_name or type(self).__name__

    @property
    def is_open(self) -> bool:
        """Whether :meth:`open` succeeded and :meth:`close` has not run since."""
        return self._open_now

    # ------------------------------------------------------------------ the public surface

    def open(self) -> None:
        """Connect to the bus and bring every motor to a safe, enabled-but-holding state.

        Opening an open backend does nothing.

        Raises:
            MotorError: If the bus itself cannot be opened (motors that do not answer are
                reported by diagnostics instead); any other exception of the backend is
                wrapped in one, with the cause kept.
        """
        if self._open_now:
            return
        try:
            self._open()
        except MotorError:
            raise
        except Exception as exc:
            raise MotorError(
                f"{self.name} bus {self.channel}: cannot open ({type(exc).__name__}: {exc})"
            ) from exc
        with self._fault_lock:
            self._faults.clear()
        self._open_now = True

    def close(self) -> None:
        """Stop every motor (hold / torque off as the hardware prefers) and release the bus.

        Idempotent; never raises (a failure is logged).
        """
        if not self._open_now:
            return
        self._open_now = False
        try:
            self._close()
        except Exception:
            log.exception("%s bus %s: close failed", self.name, self.channel)

    def read(self) -> dict[str, MotorState]:
        """The latest state of each motor that answered, keyed by joint name. Never raises."""
        if not self._open_now:
            return {}
        return self._guarded("read", self._read, dict)

    def write(self, commands: list[MotorCommand]) -> None:
        """Send commands; unknown joints are ignored (the caller validated). Never raises."""
        if self._open_now:
            self._guarded("write", lambda: self._write(list(commands)), lambda: None)

    def halt(self) -> None:
        """Stop all motion now (velocity zero, hold position). Never raises."""
        if self._open_now:
            self._guarded("halt", self._halt, lambda: None)

    def recover(self) -> None:
        """Clear faults (fault reset, reboot) and re-enable. Never raises."""
        if self._open_now:
            self._guarded("recover", self._recover, lambda: None)

    def diagnostics(self) -> list[MotorDiagnostic]:
        """Health of the bus (``joint`` empty) and of each motor. Never raises.

        Exceptions the backend let out since the last call come last, as one ERROR entry
        (``joint`` empty, ``values[FAULT_KEY]`` set) naming the backend, the channel, each
        operation and its exception.
        """
        if not self._open_now:
            values = {"channel": self.channel}
            text = f"{self.name} bus {self.channel} is not open"
            return [MotorDiagnostic("", ERROR, text, values)] + [
                MotorDiagnostic(
                    m.joint, ERROR, f"{m.joint}: motor id {m.motor_id}: {text}", dict(values)
                )
                for m in self.motors
            ]
        statuses = list(self._guarded("diagnostics", self._diagnostics, list))
        return statuses + self._take_faults()

    def __enter__(self) -> MotorBackend:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        # As python-can's BusABC: a bus dropped while open is a bug of its owner; say so,
        # then stop the motors anyway.
        if getattr(self, "_open_now", False):
            log.warning(
                "%s bus %s was garbage-collected while open; closing it now "
                "(call close() or use `with`)",
                self.name,
                getattr(self, "channel", "?"),
            )
            self.close()

    # ------------------------------------------------------------------ fault reporting

    def _guarded(
        self, operation: str, action: Callable[[], _Result], fallback: Callable[[], _Result]
    ) -> _Result:
        try:
            return action()
        except Exception as exc:
            self._report_fault(operation, exc)
            return fallback()

    def _report_fault(self, operation: str, exc: BaseException) -> None:
        """Note an exception a backend did not handle; the next diagnostics() reports it.

        Thread-safe: a backend's own I/O thread reports what it could not handle here too.
        Repeats of the same fault are counted, and logged once until a report comes back clean.
        """
        key = (operation, f"{type(exc).__name__}: {exc}")
        with self._fault_lock:
            seen = self._faults.get(key)
            if seen is None:
                self._faults[key] = [1, exc]
            else:
                seen[0] += 1
            first = key not in self._logged
            self._logged.add(key)
        if first:
            log.error(
                "%s bus %s: %s failed",
                self.name,
                self.channel,
                operation,
                exc_info=(type(exc), exc, exc.__traceback__),
            )

    def _take_faults(self) -> list[MotorDiagnostic]:
        """The faults since the last call as one ERROR entry (none if there were none)."""
        with self._fault_lock:
            faults, self._faults = self._faults, {}
            if not faults:
                self._logged.clear()
        if not faults:
            return []
        parts = []
        for (operation, text), (count, _) in faults.items():
            times = f" ({count} times)" if count > 1 else ""
            parts.append(f"{operation} failed{times}: {text}")
        operations = sorted({operation for operation, _ in faults})
        return [
            MotorDiagnostic(
                "",
                ERROR,
                f"{self.name} backend on {self.channel}: {'; '.join(parts)} (a bug of the "
                "backend: see the log)",
                {
                    "channel": self.channel,
                    FAULT_KEY: ",".join(operations),
                    "count": str(sum(count for count, _ in faults.values())),
                },
            )
        ]

    # ------------------------------------------------------------------ for the backends

    @abstractmethod
    def _open(self) -> None:
        """Open the bus and bring the motors up; raise :class:`MotorError` with the fix."""

    @abstractmethod
    def _close(self) -> None:
        """Stop the motors and release the bus (called once per successful open)."""

    @abstractmethod
    def _read(self) -> dict[str, MotorState]:
        """The latest state of each motor that answered, keyed by joint name."""

    @abstractmethod
    def _write(self, commands: list[MotorCommand]) -> None:
        """Send commands; unknown joints are ignored."""

    @abstractmethod
    def _halt(self) -> None:
        """Stop all motion now (velocity zero, hold position)."""

    def _recover(self) -> None:
        """Clear faults and re-enable; a backend without such faults keeps this no-op."""

    @abstractmethod
    def _diagnostics(self) -> list[MotorDiagnostic]:
        """The bus's health (``joint`` empty) first, then one entry per motor."""


def backend_class(name: str) -> type[MotorBackend]:
    """The backend class registered under ``name`` (shipped or from an entry point).

    Raises:
        MotorError: If the name is unknown (a :class:`MotorOptionsError` listing the known
            ones) or its module cannot be imported (with the pip hint).
    """
    return backend_info(name).load_class()
