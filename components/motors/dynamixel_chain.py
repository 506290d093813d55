"""Dynamixel Protocol 2.0 backend (G-line robots): one serial chain of X-series servos.

Everything model-specific is data: :data:`X_SERIES_REGISTERS` (control table addresses and
sizes) and :data:`MODELS` (resolution, units, torque constant, limits per model). Conversion
between register values and SI units happens only in :class:`JointUnits`.

All serial I/O runs on the backend's own I/O thread, at a steady ``cycle_period_s``
(default 10 ms); the public methods only exchange data with it and return at once, so a slow
or dead chain never delays the caller (the executor thread that also runs the joint manager).

Bus traffic per read cycle is one SYNC_READ of the contiguous block
``present_current .. present_temperature`` (addresses 126..146, 21 bytes per servo). That block
already holds temperature and input voltage, so there is no slower second cadence to schedule:
the 11 extra bytes per servo cost about 0.1 ms at 1 Mbit/s. The hardware error register (70) is
far from that block; it is read only when a status packet carries the alert bit (0x80), which
every servo sets while its hardware error status is non-zero.

The group reply is received packet by packet and sorted by servo id, rather than through
``GroupSyncRead.rxPacket``: the SDK's group receive discards the status error byte (so the alert
bit would be lost) and fails the whole group when one servo is silent, which would blind the
chain. Servos missing from the group reply get ``retries`` individual READs; if those fail too
the servo is reported not answering, left out of the group read, and pinged every
``reprobe_interval_s`` until it answers, then brought up again (mode, goal, torque).

Every servo in velocity mode has its own Bus Watchdog (register 98) armed (``bus_watchdog_ms``,
default 100 ms): if this process dies, hangs or loses the port, the servo sets its goal velocity
to 0 by itself instead of turning on at the last command. The ~100 Hz read cycle feeds it, but
only while the caller keeps calling (a hung executor must let the servos stop just as a dead
process does). Steps that can block for a whole reply timeout (retries of a silent servo,
re-probes, the boot wait in :meth:`DynamixelBackend.recover`) are each followed by a short
SYNC_READ of the armed servos, so no normal path stays silent towards them for longer than one
reply timeout (``2 * latency_timer_ms + 2`` ms) plus 10 ms. A watchdog found expired (the
register reads 0xFF and the servo ignores goals) is reported as a WARN naming the joint,
cleared and re-armed; the goal stays 0 until the next command. Position modes and
:meth:`DynamixelBackend.close` leave the watchdog off.
"""

from __future__ import annotations

import logging
import math
import threading
import time
import weakref
from dataclasses import dataclass, field
from typing import Any

from dynamixel_sdk import (
    COMM_SUCCESS,
    GroupSyncWrite,
    PacketHandler,
    PortHandler,
)
from dynamixel_sdk.protocol2_packet_handler import (
    PKT_ERROR,
    PKT_ID,
    PKT_LENGTH_H,
    PKT_LENGTH_L,
    PKT_PARAMETER0,
)

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
from components.motors.options import DynamixelOptions

log = logging.getLogger(__name__)

#: X-series (Protocol 2.0) control table: name -> (address, size in bytes).
X_SERIES_REGISTERS: dict[str, tuple[int, int]] = {
    "model_number": (0, 2),
    "firmware_version": (6, 1),
    "id": (7, 1),
    "baud_rate": (8, 1),
    "return_delay_time": (9, 1),
    "drive_mode": (10, 1),
    "operating_mode": (11, 1),
    "homing_offset": (20, 4),
    "temperature_limit": (31, 1),
    "max_voltage_limit": (32, 2),
    "min_voltage_limit": (34, 2),
    "pwm_limit": (36, 2),
    "current_limit": (38, 2),
    "velocity_limit": (44, 4),
    "max_position_limit": (48, 4),
    "min_position_limit": (52, 4),
    "shutdown": (63, 1),
    "torque_enable": (64, 1),
    "led": (65, 1),
    "status_return_level": (68, 1),
    "hardware_error_status": (70, 1),
    "bus_watchdog": (98, 1),
    "goal_pwm": (100, 2),
    "goal_current": (102, 2),
    "goal_velocity": (104, 4),
    "profile_acceleration": (108, 4),
    "profile_velocity": (112, 4),
    "goal_position": (116, 4),
    "realtime_tick": (120, 2),
    "moving": (122, 1),
    "moving_status": (123, 1),
    "present_pwm": (124, 2),
    "present_current": (126, 2),
    "present_velocity": (128, 4),
    "present_position": (132, 4),
    "velocity_trajectory": (136, 4),
    "position_trajectory": (140, 4),
    "present_input_voltage": (144, 2),
    "present_temperature": (146, 1),
}

#: Registers whose raw value is two's-complement signed.
SIGNED_REGISTERS = frozenset(
    {
        "homing_offset",
        "goal_current",
        "goal_velocity",
        "goal_position",
        "present_pwm",
        "present_current",
        "present_velocity",
        "present_position",
        "velocity_trajectory",
        "position_trajectory",
        "max_position_limit",
        "min_position_limit",
    }
)

#: Operating Mode (address 11) values by name.
OPERATING_MODES: dict[str, int] = {
    "current": 0,
    "velocity": 1,
    "position": 3,
    "extended_position": 4,
    "current_position": 5,
    "pwm": 16,
}
POSITION_MODES = frozenset({3, 4, 5})
VELOCITY_MODE = OPERATING_MODES["velocity"]

#: Hardware Error Status (address 70) bit -> meaning.
HARDWARE_ERROR_BITS: dict[int, str] = {
    0: "input voltage error",
    2: "overheating",
    3: "motor encoder error",
    4: "electrical shock",
    5: "overload",
}
ALERT_BIT = 0x80

#: Bus Watchdog (address 98): one unit in ms, the largest period in units, and the value the
#: servo shows once it has expired (-1 as a signed byte) until 0 is written.
BUS_WATCHDOG_UNIT_MS = 20
BUS_WATCHDOG_MAX_UNITS = 127
BUS_WATCHDOG_EXPIRED = 0xFF
#: How long the "stopped by its bus watchdog" warning stays in the diagnostics: long enough
#: for a 1 Hz diagnostics publisher to carry it a few times.
WATCHDOG_REPORT_S = 5.0
#: Silence towards an armed servo after which a slow step is followed by a feeding SYNC_READ:
#: above one normal cycle's bus time (a few ms), far below any useful watchdog period.
FEED_AFTER_S = 0.01

#: The block read every cycle: present current up to and including present temperature.
READ_BLOCK_START = X_SERIES_REGISTERS["present_current"][0]
READ_BLOCK_LENGTH = X_SERIES_REGISTERS["present_temperature"][0] + 1 - READ_BLOCK_START


def to_signed(value: int, size: int) -> int:
    """Two's-complement interpretation of an unsigned little-endian register value."""
    bits = 8 * size
    return value - (1 << bits) if value & (1 << (bits - 1)) else value


