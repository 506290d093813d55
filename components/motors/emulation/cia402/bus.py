"""A chain of emulated CiA 402 drives on one python-can channel, served by one thread."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import can

from components.motors.emulation.cia402.drive import EmulatedCia402Drive
from components.motors.emulation.cia402.profile import EDS_PATH

logger = logging.getLogger("components.motors.emulation.cia402")


class EmulatedCia402Bus:
    """A chain of emulated CiA 402 drives on one python-can channel, served by one thread.

    Args:
        channel: python-can channel (any name on the ``virtual`` interface; tests use a
            unique one so they can run in parallel).
        node_ids: CANopen node ids of the drives on this bus.
        interface: python-can interface; ``virtual`` unless you have a real or virtual CAN
            adapter to put the emulation on.
        tick: Physics and scheduling period in seconds.
        eds: Object dictionary the drives serve.
        counts_per_rev: Encoder counts per motor revolution, for every drive (an int) or per
            node id (a mapping; absent ids get 4096): scales the torque model to the motor.
        **bus_kwargs: Passed to :class:`can.Bus` (e.g. ``bitrate``).
    """

    def __init__(
        self,
        channel: str,
        node_ids: Iterable[int],
        *,
        interface: str = "virtual",
        tick: float = 0.002,
        eds: str | Path = EDS_PATH,
        counts_per_rev: int | Mapping[int, int] = EmulatedCia402Drive.REFERENCE_COUNTS_PER_REV,
        **bus_kwargs: Any,
    ):
        self.channel = channel
        self.interface = interface
        self.tick = tick
        self.lock = threading.RLock()
        self._bus_kwargs = bus_kwargs
        self._bus: can.BusABC | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.drives: dict[int, EmulatedCia402Drive] = {}
        for node_id in node_ids:
            if node_id in self.drives:
                raise ValueError(f"node id {node_id} appears twice on channel {channel!r}")
            counts = (
                counts_per_rev.get(node_id, EmulatedCia402Drive.REFERENCE_COUNTS_PER_REV)
                if isinstance(counts_per_rev, Mapping)
                else counts_per_rev
            )
            self.drives[node_id] = EmulatedCia402Drive(self, node_id, eds, counts)

    def drive(self, node_id: int) -> EmulatedCia402Drive:
        """The emulated drive with this node id."""
        return self.drives[node_id]

    def start(self) -> EmulatedCia402Bus:
        """Connect to the bus, boot every drive and start serving. Returns ``self``."""
        if self._thread is not None:
            return self
        self._bus = can.Bus(interface=self.interface, channel=self.channel, **self._bus_kwargs)
        self._stop.clear()
        with self.lock:
            for drive in self.drives.values():
                drive._boot()
        self._thread = threading.Thread(
            target=self._serve, name=f"cia402-emulator-{self.channel}", daemon=True
        )
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving and release the bus. Idempotent."""
        thread, self._thread = self._thread, None
        if thread is not None:
            self._stop.set()
            thread.join(timeout=2.0)
        bus, self._bus = self._bus, None
        if bus is not None:
            bus.shutdown()

    def send(self, can_id: int, data: bytes) -> None:
        """Put one frame on the bus (used by the drives; errors are logged, not raised)."""
        bus = self._bus
        if bus is None:
            return
        try:
            bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))
        except can.CanError as exc:
            logger.warning("emulated CiA 402 bus %s: send failed: %s", self.channel, exc)

    def _serve(self) -> None:
        last = time.monotonic()
        bus = self._bus
        assert bus is not None
        while not self._stop.is_set():
            try:
                msg = bus.recv(timeout=self.tick)
            except can.CanError as exc:
                logger.warning("emulated CiA 402 bus %s: receive failed: %s", self.channel, exc)
                msg = None
            now = time.monotonic()
            with self.lock:
                if msg is not None:
                    for drive in self.drives.values():
                        drive.handle(msg, now)
                if now - last >= self.tick:
                    for drive in self.drives.values():
                        drive.step(now, now - last)
                    last = now

    def __enter__(self) -> EmulatedCia402Bus:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
