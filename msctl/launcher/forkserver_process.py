"""The fork server's own process: imports once, then forks a child per worker and reaps it.

Started by :meth:`msctl.launcher.forkserver.ForkServer.start` as ``python -m
msctl.launcher.forkserver_process --control FD [--tag LOCK] [--room ...] [PRELOAD ...]``; the
protocol it speaks is in :mod:`msctl.launcher.forkserver`'s documentation. A child is what
``python -m msctl.launcher.boot MODULE ARGS`` would be, minus the imports:

* its own session and process group (``setsid``), so the supervisor's signals to the group
  reach it and whatever it starts, exactly as for a spawned worker;
* SIGINT as :mod:`msctl.launcher.boot` leaves it: the server runs with SIGINT blocked (the
  launcher starts it so) and the child sets the default action, then unblocks, so a SIGINT
  sent since the fork ends it at once, quietly;
* stdin on ``/dev/null``, stdout and stderr on the pipe the supervisor reads, its heartbeat and
  orders pipes (their numbers in the child written into the environment it names), the
  supervisor's environment and working directory, and no other descriptor of the server;
* the module run as ``__main__`` with its arguments; the process exits as the interpreter
  would after it (exit code, ``atexit``, an uncaught ``KeyboardInterrupt``).

Nothing in the server opens a Zenoh session or starts a thread: a fork copies only the calling
thread, so a thread's locks (Zenoh's runtime, an OpenBLAS pool) would be held forever in the
child. The server checks it is single-threaded before every fork and refuses otherwise (its
OpenBLAS runs single-threaded for that: ``OPENBLAS_NUM_THREADS=1``); sessions and threads are
made by the children.
"""

from __future__ import annotations

import contextlib
import importlib
import json
import os
import re
import select
import socket
import sys
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from msctl.launcher import boot

#: This module's name (``__name__`` is ``__main__`` when it runs).
MODULE = "msctl.launcher.forkserver_process"
#: Imported by the server before it says ready: what every component worker imports. Not
#: the worker module itself (only what it imports): a child runs it as ``__main__``, and a
#: module already imported would be run a second time, under runpy's RuntimeWarning in
#: every worker's log.
COMMON = (
    "argparse",
    "ctypes",
    "numpy",
    "zenoh",
    "components.messages",
    "components.assembly",
    "components.build",
    "components.executor.heartbeat",
    "components.executor.runner",
    "components.executor.executor",
    "zenoh.ext",
    "components.comm.node",
    "components.comm.topics",
    "components.comm.publishers",
    "components.comm.liveliness",
    "components.comm.graph",
    "components.claims",
    "rosbags.typesys",
)
#: Largest request (its environment is most of it).
MAX_REQUEST = 1 << 20
#: Descriptors per request: the status socket, the output pipe, and a few named pipes.
MAX_FDS = 8


class _Child:
    """What a forked child runs once it has left the server's loop."""

    def __init__(self, request: dict[str, Any], fds: list[int]) -> None:
        self.request = request
        self.fds = fds

    def run(self) -> None:
        """Become the worker: session, descriptors, environment, then its module."""
        status, output, *named = self.fds
        os.setsid()
        null = os.open(os.devnull, os.O_RDONLY)
        os.dup2(null, 0)
        os.dup2(output, 1)
        os.dup2(output, 2)
        keep = {0, 1, 2, *named}
        env = dict(self.request["env"])
        for variable, fd in zip(self.request["fd_env"], named, strict=True):
            env[variable] = str(fd)
        try:
            # Told only now, in its own session: a signal to its group cannot miss it.
            os.write(status, f"pid {os.getpid()}\n".encode())
        except OSError:
            os._exit(1)  # the supervisor gave up on it (or is gone): nobody would watch it
        _close_all_but(keep)
        os.environ.clear()
        os.environ.update(env)
        os.chdir(self.request["cwd"])
        _set_name(self.request.get("name") or self.request["module"])
        _set_command_line(self.request.get("argv") or [])
        boot.run(self.request["module"], self.request["args"])


def _close_all_but(keep: set[int]) -> None:
    for entry in os.listdir("/proc/self/fd"):
        fd = int(entry)
        if fd not in keep:
            with contextlib.suppress(OSError):
                os.close(fd)


def _set_name(name: str) -> None:
    """The process's name in ``ps``/``top`` (its command line stays the server's)."""
    with contextlib.suppress(OSError):
        Path("/proc/self/comm").write_text(name.replace("/", "_")[:15])


def _set_command_line(argv: Sequence[str]) -> None:
    """Show the worker's own command line in ``/proc/PID/cmdline`` (``ps``, ``pgrep -f``, the
    launcher's check that a pid is one of msctl's), not the server's it was forked with.

    Written over the server's argument strings (the interpreter copied them at its start and
    never reads them again), within their length: :meth:`ForkServer.start` makes room.
    """
    import ctypes

    if not argv:
        return
    try:
        fields = Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()
        start, end = int(fields[45]), int(fields[46])  # arg_start, arg_end (fields 48, 49)
    except (OSError, IndexError, ValueError):
        return
    if end - start < 2:
        return
    data = "\0".join(argv).encode()[: end - start - 1]
    ctypes.memmove(start, data + b"\0" * (end - start - len(data)), end - start)


def _threads() -> int:
    return len(os.listdir("/proc/self/task"))


