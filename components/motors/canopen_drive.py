"""CANopen CiA 402 drives (H-line robots) on python-can, through the ``canopen`` library.

One :class:`CanopenBackend` owns one CAN channel and the CiA 402 drives on it. It uses SDO only
to configure a drive (heartbeat, PDO mapping, profile parameters), then PDOs for all cyclic
data, so :meth:`~CanopenBackend.read` and :meth:`~CanopenBackend.write` never wait on the
bus:

=========  ===========================================================================
RPDO1      controlword (0x6040), modes of operation (0x6060)
RPDO2      target position (0x607A), profile velocity (0x6081)
RPDO3      target velocity (0x60FF), max torque (0x6072): the effort limit
TPDO1      statusword (0x6041), modes of operation display (0x6061), error code (0x603F)
TPDO2      position actual (0x6064), velocity actual (0x606C)
TPDO3      torque actual (0x6077), current actual (0x6078)
TPDO4      drive temperature, when ``temperature_object`` names one (vendor specific)
=========  ===========================================================================

A supervisor thread owns everything slow: it configures each drive, walks the CiA 402 state
machine to OPERATION ENABLED (holding position, in profile position mode), watches
heartbeats, and picks a drive up again (re-configure, fault reset, re-enable) when its
heartbeat returns. The drives watch the master too: the backend produces a heartbeat and
arms each drive's heartbeat consumer (0x1016), so a drive stops by itself when this process
or the cable dies.

Every conversion between drive units (encoder counts, velocity units, per-mille of rated
torque) and SI joint units lives in :class:`_Conversion`.
"""

from __future__ import annotations

import logging
import math
import threading
import time
import weakref
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import canopen
from canopen.emcy import EmcyError
from canopen.pdo import PdoMap

from components.motors.base import (
    ERROR,
    OK,
    WARN,
    MotorBackend,
    MotorCommand,
    MotorDiagnostic,
    MotorError,
    MotorSpec,
    MotorState,
)
from components.motors.options import CanopenOptions

logger = logging.getLogger(__name__)

#: The minimal CiA 402 object dictionary shipped with msctl (a vendor EDS may replace it).
DEFAULT_EDS = Path(__file__).resolve().with_name("cia402_drive.eds")

MODE_PROFILE_POSITION = 1
MODE_PROFILE_VELOCITY = 3
_MODE_NAMES = {MODE_PROFILE_POSITION: "profile position", MODE_PROFILE_VELOCITY: "profile velocity"}

# Controlword commands (CiA 402, bits 0-3 and 7) and mode-specific bits.
_CW_SHUTDOWN = 0x0006
_CW_SWITCH_ON = 0x0007
_CW_ENABLE_OPERATION = 0x000F
_CW_FAULT_RESET = 0x0080
_CW_NEW_SETPOINT = 0x0010
_CW_CHANGE_IMMEDIATELY = 0x0020
_CW_HALT = 0x0100
_SW_SETPOINT_ACK = 0x1000

# (mask, value, state) in the order CiA 402 tells to decode the statusword.
_STATUSWORD_STATES = (
    (0x4F, 0x00, "NOT READY TO SWITCH ON"),
    (0x4F, 0x40, "SWITCH ON DISABLED"),
    (0x6F, 0x21, "READY TO SWITCH ON"),
    (0x6F, 0x23, "SWITCHED ON"),
    (0x6F, 0x27, "OPERATION ENABLED"),
    (0x6F, 0x07, "QUICK STOP ACTIVE"),
    (0x4F, 0x0F, "FAULT REACTION ACTIVE"),
    (0x4F, 0x08, "FAULT"),
)

#: What common EMCY / 0x603F error codes mean (CiA 301 and CiA 402), for diagnostics.
EMCY_MEANINGS: dict[int, str] = {
    0x0000: "error reset / no error",
    0x1000: "generic error",
    0x2310: "continuous over-current",
    0x2320: "short circuit at outputs",
    0x2330: "earth leakage",
    0x3110: "mains over-voltage",
    0x3210: "DC link over-voltage",
    0x3220: "DC link under-voltage",
    0x4210: "over-temperature (device)",
    0x4310: "over-temperature (drive)",
    0x4320: "under-temperature (drive)",
    0x5000: "device hardware error",
    0x5530: "EEPROM/data storage error",
    0x6100: "internal software error",
    0x6320: "parameter error",
    0x7121: "motor blocked",
    0x7300: "sensor error",
    0x7305: "incremental encoder 1 broken",
    0x8110: "CAN overrun (frames lost)",
    0x8120: "CAN in error passive mode",
    0x8130: "life guard or heartbeat error (master lost)",
    0x8140: "recovered from bus off",
    0x8210: "PDO not processed (length error)",
    0x8611: "following error",
    0xFF00: "device specific error",
}


def emcy_meaning(code: int) -> str:
    """A short human meaning for an EMCY error code (exact code first, then its class)."""
    if code in EMCY_MEANINGS:
        return EMCY_MEANINGS[code]
    text = EmcyError(code, 0, b"", 0.0).get_desc()
    return f"{text.lower()} error" if text else "unknown error"


def decode_state(statusword: int) -> str:
    """The CiA 402 state a statusword encodes (``"OPERATION ENABLED"``...)."""
    for mask, value, name in _STATUSWORD_STATES:
        if statusword & mask == value:
            return name
    return "UNKNOWN"


