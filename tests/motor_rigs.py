"""Emulated motor buses for the backend tests: one rig per backend, with the same handles.

A rig is a bus of two emulated motors, ``limb1_joint1`` and ``limb1_joint2``, and the real
backend for it (real python-can on its in-process ``virtual`` bus for CANopen, real
dynamixel-sdk and pyserial over a pseudo-terminal for Dynamixel: only the motors are
emulated). It also reads the emulated motor's own truth (what the shaft does, not what the
backend says) and can take the bus away and give it back, as far as each bus allows:

- CANopen: the emulated drives leave the bus (their thread stops, so no heartbeat, no PDO,
  no SDO answer) and come back powered up again, as when a drive chain loses power.
- Dynamixel: the adapter is unplugged. The backend opens a stable path (a symlink, as
  udev's ``/dev/serial/by-id``) to the pty; unplugging closes the pty and removes the link,
  plugging in creates a new chain (power-cycled servos) behind the same path.

The constants (joint names, conversion parameters, options sized for a loaded test machine)
are shared with ``test_canopen_backend.py`` and ``test_dynamixel_backend.py``.
"""

from __future__ import annotations

import math
import uuid
from abc import ABC, abstractmethod
from pathlib import Path
from typing import Any

from components.motors.base import MotorBackend, MotorSpec
from components.motors.canopen.backend import CanopenBackend
from components.motors.dynamixel.backend import DynamixelBackend
from components.motors.dynamixel.units import MODELS
from components.motors.emulation.cia402 import EmulatedCia402Bus
from components.motors.emulation.dynamixel import EmulatedDynamixelChain

# ------------------------------------------------------------------------------ CANopen
COUNTS_PER_REV = 4096
GEAR_RATIO = 50.0
RATED_TORQUE = 0.5  # N·m at the motor
COUNTS_PER_RAD = COUNTS_PER_REV * GEAR_RATIO / (2 * math.pi)
CANOPEN_PARAMS = {
    "counts_per_rev": COUNTS_PER_REV,
    "gear_ratio": GEAR_RATIO,
    "rated_torque": RATED_TORQUE,
}
#: Node id -> joint.
CANOPEN_JOINTS = {1: "limb1_joint1", 2: "limb1_joint2"}
CANOPEN_OPTIONS = {"interface": "virtual", "heartbeat_timeout": 0.3, "temperature_object": "0x2100"}

# ----------------------------------------------------------------------------- Dynamixel
XM430 = MODELS["XM430-W350"]
#: One position tick of an XM430, rad.
TICK = 2 * math.pi / XM430.ticks_per_rev
#: One Goal/Present Velocity unit of an XM430, rad/s.
VELOCITY_UNIT = XM430.velocity_unit_rpm * 2 * math.pi / 60
#: The emulator is a Python thread: on a loaded CI machine it can answer tens of ms late, so
#: the tests size the reply timeout as for a slow adapter (about 80 ms instead of 34 ms).
DYNAMIXEL_OPTIONS = {"latency_timer_ms": 40.0}


def canopen_channel() -> str:
    """A fresh virtual CAN channel name, so tests can run in parallel."""
    return f"cia402-{uuid.uuid4().hex[:12]}"


class MotorRig(ABC):
    """Two emulated motors on one bus, and what a backend test needs to know about them."""

    #: The rig's name (the backend's registry name).
    name: str
    #: The joints on the bus, in motor id order.
    joints: tuple[str, ...] = ("limb1_joint1", "limb1_joint2")
    #: How far a settled motor may read from its target, rad: a few encoder counts.
    position_tolerance: float
    #: How far a motor at speed may read from the commanded velocity, rad/s: one or two
    #: units of the motor's velocity resolution.
    velocity_tolerance: float

    @abstractmethod
    def backend(self, **options: Any) -> MotorBackend:
        """A new, unopened backend for this bus; ``options`` override the rig's."""

    @abstractmethod
    def true_position(self, joint: str) -> float:
        """Where the emulated motor's shaft is, in joint radians (not what the backend says)."""

    @abstractmethod
    def true_velocity(self, joint: str) -> float:
        """How fast the emulated motor turns, in joint rad/s."""

    @abstractmethod
    def unplug(self) -> None:
        """Take the motors off the backend: the bus or the drives go away."""

    @abstractmethod
    def plug(self) -> None:
        """Give the motors back (powered up again: they hold wherever they are)."""

    @abstractmethod
    def close(self) -> None:
        """Stop the emulation and release everything it holds. Idempotent."""


