"""Live measures of the data plane: topic rates from arrival times, recent values, sparklines."""

from __future__ import annotations

import statistics
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass

from components.data_monitor.model import finite

_SPARKS = "▁▂▃▄▅▆▇█"


def sparkline(values: Iterable[float | None], width: int = 16, resolution: float = 1e-4) -> str:
    """The last ``width`` values as block characters, scaled between their min and max.

    Values that are missing or not finite are blanks; a range narrower than ``resolution``
    (a joint at rest: numerical noise) is drawn flat.
    """
    recent = list(values)[-width:]
    numbers = [v for v in (finite(v) for v in recent) if v is not None]
    if not numbers:
        return ""
    low, high = min(numbers), max(numbers)
    span = high - low
    out = []
    for value in recent:
        number = finite(value)
        if number is None:
            out.append(" ")
        elif span < resolution:
            out.append(_SPARKS[0])
        else:
            out.append(_SPARKS[min(7, int((number - low) / span * 7.999))])
    return "".join(out)


@dataclass(frozen=True)
class RateStats:
    """A topic's rate, measured from arrival times.

    Attributes:
        rate: Samples per second over the window.
        min_interval: Shortest gap between samples (s).
        max_interval: Longest gap between samples (s).
        jitter: Standard deviation of the gaps (s).
        count: Samples ever seen.
        age: Seconds since the last sample (``None``: never).
    """

    rate: float
    min_interval: float | None
    max_interval: float | None
    jitter: float | None
    count: int
    age: float | None


class RateMeter:
    """Rate, min/max interval and jitter of one topic from arrival times (no decoding).

    ``ros2 topic hz`` decodes every sample on one thread and under-reports fast topics; this
    only notes the arrival time, so it keeps up with anything Zenoh delivers.

    Args:
        window: Seconds over which statistics are computed.
        max_samples: Arrival times kept (bounds memory for very fast topics).
    """

    def __init__(self, window: float = 2.0, max_samples: int = 4000) -> None:
        self.window = window
        self._times: deque[float] = deque(maxlen=max_samples)
        self._first: float | None = None
        self._last: float | None = None
        self.count = 0

    def arrive(self, t: float) -> None:
        """One sample arrived at monotonic ``t``."""
        if self._first is None:
            self._first = t
        self._times.append(t)
        self._last = t
        self.count += 1

    def stats(self, now: float) -> RateStats:
        """Statistics over the last ``window`` seconds at ``now``."""
        horizon = now - self.window
        times = self._times
        while times and times[0] < horizon:
            times.popleft()
        age = None if self._last is None else now - self._last
        if self._first is None:
            return RateStats(0.0, None, None, None, 0, None)
        span = min(self.window, now - self._first)
        rate = len(times) / span if span > 0 else 0.0
        gaps = [b - a for a, b in zip(times, list(times)[1:], strict=False)]
        if not gaps:
            return RateStats(rate, None, None, None, self.count, age)
        jitter = statistics.pstdev(gaps) if len(gaps) > 1 else 0.0
        return RateStats(rate, min(gaps), max(gaps), jitter, self.count, age)


class History:
    """Recent values per name (joint positions for sparklines), bounded.

    Args:
        length: Values kept per name.
    """

    def __init__(self, length: int = 32) -> None:
        self.length = length
        self._values: dict[str, deque[float | None]] = {}

    def add(self, name: str, value: float | None) -> None:
        """Append one value (``None`` or NaN shows as a gap)."""
        series = self._values.get(name)
        if series is None:
            if len(self._values) >= 512:
                return  # bounded: a flood of names cannot grow this without end
            series = self._values[name] = deque(maxlen=self.length)
        series.append(finite(value))

    def get(self, name: str) -> list[float | None]:
        """The values of ``name``, oldest first."""
        return list(self._values.get(name, ()))