@dataclass(frozen=True)
class _Conversion:
    """Every unit conversion of one motor: drive units on one side, raw joint SI on the other.

    Position units are encoder counts of the motor (``counts_per_rev`` per motor revolution,
    ``gear_ratio`` motor revolutions per joint revolution). Velocity units are counts/s unless
    ``velocity_units`` says ``rpm`` or ``0.1rpm`` (motor shaft). Torque and current are
    per-mille of the motor's rated torque (``rated_torque``, N·m at the motor); the joint sees
    it multiplied by the gear ratio. A linear joint driven through a rack and pinion or a
    screw (``meters_per_rad``: metres of travel per output radian) is in metres, m/s and
    newtons instead of radians, rad/s and N·m; the method names keep saying "rad".
    """

    counts_per_rad: float
    velocity_units_per_rad_s: float
    permille_per_nm: float

    @classmethod
    def from_spec(cls, spec: MotorSpec) -> _Conversion:
        """Build from ``MotorSpec.params``.

        Raises:
            MotorError: If a parameter is missing its sense (non-positive, unknown unit).
        """
        params = spec.params
        counts_per_rev = _positive(spec, "counts_per_rev", params.get("counts_per_rev", 4096))
        gear_ratio = _positive(spec, "gear_ratio", params.get("gear_ratio", 1.0))
        rated_torque = _positive(spec, "rated_torque", params.get("rated_torque", 1.0))
        units = str(params.get("velocity_units", "counts/s"))
        # Output radians per joint unit: 1 for a revolute joint, 1/meters_per_rad for a
        # linear one (a finger), so its positions are metres as in the URDF.
        rad_per_unit = 1.0 / _positive(spec, "meters_per_rad", params.get("meters_per_rad", 1.0))
        counts_per_rad = counts_per_rev * gear_ratio / (2 * math.pi) * rad_per_unit
        motor_rpm_per_rad_s = gear_ratio * 60.0 / (2 * math.pi) * rad_per_unit
        per_rad_s = {
            "counts/s": counts_per_rad,
            "rpm": motor_rpm_per_rad_s,
            "0.1rpm": motor_rpm_per_rad_s * 10.0,
        }
        if units not in per_rad_s:
            raise MotorError(
                f"{spec.joint}: motor_params.velocity_units={units!r} is not one of "
                f"{', '.join(per_rad_s)}; fix the joint's motor_params in the module data"
            )
        per_nm = 1000.0 / (rated_torque * gear_ratio)
        return cls(counts_per_rad, per_rad_s[units], per_nm / rad_per_unit)

    def position(self, counts: int) -> float:
        """Position actual (counts) to joint radians."""
        return counts / self.counts_per_rad

    def position_counts(self, rad: float) -> int:
        """Joint radians to a target position in counts (clamped to INTEGER32)."""
        return _clamp_int(rad * self.counts_per_rad, -(2**31), 2**31 - 1)

    def velocity(self, units: int) -> float:
        """Velocity actual (drive velocity units) to joint rad/s."""
        return units / self.velocity_units_per_rad_s

    def velocity_units(self, rad_s: float) -> int:
        """Joint rad/s to drive velocity units (clamped to INTEGER32)."""
        return _clamp_int(rad_s * self.velocity_units_per_rad_s, -(2**31), 2**31 - 1)

    def acceleration_units(self, rad_s2: float) -> int:
        """Joint rad/s² to drive acceleration units (velocity units per second, UNSIGNED32)."""
        return _clamp_int(abs(rad_s2) * self.velocity_units_per_rad_s, 1, 2**32 - 1)

    def effort(self, permille: int) -> float:
        """Torque or current actual (per-mille of rated) to joint N·m."""
        return permille / self.permille_per_nm

    def effort_permille(self, nm: float) -> int:
        """A joint torque limit (N·m) to max torque per-mille (UNSIGNED16)."""
        return _clamp_int(abs(nm) * self.permille_per_nm, 0, 0xFFFF)


def _positive(spec: MotorSpec, name: str, value: Any) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        number = float("nan")
    if not number > 0:
        raise MotorError(
            f"{spec.joint}: motor_params.{name}={value!r} must be a positive number; "
            "fix the joint's motor_params in the module data"
        )
    return number


def _clamp_int(value: float, lower: int, upper: int) -> int:
    if not math.isfinite(value):
        return 0 if lower <= 0 <= upper else lower
    return max(lower, min(upper, round(value)))


# PDO layouts (index, subindex) per map number; see the module docstring.
_TPDO_LAYOUT = {
    1: [(0x6041, 0), (0x6061, 0), (0x603F, 0)],
    2: [(0x6064, 0), (0x606C, 0)],
    3: [(0x6077, 0), (0x6078, 0)],
}
_RPDO_LAYOUT = {
    1: [(0x6040, 0), (0x6060, 0)],
    2: [(0x607A, 0), (0x6081, 0)],
    3: [(0x60FF, 0), (0x6072, 0)],
}

# Position set-point handshake phases (CiA 402 profile position, single set-point).
_SP_IDLE, _SP_REQUESTED, _SP_RELEASING = "idle", "requested", "releasing"


#: NMT state OPERATIONAL as a heartbeat carries it (CiA 301).
_NMT_OPERATIONAL = 0x05


