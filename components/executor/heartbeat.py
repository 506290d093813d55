"""A worker process's proof of life: a byte down a pipe from its executor loop.

The supervisor starts each component worker with the write end of a pipe (its number in
``MSCTL_HEARTBEAT_FD``) and reads the other end. The executor loop beats at most every
:data:`PERIOD` seconds, from the loop itself and between handler calls: a process that is
stopped (SIGSTOP), deadlocked, or stuck in one handler stops beating, while its pid, its
open sockets and its liveliness tokens all still look fine. The supervisor calls it
unresponsive, then kills and restarts it (``msctl.launcher.supervisor``).

A pipe rather than a file's mtime or a Zenoh token: no disk (a full disk must not look like a
frozen worker), no network (a router restart must not either), and the supervisor stamps a
beat when it reads it, so a supervisor that was itself slow never mistakes its own delay for
the worker's.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable

#: The environment variable naming the inherited write end of the pipe.
FD_ENV = "MSCTL_HEARTBEAT_FD"
#: Seconds between beats (the supervisor calls a worker unresponsive after a few missed).
PERIOD = 0.25


class Heartbeat:
    """Writes one byte to a pipe at most every ``period`` seconds; never blocks, never raises.

    Args:
        fd: The pipe's write end.
        period: Least seconds between two beats.
        clock: Monotonic clock.
    """

    def __init__(
        self, fd: int, period: float = PERIOD, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.fd = fd
        self.period = period
        self._clock = clock
        self._last = float("-inf")
        os.set_blocking(fd, False)  # a supervisor that stops reading never stalls the loop
        os.set_inheritable(fd, False)  # nothing this process starts beats in its name

    @classmethod
    def from_env(cls) -> Heartbeat | None:
        """The heartbeat the supervisor asked for in ``MSCTL_HEARTBEAT_FD`` (or ``None``).

        The variable is removed, so nothing this process starts writes to a descriptor
        number that means something else there.
        """
        value = os.environ.pop(FD_ENV, None)
        if not value:
            return None
        try:
            return cls(int(value))
        except (ValueError, OSError):
            return None  # not a descriptor of ours: run without, as when not supervised

    def beat(self) -> None:
        """Beat if ``period`` has passed since the last one."""
        if self.fd < 0:
            return
        now = self._clock()
        if now - self._last < self.period:
            return
        self._last = now
        try:
            os.write(self.fd, b".")
        except BlockingIOError:
            pass  # the pipe is full: the supervisor has plenty of beats unread
        except OSError:
            self.close()  # the supervisor is gone: nobody to tell

    def close(self) -> None:
        """Stop beating (idempotent)."""
        if self.fd >= 0:
            try:
                os.close(self.fd)
            except OSError:
                pass
            self.fd = -1
