"""Reading the onboard computer's load, memory, disk and temperature (psutil).

This is the health monitor's only host I/O, kept out of the core: the core receives
:meth:`HostMetricsReader.read` as a plain callable, and tests pass a fake. Every metric is
optional: a computer (or container) without temperature sensors reports ``None`` for it
rather than failing.
"""

from __future__ import annotations

from typing import Any


class HostMetricsReader:
    """Reads host metrics with psutil; call :meth:`read` from a timer.

    Args:
        disk_path: The filesystem whose use is reported (``/`` by default).
    """

    def __init__(self, disk_path: str = "/") -> None:
        import psutil

        self._psutil = psutil
        self.disk_path = disk_path
        # cpu_percent(None) compares with the previous call; the first call only primes it.
        psutil.cpu_percent(interval=None)

    def read(self) -> dict[str, Any]:
        """The metrics now.

        Returns:
            ``cpu_percent`` (since the previous read), ``memory_percent``, ``disk_percent``
            (of ``disk_path``), ``temperature`` (hottest sensor, °C, or ``None``) and
            ``temperature_sensor`` (its name, or ``None``).
        """
        ps = self._psutil
        metrics: dict[str, Any] = {
            "cpu_percent": ps.cpu_percent(interval=None),
            "memory_percent": ps.virtual_memory().percent,
            "disk_percent": None,
            "temperature": None,
            "temperature_sensor": None,
        }
        try:
            metrics["disk_percent"] = ps.disk_usage(self.disk_path).percent
        except OSError:
            pass
        metrics["temperature"], metrics["temperature_sensor"] = self._hottest()
        return metrics

    def _hottest(self) -> tuple[float | None, str | None]:
        # Not every platform has sensors_temperatures (macOS, Windows), and on Linux it can
        # be empty (containers, VMs) or raise on an odd hwmon driver: all mean "not readable".
        sensors = getattr(self._psutil, "sensors_temperatures", None)
        if sensors is None:
            return None, None
        try:
            readings = sensors()
        except Exception:
            return None, None
        hottest: tuple[float | None, str | None] = (None, None)
        for chip, entries in (readings or {}).items():
            for entry in entries:
                current = getattr(entry, "current", None)
                if current is None or current <= -273.0:
                    continue
                if hottest[0] is None or current > hottest[0]:
                    label = getattr(entry, "label", "") or ""
                    hottest = (float(current), f"{chip}/{label}" if label else chip)
        return hottest

    def close(self) -> None:
        """Nothing to release (present so the reader can sit among a component's resources)."""