@dataclass
class _Drive:
    """Runtime state of one drive, guarded by the backend lock."""

    spec: MotorSpec
    node: canopen.RemoteNode
    conv: _Conversion
    profile_velocity: int
    acceleration: int
    # liveness
    heartbeat_at: float | None = None
    nmt_state: int | None = None
    configured: bool = False
    ever_configured: bool = False
    config_error: str | None = None
    next_config_at: float = 0.0
    lost_since: float | None = None
    # feedback (drive units) and when it came (monotonic; wall clock for the stamp)
    statusword: int | None = None
    mode_display: int | None = None
    error_code: int = 0
    status_at: float = 0.0
    position: int | None = None
    velocity: int | None = None
    torque: int | None = None
    current: int | None = None
    temperature: float | None = None
    feedback_at: float = 0.0
    feedback_stamp: float = 0.0
    emcys: list[EmcyError] = field(default_factory=list)
    # command side
    controlword: int = 0
    mode: int = MODE_PROFILE_POSITION
    halted: bool = False
    auto_reset: bool = True
    default_max_torque: int = 1000
    max_torque: int = 1000
    target_velocity: int = 0
    sp_phase: str = _SP_IDLE
    sp_since: float = 0.0
    sp_sent: tuple[int, int] | None = None
    sp_pending: tuple[int, int] | None = None
    sent_rpdo1: tuple[int, int] | None = None
    sent_rpdo3: tuple[int, int] | None = None

    @property
    def node_id(self) -> int:
        return self.node.id

    @property
    def state(self) -> str | None:
        return None if self.statusword is None else decode_state(self.statusword)

    def alive(self, now: float, timeout: float) -> bool:
        return self.heartbeat_at is not None and now - self.heartbeat_at <= timeout

    def enabled(self, now: float, timeout: float) -> bool:
        return self.configured and self.alive(now, timeout) and self.state == "OPERATION ENABLED"


