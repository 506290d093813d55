"""The servo models' constants (data) and the one place register values become SI units."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from components.motors.dynamixel.control_table import X_SERIES_REGISTERS, XL430_REGISTERS


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
            registers=XL430_REGISTERS,
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
