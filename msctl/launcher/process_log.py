"""A supervised process's output: each line stamped with the time, written to a file that
rotates past a size, the last lines kept in memory for ``msctl logs`` and ``ps``."""

from __future__ import annotations

import contextlib
import errno
import os
import re
import threading
import time
from collections import deque
from pathlib import Path

#: A line that already starts with a date and time (Python logging's ``asctime``).
_STAMPED = re.compile(r"^\d{4}-\d\d-\d\d[ T]\d\d:\d\d:\d\d")


def stamp(line: str, now: float | None = None) -> str:
    """``line`` with the local date and time in front, unless it already starts with one
    (a traceback or a ``print`` has none; a logging line has its own)."""
    if _STAMPED.match(line):
        return line
    when = time.time() if now is None else now
    day_time = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(when))
    return f"{day_time}.{int(when % 1 * 1000):03d} {line}"


class RotatingLog:
    """A log file that rotates to ``.1`` .. ``.N`` past a size, keeping the last lines in memory.

    Every line in the file carries the date and time it arrived (:func:`stamp`). Writing never
    raises: on a full disk (or any other write error) the line is dropped and counted, the
    supervisor warns once (:attr:`dropped`, :attr:`fault`), and once writing works again a
    line in the file says how many were lost. The lines stay in memory either way.

    Attributes:
        tail: The last lines as the process wrote them (error reasons are read from these).
        recent: The same lines as the file has them, with their times (``msctl logs``).
        dropped: Lines that could not be written to the file.
        lines: Lines written since it was opened.
        fault: The last write error, while writing fails (``""`` when it works).
    """

    def __init__(self, path: Path, max_bytes: int = 5_000_000, backups: int = 3, tail: int = 50):
        self.path = path
        self.max_bytes = max_bytes
        self.backups = backups
        self.tail: deque[str] = deque(maxlen=tail)
        self.recent: deque[str] = deque(maxlen=tail)
        self.dropped = 0
        self.fault = ""
        self.lines = 0  # written since it was opened (to find the lines after a moment)
        self._unreported = 0
        self._lock = threading.Lock()
        self._closed = False
        path.parent.mkdir(parents=True, exist_ok=True)
        # A raw descriptor: a failed write leaves nothing buffered to fail again later.
        self._fd: int | None = self._open()

    def _open(self) -> int:
        return os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_CLOEXEC, 0o644)

    def write_line(self, line: str) -> None:
        """Append one line, stamped (thread-safe), rotating first if the file is too big."""
        line = line.rstrip("\n")
        stamped = stamp(line)
        with self._lock:
            self.lines += 1
            self.tail.append(line)
            self.recent.append(stamped)
            if self._closed:
                return
            data = (stamped + "\n").encode("utf-8", "replace")
            if self._unreported:
                note = stamp(f"--- msctl: {self._unreported} log lines lost: {self.fault}")
                data = (note + "\n").encode() + data
            try:
                if self._fd is None:
                    self._fd = self._open()  # a rotation that could not reopen it
                if os.fstat(self._fd).st_size > self.max_bytes:
                    self._rotate()
                _write_all(self._fd, data)
            except OSError as exc:
                self.dropped += 1
                self._unreported += 1
                self.fault = os.strerror(exc.errno) if exc.errno else str(exc)
                return
            self._unreported = 0
            self.fault = ""

    def since(self, lines: int) -> list[str]:
        """The lines (as the process wrote them) after the first ``lines``, as far as the
        tail still holds them."""
        with self._lock:
            count = min(self.lines - lines, len(self.tail))
            return list(self.tail)[len(self.tail) - count :] if count > 0 else []

    def mark_run(self, what: str) -> None:
        """Write the line that separates this run from the previous ones in the file."""
        self.write_line(f"===== {what} =====")

    def _rotate(self) -> None:
        assert self._fd is not None
        for index in range(self.backups - 1, 0, -1):
            older = self.path.with_name(f"{self.path.name}.{index}")
            if older.exists():
                older.replace(self.path.with_name(f"{self.path.name}.{index + 1}"))
        self.path.replace(self.path.with_name(f"{self.path.name}.1"))
        os.close(self._fd)
        self._fd = None
        self._fd = self._open()

    def close(self) -> None:
        """Close the file (idempotent)."""
        with self._lock:
            self._closed = True
            if self._fd is not None:
                with contextlib.suppress(OSError):
                    os.close(self._fd)
                self._fd = None


def _write_all(fd: int, data: bytes) -> None:
    """Write every byte, or raise (a short write on a full disk is ENOSPC for the rest)."""
    view = memoryview(data)
    while view:
        written = os.write(fd, view)
        if written == 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        view = view[written:]