def hardware_error_text(bits: int) -> str:
    """Human meaning of a Hardware Error Status value, e.g. ``"overheating, overload"``."""
    names = [text for bit, text in HARDWARE_ERROR_BITS.items() if bits & (1 << bit)]
    unknown = bits & ~sum(1 << bit for bit in HARDWARE_ERROR_BITS)
    if unknown:
        names.append(f"unknown bits 0x{unknown:02x}")
    return ", ".join(names)


@dataclass(frozen=True)
class DynamixelModel:
    """Constants of one servo model (data only; :class:`JointUnits` converts).

    Attributes:
        name: Model key as written in module data (``MotorSpec.model``).
        model_number: What PING and register 0 report.
        ticks_per_rev: Encoder ticks per output revolution.
        center_tick: Tick that is 0 rad in raw joint space (the middle of the single-turn
            range, so a joint's limits sit symmetric around zero as in ROBOTIS' own tools).
        velocity_unit_rpm: One Goal/Present Velocity unit, in rev/min.
        effort_register: ``"current"`` (Present Current in ``current_unit_a``) or ``"load"``
            (XL430: Present Load in 0.1 % of stall torque).
        current_unit_a: One Present/Goal Current unit, in ampere.
        torque_constant: N·m per ampere at the output (stall torque / stall current).
        stall_torque: N·m at rated voltage from the datasheet (load-reporting models use it).
        no_load_speed_rpm: Output speed at rated voltage without load (emulator motion limit).
        temperature_limit: Default Temperature Limit (register 31), °C.
        registers: Control table of the family.
    """

    name: str
    model_number: int
    ticks_per_rev: int = 4096
    center_tick: int = 2048
    velocity_unit_rpm: float = 0.229
    effort_register: str = "current"
    current_unit_a: float = 2.69e-3
    torque_constant: float = 1.0
    stall_torque: float = 1.0
    no_load_speed_rpm: float = 46.0
    temperature_limit: int = 80
    registers: dict[str, tuple[int, int]] = field(default_factory=lambda: X_SERIES_REGISTERS)


@dataclass(frozen=True)
class JointUnits:
    """The one place register values become SI joint units (and back) for one servo.

    Attributes:
        model: The servo's model constants.
        torque_constant: N·m per ampere (the model's unless module data overrides it).
        joint_per_rad: Joint units per output radian: 1 for a revolute joint, metres per
            radian for a linear one (a gripper's rack and pinion), which makes positions metres,
            velocities m/s and efforts newtons.
    """

    model: DynamixelModel
    torque_constant: float
    joint_per_rad: float = 1.0

    def position(self, ticks: int) -> float:
        """Present/Goal Position ticks to joint position (rad, or m for a linear joint)."""
        rad = (ticks - self.model.center_tick) * 2.0 * math.pi / self.model.ticks_per_rev
        return rad * self.joint_per_rad

    def position_ticks(self, position: float) -> int:
        """Joint position to Goal Position ticks (rounded)."""
        rad = position / self.joint_per_rad
        return round(self.model.center_tick + rad * self.model.ticks_per_rev / (2.0 * math.pi))

    def velocity(self, units: int) -> float:
        """Present/Goal Velocity units to joint velocity (rad/s or m/s)."""
        return units * self.model.velocity_unit_rpm * 2.0 * math.pi / 60.0 * self.joint_per_rad

    def velocity_units(self, velocity: float) -> int:
        """Joint velocity to Goal/Profile Velocity units (rounded)."""
        rad_s = velocity / self.joint_per_rad
        return round(rad_s * 60.0 / (2.0 * math.pi * self.model.velocity_unit_rpm))

    def effort(self, raw: int) -> float:
        """Present Current (or Present Load) to joint effort (N·m, or N for a linear joint)."""
        if self.model.effort_register == "load":
            nm = raw * 1e-3 * self.model.stall_torque
        else:
            nm = raw * self.model.current_unit_a * self.torque_constant
        return nm / self.joint_per_rad


#: Known models. Torque constants are stall torque / stall current at rated voltage (12 V; 5 V
#: for XL330) from the ROBOTIS e-manual datasheets: good to ~10 %, which is what a
#: current-based effort estimate gives anyway.
MODELS: dict[str, DynamixelModel] = {
    model.name: model
    for model in (
        DynamixelModel(
            "XM430-W350", 1020, torque_constant=4.1 / 2.3, stall_torque=4.1, no_load_speed_rpm=46.0
        ),
        DynamixelModel(
            "XM430-W210", 1030, torque_constant=3.0 / 2.3, stall_torque=3.0, no_load_speed_rpm=77.0
        ),
        DynamixelModel(
            "XM540-W270",
            1120,
            torque_constant=10.6 / 4.4,
            stall_torque=10.6,
            no_load_speed_rpm=30.0,
        ),
        DynamixelModel(
            "XM540-W150", 1130, torque_constant=7.3 / 4.4, stall_torque=7.3, no_load_speed_rpm=53.0
        ),
        DynamixelModel(
            "XH430-W350",
            1010,
            current_unit_a=1.34e-3,
            torque_constant=3.4 / 1.3,
            stall_torque=3.4,
            no_load_speed_rpm=46.0,
        ),
        DynamixelModel(
            "XL430-W250",
            1060,
            effort_register="load",
            stall_torque=1.5,
            no_load_speed_rpm=57.0,
            temperature_limit=72,
        ),
        DynamixelModel(
            "XL330-M288",
            1200,
            current_unit_a=1.0e-3,
            torque_constant=0.52 / 1.47,
            stall_torque=0.52,
            no_load_speed_rpm=103.0,
            temperature_limit=70,
        ),
    )
}

MODELS_BY_NUMBER: dict[int, DynamixelModel] = {m.model_number: m for m in MODELS.values()}


class _NoAnswer(Exception):
    """A servo did not answer (or answered garbage) during a multi-step exchange."""


@dataclass
class _Servo:
    """Backend-side knowledge of one servo: what we commanded and what it last said."""

    spec: MotorSpec
    model: DynamixelModel
    position_mode: int
    profile_velocity: float | None
    temperature_limit: float
    units: JointUnits
    mode: int | None = None
    answering: bool = False
    ever_answered: bool = False
    next_probe: float = 0.0
    hardware_error: int = 0
    next_status_read: float = 0.0
    torque_on: bool = False
    min_ticks: int = -(2**31)
    max_ticks: int = 2**31 - 1
    velocity_limit: int = 2**31 - 1
    state: MotorState | None = None
    state_at: float = 0.0
    voltage: float | None = None
    model_number: int | None = None
    note: str = ""
    sent_at: float = 0.0
    watchdog_units: int = 0
    next_watchdog_check: float = 0.0
    watchdog_trips: int = 0
    watchdog_report: str = ""
    watchdog_gap: float | None = None
    watchdog_report_until: float = 0.0

    @property
    def sid(self) -> int:
        return self.spec.motor_id

    @property
    def joint(self) -> str:
        return self.spec.joint


