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
torque) and SI joint units lives in :class:`~components.motors.canopen.units.Conversion`.
"""

from __future__ import annotations

import logging
import math
import threading
import time
import weakref
from pathlib import Path
from typing import Any

import can
import canopen

from components.motors.base import (
    ERROR,
    OK,
    MotorBackend,
    MotorCommand,
    MotorDiagnostic,
    MotorError,
    MotorSpec,
    MotorState,
)
from components.motors.canopen.cia402 import (
    CW_NEW_SETPOINT,
    CW_SWITCH_ON,
    MODE_PROFILE_POSITION,
    MODE_PROFILE_VELOCITY,
    SP_IDLE,
)
from components.motors.canopen.diagnostics import drive_diagnostic
from components.motors.canopen.drive import Drive
from components.motors.canopen.pdo import PdoTraffic
from components.motors.canopen.supervision import DriveSupervision, quietly, supervise_forever
from components.motors.canopen.units import Conversion
from components.motors.options import CanopenOptions

logger = logging.getLogger(__name__)

#: The minimal CiA 402 object dictionary shipped with msctl (a vendor EDS may replace it).
DEFAULT_EDS = Path(__file__).resolve().parent.parent / "cia402_drive.eds"


class CanopenBackend(PdoTraffic, DriveSupervision, MotorBackend):
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
        self._conversions = {spec.joint: Conversion.from_spec(spec) for spec in self.motors}
        self._lock = threading.RLock()
        self._network: canopen.Network | None = None
        self._drives: dict[str, Drive] = {}
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
        network.listeners.append(BusErrorListener(_weak_method(self._note_bus_error)))
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
            quietly(network.disconnect)
            raise MotorError(f"CAN bus {self.channel}: cannot set up CANopen: {exc}") from exc
        self._stop.clear()
        # The thread and every callback hold this backend weakly, so one dropped while open
        # is collected (and the base class warns and closes it).
        self._supervisor = threading.Thread(
            target=supervise_forever,
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
                    d.controlword = CW_SWITCH_ON  # disable operation: stop, brake, no torque
                    self._send_rpdo1(d, force=True)
        for d in alive:
            quietly(lambda d=d: self._release(d))
        self._stop_producers()
        network, self._network = self._network, None
        quietly(network.disconnect)
        self._drives.clear()

    def _release(self, d: Drive) -> None:
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
                    d.sp_phase, d.sp_pending, d.sp_sent = SP_IDLE, None, None
                    d.controlword &= ~CW_NEW_SETPOINT
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
                out.append(drive_diagnostic(d, now, self.channel, self._bus_error))
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

    def _add_drive(self, network: canopen.Network, spec: MotorSpec) -> Drive:
        node = canopen.RemoteNode(spec.motor_id, self.eds)
        node.sdo.RESPONSE_TIMEOUT = self.sdo_timeout
        network.add_node(node)
        conv = self._conversions[spec.joint]
        params = spec.params
        d = Drive(
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
            quietly(self._master_heartbeat.stop)
            self._master_heartbeat = None
        if self._network is not None and self.sync_period:
            quietly(self._network.sync.stop)


class BusErrorListener(can.Listener):
    """Turns a receive error of python-can's notifier into a bus diagnostic."""

    def __init__(self, report: Any):
        self._report = report

    def on_message_received(self, msg: can.Message) -> None:
        """Frames are canopen's business; this listener only watches for errors."""

    def on_error(self, exc: Exception) -> None:
        """Report the error; the pause keeps a dead bus from spinning the receive thread."""
        self._report(exc)
        time.sleep(0.1)


def _weak_method(method: Any) -> Any:
    """A callable running ``method`` while its object lives (a no-op after): callbacks of the
    network and its notifier thread must not keep a dropped backend alive."""
    ref = weakref.WeakMethod(method)

    def call(*args: Any) -> None:
        bound = ref()
        if bound is not None:
            bound(*args)

    return call
