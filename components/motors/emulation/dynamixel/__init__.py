"""An emulated chain of Dynamixel X-series servos behind a pseudo-terminal.

The emulator speaks Protocol 2.0 byte for byte (header ``FF FF FD 00``, CRC-16 with polynomial
0x8005, byte stuffing, status packets with the alert bit), so the real dynamixel-sdk and the
real :class:`~components.motors.dynamixel.backend.DynamixelBackend` talk to it through pyserial
exactly as to a U2D2 adapter::

    with EmulatedDynamixelChain(ids=[1, 2, 3]) as chain:
        backend = DynamixelBackend(chain.port, motors, {})

Each servo has a control table (its model's, written from the datasheet in
:mod:`.datasheet`, independent of the driver's), simple motion
physics (position follows the goal at the profile velocity; velocity mode integrates; current
follows speed and tracking error), the Bus Watchdog (register 98, see
:meth:`EmulatedServo.heard`), and fault hooks: :meth:`EmulatedDynamixelChain.silence`,
:meth:`~EmulatedDynamixelChain.resume`, :meth:`~EmulatedDynamixelChain.set_hardware_error`,
:meth:`~EmulatedDynamixelChain.set_temperature`. The baud rate is irrelevant on a pty.

Run ``python -m components.motors.emulation.dynamixel --ids 1,2,3`` to serve a chain for a demo.
"""

from components.motors.emulation.dynamixel.chain import EmulatedDynamixelChain
from components.motors.emulation.dynamixel.datasheet import MODELS, ServoDatasheet
from components.motors.emulation.dynamixel.protocol import (
    Packet,
    PacketParser,
    build_packet,
    build_status,
    crc16,
    stuff,
    unstuff,
)
from components.motors.emulation.dynamixel.servo import EmulatedServo

__all__ = [
    "MODELS",
    "EmulatedDynamixelChain",
    "EmulatedServo",
    "Packet",
    "PacketParser",
    "ServoDatasheet",
    "build_packet",
    "build_status",
    "crc16",
    "stuff",
    "unstuff",
]