class DynamixelBackend(MotorBackend):
    """A serial chain of Dynamixel X-series servos spoken to in Protocol 2.0.

    All serial I/O runs on the backend's own I/O thread, as CANopen's supervisor does: it runs
    the read cycle every ``cycle_period_s`` and applies what the public methods queued. Those
    only exchange data with it under a lock and return at once, so a slow or dead chain (each
    exchange with a silent servo waits a whole reply timeout) never delays the caller's
    thread. :meth:`read` and :meth:`diagnostics` return what the latest cycle found;
    :meth:`write` keeps the newest command per joint; :meth:`halt` drops the commands still
    queued and is acted on next, even in the middle of a slow step; :meth:`recover` runs on
    the thread.

    The servos' own Bus Watchdog still guards a caller that dies or hangs: the thread talks
    to a servo whose watchdog is armed only while the caller keeps calling (any public
    method, at least every half watchdog period), so a hung executor lets those servos stop
    as if this process had stopped.

    Args:
        channel: Serial device of the chain (``/dev/ttyUSB0``, a U2D2, or a pty slave path).
        motors: One :class:`MotorSpec` per servo. ``model`` is a key of :data:`MODELS`;
            ``params`` may hold ``operating_mode`` (``"position"`` default,
            ``"extended_position"`` or ``"current_position"``: the mode used for position
            commands), ``profile_velocity`` (rad/s cap on position moves; absent = the servo's
            Velocity Limit), ``temperature_limit`` (°C, overrides the model's) and
            ``torque_constant`` (N·m/A, overrides the model's) and ``meters_per_rad`` (a
            linear joint such as a rack-and-pinion finger: positions in m, efforts in N).
        options: :class:`~components.motors.options.DynamixelOptions` (or a mapping of its
            keys): every key, default and meaning is documented there. Keep
            ``bus_watchdog_ms`` well above the cycle period and the reply timeout
            ``2 * latency_timer_ms + 2``.
    """

    backend_name = "dynamixel"
    options: DynamixelOptions

    def __init__(
        self,
        channel: str,
        motors: list[MotorSpec],
        options: DynamixelOptions | dict[str, Any] | None = None,
    ):
        super().__init__(channel, motors, options)
        opts = self.options
        self.baudrate = opts.baudrate
        self.latency_timer_ms = opts.latency_timer_ms
        self.retries = opts.retries
        self.reprobe_interval = opts.reprobe_interval_s
        self.status_interval = opts.status_interval_s
        self.boot_timeout = opts.boot_timeout_s
        self.reopen_interval = opts.reopen_interval_s
        self.hold_on_close = opts.hold_on_close
        self.bus_watchdog_ms = opts.bus_watchdog_ms
        self.cycle_period = opts.cycle_period_s
        self.stale_after = opts.stale_after_s
        # Everything below the lock is owned by the I/O thread (by the caller only before
        # the thread starts and after it ends).
        self._watchdog_units = 0
        self._port: PortHandler | None = None
        self._packet = PacketHandler(2.0)
        self._servos: list[_Servo] = []
        self._by_joint: dict[str, _Servo] = {}
        self._by_id: dict[int, _Servo] = {}
        self._bus_error = ""
        self._next_reopen = 0.0
        self._next_cycle = 0.0
        self._halts = 0
        self._recent_pause = 0.0
        self._bus_shut = True
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._wake = threading.Event()
        # Exchanged with the I/O thread under _io_lock.
        self._io_lock = threading.Lock()
        self._pending: dict[str, MotorCommand] = {}
        self._halt_asked = False
        self._recover_asked = False
        self._last_call = 0.0
        self._caller_pause = 0.0
        self._states: dict[str, tuple[float, MotorState]] = {}
        self._diags: list[MotorDiagnostic] = []
        self._published_at = 0.0

    # -- lifecycle (caller's thread) ------------------------------------------------------

    def _open(self) -> None:
        """Open the port, ping every servo, set its operating mode, hold position, enable
        torque, read the chain once, then start the I/O thread.

        Raises:
            MotorError: If a motor's model is unknown or the serial port cannot be opened.
        """
        self._watchdog_units = self._bus_watchdog_units()
        self._servos = [self._make_servo(spec) for spec in self.motors]
        self._by_joint = {s.joint: s for s in self._servos}
        self._by_id = {s.sid: s for s in self._servos}
        try:
            self._open_port()
        except MotorError:
            raise
        except Exception as exc:
            raise MotorError(self._port_error_text(exc)) from exc
        now = time.monotonic()
        try:
            for servo in self._servos:
                # A reply that comes late once (a busy computer, a long cable) must not leave
                # the servo limp until the next re-probe: try again at once, a few times.
                for _ in range(1 + max(self.retries, 0)):
                    if self._probe(servo, now):
                        break
        except Exception as exc:
            # The device opened but is not a working serial line (or vanished at once).
            self._close_port()
            raise MotorError(self._port_error_text(exc)) from exc
        self._bus_shut = False
        with self._io_lock:
            self._pending.clear()
            self._halt_asked = self._recover_asked = False
            self._last_call = time.monotonic()
            self._caller_pause = 0.0
        # The first cycle here, so the first read() after open already has every servo.
        try:
            self._read_cycle(time.monotonic())
        except Exception as exc:
            self._bus_lost(exc)
        self._publish()
        self._next_cycle = time.monotonic() + self.cycle_period
        self._stop = threading.Event()
        self._wake = threading.Event()
        # The thread holds the backend weakly, so one dropped while open is collected (and
        # the base class warns and closes it).
        self._thread = threading.Thread(
            target=_run_io,
            args=(weakref.ref(self), self._stop, self._wake),
            name=f"dynamixel-io {self.channel}",
            daemon=True,
        )
        self._thread.start()

    def _close(self) -> None:
        """Stop the I/O thread, which torques off every answering servo (or holds, with
        ``hold_on_close``) and releases the port."""
        self._stop.set()
        self._wake.set()
        thread, self._thread = self._thread, None
        if thread is None or thread is threading.current_thread() or not thread.is_alive():
            self._shutdown_bus()  # no thread left to do it (or this is it, collecting us)
            return
        # Bounded by the slowest step: a boot wait plus a reply timeout per servo.
        thread.join(timeout=self.boot_timeout + 2.0 + len(self._servos) * self._reply_timeout())
        if thread.is_alive():
            log.warning(
                "%s: the I/O thread is still in a slow step; it stops the servos and closes "
                "the port when that step ends",
                self.channel,
            )

    def _shutdown_bus(self) -> None:
        """Torque off (or hold) every answering servo and release the port. Once per open."""
        if self._bus_shut:
            return
        self._bus_shut = True
        answering = [s for s in self._servos if s.answering]
        try:
            if self._port is not None and self._port.is_open:
                if self.hold_on_close:
                    # Holding a velocity means turning on: those servos hold still instead.
                    self._sync_write(
                        "goal_velocity", {s.sid: 0 for s in answering if s.mode == VELOCITY_MODE}
                    )
                else:
                    self._sync_write("torque_enable", {s.sid: 0 for s in answering})
                # Off only after torque off (or goal 0), so no moment runs unguarded. Left
                # armed, it would expire once the port is closed and make the servo refuse
                # the goals of whoever opens the chain next.
                self._sync_write("bus_watchdog", {s.sid: 0 for s in answering if s.watchdog_units})
        except Exception as exc:
            log.warning("%s: stopping the servos on close failed: %s", self.channel, exc)
        for servo in self._servos:
            servo.watchdog_units = 0
            if not self.hold_on_close:
                servo.torque_on = False
        self._close_port()

    # -- the public side: exchange with the I/O thread, never wait on the bus -------------

    def _note_call(self) -> None:
        """The caller is alive: armed servos may keep hearing from the I/O thread."""
        now = time.monotonic()
        with self._io_lock:
            silent = now - self._last_call
            if silent > self._caller_timeout():
                self._caller_pause = max(self._caller_pause, silent)
            self._last_call = now

    def _read(self) -> dict[str, MotorState]:
        """The state of every answering servo from the latest cycle (none older than
        ``stale_after_s``: a stalled chain's last reading is not passed off as fresh)."""
        self._note_call()
        now = time.monotonic()
        with self._io_lock:
            return {
                joint: state
                for joint, (at, state) in self._states.items()
                if now - at <= self.stale_after
            }

    def _write(self, commands: list[MotorCommand]) -> None:
        """Queue goal positions and goal velocities (the newest per joint wins).

        The I/O thread sync-writes them. A joint commanded by velocity while in a position
        mode (or the reverse) is switched first: torque off, Operating Mode, the new goal,
        torque on (the servo refuses mode writes while torque is on). ``effort`` is ignored:
        X-series take a current goal only in current-based position mode, which needs gains
        tuned per joint.
        """
        self._note_call()
        with self._io_lock:
            for command in commands:
                self._pending[command.joint] = command
        self._wake.set()

    def _halt(self) -> None:
        """Hold where each servo is now (goal position = present, goal velocity 0).

        Commands still queued are dropped (the halt wins over them); the I/O thread acts on
        the halt next, between two exchanges even in the middle of a slow step.
        """
        self._note_call()
        with self._io_lock:
            self._pending.clear()
            self._halt_asked = True
        self._wake.set()

    def _recover(self) -> None:
        """Reboot servos with hardware errors, then restore their mode, goal and torque.

        Servos that are silent are pinged now rather than at their next re-probe time; a
        lost port is reopened now. Runs on the I/O thread.
        """
        self._note_call()
        with self._io_lock:
            self._recover_asked = True
        self._wake.set()

    def _diagnostics(self) -> list[MotorDiagnostic]:
        """One entry for the bus (``joint == ""``) and one per joint, as of the last cycle."""
        self._note_call()
        now = time.monotonic()
        with self._io_lock:
            diags = list(self._diags)
            silent = now - self._published_at
        if silent > self._stall_after():
            values = {"channel": self.channel, "stalled_s": f"{silent:.1f}"}
            diags.insert(
                0,
                MotorDiagnostic(
                    "",
                    ERROR,
                    f"dynamixel bus {self.channel}: the I/O thread has not finished a step for "
                    f"{silent:.1f} s; readings are stale (check the USB adapter)",
                    values,
                ),
            )
        return diags

    # -- the I/O thread -------------------------------------------------------------------

    def _reply_timeout(self) -> float:
        """Seconds one exchange with a silent servo waits (the port's packet timeout)."""
        return (2.0 * self.latency_timer_ms + 2.0) / 1000.0

    def _caller_timeout(self) -> float:
        """Caller silence after which armed servos stop hearing from the I/O thread."""
        if not self._watchdog_units:
            return math.inf
        return self._watchdog_units * BUS_WATCHDOG_UNIT_MS / 1000.0 / 2.0

    def _stall_after(self) -> float:
        """How long one step may take before diagnostics call the I/O thread stalled: well
        beyond the slowest normal step (a boot wait, every servo silent with retries)."""
        per_round = len(self._servos) * (2 + max(self.retries, 0)) * self._reply_timeout()
        return 2.0 + self.boot_timeout + 2.0 * per_round

    def _caller_live(self) -> bool:
        # A float read without the lock: the writer replaces it whole.
        return time.monotonic() - self._last_call <= self._caller_timeout()

    def _talks_to(self, servo: _Servo) -> bool:
        """Whether the thread may send to ``servo`` now: a servo with an armed watchdog only
        hears from this backend while the caller is alive, so a hung caller lets it stop."""
        return not servo.watchdog_units or self._caller_live()

    def _io_step(self) -> None:
        """One turn of the I/O thread: a halt, the queued writes, a recover, then the read
        cycle when it is due; then publish what the caller may see."""
        now = time.monotonic()
        with self._io_lock:
            halt, self._halt_asked = self._halt_asked, False
            writes = list(self._pending.values())
            self._pending.clear()
            recover, self._recover_asked = self._recover_asked, False
            pause, self._caller_pause = self._caller_pause, 0.0
        self._recent_pause = max(self._recent_pause, pause)
        try:
            if halt:
                self._do_halt()
            if writes and self._port is not None:
                self._write_commands(writes)
            if recover:
                self._do_recover(time.monotonic())
            if now >= self._next_cycle:
                # Steady period; after a slow step, start again from now rather than burst.
                self._next_cycle = max(self._next_cycle + self.cycle_period, now)
                self._read_cycle(now)
        except Exception as exc:
            self._bus_lost(exc)
        self._publish()

    def _halt_if_asked(self) -> None:
        """Act on a halt queued while the thread is busy (called between exchanges)."""
        if not self._halt_asked:  # read without the lock: a halt seen next time is fine
            return
        with self._io_lock:
            halt, self._halt_asked = self._halt_asked, False
        if halt:
            self._do_halt()

    def _do_halt(self) -> None:
        """Velocity servos to goal 0 at once, position servos to where they are now."""
        self._halts += 1
        if self._port is None:
            return
        answering = [s for s in self._servos if s.answering]
        self._sync_write("goal_velocity", {s.sid: 0 for s in answering if s.mode == VELOCITY_MODE})
        holding = [s for s in answering if s.mode != VELOCITY_MODE]
        replies = self._sync_read_block(holding)
        stamp = time.time()
        positions: dict[int, int] = {}
        for servo in holding:
            if servo.sid in replies:
                self._decode(servo, replies[servo.sid][0], stamp)
            if servo.state is not None and servo.state.position is not None:
                positions[servo.sid] = self._clamp_ticks(
                    servo, servo.units.position_ticks(servo.state.position)
                )
        self._sync_write("goal_position", positions)

    def _do_recover(self, now: float) -> None:
        if self._port is None:
            self._try_reopen(now, force=True)
            return
        rebooted: list[_Servo] = []
        for servo in self._servos:
            if servo.answering and servo.hardware_error:
                servo.sent_at = time.monotonic()
                result, _ = self._packet.reboot(self._port, servo.sid)
                self._release()
                log.info(
                    "%s: reboot servo id %d -> %s",
                    servo.joint,
                    servo.sid,
                    self._packet.getTxRxResult(result),
                )
                rebooted.append(servo)
        deadline = time.monotonic() + self.boot_timeout
        for servo in rebooted:
            servo.hardware_error = 0
            servo.answering = False
            servo.watchdog_units = 0  # a reboot resets RAM, the watchdog included
            while not self._probe(servo, time.monotonic()) and time.monotonic() < deadline:
                self._feed_watchdogs()  # the boot wait must not starve the other servos
                if self._stop.wait(0.02):
                    return
            self._feed_watchdogs()
        rebooted_ids = {s.sid for s in rebooted}
        for servo in self._servos:
            if not servo.answering and servo.sid not in rebooted_ids:
                if self._talks_to(servo):
                    self._probe(servo, time.monotonic())
            elif servo.answering and not servo.torque_on:
                self._bring_up_or_drop(servo, time.monotonic())
            self._feed_watchdogs()

    def _publish(self) -> None:
        """Hand the caller this step's readings and health (new objects: never shared)."""
        states = {
            s.joint: (s.state_at, s.state)
            for s in self._servos
            if s.answering and s.state is not None
        }
        diags = [self._bus_diagnostic()] + [self._servo_diagnostic(s) for s in self._servos]
        with self._io_lock:
            self._states = states
            self._diags = diags
            self._published_at = time.monotonic()

    def _bus_diagnostic(self) -> MotorDiagnostic:
        answering = sum(s.answering for s in self._servos)
        bus_values = {"channel": self.channel, "baudrate": str(self.baudrate)}
        if self._bus_error:
            return MotorDiagnostic(
                "",
                ERROR,
                f"dynamixel bus {self.channel} lost ({self._bus_error}); reopening every "
                f"{self.reopen_interval:g} s: check the USB cable and adapter power",
                bus_values,
            )
        if answering < len(self._servos):
            return MotorDiagnostic(
                "",
                WARN,
                f"dynamixel bus {self.channel}: {answering}/{len(self._servos)} servos answering",
                bus_values,
            )
        return MotorDiagnostic(
            "", OK, f"dynamixel bus {self.channel}: {answering} servos answering", bus_values
        )

    # -- construction helpers -------------------------------------------------------------

    def _make_servo(self, spec: MotorSpec) -> _Servo:
        model = MODELS.get(spec.model)
        if model is None:
            raise MotorError(
                f"{spec.joint}: unknown Dynamixel model {spec.model!r} on {self.channel}; "
                f"known: {', '.join(sorted(MODELS))} (fix the module data's motor model, or add "
                f"the model to components/motors/dynamixel_chain.py MODELS)"
            )
        mode_name = spec.params.get("operating_mode", "position")
        mode = OPERATING_MODES.get(mode_name)
        if mode not in POSITION_MODES:
            raise MotorError(
                f"{spec.joint}: operating_mode {mode_name!r} is not a position mode; use one of "
                "position, extended_position, current_position"
            )
        profile = spec.params.get("profile_velocity")
        return _Servo(
            spec=spec,
            model=model,
            position_mode=mode,
            profile_velocity=None if profile is None else float(profile),
            temperature_limit=float(spec.params.get("temperature_limit", model.temperature_limit)),
            units=JointUnits(
                model,
                torque_constant=float(spec.params.get("torque_constant", model.torque_constant)),
                joint_per_rad=float(spec.params.get("meters_per_rad", 1.0)),
            ),
        )

    def _bus_watchdog_units(self) -> int:
        """``bus_watchdog_ms`` (range-checked by its options type) as Bus Watchdog units."""
        ms = self.bus_watchdog_ms
        if ms == 0.0:
            return 0
        units = max(1, round(ms / BUS_WATCHDOG_UNIT_MS))
        # Steps that wait for a silent servo block for one reply timeout: a period that short
        # would trip on a lost reply rather than on a dead process.
        reply_timeout_ms = 2.0 * self.latency_timer_ms + 2.0
        if units * BUS_WATCHDOG_UNIT_MS < 1.25 * reply_timeout_ms:
            log.warning(
                "%s: bus_watchdog_ms %d is close to the reply timeout (%.0f ms): a silent servo "
                "may trip the watchdog of the others; raise it or lower latency_timer_ms",
                self.channel,
                units * BUS_WATCHDOG_UNIT_MS,
                reply_timeout_ms,
            )
        return units

    def _port_error_text(self, exc: object) -> str:
        return (
            f"cannot open Dynamixel port {self.channel} at {self.baudrate} baud ({exc}); check "
            f"that the U2D2/USB adapter is plugged in and the path exists (ls -l {self.channel}), "
            "and that your user may open it (sudo usermod -aG dialout $USER, then log in again)"
        )

    def _open_port(self) -> None:
        port = _LatencyAwarePort(self.channel, self.latency_timer_ms)
        if not port.setBaudRate(self.baudrate):
            raise MotorError(
                f"cannot open Dynamixel port {self.channel}: baud rate {self.baudrate} is not one "
                "the SDK supports; use 57600, 115200, 1000000, 2000000, 3000000 or 4000000"
            )
        self._port = port
        self._bus_error = ""

    def _close_port(self) -> None:
        port, self._port = self._port, None
        if port is not None and port.ser is not None:
            try:
                port.closePort()
            except Exception as exc:
                log.debug("%s: close failed: %s", self.channel, exc)

    def _bus_lost(self, exc: BaseException) -> None:
        """Any exception from the SDK or pyserial: report, drop the port, reopen later."""
        log.warning("%s: bus error: %s", self.channel, exc)
        self._bus_error = str(exc) or type(exc).__name__
        for servo in self._servos:
            servo.answering = False
            servo.torque_on = False
        self._close_port()
        self._next_reopen = time.monotonic() + self.reopen_interval

    def _try_reopen(self, now: float, force: bool = False) -> None:
        if not force and now < self._next_reopen:
            return
        self._next_reopen = now + self.reopen_interval
        try:
            self._open_port()
        except Exception as exc:
            self._bus_error = str(exc)
            return
        for servo in self._servos:
            if self._talks_to(servo):
                self._probe(servo, now)
            self._feed_watchdogs()

    # -- low-level exchanges --------------------------------------------------------------

    def _mark_sent(self, ids: Any) -> None:
        """Note that an instruction including these servo ids goes out now (feeds watchdogs)."""
        now = time.monotonic()
        for sid in ids:
            servo = self._by_id.get(sid)
            if servo is not None:
                servo.sent_at = now

    def _release(self) -> None:
        # The SDK marks the port busy per transaction and clears it on the happy paths only;
        # an exception mid-transaction would otherwise leave every later call COMM_PORT_BUSY.
        if self._port is not None:
            self._port.is_using = False

    def _read_register(self, servo: _Servo, name: str) -> tuple[int, int]:
        """(value, status error byte) of one register; raises _NoAnswer when silent."""
        address, size = servo.model.registers[name]
        servo.sent_at = time.monotonic()
        data, result, error = self._packet.readTxRx(self._port, servo.sid, address, size)
        self._release()
        if result != COMM_SUCCESS or len(data) != size:
            raise _NoAnswer(self._packet.getTxRxResult(result))
        value = int.from_bytes(bytes(data), "little")
        if name in SIGNED_REGISTERS:
            value = to_signed(value, size)
        return value, error

    def _write_register(self, servo: _Servo, name: str, value: int) -> int:
        """Write one register and return the status error byte; raises _NoAnswer when silent."""
        address, size = servo.model.registers[name]
        data = list((value & ((1 << (8 * size)) - 1)).to_bytes(size, "little"))
        servo.sent_at = time.monotonic()
        result, error = self._packet.writeTxRx(self._port, servo.sid, address, size, data)
        self._release()
        if result != COMM_SUCCESS:
            raise _NoAnswer(self._packet.getTxRxResult(result))
        if error & 0x7F:
            servo.note = f"write {name}={value}: {self._packet.getRxPacketError(error & 0x7F)}"
            log.warning("%s: servo id %d %s", servo.joint, servo.sid, servo.note)
        return error

    def _sync_write(self, name: str, values: dict[int, int]) -> None:
        if not values or self._port is None:
            return
        address, size = X_SERIES_REGISTERS[name]
        group = GroupSyncWrite(self._port, self._packet, address, size)
        mask = (1 << (8 * size)) - 1
        for sid, value in values.items():
            group.addParam(sid, list((value & mask).to_bytes(size, "little")))
        self._mark_sent(values)
        result = group.txPacket()
        self._release()
        if result != COMM_SUCCESS:
            raise OSError(f"sync write {name} failed: {self._packet.getTxRxResult(result)}")

    def _sync_read_block(self, servos: list[_Servo]) -> dict[int, tuple[bytes, int]]:
        """SYNC_READ the state block; servo id -> (data, status error byte) for each reply."""
        if not servos:
            return {}
        ids = [s.sid for s in servos]
        self._mark_sent(ids)
        result = self._packet.syncReadTx(
            self._port, READ_BLOCK_START, READ_BLOCK_LENGTH, ids, len(ids), False
        )
        if result != COMM_SUCCESS:
            self._release()
            raise OSError(f"sync read failed: {self._packet.getTxRxResult(result)}")
        replies: dict[int, tuple[bytes, int]] = {}
        wanted = set(ids)
        # Replies come back in id order. A silent servo leaves a gap (later replies still come
        # within the group timeout) or, on some firmware, ends the reply; either way keep what
        # arrived, and the caller reads the missing servos one by one.
        while len(replies) < len(ids):
            packet, result = self._packet.rxPacket(self._port, False)
            if result != COMM_SUCCESS:
                break
            sid = packet[PKT_ID]
            length = (packet[PKT_LENGTH_L] | packet[PKT_LENGTH_H] << 8) - 4
            if sid in wanted and length == READ_BLOCK_LENGTH:
                start = PKT_PARAMETER0 + 1
                replies[sid] = (bytes(packet[start : start + length]), packet[PKT_ERROR])
        self._release()
        return replies

    def _read_block_single(self, servo: _Servo) -> tuple[bytes, int] | None:
        servo.sent_at = time.monotonic()
        data, result, error = self._packet.readTxRx(
            self._port, servo.sid, READ_BLOCK_START, READ_BLOCK_LENGTH
        )
        self._release()
        if result != COMM_SUCCESS or len(data) != READ_BLOCK_LENGTH:
            return None
        return bytes(data), error

    # -- bring-up and liveness ------------------------------------------------------------

    def _probe(self, servo: _Servo, now: float) -> bool:
        """Ping a servo; if it answers, bring it up. Returns whether it is answering now."""
        servo.next_probe = now + self.reprobe_interval
        if self._port is None:
            return False
        servo.sent_at = time.monotonic()
        model_number, result, error = self._packet.ping(self._port, servo.sid)
        self._release()
        if result != COMM_SUCCESS:
            servo.answering = False
            return False
        servo.model_number = model_number
        return self._bring_up_or_drop(servo, now, error)

    def _bring_up_or_drop(self, servo: _Servo, now: float, status_error: int = 0) -> bool:
        try:
            self._bring_up(servo, status_error)
        except _NoAnswer as exc:
            log.info("%s: servo id %d dropped during bring-up: %s", servo.joint, servo.sid, exc)
            servo.answering = False
            servo.torque_on = False
            servo.next_probe = now + self.reprobe_interval
            return False
        return True

    def _bring_up(self, servo: _Servo, status_error: int) -> None:
        """Mode, limits, goal = present, profile, torque on. Raises _NoAnswer if it goes silent."""
        servo.note = ""
        if status_error & ALERT_BIT:
            servo.hardware_error, _ = self._read_register(servo, "hardware_error_status")
        else:
            servo.hardware_error = 0
        target_mode = servo.mode if servo.mode is not None else servo.position_mode
        self._set_mode(servo, target_mode, goal=None)
        servo.min_ticks, _ = self._read_register(servo, "min_position_limit")
        servo.max_ticks, _ = self._read_register(servo, "max_position_limit")
        servo.velocity_limit, _ = self._read_register(servo, "velocity_limit")
        if servo.profile_velocity is not None:
            profile = abs(servo.units.velocity_units(servo.profile_velocity))
            self._write_register(servo, "profile_velocity", profile)
        self._enable_torque(servo)
        servo.answering = True
        servo.ever_answered = True
        if servo.hardware_error:
            servo.next_status_read = time.monotonic() + self.status_interval

    def _set_mode(self, servo: _Servo, mode: int, goal: int | None) -> None:
        """Put the servo in ``mode`` with a goal that holds still (or ``goal``), torque off.

        The servo only accepts Operating Mode with torque off, and on torque on it drives to
        whatever goal is in its RAM, so the goal is written before torque comes back.
        """
        self._write_register(servo, "torque_enable", 0)
        servo.torque_on = False
        # Cleared first: after an expiry the servo ignores goal writes until it reads 0.
        self._disarm_watchdog(servo)
        current, _ = self._read_register(servo, "operating_mode")
        if current != mode:
            self._write_register(servo, "operating_mode", mode)
        servo.mode = mode
        if mode == VELOCITY_MODE:
            self._write_register(servo, "goal_velocity", 0 if goal is None else goal)
            if self._watchdog_units:
                # Armed with torque still off: it starts counting when torque comes on.
                self._write_register(servo, "bus_watchdog", self._watchdog_units)
                servo.watchdog_units = self._watchdog_units
                servo.next_watchdog_check = time.monotonic() + self.status_interval
        else:
            if goal is None:
                goal, _ = self._read_register(servo, "present_position")
            self._write_register(servo, "goal_position", goal)

    def _disarm_watchdog(self, servo: _Servo) -> None:
        """Bus Watchdog to 0, reporting an expiry found on the way (e.g. after a lost bus)."""
        value, _ = self._read_register(servo, "bus_watchdog")
        if value == BUS_WATCHDOG_EXPIRED:
            self._report_trip(servo, servo.watchdog_units or self._watchdog_units, None, "cleared")
        if value:
            self._write_register(servo, "bus_watchdog", 0)
        servo.watchdog_units = 0

    def _report_trip(self, servo: _Servo, units: int, gap: float | None, action: str) -> None:
        period = f" (no command for {units * BUS_WATCHDOG_UNIT_MS} ms)" if units else ""
        servo.watchdog_trips += 1
        servo.watchdog_gap = gap
        servo.watchdog_report = (
            f"{servo.joint}: servo id {servo.sid} stopped by its bus watchdog{period}; {action}"
        )
        servo.watchdog_report_until = time.monotonic() + WATCHDOG_REPORT_S
        seen = "" if gap is None else f" (this backend was silent for {gap * 1000:.0f} ms)"
        log.warning("%s%s", servo.watchdog_report, seen)

    def _check_watchdogs(self, now: float) -> None:
        """Find armed servos whose watchdog expired; clear, re-arm and report them.

        A servo is asked when this backend itself was silent towards it for most of the
        period (a paused process, a slow step), and every ``status_interval_s`` anyway,
        since an expiry is invisible otherwise: the servo takes no alert bit for it and
        ignores SYNC_WRITE goals silently.
        """
        suspect_after = 0.8 * self._watchdog_units * BUS_WATCHDOG_UNIT_MS / 1000.0
        if not self._caller_live():
            return  # the caller is silent: let the armed servos' watchdogs run out
        # The silence as this side saw it includes a pause of the caller, during which this
        # thread stopped talking to the armed servos on purpose.
        pause, self._recent_pause = self._recent_pause, 0.0
        for servo in self._servos:
            if not (servo.answering and servo.watchdog_units):
                continue
            gap = max(now - servo.sent_at, pause)
            if gap < suspect_after and now < servo.next_watchdog_check:
                continue
            servo.next_watchdog_check = now + self.status_interval
            try:
                value, _ = self._read_register(servo, "bus_watchdog")
                if value == servo.watchdog_units:
                    continue
                if value == BUS_WATCHDOG_EXPIRED:
                    self._write_register(servo, "bus_watchdog", 0)
                    self._write_register(servo, "bus_watchdog", servo.watchdog_units)
                    self._report_trip(servo, servo.watchdog_units, gap, "re-armed")
                else:
                    log.warning(
                        "%s: servo id %d bus watchdog read %d, expected %d; re-armed",
                        servo.joint,
                        servo.sid,
                        value,
                        servo.watchdog_units,
                    )
                    self._write_register(servo, "bus_watchdog", servo.watchdog_units)
            except _NoAnswer:
                continue  # the group read decides whether the servo is gone

    def _feed_watchdogs(self) -> None:
        """SYNC_READ the armed servos if a slow step just kept them waiting.

        Retries, re-probes and boot waits each block for up to one reply timeout; calling
        this between them keeps every armed servo's silence to about one timeout (plus
        :data:`FEED_AFTER_S`) instead of their sum. After a normal step it sends nothing.
        """
        self._halt_if_asked()  # between two slow exchanges: the halt goes first
        if self._port is None or not self._watchdog_units or not self._caller_live():
            return
        now = time.monotonic()
        period = self._watchdog_units * BUS_WATCHDOG_UNIT_MS / 1000.0
        feed_after = min(FEED_AFTER_S, period / 4.0)
        stale = [
            s
            for s in self._servos
            if s.answering and s.watchdog_units and now - s.sent_at > feed_after
        ]
        replies = self._sync_read_block(stale)
        stamp = time.time()
        for servo in stale:
            if servo.sid in replies:
                self._decode(servo, replies[servo.sid][0], stamp)

    def _enable_torque(self, servo: _Servo) -> None:
        # Read back: a servo in hardware-error shutdown acknowledges the write but stays off.
        self._write_register(servo, "torque_enable", 1)
        torque, _ = self._read_register(servo, "torque_enable")
        servo.torque_on = bool(torque)

    def _switch_mode(self, servo: _Servo, mode: int, goal: int) -> None:
        try:
            self._set_mode(servo, mode, goal)
            self._enable_torque(servo)
        except _NoAnswer:
            servo.answering = False
            servo.torque_on = False
            servo.next_probe = time.monotonic() + self.reprobe_interval

    # -- read cycle -----------------------------------------------------------------------

    def _read_cycle(self, now: float) -> None:
        if self._port is None:
            self._try_reopen(now)
            return
        self._check_watchdogs(now)
        live = [s for s in self._servos if s.answering and self._talks_to(s)]
        replies = self._sync_read_block(live)
        for servo in live:
            if servo.sid in replies:
                continue
            for _ in range(max(self.retries, 0)):
                self._feed_watchdogs()
                reply = self._read_block_single(servo)
                if reply is not None:
                    replies[servo.sid] = reply
                    break
            else:
                log.warning("%s: servo id %d not answering", servo.joint, servo.sid)
                servo.answering = False
                servo.torque_on = False
                servo.next_probe = now + self.reprobe_interval
        stamp = time.time()
        for servo in live:
            if servo.sid in replies:
                data, error = replies[servo.sid]
                self._decode(servo, data, stamp)
                self._track_alert(servo, error, now)
                self._feed_watchdogs()
        for servo in self._servos:
            if not servo.answering and now >= servo.next_probe and self._talks_to(servo):
                self._feed_watchdogs()
                if self._probe(servo, now):
                    reply = self._read_block_single(servo)
                    if reply is not None:
                        self._decode(servo, reply[0], time.time())
        self._feed_watchdogs()

    def _decode(self, servo: _Servo, data: bytes, stamp: float) -> None:
        """The one place a state block becomes SI units."""
        model = servo.model

        def field_value(name: str) -> int:
            address, size = model.registers[name]
            offset = address - READ_BLOCK_START
            value = int.from_bytes(data[offset : offset + size], "little")
            return to_signed(value, size) if name in SIGNED_REGISTERS else value

        servo.voltage = field_value("present_input_voltage") * 0.1
        servo.state_at = time.monotonic()
        units = servo.units
        servo.state = MotorState(
            joint=servo.joint,
            position=units.position(field_value("present_position")),
            velocity=units.velocity(field_value("present_velocity")),
            effort=units.effort(field_value("present_current")),
            temperature=float(field_value("present_temperature")),
            stamp=stamp,
        )

    def _track_alert(self, servo: _Servo, error: int, now: float) -> None:
        if not error & ALERT_BIT:
            servo.hardware_error = 0
            return
        if servo.hardware_error and now < servo.next_status_read:
            return
        servo.next_status_read = now + self.status_interval
        try:
            servo.hardware_error, _ = self._read_register(servo, "hardware_error_status")
            torque, _ = self._read_register(servo, "torque_enable")
            servo.torque_on = bool(torque)
        except _NoAnswer:
            pass  # the next group read decides whether the servo is gone
        if servo.hardware_error:
            log.warning(
                "%s: servo id %d hardware error: %s",
                servo.joint,
                servo.sid,
                hardware_error_text(servo.hardware_error),
            )

    # -- write ----------------------------------------------------------------------------

    def _clamp_ticks(self, servo: _Servo, ticks: int) -> int:
        if servo.mode == OPERATING_MODES["position"]:
            return max(servo.min_ticks, min(servo.max_ticks, ticks))
        return ticks

    def _write_commands(self, commands: list[MotorCommand]) -> None:
        # Before the goals: a servo whose watchdog expired would drop them without a word.
        self._check_watchdogs(time.monotonic())
        halts = self._halts
        positions: dict[int, int] = {}
        velocities: dict[int, int] = {}
        for command in commands:
            if self._halts != halts:
                return  # a halt came in between two mode switches: it wins over the rest
            servo = self._by_joint.get(command.joint)
            if servo is None or not servo.answering:
                continue
            if command.position is not None and math.isfinite(command.position):
                if servo.mode not in POSITION_MODES:
                    servo.mode = servo.position_mode  # so clamping uses the new mode's range
                    goal = self._clamp_ticks(servo, servo.units.position_ticks(command.position))
                    self._switch_mode(servo, servo.position_mode, goal)
                    self._feed_watchdogs()
                    continue
                positions[servo.sid] = self._clamp_ticks(
                    servo, servo.units.position_ticks(command.position)
                )
            elif command.velocity is not None and math.isfinite(command.velocity):
                units = servo.units.velocity_units(command.velocity)
                units = max(-servo.velocity_limit, min(servo.velocity_limit, units))
                if servo.mode != VELOCITY_MODE:
                    self._switch_mode(servo, VELOCITY_MODE, units)
                    self._feed_watchdogs()
                    continue
                velocities[servo.sid] = units
        if self._halts != halts:
            return
        self._sync_write("goal_position", positions)
        self._sync_write("goal_velocity", velocities)

    # -- diagnostics ----------------------------------------------------------------------

    def _servo_diagnostic(self, servo: _Servo) -> MotorDiagnostic:
        values = {"id": str(servo.sid), "model": servo.model.name}
        if servo.mode is not None:
            mode_name = {v: k for k, v in OPERATING_MODES.items()}.get(servo.mode, str(servo.mode))
            values["operating_mode"] = mode_name
        values["torque"] = "on" if servo.torque_on else "off"
        state = servo.state
        if state is not None and state.temperature is not None:
            values["temperature_c"] = f"{state.temperature:.0f}"
        if servo.voltage is not None:
            values["input_voltage_v"] = f"{servo.voltage:.1f}"
        values["hardware_error_status"] = f"0x{servo.hardware_error:02x}"
        values["bus_watchdog"] = (
            f"{servo.watchdog_units * BUS_WATCHDOG_UNIT_MS} ms" if servo.watchdog_units else "off"
        )
        values["bus_watchdog_trips"] = str(servo.watchdog_trips)
        if servo.watchdog_gap is not None:
            values["bus_watchdog_last_gap_ms"] = f"{servo.watchdog_gap * 1000:.0f}"
        prefix = f"{servo.joint}: servo id {servo.sid}"
        if not servo.answering:
            hint = "" if servo.ever_answered else " (check id, baud rate and cable)"
            return MotorDiagnostic(servo.joint, ERROR, f"{prefix} not answering{hint}", values)
        if servo.hardware_error:
            return MotorDiagnostic(
                servo.joint,
                ERROR,
                f"{prefix} hardware error: {hardware_error_text(servo.hardware_error)}; "
                "call recover to reboot it",
                values,
            )
        if state is not None and state.temperature is not None:
            if state.temperature >= servo.temperature_limit:
                return MotorDiagnostic(
                    servo.joint,
                    ERROR,
                    f"{prefix} over temperature: {state.temperature:.0f} °C "
                    f"(limit {servo.temperature_limit:.0f} °C)",
                    values,
                )
            if state.temperature >= servo.temperature_limit - 5:
                return MotorDiagnostic(
                    servo.joint,
                    WARN,
                    f"{prefix} hot: {state.temperature:.0f} °C "
                    f"(limit {servo.temperature_limit:.0f} °C)",
                    values,
                )
        if servo.watchdog_report and time.monotonic() < servo.watchdog_report_until:
            return MotorDiagnostic(servo.joint, WARN, servo.watchdog_report, values)
        if servo.model_number is not None and servo.model_number != servo.model.model_number:
            seen = MODELS_BY_NUMBER.get(servo.model_number)
            seen_name = seen.name if seen else f"model number {servo.model_number}"
            return MotorDiagnostic(
                servo.joint,
                WARN,
                f"{prefix} is a {seen_name}, module data says {servo.model.name}: fix the data",
                values,
            )
        if not servo.torque_on:
            return MotorDiagnostic(
                servo.joint, WARN, f"{prefix} torque off {servo.note}".rstrip(), values
            )
        return MotorDiagnostic(servo.joint, OK, "OK", values)


