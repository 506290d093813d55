"""Start the launcher's processes so that a SIGINT while they start ends them quietly.

The launcher starts every process it supervises (the component workers, the embedded router)
through this module::

    python -m msctl.launcher.boot components.executor.worker --lock PATH --component ...

Python turns SIGINT into ``KeyboardInterrupt`` from its first line of code, and even earlier,
while it imports ``site``; a process spends its first second or more importing (its package,
Zenoh, the message types, MuJoCo). The supervisor stops a run with SIGINT first, so a Ctrl-C
on ``msctl up`` while it was still starting left a ``KeyboardInterrupt`` traceback (or a
"Fatal Python error: init_import_site") from deep inside some import in every log, and a long
import in C code made the supervisor wait for it.

So the launcher spawns them with SIGINT blocked (:func:`held_sigint`: a blocked signal stays
pending, never lost, and the mask survives ``exec``), and here, before anything else is
imported, SIGINT gets the system's default action and is unblocked: a SIGINT that came
during the interpreter's start-up, or comes while the program imports, ends the process at
once, and it has nothing to close yet. The program sets its own handling once it has
something to close (``components.executor.worker``'s ``main``, ``msctl router``'s command).
"""

from __future__ import annotations

import contextlib
import faulthandler
import runpy
import signal
import sys
from collections.abc import Iterator

#: This module's name (``__name__`` is ``__main__`` when it runs).
MODULE = "msctl.launcher.boot"
USAGE = f"usage: python -m {MODULE} MODULE [ARG ...]"


def argv(module: str, *args: str) -> list[str]:
    """The command line that runs ``python -m MODULE ARGS`` through this module."""
    return [sys.executable, "-m", MODULE, module, *args]


@contextlib.contextmanager
def held_sigint() -> Iterator[None]:
    """Block SIGINT in the calling thread meanwhile: what it spawns starts with SIGINT
    blocked (for :func:`main` to unblock), and a SIGINT sent meanwhile waits, never lost.

    Python runs signal handlers on the main thread only, and another thread (a Zenoh one)
    may take the signal meanwhile for it, so the caller's own Ctrl-C is not delayed either.
    """
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def main() -> None:
    """Run the module named by the first argument as ``__main__``, with the rest as its argv."""
    # First of all, then unblocked: a SIGINT pending since the spawn ends the process here.
    _default_sigint()
    if len(sys.argv) < 2 or sys.argv[1].startswith("-"):
        print(USAGE, file=sys.stderr)
        sys.exit(2)
    run(sys.argv[1], sys.argv[2:])


def run(module: str, args: list[str]) -> None:
    """Run ``module`` as ``__main__`` with ``args``, SIGINT ending it at once until it sets its
    own handling (also what a worker forked by :mod:`msctl.launcher.forkserver_process` does)."""
    _default_sigint()
    # A crash in native code leaves where each thread was in the process's log.
    enable_faulthandler()
    # As `python -m MODULE ARG ...` would see it (runpy sets argv[0] to the module's file).
    sys.argv = [sys.argv[0], *args]
    runpy.run_module(module, run_name="__main__", alter_sys=True)


def _default_sigint() -> None:
    """SIGINT's default action, then unblocked: one pending since the spawn (or the fork)
    ends the process here."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def enable_faulthandler() -> None:
    """Dump every thread's traceback on a fatal signal, where stderr is a real file (a
    caller that replaced ``sys.stderr``, e.g. a test capturing it, has none to write to)."""
    try:
        faulthandler.enable()
    except (OSError, ValueError, AttributeError):  # io.UnsupportedOperation: no fileno()
        pass


if __name__ == "__main__":
    main()
