"""A real :class:`Supervisor` with quick restarts for tests, and nothing it started left over."""

from __future__ import annotations

import contextlib
import os
import signal
from collections.abc import Iterator
from pathlib import Path

from msctl.launcher.supervisor import RestartPolicy, ShutdownPolicy, Supervisor


@contextlib.contextmanager
def quick_supervisor(logs: Path, backoff_max: float = 1.0) -> Iterator[Supervisor]:
    """A supervisor with quick backoff; every process group it started is killed at the end.

    Args:
        logs: Its log directory.
        backoff_max: The longest wait before a restart (s).
    """
    sup = Supervisor(
        logs,
        RestartPolicy(max_restarts=3, window=30.0, backoff_initial=0.05, backoff_max=backoff_max),
        ShutdownPolicy(after_sigint=0.5, after_sigterm=0.5),
    )
    pgids: set[int] = set()
    original = sup._spawn

    def spawn(process):
        original(process)
        if process.popen is not None:
            pgids.add(process.popen.pid)

    sup._spawn = spawn  # type: ignore[method-assign]
    try:
        yield sup
    finally:
        sup.shutdown()
        for pgid in pgids:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(pgid, signal.SIGKILL)
