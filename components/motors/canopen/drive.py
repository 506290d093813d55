"""What the backend knows of one drive: liveness, feedback in drive units, the command side."""

from __future__ import annotations

from dataclasses import dataclass, field

import canopen
from canopen.emcy import EmcyError

from components.motors.base import MotorSpec
from components.motors.canopen.cia402 import MODE_PROFILE_POSITION, SP_IDLE, decode_state
from components.motors.canopen.units import Conversion


@dataclass
class Drive:
    """Runtime state of one drive, guarded by the backend lock."""

    spec: MotorSpec
    node: canopen.RemoteNode
    conv: Conversion
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
    sp_phase: str = SP_IDLE
    sp_since: float = 0.0
    sp_sent: tuple[int, int] | None = None
    sp_pending: tuple[int, int] | None = None
    sent_rpdo1: tuple[int, int] | None = None
    sent_rpdo3: tuple[int, int] | None = None

    @property
    def node_id(self) -> int:
        """The drive's CANopen node id."""
        return self.node.id

    @property
    def state(self) -> str | None:
        """The CiA 402 state of the latest statusword (None before one came)."""
        return None if self.statusword is None else decode_state(self.statusword)

    def alive(self, now: float, timeout: float) -> bool:
        """Whether its heartbeat is younger than ``timeout``."""
        return self.heartbeat_at is not None and now - self.heartbeat_at <= timeout

    def enabled(self, now: float, timeout: float) -> bool:
        """Whether it takes commands now: configured, alive, OPERATION ENABLED."""
        return self.configured and self.alive(now, timeout) and self.state == "OPERATION ENABLED"
