"""Emulated motor hardware (servo chains, CAN drives) for tests, demos and rehearsals.

Each shipped backend names its emulator in its :class:`~components.motors.options.BackendInfo`
(``emulator_path``), so a motor interface can run its real backend against emulated hardware
on a computer with no motors (``msctl rehearse``: ``MSCTL_EMULATE_HARDWARE=1``): the emulator
runs in the motor interface's own process, on the channel the backend then opens, and the
backend's code is the code that runs on the robot.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

#: Environment variable that makes a motor interface start its bus's emulator first.
EMULATE_ENV = "MSCTL_EMULATE_HARDWARE"


@dataclass
class EmulatedHardware:
    """A running emulation of one module's bus.

    Attributes:
        channel: The channel the backend opens instead of the module's own (a virtual CAN
            channel, a pseudo-terminal).
        bus_options: Backend options the emulation needs over the module data's (e.g. the
            python-can interface), as keys of the backend's options type.
        describe: One line for logs: what is emulated, on which channel.
        close: Stops the emulation (idempotent).
    """

    channel: str
    bus_options: dict[str, Any]
    describe: str
    close: Callable[[], None] = field(repr=False)


def cia402_drives(channel: str, motors: Sequence[Any]) -> EmulatedHardware:
    """Emulated CiA 402 drives for ``motors`` on python-can's in-process virtual bus.

    The virtual bus joins only buses of the same process and channel name, so the channel
    is made unique to the module (``emulated-<channel>``) and the drives serve it from a
    thread of this process.
    """
    from components.motors.emulation.cia402 import EmulatedCia402Bus

    counts = {m.motor_id: int(m.params.get("counts_per_rev", 4096)) for m in motors}
    virtual = f"emulated-{channel.strip('/').replace('/', '-')}"
    bus = EmulatedCia402Bus(virtual, counts, counts_per_rev=counts).start()
    return EmulatedHardware(
        channel=virtual,
        bus_options={"interface": "virtual"},
        describe=f"{len(counts)} emulated CiA 402 drives on virtual CAN {virtual!r}",
        close=bus.stop,
    )


def dynamixel_chain(channel: str, motors: Sequence[Any]) -> EmulatedHardware:
    """An emulated Dynamixel chain for ``motors`` behind a pseudo-terminal.

    Each servo is of its motor's model when the emulator knows it, else an XM430-W350.
    The serial reply timeout is sized for a slow adapter: the chain is a Python thread
    sharing the computer with the rest of the module.
    """
    from components.motors.emulation.dynamixel import MODELS, EmulatedDynamixelChain

    models = {m.motor_id: m.model for m in motors if m.model in MODELS}
    chain = EmulatedDynamixelChain(ids=[m.motor_id for m in motors], models=models)
    return EmulatedHardware(
        channel=chain.port,
        bus_options={"latency_timer_ms": 40.0},
        describe=f"{len(motors)} emulated Dynamixel servos on {chain.port} (for {channel})",
        close=chain.close,
    )
