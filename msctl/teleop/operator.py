"""The teleop core run with the real clock, on its own thread, onto the wire.

Keys come in from the screen's thread (:meth:`Operator.press`): the core notes them under a
lock and the operator's thread is woken, so the screen never waits on the network. That
thread ticks the core when it is due (a key, the next period, the deadman's expiry) and puts
the commands on the wire through each mode's output.

Because the deadman runs here and not in the screen's loop, motion also stops when the screen
freezes: no key event reaches the core, the deadman runs out, the stop goes out.
:meth:`Operator.close` (quit, a crash, a signal) ends any motion with its one stop before it
returns.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from msctl.teleop.core import Command, Move, TeleopCore, TeleopView
from msctl.teleop.wire import Output

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Sent:
    """A command that went on the wire.

    Attributes:
        command: The core's command.
        at: Monotonic time it was handed to the wire.
        ok: Whether the output took it (False: it raised; see ``error``).
        error: What went wrong.
    """

    command: Command
    at: float
    ok: bool = True
    error: str = ""


class Operator:
    """A :class:`~msctl.teleop.core.TeleopCore` on its own thread.

    Args:
        core: The core.
        outputs: One output per mode (``joint``, ``ik``, ``drive``); a mode without one
            cannot send (its commands are reported as failed).
        clock: Monotonic seconds.
        on_sent: Called on the operator's thread after each command is handed to the wire
            (the screen's news, tests and the benchmark's timing).
    """

    def __init__(
        self,
        core: TeleopCore,
        outputs: Mapping[str, Output],
        clock: Callable[[], float] = time.monotonic,
        on_sent: Callable[[Sent], None] | None = None,
    ) -> None:
        self.core = core
        self.outputs = dict(outputs)
        self.clock = clock
        self.on_sent = on_sent
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._closing = False
        self._closed = False
        self._thread: threading.Thread | None = None
        #: Commands handed to the wire, and those an output refused.
        self.moves_sent = 0
        self.stops_sent = 0
        self.failures = 0
        #: The latest failure's text ("" when none).
        self.last_error = ""

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> Operator:
        """Start the thread."""
        self._thread = threading.Thread(target=self._run, name="teleop-operator", daemon=True)
        self._thread.start()
        return self

    def close(self, reason: str = "quit") -> None:
        """End any motion with its one stop, on the wire before this returns; stop the thread
        (idempotent)."""
        if self._closed:
            return
        with self._lock:
            self.core.stop(reason, self.clock())
            self._closing = True
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            if self._thread.is_alive():
                log.warning("the teleop operator thread did not stop within 5 s")
        # Whatever the thread had not flushed when it left (or all of it, never started).
        self._flush()
        self._closed = True

    def __enter__(self) -> Operator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close("crash" if exc[0] is not None else "quit")

    # ------------------------------------------------------------------ inputs (any thread)
    def press(self, key: str) -> str:
        """A key event; what it did (see :meth:`TeleopCore.press`)."""
        with self._lock:
            if self._closing:
                return "refused"
            result = self.core.press(key, self.clock())
        self._wake.set()
        return result

    def set_mode(self, mode: str) -> str:
        """Switch mode (the old mode's motion stops)."""
        with self._lock:
            result = self.core.set_mode(mode, self.clock())
        self._wake.set()
        return result

    def select(self, module: str, joint: str | None = None) -> None:
        """Select a module and joint of joint mode by name."""
        with self._lock:
            self.core.select(module, joint, self.clock())
        self._wake.set()

    def block(self, module: str, reason: str, why: str = "claim lost") -> None:
        """Command ``module`` no more (its claim was taken over, it was halted or is
        gone); see :meth:`TeleopCore.block`."""
        with self._lock:
            self.core.block(module, reason, self.clock(), why)
        self._wake.set()

    def unblock(self, module: str) -> None:
        """Command ``module`` again; see :meth:`TeleopCore.unblock`."""
        with self._lock:
            self.core.unblock(module)

    def stop(self, reason: str) -> None:
        """End the motion now (focus lost, e-stop...): one stop if anything moved."""
        with self._lock:
            self.core.stop(reason, self.clock())
        self._wake.set()

    def view(self) -> TeleopView:
        """The core's state for the screen."""
        with self._lock:
            return self.core.view()

    @property
    def idle(self) -> bool:
        """Nothing moving and nothing owed: the operator is silent until a key comes."""
        with self._lock:
            return self.core.next_wake(self.clock()) is None

    # ------------------------------------------------------------------ the thread
    def _run(self) -> None:
        while True:
            self._wake.clear()
            wake_at = self._flush()
            if self._closing:
                return
            timeout = None if wake_at is None else max(wake_at - self.clock(), 0.0)
            self._wake.wait(timeout)

    def _flush(self) -> float | None:
        """Tick the core and put its commands on the wire; when to tick next."""
        with self._lock:
            now = self.clock()
            commands = self.core.tick(now)
            wake_at = self.core.next_wake(now)
        for command in commands:
            self._send(command)
        return wake_at

    def _send(self, command: Command) -> None:
        output = self.outputs.get(command.mode)
        try:
            if output is None:
                raise RuntimeError(f"{command.mode} mode has no output")
            if isinstance(command, Move):
                output.move(command)
                self.moves_sent += 1
            else:
                output.stop(command)
                self.stops_sent += 1
            sent = Sent(command, self.clock())
        except Exception as exc:  # an output's failure must not end the deadman's thread
            self.failures += 1
            self.last_error = f"{_what(command)}: {exc}"
            log.debug("teleop command failed", exc_info=True)
            sent = Sent(command, self.clock(), ok=False, error=self.last_error)
        if self.on_sent is not None:
            try:
                self.on_sent(sent)
            except Exception:
                log.exception("teleop on_sent callback failed")


def _what(command: Command) -> str:
    kind = "move" if isinstance(command, Move) else "stop"
    where = command.target + (f" {command.joint}" if command.joint else "")
    return f"{command.mode} {kind} of {where}"
