"""A fork server for the component workers: the heavy modules imported once, each worker forked.

Every component worker imports the same modules before it builds anything (Zenoh, NumPy, the
message types, the executor, its kinds' builders, Pinocchio for a limb, MuJoCo for the
simulator): about a CPU-second each, most of ``msctl up``'s start-up on a small computer. The
launcher starts one of these servers per run instead; it imports what every worker needs and
makes the message types (:data:`COMMON`), says it is ready, then forks one child per worker the
supervisor asks for, importing a worker's own kinds' modules first when no earlier worker
needed them (so a heavy import runs while the workers forked before it start). A child is what
``python -m msctl.launcher.boot MODULE ARGS`` would be, minus the imports.

This module is the supervisor's side (:class:`ForkServer`, :class:`ForkedProcess`, which
modules a kind's workers need); the server's own process, what a child is and why the server
keeps a single thread, are :mod:`msctl.launcher.forkserver_process` (run as
``python -m msctl.launcher.forkserver_process``).

The server is the children's parent, so it reaps them: each exit status goes back to the
supervisor on that child's own status socket (:class:`ForkedProcess` is the supervisor's
``subprocess.Popen`` for it). The supervisor ends the server after its children
(:meth:`ForkServer.close`); if the server dies, its children are judged by their pids (a pidfd
each, immune to pid reuse) and new workers are spawned as plain interpreters again.

Protocol (one ``AF_UNIX`` ``SOCK_SEQPACKET`` control socket; a ``SOCK_STREAM`` pair per child):

* server -> supervisor, once: ``ready`` (or ``error <why>``) after the first imports;
* supervisor -> server: a JSON request (module, arguments, environment, working directory, the
  environment variables that name passed pipes, modules to import first, a process name) with
  the descriptors: the status socket's server end, the output pipe, then the named pipes;
* child -> supervisor, on the status socket: ``pid <pid>`` once it is in its own session;
* server -> supervisor, on the status socket: ``exit <code>`` (``subprocess`` style: minus the
  signal's number when killed by one), or ``error <why>`` when it could not fork.
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import os
import select
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import IO, Any

from msctl.launcher import boot
from msctl.launcher.forkserver_process import COMMON
from msctl.launcher.forkserver_process import MODULE as SERVER_MODULE

__all__ = [
    "COMMON",
    "ENABLE_ENV",
    "RUN_ROOM",
    "SERVER_MODULE",
    "ForkServer",
    "ForkServerError",
    "ForkedProcess",
    "enabled",
    "for_run",
    "preload_for",
]

#: ``MSCTL_FORKSERVER=0`` spawns every worker as a fresh interpreter (as before the server).
ENABLE_ENV = "MSCTL_FORKSERVER"


class ForkServerError(RuntimeError):
    """The fork server cannot start this worker (the caller spawns it as before)."""


def enabled(environ: Mapping[str, str] = os.environ) -> bool:
    """Whether the launcher forks its Zenoh workers from a server (``MSCTL_FORKSERVER``)."""
    return environ.get(ENABLE_ENV, "1") != "0"


def preload_for(kind_names: Iterable[str]) -> list[str]:
    """The modules to import before forking the workers of these component kinds: each
    kind's registered modules (builder, interface, config, extensions), the other modules of
    its package and of the packages within it (its core, what the builder imports when it
    runs: a limb's Pinocchio model; an operator's scripts), and what it imports lazily once
    running (:attr:`ComponentKind.preload`)."""
    from components import kinds

    names: dict[str, None] = {}  # ordered, once each
    scanned: set[str] = set()
    for kind_name in dict.fromkeys(kind_names):
        try:
            kind = kinds.get(kind_name)
        except kinds.KindError:
            continue
        paths = [
            kind.builder,
            kind.interface,
            kind.validate,
            *kind.config,
            *kind.checks.values(),
            *kind.extensions,
        ]
        modules = [p.partition(":")[0] for p in paths if p]
        for module in list(modules):
            for package in (module.rpartition(".")[0], module):
                if package not in scanned:
                    scanned.add(package)
                    modules += _package_modules(package)
        names.update(dict.fromkeys((*modules, *kind.preload)))
    return list(names)


def _package_modules(package: str) -> list[str]:
    """Every module of one of msctl's component packages, its subpackages' included; none
    for a module that is not a package, or a package outside ``components``."""
    import pkgutil

    if not package.startswith("components."):
        return []
    try:
        found = importlib.util.find_spec(package)
    except (ImportError, ValueError):
        return []
    if found is None or not found.submodule_search_locations:
        return []
    found_names = []
    for info in pkgutil.iter_modules(found.submodule_search_locations):
        name = f"{package}.{info.name}"
        found_names.append(name)
        if info.ispkg:
            found_names += _package_modules(name)
    return found_names


# ---------------------------------------------------------------------------- supervisor side
class ForkedProcess:
    """A worker forked by the server, as the supervisor uses a :class:`subprocess.Popen`.

    Attributes:
        args: The command line it stands for (the boot one).
        pid: Its pid, also its process group's id.
        returncode: Its exit code once known (minus the signal's number when killed by one).
        stdout: Its output (stdout and stderr), text, read by the supervisor's pump.
    """

    def __init__(self, args: Sequence[str], pid: int, status: socket.socket, stdout: IO[str]):
        self.args = list(args)
        self.pid = pid
        self.returncode: int | None = None
        self.stdout: IO[str] | None = stdout
        self._status = status
        self._pending = b""
        try:
            # Ours, opened while it lives: tells its end even if the server is gone, and is
            # never another process that reused the pid.
            self._pidfd: int | None = os.pidfd_open(pid)
        except OSError:
            self._pidfd = None  # already gone (and reaped): the server tells its code

    def poll(self) -> int | None:
        """Its exit code if it has ended, else ``None`` (never blocks)."""
        if self.returncode is None:
            self._read(0.0)
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        """Wait for it to end; its exit code.

        Raises:
            subprocess.TimeoutExpired: If it is still running after ``timeout`` seconds.
        """
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.returncode is None:
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                raise subprocess.TimeoutExpired(self.args, timeout or 0.0)
            self._read(left if left is None else max(0.0, left))
        return self.returncode

    def _read(self, timeout: float | None) -> None:
        watched: list[Any] = [self._status]
        if self._status.fileno() < 0 and self._pidfd is not None:
            watched = [self._pidfd]  # the server is gone: its pidfd alone says it ended
        if self._status.fileno() < 0 and self._pidfd is None:
            self._finish(1)
            return
        ready, _, _ = select.select(watched, [], [], timeout)
        if not ready:
            return
        if ready[0] is not self._status:
            self._finish(1)  # ended while no server was there to reap it: code unknown
            return
        try:
            data = self._status.recv(4096)
        except OSError:
            data = b""
        if not data:
            self._status.close()  # the server died before telling; the pidfd decides
            if self._pidfd is not None and select.select([self._pidfd], [], [], 0)[0]:
                self._finish(1)
            return
        self.take(data)

    def take(self, data: bytes) -> None:
        """Read status lines (``exit <code>``) from the server."""
        self._pending += data
        while b"\n" in self._pending:
            line, self._pending = self._pending.split(b"\n", 1)
            word, _, value = line.decode().partition(" ")
            if word == "exit":
                self._finish(int(value))

    def _finish(self, code: int) -> None:
        self.returncode = code
        self._status.close()
        if self._pidfd is not None:
            with contextlib.suppress(OSError):
                os.close(self._pidfd)
            self._pidfd = None


#: Bytes of command line a server started before the plan is known keeps for its children's
#: (a longer one is shown cut; a plan's longest is a few hundred).
RUN_ROOM = 4096


def for_run(tag: Path | str, room: int = RUN_ROOM) -> ForkServer | None:
    """A fork server for one run's component workers, importing :data:`COMMON` from now on;
    ``None`` when workers start as new interpreters (``MSCTL_FORKSERVER=0``, or the rclpy
    transport, whose workers each initialise their own rclpy context).

    ``msctl up`` starts it before resolving the assembly: its imports (0.3 s of CPU) then run
    beside the resolution, on a core that is otherwise idle.

    Args:
        tag: The assembly's lock file (see :meth:`ForkServer.start`).
        room: Bytes of command line to keep for the children's.

    Raises:
        OSError: If it cannot be started.
    """
    from msctl.launcher import state

    if os.environ.get("MSCTL_TRANSPORT", "zenoh") != "zenoh" or not enabled():
        return None
    return ForkServer.start((), state.log_dir() / "forkserver.log", tag=str(tag), room=room)


class ForkServer:
    """The supervisor's handle on one fork server (started by :meth:`start`).

    Not thread-safe: used from the launcher's loop only, like the supervisor.
    """

    def __init__(self, popen: subprocess.Popen, control: socket.socket) -> None:
        self.popen = popen
        self._control = control
        self.ready = False
        self.failure = ""
        #: Process name -> modules the server imports before forking its worker (once: the
        #: server keeps them), so that it is ready after :data:`COMMON` alone and a heavy
        #: import (Pinocchio) runs while the workers forked before it start.
        self.preloads: dict[str, Sequence[str]] = {}

    @classmethod
    def start(
        cls, preload: Sequence[str], log_path: Path, tag: str = "", room: int = 0
    ) -> ForkServer:
        """Start a server that imports ``preload`` (after :data:`COMMON`) before saying ready.

        Args:
            preload: Further modules to import before forking.
            log_path: Where its own output goes (an import that failed, a refused fork).
            tag: Shown in its command line (a run's processes are found by it): the
                assembly's lock file.
            room: Bytes its command line spans at least: a child shows its own command line
                in that space (the longest worker's; a longer one is cut).
        """
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        argv = [sys.executable, "-m", SERVER_MODULE, "--control", str(theirs.fileno())]
        if tag:
            argv += ["--tag", tag]
        argv += [m for m in preload if m not in COMMON]
        missing = room - len("\0".join(argv)) - len(" --room ")
        if missing > 0:
            argv += ["--room", " " * missing]
        # One BLAS thread: a fork copies only the calling thread (see the module's doc).
        env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
        log_path.parent.mkdir(parents=True, exist_ok=True)
        try:
            with open(log_path, "ab") as log, boot.held_sigint():
                popen = subprocess.Popen(
                    argv,
                    env=env,
                    stdin=subprocess.DEVNULL,
                    stdout=log,
                    stderr=subprocess.STDOUT,
                    start_new_session=True,  # no terminal's Ctrl-C; ended by close()
                    pass_fds=(theirs.fileno(),),
                )
        finally:
            theirs.close()
        return cls(popen, ours)

    def wait_ready(self, timeout: float, stopping: Callable[[], bool] | None = None) -> bool:
        """Wait until it has imported :data:`COMMON` and says ready.

        Returns:
            Whether it is ready (``False``: it failed, timed out, or ``stopping`` said so;
            :attr:`failure` says which, and the caller spawns plain workers).
        """
        deadline = time.monotonic() + timeout
        while not self.ready and not self.failure:
            if stopping is not None and stopping():
                return False
            left = deadline - time.monotonic()
            if left <= 0:
                self.failure = f"not ready within {timeout:g} s"
                break
            ready, _, _ = select.select([self._control], [], [], min(left, 0.1))
            if not ready:
                continue
            try:
                message = self._control.recv(4096).decode()
            except OSError as exc:
                message = f"error {exc}"
            if message == "ready":
                self.ready = True
            else:
                self.failure = message.removeprefix("error ") or "it exited while importing"
        return self.ready

    def spawn(
        self,
        argv: Sequence[str],
        env: Mapping[str, str],
        pass_fds: Mapping[str, int],
        name: str = "",
        timeout: float = 120.0,
    ) -> ForkedProcess:
        """Fork a worker for ``argv`` (a :func:`msctl.launcher.boot.argv` command line).

        Args:
            argv: ``python -m msctl.launcher.boot MODULE ARGS``.
            env: Its environment.
            pass_fds: Environment variable -> descriptor of ours to pass; in the child the
                variable holds the descriptor's number there.
            name: Its process name (``/proc/PID/comm``: ``ps``, ``top``).
            timeout: Seconds to wait for it to start (the server may still be importing).

        Raises:
            ForkServerError: If the server cannot start it (the caller spawns it as before).
        """
        if not self.ready:
            raise ForkServerError(f"the fork server is not ready: {self.failure or 'starting'}")
        if list(argv[1:3]) != ["-m", boot.MODULE] or len(argv) < 4:
            raise ForkServerError(f"not a boot command line: {' '.join(argv)}")
        request = {
            "argv": list(argv),
            "module": argv[3],
            "args": list(argv[4:]),
            "env": dict(env),
            "cwd": os.getcwd(),
            "fd_env": list(pass_fds),
            "name": name,
            "preload": list(self.preloads.get(name, ())),
        }
        status_ours, status_theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        output_read, output_write = os.pipe()
        try:
            fds = [status_theirs.fileno(), output_write, *pass_fds.values()]
            try:
                socket.send_fds(self._control, [json.dumps(request).encode()], fds)
            except OSError as exc:
                self._broken(f"cannot reach it: {exc}")
                raise ForkServerError(self.failure) from exc
        finally:
            status_theirs.close()
            os.close(output_write)  # the child's copy only: its end closes the pipe
        try:
            pid, rest = _first_pid(status_ours, timeout)
        except ForkServerError as exc:
            _abandon(status_ours)
            os.close(output_read)
            self._broken(str(exc))  # plain interpreters from now on
            raise
        # As Popen(text=True) reads it; closed by the supervisor's pump.
        stdout = open(output_read, encoding=None, errors=None)  # noqa: SIM115
        process = ForkedProcess(argv, pid, status_ours, stdout)
        process.take(rest)  # its exit, when it came with the pid
        return process

    def _broken(self, why: str) -> None:
        self.ready = False
        self.failure = why

    def close(self, timeout: float = 2.0) -> None:
        """End the server (after its children: it reports their exits until they are gone);
        killed after ``timeout`` seconds (idempotent)."""
        self.ready = False
        self._control.close()
        try:
            self.popen.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(self.popen.pid, signal.SIGKILL)
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.popen.wait(timeout=5.0)


def _abandon(status: socket.socket) -> None:
    """Give up on a worker that did not say its pid in time: from now on its own ``pid``
    line fails and it exits at once; one that said it meanwhile is killed here."""
    with contextlib.suppress(OSError):
        status.shutdown(socket.SHUT_RD)  # its writes fail from here on (EPIPE)
        status.setblocking(False)
        late = status.recv(4096)
        word, _, value = late.split(b"\n", 1)[0].decode().partition(" ")
        if word == "pid" and value.isdigit() and int(value) > 0:
            os.killpg(int(value), signal.SIGKILL)
    status.close()


def _first_pid(status: socket.socket, timeout: float) -> tuple[int, bytes]:
    """The ``pid`` line the child sends once in its own session, and what came after it."""
    deadline = time.monotonic() + timeout
    pending = b""
    while b"\n" not in pending:
        left = deadline - time.monotonic()
        if left <= 0 or not select.select([status], [], [], left)[0]:
            raise ForkServerError(f"no worker started within {timeout:g} s")
        chunk = status.recv(4096)
        if not chunk:
            raise ForkServerError("the fork server ended before the worker started")
        pending += chunk
    line, rest = pending.split(b"\n", 1)
    word, _, value = line.decode().partition(" ")
    if word != "pid":
        raise ForkServerError(f"the fork server could not start it: {value or line.decode()}")
    return int(value), rest
