"""The supervisor thread's work: configure each drive over SDO, walk the CiA 402 state machine
to OPERATION ENABLED, watch heartbeats and emergencies, pick a drive up again when it returns,
and re-open a bus that failed.

A drive whose heartbeat comes back OPERATIONAL, with no boot-up, kept its configuration and is
read again at once; one back pre-operational or stopped, or that booted, is configured again.
"""

from __future__ import annotations

import logging
import threading
import time
import weakref
from typing import TYPE_CHECKING, Any

import canopen
from canopen.emcy import EmcyError

from components.motors.canopen.cia402 import (
    CW_ENABLE_OPERATION,
    CW_FAULT_RESET,
    CW_SHUTDOWN,
    CW_SWITCH_ON,
    MODE_PROFILE_POSITION,
    NMT_OPERATIONAL,
    SP_IDLE,
    emcy_meaning,
)
from components.motors.canopen.drive import Drive
from components.motors.canopen.pdo import RPDO_LAYOUT, TPDO_LAYOUT, map_pdo

if TYPE_CHECKING:
    from components.motors.canopen.backend import CanopenBackend

logger = logging.getLogger("components.motors.canopen")


class DriveSupervision:
    """The supervisor's side of the backend (a mixin of
    :class:`~components.motors.canopen.backend.CanopenBackend`).
    """

    channel: str
    interface: str
    bitrate: int
    heartbeat_timeout: float
    heartbeat_ms: int
    sync_period: float | None
    pdo_period: float
    master_node_id: int
    temperature_object: int | None
    _lock: threading.RLock
    _stop: threading.Event
    _network: canopen.Network | None
    _drives: dict[str, Drive]
    _bus_error: str | None
    _next_reconnect: float
    _CONFIG_RETRY: float
    _RECONNECT_PERIOD: float

    def _configure(self, d: Drive) -> None:
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
        tpdo_layout = dict(TPDO_LAYOUT)
        if self.temperature_object is not None:
            tpdo_layout[4] = [(self.temperature_object, 0)]
        event_ms = max(1, round(self.pdo_period * 1000))
        for number in (1, 2, 3, 4):
            pdo = node.tpdo[number]
            synced = self.sync_period is not None and number != 1
            # The statusword TPDO stays event-driven so the enable and set-point handshakes
            # do not wait for a SYNC; the rest follow SYNC when there is one.
            map_pdo(pdo, tpdo_layout.get(number), 1 if synced else 255, 0 if synced else event_ms)
        for number in (1, 2, 3, 4):
            map_pdo(node.rpdo[number], RPDO_LAYOUT.get(number), 255, None)
        node.nmt.state = "OPERATIONAL"
        with self._lock:
            d.default_max_torque = d.max_torque = default_max_torque
            d.mode = MODE_PROFILE_POSITION
            d.halted = False
            d.target_velocity = 0
            d.sp_phase, d.sp_pending, d.sp_sent = SP_IDLE, None, None
            d.controlword = 0
            d.sent_rpdo1 = d.sent_rpdo3 = None
            d.statusword = None  # wait for this configuration's first statusword
            d.configured = d.ever_configured = True
            d.config_error = None
            d.lost_since = None
            d.heartbeat_at = time.monotonic()

    def _on_heartbeat(self, d: Drive, state: int) -> None:
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
                if state == NMT_OPERATIONAL:
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

    def _on_emcy(self, d: Drive, emcy: EmcyError) -> None:
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

    def _step_enable(self, d: Drive, now: float) -> None:
        """Walk the CiA 402 state machine one step toward OPERATION ENABLED (lock held)."""
        state = d.state
        if state is None or now - d.status_at > self.heartbeat_timeout:
            return
        word = None
        if state == "FAULT":
            comm_fault = d.error_code & 0xFF00 == 0x8100
            if d.auto_reset or comm_fault:
                # Fault reset acts on the rising edge of bit 7: drop it first if it is up.
                word = 0 if d.controlword & CW_FAULT_RESET else CW_FAULT_RESET
        elif state == "SWITCH ON DISABLED":
            word = CW_SHUTDOWN
        elif state == "READY TO SWITCH ON":
            word = CW_SWITCH_ON
        elif state in ("SWITCHED ON", "QUICK STOP ACTIVE"):
            # Enter operation in profile position with no new set-point: the drive holds.
            d.mode = MODE_PROFILE_POSITION
            d.sp_phase, d.sp_pending, d.sp_sent = SP_IDLE, None, None
            word = CW_ENABLE_OPERATION
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
        quietly(network.disconnect)
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


def quietly(action: Any) -> None:
    """Run a best-effort shutdown step; a dead bus must not stop the rest of the cleanup."""
    try:
        action()
    except Exception as exc:
        logger.debug("ignored during CANopen cleanup: %s", exc)


def supervise_forever(
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