class _LatencyAwarePort(PortHandler):
    """PortHandler whose reply timeout uses the adapter's real latency timer.

    The SDK hard-codes 16 ms (FTDI's default) into every timeout; an adapter set to 1 ms can
    use a much shorter one, which is what keeps a silent servo from stalling the cycle.
    """

    def __init__(self, port_name: str, latency_timer_ms: float):
        super().__init__(port_name)
        self.latency_timer_ms = latency_timer_ms

    def setPacketTimeout(self, packet_length: int) -> None:
        """Start a reply timeout sized for ``packet_length`` bytes plus two latency periods."""
        self.packet_start_time = self.getCurrentTime()
        self.packet_timeout = (
            self.tx_time_per_byte * packet_length + 2.0 * self.latency_timer_ms + 2.0
        )


def _run_io(
    ref: weakref.ReferenceType[DynamixelBackend], stop: threading.Event, wake: threading.Event
) -> None:
    """The I/O thread: a step per cycle period (or at once when the caller queued something)
    until stopped, then stop the servos and release the port."""
    while True:
        wake.clear()  # before the step takes the requests: a later one wakes the next wait
        if stop.is_set():
            break
        backend = ref()
        if backend is None:
            return
        try:
            backend._io_step()
        except Exception as exc:  # the thread must outlive any one bad moment
            backend._report_fault("I/O step", exc)
        delay = backend._next_cycle - time.monotonic()
        del backend  # held only while working, so a dropped backend can be collected
        if delay > 0:
            wake.wait(delay)
    backend = ref()
    if backend is not None:
        backend._shutdown_bus()
