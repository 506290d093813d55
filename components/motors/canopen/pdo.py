"""The PDOs: their layouts, the command frames sent to a drive and the feedback it sends.

Cyclic data only travels in PDOs, so reading and commanding never wait on the bus; SDO is for
configuration (:mod:`components.motors.canopen.supervision`).
"""

from __future__ import annotations

import logging
import threading
import time

import can
from canopen.pdo import PdoMap

from components.motors.canopen.cia402 import (
    CW_CHANGE_IMMEDIATELY,
    CW_HALT,
    CW_NEW_SETPOINT,
    MODE_PROFILE_POSITION,
    SP_IDLE,
    SP_RELEASING,
    SP_REQUESTED,
    SW_SETPOINT_ACK,
    decode_state,
)
from components.motors.canopen.drive import Drive

logger = logging.getLogger("components.motors.canopen")

# PDO layouts (index, subindex) per map number; see the module docstring.
TPDO_LAYOUT = {
    1: [(0x6041, 0), (0x6061, 0), (0x603F, 0)],
    2: [(0x6064, 0), (0x606C, 0)],
    3: [(0x6077, 0), (0x6078, 0)],
}
RPDO_LAYOUT = {
    1: [(0x6040, 0), (0x6060, 0)],
    2: [(0x607A, 0), (0x6081, 0)],
    3: [(0x60FF, 0), (0x6072, 0)],
}


def map_pdo(
    pdo: PdoMap, layout: list[tuple[int, int]] | None, trans_type: int, event_ms: int | None
) -> None:
    """Map ``pdo`` to ``layout`` (None disables it) and save it to the drive over SDO."""
    pdo.clear()
    pdo.cob_id = pdo.predefined_cob_id
    pdo.enabled = layout is not None
    for index, subindex in layout or []:
        pdo.add_variable(index, subindex)
    pdo.trans_type = trans_type
    pdo.event_timer = event_ms
    pdo.save()


class PdoTraffic:
    """The backend's PDO side (a mixin of
    :class:`~components.motors.canopen.backend.CanopenBackend`): frames out under its lock,
    feedback in on the network's notifier thread.
    """

    _lock: threading.RLock
    _SETPOINT_TIMEOUT: float

    def _on_tpdo(self, d: Drive, number: int, pdo: PdoMap) -> None:
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

    def _send_rpdo1(self, d: Drive, force: bool = False) -> None:
        word = d.controlword | (CW_HALT if d.halted else 0)
        if d.mode == MODE_PROFILE_POSITION:
            word |= CW_CHANGE_IMMEDIATELY
        frame = (word, d.mode)
        if frame == d.sent_rpdo1 and not force:
            return
        pdo = d.node.rpdo[1]
        pdo[0x6040].raw = word
        pdo[0x6060].raw = d.mode
        if self._transmit(pdo):
            d.sent_rpdo1 = frame

    def _send_rpdo3(self, d: Drive, force: bool = False) -> None:
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

    def _advance_setpoint(self, d: Drive, now: float) -> None:
        """One step of the profile position set-point handshake (lock held).

        New set-point bit up, wait for the acknowledge, bit down, wait for the acknowledge
        to drop, next set-point: the single set-point handshake of CiA 402, so no target is
        lost even if the drive is slow to take it.
        """
        if d.mode != MODE_PROFILE_POSITION or d.statusword is None:
            return
        ack = bool(d.statusword & SW_SETPOINT_ACK)
        if d.sp_phase == SP_REQUESTED:
            if ack or now - d.sp_since > self._SETPOINT_TIMEOUT:
                d.controlword &= ~CW_NEW_SETPOINT
                d.sp_phase, d.sp_since = SP_RELEASING, now
                self._send_rpdo1(d)
            return
        if d.sp_phase == SP_RELEASING:
            if ack and now - d.sp_since <= self._SETPOINT_TIMEOUT:
                return
            d.sp_phase = SP_IDLE
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
        d.controlword |= CW_NEW_SETPOINT
        d.sp_phase, d.sp_since = SP_REQUESTED, now
        d.sp_sent, d.sp_pending = d.sp_pending, None
        self._send_rpdo1(d)

    def _transmit(self, pdo: PdoMap) -> bool:
        try:
            pdo.transmit()
        except (can.CanError, OSError, RuntimeError, ValueError) as exc:
            self._note_bus_error(exc)
            return False
        return True