class CanopenBackend(MotorBackend):
    """CiA 402 drives on one CAN channel, through python-can and ``canopen``.

    Args:
        channel: python-can channel (``can0`` on a robot; any name on ``virtual``).
        motors: One :class:`MotorSpec` per drive; ``motor_id`` is the CANopen node id.
            ``params`` keys: ``counts_per_rev`` (encoder counts per motor revolution,
            default 4096), ``gear_ratio`` (motor revolutions per joint revolution, default 1),
            ``rated_torque`` (motor rated torque in N·m, the 1000 per-mille of 0x6077/0x6072,
            default 1), ``velocity_units`` (``counts/s`` default, ``rpm``, ``0.1rpm``),
            ``profile_velocity`` (rad/s of a position move without its own speed, default 1),
            ``profile_acceleration`` (rad/s², default 10), ``effort_source`` (``torque``
            reads 0x6077, ``current`` reads 0x6078; default ``torque``).
        options: :class:`~components.motors.options.CanopenOptions` (or a mapping of its
            keys): every key, default and meaning is documented there.
    """

    backend_name = "canopen"
    options: CanopenOptions

    _LOOP_PERIOD = 0.02  # supervisor period: enable steps and liveness checks
    _CONFIG_RETRY = 1.0  # seconds between configuration attempts of a silent drive
    _RECONNECT_PERIOD = 1.0
    _SETPOINT_TIMEOUT = 0.5

    def __init__(
        self,
        channel: str,
        motors: list[MotorSpec],
        options: CanopenOptions | dict[str, Any] | None = None,
    ):
        super().__init__(channel, motors, options)
        opts = self.options
        self.interface = opts.interface
        self.bitrate = opts.bitrate
        self.heartbeat_timeout = opts.heartbeat_timeout
        self.heartbeat_ms = opts.drive_heartbeat_ms
        self.sync_period = opts.sync_period
        self.pdo_period = opts.feedback_period
        self.master_node_id = opts.master_node_id
        self.eds = opts.eds or str(DEFAULT_EDS)
        self.temperature_object = opts.temperature_object
        self.sdo_timeout = opts.sdo_timeout
        self.enable_timeout = opts.enable_timeout
        seen: dict[int, str] = {}
        for spec in self.motors:
            if not 1 <= spec.motor_id <= 127:
                raise MotorError(f"{spec.joint}: CANopen node id {spec.motor_id} is not 1..127")
            if spec.motor_id in seen:
                raise MotorError(
                    f"{spec.joint} and {seen[spec.motor_id]} both use node id {spec.motor_id} "
                    f"on {channel}; fix motor_id in the module or calibration data"
                )
            seen[spec.motor_id] = spec.joint
        self._conversions = {spec.joint: _Conversion.from_spec(spec) for spec in self.motors}
        self._lock = threading.RLock()
        self._network: canopen.Network | None = None
        self._drives: dict[str, _Drive] = {}
        self._supervisor: threading.Thread | None = None
        self._stop = threading.Event()
        self._master_heartbeat: Any = None
        self._bus_error: str | None = None
        self._next_reconnect = 0.0

    # ------------------------------------------------------------------------ lifecycle

    def _open(self) -> None:
        """Connect, configure and enable every drive that answers (holding position).

        Raises:
            MotorError: If the CAN bus itself cannot be opened.
        """
        network = canopen.Network()
        network.listeners.append(_BusErrorListener(_weak_method(self._note_bus_error)))
        try:
            network.connect(interface=self.interface, channel=self.channel, bitrate=self.bitrate)
        except (can.CanError, OSError, ValueError, ImportError, NotImplementedError) as exc:
            raise MotorError(self._bus_open_hint(exc)) from exc
        self._network = network
        try:
            for spec in self.motors:
                self._drives[spec.joint] = self._add_drive(network, spec)
            self._start_producers()
        except Exception as exc:
            self._network = None
            self._drives.clear()
            _quietly(network.disconnect)
            raise MotorError(f"CAN bus {self.channel}: cannot set up CANopen: {exc}") from exc
        self._stop.clear()
        # The thread and every callback hold this backend weakly, so one dropped while open
        # is collected (and the base class warns and closes it).
        self._supervisor = threading.Thread(
            target=_supervise_forever,
            args=(weakref.ref(self), self._stop, self._LOOP_PERIOD),
            name=f"canopen-{self.channel}",
            daemon=True,
        )
        self._supervisor.start()
        # Give the drives a moment to come up so the first read() already has them; drives
        # that stay silent are reported by diagnostics(), never raised.
        deadline = time.monotonic() + self.enable_timeout
        while time.monotonic() < deadline:
            now = time.monotonic()
            with self._lock:
                settled = all(
                    d.enabled(now, self.heartbeat_timeout) or d.config_error is not None
                    for d in self._drives.values()
                )
            if settled:
                break
            time.sleep(0.01)

    def _close(self) -> None:
        """Halt, disable operation, disarm the drives' watchdog and release the bus."""
        if self._network is None:
            return
        self._stop.set()
        supervisor, self._supervisor = self._supervisor, None
        if supervisor is not None and supervisor is not threading.current_thread():
            supervisor.join(timeout=5.0)
        now = time.monotonic()
        with self._lock:
            alive = [d for d in self._drives.values() if d.alive(now, self.heartbeat_timeout)]
            for d in alive:
                if d.configured:
                    d.halted = True
                    d.controlword = _CW_SWITCH_ON  # disable operation: stop, brake, no torque
                    self._send_rpdo1(d, force=True)
        for d in alive:
            _quietly(lambda d=d: self._release(d))
        self._stop_producers()
        network, self._network = self._network, None
        _quietly(network.disconnect)
        self._drives.clear()

    def _release(self, d: _Drive) -> None:
        """Disarm a drive's master watchdog and park it in pre-operational (at close)."""
        if self.master_node_id and 0x1016 in d.node.object_dictionary:
            # Without this the drive would fault on the master heartbeat we stop sending.
            d.node.sdo[0x1016][1].raw = 0
        d.node.nmt.state = "PRE-OPERATIONAL"

    # ---------------------------------------------------------------------- data path

    def _read(self) -> dict[str, MotorState]:
        """Latest state of every drive whose heartbeat and feedback are fresh."""
        now = time.monotonic()
        states: dict[str, MotorState] = {}
        with self._lock:
            for joint, d in self._drives.items():
                fresh = now - d.feedback_at <= self.heartbeat_timeout
                if not (d.alive(now, self.heartbeat_timeout) and fresh and d.position is not None):
                    continue
                effort_raw = (
                    d.current if d.spec.params.get("effort_source") == "current" else d.torque
                )
                states[joint] = MotorState(
                    joint=joint,
                    position=d.conv.position(d.position),
                    velocity=None if d.velocity is None else d.conv.velocity(d.velocity),
                    effort=None if effort_raw is None else d.conv.effort(effort_raw),
                    temperature=d.temperature,
                    stamp=d.feedback_stamp,
                )
        return states

    def _write(self, commands: list[MotorCommand]) -> None:
        """Send position (profile position) or velocity (profile velocity) targets.

        ``effort`` becomes the drive's max torque (a limit). Commands to drives that are not
        enabled are dropped: a drive picked up again holds where it is.
        """
        now = time.monotonic()
        with self._lock:
            for command in commands:
                d = self._drives.get(command.joint)
                if d is None or not d.enabled(now, self.heartbeat_timeout):
                    continue
                if command.effort is not None and math.isfinite(command.effort):
                    d.max_torque = d.conv.effort_permille(command.effort)
                else:
                    d.max_torque = d.default_max_torque
                if command.position is not None and math.isfinite(command.position):
                    speed = command.velocity
                    if speed is not None and math.isfinite(speed) and speed != 0:
                        profile = max(1, abs(d.conv.velocity_units(speed)))
                    else:
                        profile = d.profile_velocity
                    d.halted = False
                    if d.mode != MODE_PROFILE_POSITION:
                        d.mode = MODE_PROFILE_POSITION
                        d.sp_sent = None
                    d.target_velocity = 0
                    self._send_rpdo3(d)
                    d.sp_pending = (d.conv.position_counts(command.position), profile)
                    self._advance_setpoint(d, now)
                elif command.velocity is not None and math.isfinite(command.velocity):
                    d.halted = False
                    d.mode = MODE_PROFILE_VELOCITY
                    d.sp_phase, d.sp_pending, d.sp_sent = _SP_IDLE, None, None
                    d.controlword &= ~_CW_NEW_SETPOINT
                    d.target_velocity = d.conv.velocity_units(command.velocity)
                    self._send_rpdo3(d)
                    self._send_rpdo1(d)

    def _diagnostics(self) -> list[MotorDiagnostic]:
        """Bus health first (``joint`` empty), then one entry per drive."""
        now = time.monotonic()
        out: list[MotorDiagnostic] = []
        with self._lock:
            if self._bus_error:
                out.append(MotorDiagnostic("", ERROR, self._bus_error, {"channel": self.channel}))
            else:
                up = f"CAN bus {self.channel} ({self.interface}, {self.bitrate} bit/s): up"
                out.append(MotorDiagnostic("", OK, up, {"channel": self.channel}))
            for d in self._drives.values():
                out.append(self._drive_diagnostic(d, now))
        return out

    def _halt(self) -> None:
        """Stop every drive now with the halt bit (velocity targets zero, positions held)."""
        now = time.monotonic()
        with self._lock:
            for d in self._drives.values():
                if not d.enabled(now, self.heartbeat_timeout):
                    continue
                d.halted = True
                d.sp_pending = None
                d.sp_sent = None
                d.target_velocity = 0
                self._send_rpdo3(d, force=True)
                self._send_rpdo1(d)

    def _recover(self) -> None:
        """Forget reported emergencies, fault-reset and re-enable every drive."""
        with self._lock:
            for d in self._drives.values():
                d.emcys.clear()
                d.auto_reset = True
                d.next_config_at = 0.0  # a drive that never answered: try again now
            self._next_reconnect = 0.0

    # ------------------------------------------------------------------ setup helpers

    def _bus_open_hint(self, exc: BaseException) -> str:
        if isinstance(exc, can.CanInterfaceNotImplementedError | ImportError | NotImplementedError):
            known = ", ".join(sorted(can.interfaces.VALID_INTERFACES))
            fix = f"set the bus option interface to one python-can knows ({known})"
        elif self.interface == "socketcan":
            fix = (
                f"check the CAN adapter is plugged in and the link is up: "
                f"`sudo ip link set {self.channel} up type can bitrate {self.bitrate}`"
            )
        else:
            fix = f"check the {self.interface} adapter is connected and the channel name is right"
        return (
            f"cannot open CAN bus {self.channel!r} with python-can interface "
            f"{self.interface!r}: {exc}; {fix}"
        )

    def _add_drive(self, network: canopen.Network, spec: MotorSpec) -> _Drive:
        node = canopen.RemoteNode(spec.motor_id, self.eds)
        node.sdo.RESPONSE_TIMEOUT = self.sdo_timeout
        network.add_node(node)
        conv = self._conversions[spec.joint]
        params = spec.params
        d = _Drive(
            spec=spec,
            node=node,
            conv=conv,
            profile_velocity=max(
                1, abs(conv.velocity_units(float(params.get("profile_velocity", 1.0))))
            ),
            acceleration=conv.acceleration_units(float(params.get("profile_acceleration", 10.0))),
        )
        on_heartbeat = _weak_method(self._on_heartbeat)
        on_emcy = _weak_method(self._on_emcy)
        on_tpdo = _weak_method(self._on_tpdo)
        node.nmt.add_heartbeat_callback(lambda state, d=d: on_heartbeat(d, state))
        node.emcy.add_callback(lambda emcy, d=d: on_emcy(d, emcy))
        for number in (1, 2, 3, 4):
            node.tpdo[number].add_callback(lambda pdo, d=d, n=number: on_tpdo(d, n, pdo))
        return d

    def _start_producers(self) -> None:
        network = self._network
        assert network is not None
        if self.master_node_id:
            self._master_heartbeat = network.send_periodic(
                0x700 + self.master_node_id, b"\x05", self.heartbeat_ms / 1000.0
            )
        if self.sync_period:
            network.sync.start(self.sync_period)

    def _stop_producers(self) -> None:
        if self._master_heartbeat is not None:
            _quietly(self._master_heartbeat.stop)
            self._master_heartbeat = None
        if self._network is not None and self.sync_period:
            _quietly(self._network.sync.stop)

    def _configure(self, d: _Drive) -> None:
        """Put one drive in a known configuration over SDO and start it (supervisor thread).

        Raises:
            canopen.SdoError, can.CanError, OSError: When the drive does not answer or refuses.
        """
        node = d.node
        od = node.object_dictionary
        node.nmt.state = "PRE-OPERATIONAL"  # PDO mapping may only change there
        sdo = node.sdo
        sdo[0x1017].raw = self.heartbeat_ms
        if self.master_node_id and 0x1016 in od:
            consumer_ms = max(self.heartbeat_ms * 2, round(self.heartbeat_timeout * 1000))
            sdo[0x1016][1].raw = (self.master_node_id << 16) | min(consumer_ms, 0xFFFF)
        sdo[0x60FF].raw = 0  # never enable into a stale velocity target
        sdo[0x6060].raw = MODE_PROFILE_POSITION
        sdo[0x6081].raw = d.profile_velocity
        sdo[0x6083].raw = d.acceleration
        sdo[0x6084].raw = d.acceleration
        default_max_torque = int(sdo[0x6072].raw)
        tpdo_layout = dict(_TPDO_LAYOUT)
        if self.temperature_object is not None:
            tpdo_layout[4] = [(self.temperature_object, 0)]
        event_ms = max(1, round(self.pdo_period * 1000))
        for number in (1, 2, 3, 4):
            pdo = node.tpdo[number]
            synced = self.sync_period is not None and number != 1
            # The statusword TPDO stays event-driven so the enable and set-point handshakes
            # do not wait for a SYNC; the rest follow SYNC when there is one.
            self._map(pdo, tpdo_layout.get(number), 1 if synced else 255, 0 if synced else event_ms)
        for number in (1, 2, 3, 4):
            self._map(node.rpdo[number], _RPDO_LAYOUT.get(number), 255, None)
        node.nmt.state = "OPERATIONAL"
        with self._lock:
            d.default_max_torque = d.max_torque = default_max_torque
            d.mode = MODE_PROFILE_POSITION
            d.halted = False
            d.target_velocity = 0
            d.sp_phase, d.sp_pending, d.sp_sent = _SP_IDLE, None, None
            d.controlword = 0
            d.sent_rpdo1 = d.sent_rpdo3 = None
            d.statusword = None  # wait for this configuration's first statusword
            d.configured = d.ever_configured = True
            d.config_error = None
            d.lost_since = None
            d.heartbeat_at = time.monotonic()

    @staticmethod
    def _map(
        pdo: PdoMap, layout: list[tuple[int, int]] | None, trans_type: int, event_ms: int | None
    ) -> None:
        pdo.clear()
        pdo.cob_id = pdo.predefined_cob_id
        pdo.enabled = layout is not None
        for index, subindex in layout or []:
            pdo.add_variable(index, subindex)
        pdo.trans_type = trans_type
        pdo.event_timer = event_ms
        pdo.save()

    # ---------------------------------------------------- callbacks (notifier thread)

    def _on_heartbeat(self, d: _Drive, state: int) -> None:
        now = time.monotonic()
        with self._lock:
            # Back after a silence longer than the timeout, whether or not the supervisor
            # (every 20 ms, later on a loaded machine) has marked it lost yet.
            back = d.heartbeat_at is None or now - d.heartbeat_at > self.heartbeat_timeout
            if back:
                d.next_config_at = 0.0  # pick it up at once
            d.heartbeat_at = now
            d.nmt_state = state
            if state == 0 and d.configured:
                # Boot-up: the drive rebooted and lost our configuration.
                d.configured = False
                d.auto_reset = True
                d.next_config_at = 0.0
            elif back and d.configured:
                # What the supervisor does on a loss, in case it had not seen this one: the
                # readings from before the silence are not passed off as fresh (they could
                # be up to a timeout old, and read() took them for current), and the state
                # is learnt again from the next statusword.
                d.auto_reset = True
                d.statusword = None
                d.position = None
                if state == _NMT_OPERATIONAL:
                    # No boot-up seen: it kept its configuration (a cut cable, or heartbeats
                    # late on a loaded bus). Trusted again at once: a configuration over SDO,
                    # one drive after another, left every drive of a limb blind for seconds
                    # after a hiccup that lost them all.
                    d.lost_since = None
                else:
                    # Pre-operational or stopped (its own reaction to a communication
                    # error, or a reboot whose boot-up was lost): its PDOs are off,
                    # configure it again.
                    d.configured = False

    def _on_emcy(self, d: _Drive, emcy: EmcyError) -> None:
        with self._lock:
            if emcy.code & 0xFF00 == 0:
                d.emcys.clear()  # "error reset / no error"
                logger.info("%s: drive node %d cleared its errors", d.spec.joint, d.node_id)
                return
            if all(e.code != emcy.code for e in d.emcys):
                d.emcys.append(emcy)
        logger.warning(
            "%s: drive node %d emergency 0x%04X (%s)",
            d.spec.joint,
            d.node_id,
            emcy.code,
            emcy_meaning(emcy.code),
        )

    def _on_tpdo(self, d: _Drive, number: int, pdo: PdoMap) -> None:
        try:
            values = [var.raw for var in pdo.map]
        except Exception as exc:  # a short or foreign frame must not kill the notifier
            logger.debug("%s: bad TPDO%d: %s", d.spec.joint, number, exc)
            return
        now = time.monotonic()
        with self._lock:
            if not d.configured:
                return
            if number == 1 and len(values) >= 3:
                d.statusword, d.mode_display, d.error_code = values[0], values[1], values[2]
                d.status_at = now
                if decode_state(d.statusword) == "OPERATION ENABLED":
                    # Enabled again: from now on a fault waits for recover().
                    d.auto_reset = False
                self._advance_setpoint(d, now)
            elif number == 2 and len(values) >= 2:
                d.position, d.velocity = values[0], values[1]
                d.feedback_at = now
                d.feedback_stamp = pdo.timestamp or time.time()
            elif number == 3 and len(values) >= 2:
                d.torque, d.current = values[0], values[1]
            elif number == 4 and values:
                d.temperature = values[0] / 10.0

    # -------------------------------------------------------------- command frames

    def _send_rpdo1(self, d: _Drive, force: bool = False) -> None:
        word = d.controlword | (_CW_HALT if d.halted else 0)
        if d.mode == MODE_PROFILE_POSITION:
            word |= _CW_CHANGE_IMMEDIATELY
        frame = (word, d.mode)
        if frame == d.sent_rpdo1 and not force:
            return
        pdo = d.node.rpdo[1]
        pdo[0x6040].raw = word
        pdo[0x6060].raw = d.mode
        if self._transmit(pdo):
            d.sent_rpdo1 = frame

    def _send_rpdo3(self, d: _Drive, force: bool = False) -> None:
        frame = (d.target_velocity, d.max_torque)
        # Velocity targets are streamed (a drive may watch them arrive); in profile position
        # the frame only carries the torque limit, so it is sent when that changes.
        if frame == d.sent_rpdo3 and d.mode == MODE_PROFILE_POSITION and not force:
            return
        pdo = d.node.rpdo[3]
        pdo[0x60FF].raw = d.target_velocity
        pdo[0x6072].raw = d.max_torque
        if self._transmit(pdo):
            d.sent_rpdo3 = frame

    def _advance_setpoint(self, d: _Drive, now: float) -> None:
        """One step of the profile position set-point handshake (lock held).

        New set-point bit up, wait for the acknowledge, bit down, wait for the acknowledge
        to drop, next set-point: the single set-point handshake of CiA 402, so no target is
        lost even if the drive is slow to take it.
        """
        if d.mode != MODE_PROFILE_POSITION or d.statusword is None:
            return
        ack = bool(d.statusword & _SW_SETPOINT_ACK)
        if d.sp_phase == _SP_REQUESTED:
            if ack or now - d.sp_since > self._SETPOINT_TIMEOUT:
                d.controlword &= ~_CW_NEW_SETPOINT
                d.sp_phase, d.sp_since = _SP_RELEASING, now
                self._send_rpdo1(d)
            return
        if d.sp_phase == _SP_RELEASING:
            if ack and now - d.sp_since <= self._SETPOINT_TIMEOUT:
                return
            d.sp_phase = _SP_IDLE
        if d.mode_display != MODE_PROFILE_POSITION:
            self._send_rpdo1(d)  # switching mode: the set-point waits for the drive to follow
            return
        if d.sp_pending is None or d.sp_pending == d.sp_sent:
            return
        target, profile = d.sp_pending
        pdo = d.node.rpdo[2]
        pdo[0x607A].raw = target
        pdo[0x6081].raw = profile
        if not self._transmit(pdo):
            return
        d.controlword |= _CW_NEW_SETPOINT
        d.sp_phase, d.sp_since = _SP_REQUESTED, now
        d.sp_sent, d.sp_pending = d.sp_pending, None
        self._send_rpdo1(d)

    def _transmit(self, pdo: PdoMap) -> bool:
        try:
            pdo.transmit()
        except (can.CanError, OSError, RuntimeError, ValueError) as exc:
            self._note_bus_error(exc)
            return False
        return True

    def _note_bus_error(self, exc: BaseException) -> None:
        with self._lock:
            if self._bus_error is None:
                # Give the adapter a moment before the first re-open (and the diagnostic a
                # chance to be seen); recover() asks for an immediate retry.
                self._next_reconnect = time.monotonic() + self._RECONNECT_PERIOD
            self._bus_error = (
                f"CAN bus {self.channel}: {exc}; check the cable, termination and that the "
                f"{self.interface} link is up (reconnecting every {self._RECONNECT_PERIOD:g} s)"
            )

    # ------------------------------------------------------------------ supervisor

    def _supervise(self, now: float) -> None:
        if not self._bus_ok(now):
            return
        for d in list(self._drives.values()):
            if self._stop.is_set():
                return
            with self._lock:
                alive = d.alive(now, self.heartbeat_timeout)
                if d.configured and not alive:
                    # Lost: stop trusting its state (read() leaves it out, commands are not
                    # sent); its next heartbeat says whether it kept its configuration.
                    if d.lost_since is None:
                        d.lost_since = d.heartbeat_at
                        d.auto_reset = True
                        d.statusword = None
                    continue
                # A drive that answered before is only retried once its heartbeat is back;
                # one that never answered is tried blind now and then (its heartbeat may be
                # off by default until we configure it).
                must_configure = (
                    not d.configured
                    and now >= d.next_config_at
                    and (alive or not d.ever_configured)
                )
            if must_configure:
                try:
                    self._configure(d)
                except Exception as exc:
                    with self._lock:
                        d.configured = False
                        d.config_error = f"{type(exc).__name__}: {exc}"
                        d.next_config_at = now + self._CONFIG_RETRY
                continue
            with self._lock:
                if d.configured and alive:
                    self._step_enable(d, now)

    def _step_enable(self, d: _Drive, now: float) -> None:
        """Walk the CiA 402 state machine one step toward OPERATION ENABLED (lock held)."""
        state = d.state
        if state is None or now - d.status_at > self.heartbeat_timeout:
            return
        word = None
        if state == "FAULT":
            comm_fault = d.error_code & 0xFF00 == 0x8100
            if d.auto_reset or comm_fault:
                # Fault reset acts on the rising edge of bit 7: drop it first if it is up.
                word = 0 if d.controlword & _CW_FAULT_RESET else _CW_FAULT_RESET
        elif state == "SWITCH ON DISABLED":
            word = _CW_SHUTDOWN
        elif state == "READY TO SWITCH ON":
            word = _CW_SWITCH_ON
        elif state in ("SWITCHED ON", "QUICK STOP ACTIVE"):
            # Enter operation in profile position with no new set-point: the drive holds.
            d.mode = MODE_PROFILE_POSITION
            d.sp_phase, d.sp_pending, d.sp_sent = _SP_IDLE, None, None
            word = _CW_ENABLE_OPERATION
        elif state == "OPERATION ENABLED":
            d.auto_reset = False
        if word is not None:
            d.controlword = word
            self._send_rpdo1(d, force=True)

    def _bus_ok(self, now: float) -> bool:
        network = self._network
        if network is None:
            return False
        notifier = network.notifier
        if self._bus_error is None and (notifier is None or notifier.exception is not None):
            self._note_bus_error(notifier.exception if notifier else RuntimeError("not receiving"))
        with self._lock:
            broken = self._bus_error is not None
            if not broken:
                return True
            if now < self._next_reconnect:
                return False
            self._next_reconnect = now + self._RECONNECT_PERIOD
        self._reconnect(network)
        return self._bus_error is None

    def _reconnect(self, network: canopen.Network) -> None:
        """Re-open the bus after an error; every drive is configured again after it."""
        self._stop_producers()
        _quietly(network.disconnect)
        try:
            network.connect(interface=self.interface, channel=self.channel, bitrate=self.bitrate)
            self._start_producers()
        except Exception as exc:
            with self._lock:
                self._bus_error = self._bus_open_hint(exc)
            return
        with self._lock:
            self._bus_error = None
            for d in self._drives.values():
                d.configured = False
                d.auto_reset = True
                d.next_config_at = 0.0
        logger.info("CAN bus %s re-opened", self.channel)

    # ------------------------------------------------------------------ diagnostics

    def _drive_diagnostic(self, d: _Drive, now: float) -> MotorDiagnostic:
        joint = d.spec.joint
        who = f"{joint}: drive node {d.node_id}"
        state = d.state
        values = {
            "node_id": str(d.node_id),
            "channel": self.channel,
            "state": state or "unknown",
            "mode": _MODE_NAMES.get(d.mode_display or 0, str(d.mode_display)),
        }
        if d.statusword is not None:
            values["statusword"] = f"0x{d.statusword:04X}"
        if d.heartbeat_at is not None:
            values["heartbeat_age"] = f"{now - d.heartbeat_at:.2f}"
        if d.error_code:
            values["error_code"] = f"0x{d.error_code:04X}"
        if d.temperature is not None:
            values["temperature"] = f"{d.temperature:.1f}"
        if d.emcys:
            values["emcy"] = ",".join(f"0x{e.code:04X}" for e in d.emcys)
        if self._bus_error:
            return MotorDiagnostic(joint, ERROR, f"{who}: unreachable, the bus is down", values)
        if d.ever_configured and d.lost_since is not None:
            silent = now - d.lost_since
            return MotorDiagnostic(
                joint,
                ERROR,
                f"{who} stopped answering (no heartbeat for {silent:.1f} s); check its power "
                "and cable, it is picked up again when it returns",
                values,
            )
        if not d.ever_configured:
            why = d.config_error or "no answer yet"
            return MotorDiagnostic(
                joint,
                ERROR if d.config_error else WARN,
                f"{who} not answering on {self.channel} ({why}); check its power, cable and "
                "node id",
                values,
            )
        if d.emcys:
            codes = "; ".join(f"0x{e.code:04X} {emcy_meaning(e.code)}" for e in d.emcys)
            return MotorDiagnostic(
                joint, ERROR, f"{who} emergency {codes}; call recover() to fault-reset", values
            )
        if state == "FAULT":
            meaning = emcy_meaning(d.error_code) if d.error_code else "no error code"
            hint = "resetting" if d.auto_reset else "call recover() to fault-reset"
            return MotorDiagnostic(
                joint, ERROR, f"{who} in FAULT (0x{d.error_code:04X} {meaning}); {hint}", values
            )
        if not d.configured or state != "OPERATION ENABLED":
            return MotorDiagnostic(joint, WARN, f"{who} enabling ({state or 'starting'})", values)
        mode = _MODE_NAMES.get(d.mode_display or 0, f"mode {d.mode_display}")
        halted = ", halted" if d.halted else ""
        return MotorDiagnostic(joint, OK, f"{who} operation enabled, {mode}{halted}", values)


