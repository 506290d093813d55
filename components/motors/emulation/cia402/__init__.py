"""An emulated chain of CiA 402 servo drives on a python-can bus.

Each :class:`EmulatedCia402Drive` speaks real CANopen framing (CiA 301: NMT, heartbeat
producer and consumer, expedited SDO server, four RPDOs and four TPDOs with configurable
mapping, SYNC, EMCY) and runs the CiA 402 drive state machine driven by the controlword,
with profile position (mode 1) and profile velocity (mode 3) motion. Position is in encoder
counts, velocity in counts/s, torque and current in per-mille of rated, exactly like a real
drive, so the backend's unit conversion is exercised for real.

One background thread serves every drive of one :class:`EmulatedCia402Bus`. Fault injection
for tests and demos: :meth:`EmulatedCia402Drive.silence` / :meth:`~EmulatedCia402Drive.resume`
(a cut cable), :meth:`~EmulatedCia402Drive.raise_fault` (EMCY + FAULT state),
:meth:`~EmulatedCia402Drive.set_temperature` (over-temperature above the limit) and
:meth:`~EmulatedCia402Drive.set_load` (an external torque the drive has to hold).

Example::

    with EmulatedCia402Bus(channel="demo", node_ids=[1, 2, 3]) as bus:
        ...  # open a CanopenBackend on interface "virtual", channel "demo"
        bus.drive(2).silence()
"""

from components.motors.emulation.cia402.bus import EmulatedCia402Bus
from components.motors.emulation.cia402.drive import EmulatedCia402Drive
from components.motors.emulation.cia402.profile import (
    EDS_PATH,
    HEARTBEAT_ERROR,
    OVER_TEMPERATURE,
)

__all__ = [
    "EDS_PATH",
    "HEARTBEAT_ERROR",
    "OVER_TEMPERATURE",
    "EmulatedCia402Bus",
    "EmulatedCia402Drive",
]
