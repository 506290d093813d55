"""The bookkeeping of a pull's requests, pure and tested with plain calls: which chunks of a
file to ask and in what order they are written (:class:`ChunkWindow`), a rate limit
(:class:`RateBudget`), the link's rate as seen (:class:`RateMeter`) and how long one request
may take (:func:`request_timeout`); :mod:`msctl.recorder.pull` does the I/O."""

from __future__ import annotations

#: Bytes asked per request. 64 KiB keeps each answer small: a cut throws away little, and
#: halts (sent at a higher priority) pass between its fragments.
CHUNK = 64 * 1024
#: Requests in flight at most. The agent answers the requests queued at each turn of its
#: loop, so more in flight is more per turn: on the rehearsal's wifi profile (two loaded
#: cores) 64 KiB x 8 pulled 2.2-2.4 MB/s where x 4 pulled 1.0-1.3 and x 1 1.0 (16 KiB x 4:
#: 0.6; 256 KiB x 4: 1.1-2.2). On a slow link :data:`IN_FLIGHT_SECONDS` bounds it lower.
WINDOW = 8


class ShortRead(ValueError):
    """A chunk of another size than asked: the file changed there while it was pulled."""


class ChunkWindow:
    """The resume bookkeeping of one file: which chunks to ask, which are in flight, and which
    bytes can be appended to the ``.part`` now (strictly in order).

    Args:
        size: The file's size.
        start: Bytes already in the ``.part`` (fetching starts there).
        chunk: Bytes per request.
        window: Requests in flight at most.
    """

    def __init__(self, size: int, start: int, chunk: int = CHUNK, window: int = WINDOW) -> None:
        if not 0 <= start <= size:
            raise ValueError(f"start {start} is outside a file of {size} bytes")
        if chunk <= 0 or window <= 0:
            raise ValueError("chunk and window must be positive")
        self.size = size
        self.chunk = chunk
        self.window = window
        #: Bytes in order so far: what the ``.part`` holds, where a later pull resumes.
        self.written = start
        self._next = start
        self._waiting: set[int] = set()
        self._early: dict[int, bytes] = {}
        self._again: list[int] = []

    @property
    def done(self) -> bool:
        """Whether every byte is written."""
        return self.written >= self.size

    @property
    def in_flight(self) -> int:
        """Requests asked and not answered."""
        return len(self._waiting)

    def expected(self, offset: int) -> int:
        """The bytes a request at ``offset`` returns."""
        return min(self.chunk, self.size - offset)

    @property
    def bytes_in_flight(self) -> int:
        """Bytes asked and not answered."""
        return sum(self.expected(offset) for offset in self._waiting)

    def asks(self, max_bytes: int = 0) -> list[tuple[int, int]]:
        """``(offset, size)`` of the requests to send now: the window's free places, chunks
        that failed first.

        Args:
            max_bytes: Bytes in flight at most (0: no bound); one request always may go.
        """
        asks = []
        in_flight = self.bytes_in_flight
        while len(self._waiting) < self.window:
            if self._again:
                offset = self._again[0]
            elif self._next < self.size:
                offset = self._next
            else:
                break
            size = self.expected(offset)
            if max_bytes and self._waiting and in_flight + size > max_bytes:
                break
            if self._again:
                self._again.pop(0)
            else:
                self._next += size
            self._waiting.add(offset)
            in_flight += size
            asks.append((offset, size))
        return asks

    def arrived(self, offset: int, data: bytes) -> bytes:
        """Take the answer to the request at ``offset``; returns the bytes to append now
        (empty while an earlier chunk is missing).

        Raises:
            ShortRead: If ``data`` is not as long as asked.
            ValueError: If nothing was asked at ``offset``.
        """
        if offset not in self._waiting:
            raise ValueError(f"no request at byte {offset} is waiting")
        if len(data) != self.expected(offset):
            raise ShortRead(
                f"{len(data)} bytes came at byte {offset:,} where {self.expected(offset)} were "
                "asked"
            )
        self._waiting.discard(offset)
        self._early[offset] = data
        ready = bytearray()
        while self.written in self._early:
            piece = self._early.pop(self.written)
            ready += piece
            self.written += len(piece)
        return bytes(ready)

    def failed(self, offset: int) -> None:
        """The request at ``offset`` got no answer: ask it again (before any new one)."""
        if offset in self._waiting:
            self._waiting.discard(offset)
            self._again.append(offset)
            self._again.sort()


class RateBudget:
    """A token bucket over the bytes asked, so a pull leaves the radio room for the rest.

    Args:
        rate: Bytes per second at most (0: no limit).
        burst: Bytes that may go at once (one chunk).
        now: The time it starts (seconds, any clock).
    """

    def __init__(self, rate: float, burst: int, now: float) -> None:
        self.rate = rate
        self.burst = burst
        self._tokens = float(burst)
        self._then = now

    def delay(self, size: int, now: float) -> float:
        """Seconds to wait before asking for ``size`` more bytes (the bytes are taken)."""
        if self.rate <= 0:
            return 0.0
        self._tokens = min(self.burst, self._tokens + (now - self._then) * self.rate)
        self._then = now
        self._tokens -= size
        return 0.0 if self._tokens >= 0 else -self._tokens / self.rate


def request_timeout(in_flight_bytes: int, rate: float, floor: float, ceiling: float) -> float:
    """Seconds a chunk request may take before it is asked again.

    On a slow link the answers of a window queue behind each other: at 256 kbit/s four
    64 KiB chunks take 8 s to come through, and a fixed bound would ask the last ones again
    while they are on their way, sending them twice. So the bound is three times what the
    link, at the rate seen so far, needs for every byte in flight, never below ``floor``
    (no rate known yet, or a fast link: a lost request is asked again soon) nor above
    ``ceiling``.

    Args:
        in_flight_bytes: Bytes asked and not answered, this request's included.
        rate: Bytes per second answered so far (0: not known yet).
        floor: The least bound.
        ceiling: The largest bound.
    """
    if rate <= 0:
        return floor
    return min(max(floor, 3.0 * in_flight_bytes / rate), max(ceiling, floor))


class RateMeter:
    """Bytes per second answered, from the first request on, over the whole pull (a radio's
    rate changes slowly; a short window would chase every burst of loss).

    Args:
        now: When the first request left (seconds, any clock); ``None``: not yet, see
            :meth:`asked`.
    """

    def __init__(self, now: float | None = None) -> None:
        self._started = now
        self._bytes = 0
        self._seconds = 0.0

    def asked(self, now: float) -> None:
        """A request left at ``now``: the clock starts at the first."""
        if self._started is None:
            self._started = now

    def answered(self, size: int, now: float) -> None:
        """``size`` bytes came at ``now``."""
        self.asked(now)
        assert self._started is not None
        self._bytes += size
        self._seconds = now - self._started

    @property
    def rate(self) -> float:
        """Bytes per second so far (0 until a second's worth is known)."""
        return self._bytes / self._seconds if self._seconds >= 1.0 else 0.0
