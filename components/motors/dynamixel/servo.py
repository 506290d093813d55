"""What the backend knows of one servo: what it commanded and what the servo last said."""

from __future__ import annotations

from dataclasses import dataclass

from components.motors.base import MotorError, MotorSpec, MotorState
from components.motors.dynamixel.control_table import OPERATING_MODES, POSITION_MODES
from components.motors.dynamixel.units import MODELS, DynamixelModel, JointUnits


@dataclass
class Servo:
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
        """The servo's Dynamixel id."""
        return self.spec.motor_id

    @property
    def joint(self) -> str:
        """The raw joint the servo drives."""
        return self.spec.joint


def make_servo(spec: MotorSpec, channel: str) -> Servo:
    """A servo's record from its motor spec, its parameters checked.

    Raises:
        MotorError: If the model is unknown or ``operating_mode`` is not a position mode.
    """
    model = MODELS.get(spec.model)
    if model is None:
        raise MotorError(
            f"{spec.joint}: unknown Dynamixel model {spec.model!r} on {channel}; "
            f"known: {', '.join(sorted(MODELS))} (fix the module data's motor model, or add "
            f"the model to components/motors/dynamixel/units.py MODELS)"
        )
    mode_name = spec.params.get("operating_mode", "position")
    mode = OPERATING_MODES.get(mode_name)
    if mode not in POSITION_MODES:
        raise MotorError(
            f"{spec.joint}: operating_mode {mode_name!r} is not a position mode; use one of "
            "position, extended_position, current_position"
        )
    profile = spec.params.get("profile_velocity")
    return Servo(
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