def _import_all(modules: Iterable[str]) -> None:
    for module in modules:
        if module in sys.modules:
            continue
        try:
            importlib.import_module(module)
        except Exception as exc:  # its worker will say the same, in its own log
            print(f"forkserver: not preloaded {module}: {exc!r}", file=sys.stderr, flush=True)


def _warm_kinds() -> None:
    """Load the kind registry once: every worker looks its kinds up in it, and loading it
    imports the kind modules not preloaded (kinds that do not run here) and reads the
    installed distributions' entry points."""
    from components import kinds

    try:
        kinds.registry()
    except Exception as exc:  # a broken kind: each worker says so in its own log
        print(f"forkserver: kinds not preloaded: {exc!r}", file=sys.stderr, flush=True)


#: A ROS type name as msctl's modules spell them in constants (``sensor_msgs/msg/JointState``).
_TYPE_NAME = re.compile(r"^[A-Za-z]\w*/(msg|srv)/[A-Za-z]\w*$")


def _type_names() -> list[str]:
    """The message and service types the imported component modules name: their interface
    declarations and their module-level type-name constants."""
    from components.executor.interface import InterfaceSpec

    names: set[str] = set()
    for module_name, module in list(sys.modules.items()):
        if not module_name.startswith("components.") or module is None:
            continue
        for value in list(vars(module).values()):
            if isinstance(value, str) and _TYPE_NAME.match(value):
                names.add(value)
            elif isinstance(value, InterfaceSpec):
                names.update(entry.msg_type for entry in (*value.subscribe, *value.publish))
                names.update(entry.srv_type for entry in value.serve)
    return sorted(names)


#: The types :func:`_warm_types` has made (or tried to).
_warmed: set[str] = set()


def _warm_types(names: Iterable[str]) -> None:
    """Make each type's classes, codecs and hash in the shared type registry now, once: every
    worker made them again on its first publisher, subscription and service (a few tenths of
    a CPU-second each: parsing definitions, compiling the codecs)."""
    from components.comm.types import registry

    types = registry()
    for name in names:
        if name in _warmed:
            continue
        _warmed.add(name)
        try:
            types.prepare(name)
        except Exception as exc:  # a worker using it says the same, in its own log
            print(f"forkserver: type {name} not prepared: {exc!r}", file=sys.stderr, flush=True)


def _serve(control: socket.socket) -> _Child | None:
    """Fork a child per request and report their exits; returns in a child (to run it), or
    ``None`` in the server once the supervisor has gone and every child has ended."""
    children: dict[int, tuple[int, socket.socket]] = {}  # pidfd -> (pid, status socket)
    open_control = True
    while open_control or children:
        watched = ([control.fileno()] if open_control else []) + list(children)
        ready, _, _ = select.select(watched, [], [])
        for fd in ready:
            if fd in children:
                pid, status = children.pop(fd)
                _, wait_status = os.waitpid(pid, 0)
                os.close(fd)
                with contextlib.suppress(OSError):
                    status.sendall(f"exit {os.waitstatus_to_exitcode(wait_status)}\n".encode())
                status.close()
                continue
            try:
                data, fds, _, _ = socket.recv_fds(control, MAX_REQUEST, MAX_FDS)
            except OSError:
                data, fds = b"", []
            if not data:
                open_control = False  # the supervisor is gone or done: reap, then exit
                control.close()
                continue
            child = _fork(json.loads(data), fds, children, control)
            if child is not None:
                return child
    return None


def _fork(
    request: dict[str, Any],
    fds: list[int],
    children: dict[int, tuple[int, socket.socket]],
    control: socket.socket,
) -> _Child | None:
    status = socket.socket(fileno=fds[0])
    new = [m for m in request.get("preload", ()) if m not in sys.modules]
    if new:
        _import_all(new)
        _warm_types(_type_names())
    threads = _threads()
    if threads != 1:
        why = f"the fork server runs {threads} threads: forking would copy one"
        with contextlib.suppress(OSError):
            status.sendall(f"error {why}\n".encode())
        status.close()
        for fd in fds[1:]:
            os.close(fd)
        return None
    sys.stdout.flush()
    sys.stderr.flush()
    try:
        pid = os.fork()
    except OSError as exc:
        with contextlib.suppress(OSError):
            status.sendall(f"error cannot fork: {exc}\n".encode())
        status.close()
        for fd in fds[1:]:
            os.close(fd)
        return None
    if pid == 0:
        control.detach()  # closed with every other descriptor by the child itself
        status.detach()
        return _Child(request, fds)
    for fd in fds[1:]:
        os.close(fd)  # the child's: our copies would keep its pipes open after it
    children[os.pidfd_open(pid)] = (pid, status)
    return None


def main() -> None:
    """Import, say ready, serve; in a forked child, run its module as ``__main__``."""
    import argparse

    parser = argparse.ArgumentParser(prog=f"python -m {MODULE}")
    parser.add_argument("--control", type=int, required=True)
    parser.add_argument("--tag", default="")
    parser.add_argument("--room", default="", help="space for the children's command lines")
    parser.add_argument("preload", nargs="*")
    args = parser.parse_args()
    control = socket.socket(fileno=args.control)
    _import_all((*COMMON, *args.preload))
    _warm_kinds()
    _warm_types(_type_names())
    threads = _threads()
    message = "ready" if threads == 1 else f"error {threads} threads after importing"
    with contextlib.suppress(OSError):
        control.send(message.encode())
    if threads != 1:
        return
    child = _serve(control)
    if child is not None:
        child.run()


if __name__ == "__main__":
    main()
