"""Orders from the supervisor to a worker process: lines down a pipe.

The heartbeat (:mod:`components.executor.heartbeat`) goes up from the worker; orders go down.
The supervisor starts each component worker with the read end of a second pipe (its number
in ``MSCTL_ORDERS_FD``) and writes one order per line. The only order today is
``rebuild <component>``: stop that one core, take its node off the data plane, build it
anew from the assembly and start it, leaving the process's other components running
(``msctl restart --only``).

A pipe, like the heartbeat, and for the same reasons: no network (an order must not depend on
the router the order may be about), no disk, and nobody but the supervisor holds the write end.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Callable

#: The environment variable naming the inherited read end of the pipe.
FD_ENV = "MSCTL_ORDERS_FD"
#: The order to rebuild one component (followed by a space and its name).
REBUILD = "rebuild"
#: Longest order line accepted (a component name is far shorter).
MAX_LINE = 4096

log = logging.getLogger("msctl.orders")


def encode(order: str, argument: str) -> bytes:
    """One order line (``argument`` must be one line: a component name)."""
    if "\n" in argument or "\r" in argument:
        raise ValueError(f"an order's argument is one line, not {argument!r}")
    return f"{order} {argument}\n".encode()


class Orders:
    """Reads order lines from a pipe on a daemon thread and hands each to ``on_order``.

    Args:
        fd: The pipe's read end.
        on_order: Called as ``on_order(order, argument)`` from the reading thread; it must
            hand the work to the executor (``Executor.post``), never do it there.
    """

    def __init__(self, fd: int, on_order: Callable[[str, str], None]) -> None:
        self.fd = fd
        os.set_inheritable(fd, False)  # nothing this process starts reads our orders
        self._on_order = on_order
        self._thread = threading.Thread(target=self._read, name="orders", daemon=True)

    @classmethod
    def from_env(cls, on_order: Callable[[str, str], None]) -> Orders | None:
        """The pipe the supervisor handed down in ``MSCTL_ORDERS_FD`` (or ``None``).

        The variable is removed, so nothing this process starts reads a descriptor number
        that means something else there.
        """
        value = os.environ.pop(FD_ENV, None)
        if not value:
            return None
        try:
            return cls(int(value), on_order)
        except (ValueError, OSError):
            return None  # not a descriptor of ours: no orders, as when not supervised

    def start(self) -> Orders:
        """Start reading; returns itself."""
        self._thread.start()
        return self

    def _read(self) -> None:
        pending = b""
        while True:
            try:
                chunk = os.read(self.fd, 4096)
            except OSError:
                return
            if not chunk:
                return  # the supervisor is gone (or closed its end): no more orders
            pending += chunk
            while b"\n" in pending:
                line, pending = pending.split(b"\n", 1)
                self._handle(line)
            if len(pending) > MAX_LINE:
                log.warning("dropped an order line longer than %d bytes", MAX_LINE)
                pending = b""

    def _handle(self, line: bytes) -> None:
        order, _, argument = line.decode("utf-8", "replace").strip().partition(" ")
        if order != REBUILD or not argument:
            log.warning("ignored an unknown order %r", line[:80])
            return
        try:
            self._on_order(order, argument)
        except Exception:
            log.exception("order %r failed", order)
