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
import threading
import time
import weakref
from typing import Any

from dynamixel_sdk import PacketHandler, PortHandler

from components.motors.base import (
    ERROR,
    MotorBackend,
    MotorCommand,
    MotorDiagnostic,
    MotorError,
    MotorSpec,
    MotorState,
)
from components.motors.dynamixel.bringup import ServoBringUp
from components.motors.dynamixel.control_table import (
    VELOCITY_MODE,
)
from components.motors.dynamixel.cycle import ChainCycle
from components.motors.dynamixel.diagnostics import bus_diagnostic, servo_diagnostic
from components.motors.dynamixel.port import ChainExchanges
from components.motors.dynamixel.servo import Servo, make_servo
from components.motors.dynamixel.watchdog import BusWatchdogs
from components.motors.options import DynamixelOptions

log = logging.getLogger(__name__)


class DynamixelBackend(ChainCycle, ChainExchanges, ServoBringUp, BusWatchdogs, MotorBackend):
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
        self._servos: list[Servo] = []
        self._by_joint: dict[str, Servo] = {}
        self._by_id: dict[int, Servo] = {}
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
        self._servos = [make_servo(spec, self.channel) for spec in self.motors]
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

    def _stall_after(self) -> float:
        """How long one step may take before diagnostics call the I/O thread stalled: well
        beyond the slowest normal step (a boot wait, every servo silent with retries)."""
        per_round = len(self._servos) * (2 + max(self.retries, 0)) * self._reply_timeout()
        return 2.0 + self.boot_timeout + 2.0 * per_round

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

    def _do_recover(self, now: float) -> None:
        if self._port is None:
            self._try_reopen(now, force=True)
            return
        rebooted: list[Servo] = []
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
        diags = [
            bus_diagnostic(
                self.channel, self.baudrate, self._bus_error, self.reopen_interval, self._servos
            )
        ] + [servo_diagnostic(s) for s in self._servos]
        with self._io_lock:
            self._states = states
            self._diags = diags
            self._published_at = time.monotonic()

    # -- a lost port ----------------------------------------------------------------------

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