class _BusErrorListener(can.Listener):
    """Turns a receive error of python-can's notifier into a bus diagnostic."""

    def __init__(self, report: Any):
        self._report = report

    def on_message_received(self, msg: can.Message) -> None:
        """Frames are canopen's business; this listener only watches for errors."""

    def on_error(self, exc: Exception) -> None:
        """Report the error; the pause keeps a dead bus from spinning the receive thread."""
        self._report(exc)
        time.sleep(0.1)


def _quietly(action: Any) -> None:
    """Run a best-effort shutdown step; a dead bus must not stop the rest of the cleanup."""
    try:
        action()
    except Exception as exc:
        logger.debug("ignored during CANopen cleanup: %s", exc)


def _weak_method(method: Any) -> Any:
    """A callable running ``method`` while its object lives (a no-op after): callbacks of the
    network and its notifier thread must not keep a dropped backend alive."""
    ref = weakref.WeakMethod(method)

    def call(*args: Any) -> None:
        bound = ref()
        if bound is not None:
            bound(*args)

    return call


def _supervise_forever(
    ref: weakref.ReferenceType[CanopenBackend], stop: threading.Event, period: float
) -> None:
    """The supervisor thread: one supervision step per period until stopped or dropped."""
    while not stop.wait(period):
        backend = ref()
        if backend is None:
            return
        try:
            backend._supervise(time.monotonic())
        except Exception as exc:  # the supervisor must outlive any one bad moment
            backend._report_fault("supervise", exc)
        del backend  # hold it only while working, so it can be collected in between
