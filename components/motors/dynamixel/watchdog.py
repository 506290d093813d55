"""The servos' own Bus Watchdog (register 98): armed in velocity mode, fed, checked, reported.

Every servo in velocity mode has its Bus Watchdog armed (``bus_watchdog_ms``, default 100 ms):
if this process dies, hangs or loses the port, the servo sets its goal velocity to 0 by itself
instead of turning on at the last command. The read cycle feeds it, but only while the caller
keeps calling (a hung executor must let the servos stop just as a dead process does). A
watchdog found expired (the register reads 0xFF and the servo ignores goals) is reported as a
WARN naming the joint, cleared and re-armed.
"""

from __future__ import annotations

import logging
import math
import time

from components.motors.dynamixel.control_table import BUS_WATCHDOG_EXPIRED, BUS_WATCHDOG_UNIT_MS
from components.motors.dynamixel.port import NoAnswer
from components.motors.dynamixel.servo import Servo

log = logging.getLogger("components.motors.dynamixel")

#: How long the "stopped by its bus watchdog" warning stays in the diagnostics: long enough
#: for a 1 Hz diagnostics publisher to carry it a few times.
WATCHDOG_REPORT_S = 5.0
#: Silence towards an armed servo after which a slow step is followed by a feeding SYNC_READ:
#: above one normal cycle's bus time (a few ms), far below any useful watchdog period.
FEED_AFTER_S = 0.01


class BusWatchdogs:
    """The Bus Watchdog's side of the backend (a mixin of
    :class:`~components.motors.dynamixel.backend.DynamixelBackend`, run on its I/O thread).
    """

    channel: str
    latency_timer_ms: float
    bus_watchdog_ms: float
    status_interval: float
    _servos: list[Servo]
    _watchdog_units: int
    _last_call: float
    _recent_pause: float

    def _caller_timeout(self) -> float:
        """Caller silence after which armed servos stop hearing from the I/O thread."""
        if not self._watchdog_units:
            return math.inf
        return self._watchdog_units * BUS_WATCHDOG_UNIT_MS / 1000.0 / 2.0

    def _caller_live(self) -> bool:
        # A float read without the lock: the writer replaces it whole.
        return time.monotonic() - self._last_call <= self._caller_timeout()

    def _talks_to(self, servo: Servo) -> bool:
        """Whether the thread may send to ``servo`` now: a servo with an armed watchdog only
        hears from this backend while the caller is alive, so a hung caller lets it stop."""
        return not servo.watchdog_units or self._caller_live()

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

    def _disarm_watchdog(self, servo: Servo) -> None:
        """Bus Watchdog to 0, reporting an expiry found on the way (e.g. after a lost bus)."""
        value, _ = self._read_register(servo, "bus_watchdog")
        if value == BUS_WATCHDOG_EXPIRED:
            self._report_trip(servo, servo.watchdog_units or self._watchdog_units, None, "cleared")
        if value:
            self._write_register(servo, "bus_watchdog", 0)
        servo.watchdog_units = 0

    def _report_trip(self, servo: Servo, units: int, gap: float | None, action: str) -> None:
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
            except NoAnswer:
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
