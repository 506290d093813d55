"""The playhead of a bag played to Foxglove: where in the bag's time the picture is, moved by
the Foxglove app's playback bar (play, pause, seek, speed). The Core of ``msctl bag view
--foxglove``: pure, wall-clock seconds are passed in, so it is tested with plain calls.
"""

from __future__ import annotations

import math

#: The slowest and fastest playback speeds taken (factors of real time); others are clamped.
MIN_SPEED = 0.01
MAX_SPEED = 100.0

PLAYING, PAUSED, ENDED = "playing", "paused", "ended"


def clamp_speed(speed: float) -> float:
    """A requested speed within :data:`MIN_SPEED` .. :data:`MAX_SPEED` (NaN: the slowest)."""
    if math.isnan(speed):
        return MIN_SPEED
    return min(max(speed, MIN_SPEED), MAX_SPEED)


class Playhead:
    """A position in a bag's time that advances at ``speed`` while playing.

    Args:
        start: The bag's first log time (ns).
        end: Its last log time (ns).

    Attributes:
        start: The first log time (ns).
        end: The last log time (ns).
        speed: Factor of real time.
        playing: Whether it advances (it stops by itself at :attr:`end`).
    """

    def __init__(self, start: int, end: int) -> None:
        if end < start:
            raise ValueError(f"a bag's end ({end}) cannot come before its start ({start})")
        self.start, self.end = start, end
        self.speed = 1.0
        self.playing = False
        self._at = start  # bag time (ns) at wall time _since
        self._since = 0.0

    def time(self, now: float) -> int:
        """The bag time (ns) at wall-clock ``now`` (s)."""
        if not self.playing:
            return self._at
        return min(self.end, self._at + int((now - self._since) * self.speed * 1e9))

    def status(self, now: float) -> str:
        """:data:`PLAYING`, :data:`PAUSED` or :data:`ENDED` (at the end, whether or not it was
        playing: nothing more comes until a seek or a play)."""
        if self.time(now) >= self.end:
            return ENDED
        return PLAYING if self.playing else PAUSED

    def play(self, now: float) -> bool:
        """Start advancing; from the beginning when at the end (as a file player restarts).

        Returns:
            Whether it jumped back to the start (a seek, for whoever shows the picture).
        """
        restarted = self.time(now) >= self.end
        self._at = self.start if restarted else self.time(now)
        self._since, self.playing = now, True
        return restarted

    def pause(self, now: float) -> None:
        """Stop where it is."""
        self._at, self._since, self.playing = self.time(now), now, False

    def seek(self, to: int, now: float) -> int:
        """Jump to bag time ``to`` (clamped to the bag); keeps playing or paused. Returns it."""
        self._at, self._since = min(max(to, self.start), self.end), now
        return self._at

    def set_speed(self, speed: float, now: float) -> None:
        """Advance at ``speed`` from now on (clamped, see :func:`clamp_speed`)."""
        self._at, self._since = self.time(now), now
        self.speed = clamp_speed(speed)