class CanopenRig(MotorRig):
    """Two emulated CiA 402 drives (node 1 and 2) on a fresh python-can virtual channel."""

    name = "canopen"
    position_tolerance = 4 / COUNTS_PER_RAD
    velocity_tolerance = 2 / COUNTS_PER_RAD

    def __init__(self) -> None:
        self.channel = canopen_channel()
        self.emulator = EmulatedCia402Bus(self.channel, CANOPEN_JOINTS).start()
        self._node = {joint: node for node, joint in CANOPEN_JOINTS.items()}

    def backend(self, **options: Any) -> MotorBackend:
        # Position moves at 4 rad/s (the default is 1), about as fast as an XM430's.
        params = {**CANOPEN_PARAMS, "profile_velocity": 4.0}
        specs = [
            MotorSpec(joint, node, "cia402", dict(params)) for node, joint in CANOPEN_JOINTS.items()
        ]
        return CanopenBackend(self.channel, specs, {**CANOPEN_OPTIONS, **options})

    def true_position(self, joint: str) -> float:
        return self.emulator.drive(self._node[joint]).position / COUNTS_PER_RAD

    def true_velocity(self, joint: str) -> float:
        return self.emulator.drive(self._node[joint]).velocity / COUNTS_PER_RAD

    def unplug(self) -> None:
        self.emulator.stop()

    def plug(self) -> None:
        # Power comes back with the bus: every object at its default, boot-up on the bus.
        for drive in self.emulator.drives.values():
            drive.power_cycle()
        self.emulator.start()

    def close(self) -> None:
        self.emulator.stop()


class DynamixelRig(MotorRig):
    """Two emulated XM430-W350 servos (id 1 and 2) behind a pty, opened through a symlink.

    Args:
        directory: Where the symlink lives (a test's temporary directory).
    """

    name = "dynamixel"
    position_tolerance = 2 * TICK
    velocity_tolerance = 2 * VELOCITY_UNIT
    ids = (1, 2)

    def __init__(self, directory: Path) -> None:
        self.link = Path(directory) / "ttyDXL0"
        self.chain: EmulatedDynamixelChain | None = None
        self._id = dict(zip(self.joints, self.ids, strict=True))
        self.plug()

    def backend(self, **options: Any) -> MotorBackend:
        specs = [MotorSpec(joint, self._id[joint], XM430.name) for joint in self.joints]
        # Reopen a lost port quickly: the tests unplug and plug the adapter.
        defaults = {**DYNAMIXEL_OPTIONS, "reopen_interval_s": 0.05, "reprobe_interval_s": 0.1}
        return DynamixelBackend(str(self.link), specs, {**defaults, **options})

    def _chain(self) -> EmulatedDynamixelChain:
        if self.chain is None:
            raise AssertionError("the Dynamixel rig is unplugged")
        return self.chain

    def true_position(self, joint: str) -> float:
        ticks = self._chain().register(self._id[joint], "present_position")
        return (ticks - XM430.center_tick) * TICK

    def true_velocity(self, joint: str) -> float:
        return self._chain().register(self._id[joint], "present_velocity") * VELOCITY_UNIT

    def unplug(self) -> None:
        chain, self.chain = self.chain, None
        if chain is not None:
            chain.close()
        self.link.unlink(missing_ok=True)

    def plug(self) -> None:
        if self.chain is not None:
            return
        self.chain = EmulatedDynamixelChain(ids=self.ids, model=XM430.name)
        self.link.unlink(missing_ok=True)
        self.link.symlink_to(self.chain.port)

    def close(self) -> None:
        self.unplug()
