"""The supervisor: owns this computer's component processes.

Each process runs in its own process group (so nothing it starts is orphaned), its output
is pumped into a per-process log file with rotation (and the last lines kept for error
messages), and it is restarted with exponential backoff when it dies, up to a maximum in a
window, after which it is FAILED with the reason. A process whose exit code says a restart
would fail the same way (its ``final_exits``: the component worker's "cannot be built") is
FAILED at once, with the line that says why. Shutdown is SIGINT, then SIGTERM, then
SIGKILL to the whole group, with short timeouts: never a 19-second hang.

A process started with a heartbeat (the component workers) gets the write end of a pipe
(:mod:`components.executor.heartbeat`); once it has beaten, silence for
:attr:`LivenessPolicy.unresponsive_after` makes it UNRESPONSIVE (a stopped or stuck process
keeps its pid and its sockets, so nothing else would tell), and silence for
:attr:`LivenessPolicy.kill_after` more gets it SIGKILLed and restarted as for a crash.

A process given a fork server (:mod:`msctl.launcher.forkserver`: the launcher's component
workers) is forked from it instead of started as a new interpreter, with the same process
group, pipes and signals; while the server does not work, it is started as a new interpreter.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import threading
import time
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path

from components.executor.heartbeat import FD_ENV as HEARTBEAT_FD_ENV
from components.executor.orders import FD_ENV as ORDERS_FD_ENV
from components.executor.orders import REBUILD, encode
from components.supervision.protocol import ProcessRow
from msctl.launcher.forkserver import ForkedProcess, ForkServer, ForkServerError
from msctl.launcher.process_log import RotatingLog

#: A supervised process's handle: spawned, or forked from a fork server.
Child = subprocess.Popen | ForkedProcess


class ProcessState(StrEnum):
    """Lifecycle of a supervised process (and of the components in it)."""

    STARTING = "starting"
    RUNNING = "running"
    RESTARTING = "restarting"
    UNRESPONSIVE = "unresponsive"
    FAILED = "failed"
    STOPPED = "stopped"


@dataclass(frozen=True)
class RestartPolicy:
    """When and how often a dead process is started again.

    Attributes:
        max_restarts: Restarts allowed within ``window`` seconds before giving up (FAILED).
        window: Seconds over which restarts are counted.
        backoff_initial: Delay before the first restart; doubled for each further one.
        backoff_max: Largest delay.
        stable_after: A process alive this long resets its backoff.
    """

    max_restarts: int = 5
    window: float = 60.0
    backoff_initial: float = 0.25
    backoff_max: float = 8.0
    stable_after: float = 10.0


@dataclass(frozen=True)
class LivenessPolicy:
    """When a process with a heartbeat that stopped beating is unresponsive, then killed.

    Attributes:
        unresponsive_after: Seconds without a beat before it is UNRESPONSIVE (it beats
            every 0.25 s; a loaded machine delays beats by far less than this).
        kill_after: Further seconds of silence before it is SIGKILLed and restarted; until
            then it may come back by itself (a long garbage collection, a SIGCONT).
    """

    unresponsive_after: float = 1.0
    kill_after: float = 5.0


@dataclass(frozen=True)
class ShutdownPolicy:
    """Seconds to wait after SIGINT, then after SIGTERM, before SIGKILL."""

    after_sigint: float = 2.0
    after_sigterm: float = 1.0


@dataclass
class ManagedProcess:
    """One supervised process and its history.

    Attributes:
        final_exits: Exit codes by which the program says a restart would fail the same way
            (a configuration or build error, bad arguments), each with what it means: such an
            exit is FAILED at once, never retried.
    """

    name: str
    argv: list[str]
    env: dict[str, str]
    log: RotatingLog
    components: tuple[str, ...] = ()
    final_exits: Mapping[int, str] = field(default_factory=dict)
    state: ProcessState = ProcessState.STOPPED
    popen: Child | None = None
    started_at: float = 0.0
    restarts: int = 0
    last_error: str = ""
    next_start: float | None = None
    restart_times: deque[float] = field(default_factory=lambda: deque(maxlen=64))
    backoff: float = 0.0
    wanted: bool = True
    pump: threading.Thread | None = None
    heartbeat: bool = False
    beat_fd: int | None = None
    orders_fd: int | None = None
    last_beat: float | None = None
    state_before_silence: ProcessState | None = None
    forkserver: ForkServer | None = None

    @property
    def pid(self) -> int | None:
        """The live pid, if running."""
        return self.popen.pid if self.popen is not None and self.popen.poll() is None else None

    def uptime(self, now: float) -> float:
        """Seconds since the current incarnation started (0 when not running)."""
        return now - self.started_at if self.pid is not None else 0.0


class Supervisor:
    """Starts, watches, restarts and stops this computer's processes.

    Not thread-safe by itself: call :meth:`poll`, :meth:`restart`, :meth:`stop` from one
    thread (the launcher's loop); output pumping runs on its own threads.
    """

    def __init__(
        self,
        log_dir: Path,
        policy: RestartPolicy | None = None,
        shutdown: ShutdownPolicy | None = None,
        liveness: LivenessPolicy | None = None,
        run: str = "",
    ) -> None:
        self.log_dir = log_dir
        self.policy = policy or RestartPolicy()
        self.liveness = liveness or LivenessPolicy()
        self.shutdown_policy = shutdown or ShutdownPolicy()
        self.run = run
        self.processes: dict[str, ManagedProcess] = {}
        self._log_faults: dict[str, str] = {}  # process -> the fault warned about

    def add(
        self,
        name: str,
        argv: Sequence[str],
        env: dict[str, str] | None = None,
        components: Sequence[str] = (),
        final_exits: Mapping[int, str] | None = None,
        heartbeat: bool = False,
        forkserver: ForkServer | None = None,
    ) -> ManagedProcess:
        """Register a process (not started yet).

        Args:
            name: The process's name (its log file is named after it).
            argv: Its command line.
            env: Variables added to this process's environment.
            components: The components it runs.
            final_exits: Exit codes after which it is FAILED at once, never restarted, each
                with what it means (see :class:`ManagedProcess`).
            heartbeat: Hand it a heartbeat pipe (``MSCTL_HEARTBEAT_FD``) and watch it.
            forkserver: Fork it from this server (``argv`` a :func:`msctl.launcher.boot.argv`
                line) rather than start a new interpreter, while the server works.
        """
        log = RotatingLog(self.log_dir / f"{name.replace('/', '_')}.log")
        # The file keeps earlier runs' lines: this one starts here.
        log.mark_run(f"{self.run or 'run'} started, supervisor pid {os.getpid()}")
        process = ManagedProcess(
            name=name,
            argv=list(argv),
            env={**os.environ, **(env or {})},
            log=log,
            components=tuple(components),
            final_exits=dict(final_exits or {}),
            heartbeat=heartbeat,
            forkserver=forkserver,
        )
        self.processes[name] = process
        return process

    # ------------------------------------------------------------------ starting
    def start(self, name: str) -> None:
        """Start one process now (it becomes STARTING); one already alive is left as it is."""
        process = self.processes[name]
        process.wanted = True
        process.next_start = None
        if process.pid is not None:
            return  # a second copy would drive the same hardware, and the first be lost
        self._spawn(process)

    def start_all(self) -> None:
        """Start every registered process."""
        for name in self.processes:
            self.start(name)

    def _spawn(self, process: ManagedProcess) -> None:
        process.log.write_line(f"--- msctl: starting {process.name}: {' '.join(process.argv)}")
        _close_heartbeat(process)
        env, named, writer, reader = process.env, {}, None, None
        try:
            if process.heartbeat:
                # Two pipes: its heartbeat up, our orders down (components.executor.orders).
                process.beat_fd, writer = os.pipe()
                os.set_blocking(process.beat_fd, False)
                reader, process.orders_fd = os.pipe()
                os.set_blocking(process.orders_fd, False)
                env = {**process.env, HEARTBEAT_FD_ENV: str(writer), ORDERS_FD_ENV: str(reader)}
                named = {HEARTBEAT_FD_ENV: writer, ORDERS_FD_ENV: reader}
            popen: Child | None = None
            server = process.forkserver
            if server is not None and server.ready:
                try:
                    popen = server.spawn(process.argv, env, named, name=process.name)
                except ForkServerError as exc:
                    process.log.write_line(
                        f"--- msctl: not forked ({exc}); starting a new interpreter"
                    )
            if popen is None:
                popen = subprocess.Popen(
                    process.argv,
                    env=env,
                    stdin=subprocess.DEVNULL,
                    stdout=subprocess.PIPE,
                    stderr=subprocess.STDOUT,
                    text=True,
                    bufsize=1,
                    start_new_session=True,  # its own process group: nothing outlives a kill
                    pass_fds=tuple(named.values()),
                )
        except OSError as exc:
            _close_heartbeat(process)
            process.state = ProcessState.FAILED
            process.last_error = f"cannot start: {exc}"
            process.log.write_line(f"--- msctl: {process.last_error}")
            return
        finally:
            for child_end in (writer, reader):
                if child_end is not None:
                    os.close(child_end)  # the child's copies only: its death closes the pipes
        process.popen = popen
        process.started_at = time.monotonic()
        process.state = ProcessState.STARTING
        process.pump = threading.Thread(
            target=self._pump, args=(process, popen), name=f"log-{process.name}", daemon=True
        )
        process.pump.start()

    @staticmethod
    def _pump(process: ManagedProcess, popen: Child) -> None:
        assert popen.stdout is not None
        for line in popen.stdout:
            process.log.write_line(line)
        popen.stdout.close()

    # ------------------------------------------------------------------ watching
    def poll(self, now: float | None = None) -> list[str]:
        """Notice dead processes and (re)start what is due. Returns human-readable events."""
        now = time.monotonic() if now is None else now
        events = self._log_events()
        for process in self.processes.values():
            popen = process.popen
            if popen is not None and popen.poll() is not None:
                events.append(self._on_exit(process, popen.returncode, now))
            elif popen is not None and process.heartbeat:
                event = self._check_heartbeat(process, popen, now)
                if event:
                    events.append(event)
            if (
                process.next_start is not None
                and now >= process.next_start
                and process.wanted
                and process.state is ProcessState.RESTARTING
            ):
                process.next_start = None
                process.restarts += 1
                self._spawn(process)
                events.append(f"{process.name}: restarted (restart #{process.restarts})")
            # Alive long enough, whatever its health says: a process with no components to
            # judge it by (the embedded router) never turns RUNNING after a restart, and its
            # backoff must not keep doubling over a long run.
            if process.pid is not None and process.uptime(now) > self.policy.stable_after:
                process.backoff = 0.0
        return events

    def _log_events(self) -> list[str]:
        """One warning when a process's log stops being written, one when it works again."""
        events = []
        for process in self.processes.values():
            fault, warned = process.log.fault, self._log_faults.get(process.name)
            if fault and not warned:
                self._log_faults[process.name] = fault
                events.append(
                    f"{process.name}: cannot write its log {process.log.path} ({fault}); "
                    "dropping lines and counting them, still supervising"
                )
            elif not fault and warned:
                del self._log_faults[process.name]
                events.append(
                    f"{process.name}: its log is written again "
                    f"({process.log.dropped} lines lost in all)"
                )
        return events

    def faults(self) -> list[str]:
        """What is wrong with this supervisor's own files now (``msctl ps`` shows it)."""
        return [
            f"log of {p.name}: {p.log.fault}; {p.log.dropped} lines lost"
            for p in self.processes.values()
            if p.log.fault
        ]

    def _check_heartbeat(self, process: ManagedProcess, popen: Child, now: float) -> str | None:
        """Read the beats of a live process; mark it UNRESPONSIVE, or kill it, when silent.

        Returns:
            An event, or ``None`` when nothing changed.
        """
        if _read_beats(process):
            process.last_beat = now  # stamped on reading: our own delays are never its
        if process.last_beat is None:
            return None  # not beating yet (still importing, building): nothing to judge
        silent = now - process.last_beat
        policy = self.liveness
        if silent >= policy.unresponsive_after + policy.kill_after:
            why = f"unresponsive (no heartbeat for {silent:.1f} s), killed"
            _signal_group(popen, signal.SIGKILL)  # a stopped process dies of it too
            with contextlib.suppress(subprocess.TimeoutExpired):
                popen.wait(timeout=5.0)
            return self._on_exit(process, popen.returncode or -signal.SIGKILL, now, why)
        if silent >= policy.unresponsive_after:
            if process.state in (ProcessState.STARTING, ProcessState.RUNNING):
                process.state_before_silence = process.state
                process.state = ProcessState.UNRESPONSIVE
                process.log.write_line(
                    f"--- msctl: {process.name} unresponsive: no heartbeat for {silent:.1f} s"
                )
                return (
                    f"{process.name}: unresponsive (no heartbeat for {silent:.1f} s); "
                    f"killed and restarted if still silent in {policy.kill_after:g} s"
                )
            return None
        if process.state is ProcessState.UNRESPONSIVE:
            process.state = process.state_before_silence or ProcessState.STARTING
            process.state_before_silence = None
            process.log.write_line(f"--- msctl: {process.name} responsive again")
            return f"{process.name}: responsive again"
        return None

    def _on_exit(
        self, process: ManagedProcess, code: int, now: float, cause: str | None = None
    ) -> str:
        assert process.popen is not None
        # The leader is gone; whatever it started in its group goes too (no orphans), and
        # before the pump is joined, since an orphan holding the pipe would stall it.
        _signal_group(process.popen, signal.SIGKILL)
        if process.pump is not None:
            process.pump.join(timeout=1.0)  # the last lines carry the reason
        process.popen = None
        _close_heartbeat(process)
        process.state_before_silence = None
        reason = cause or _describe_exit(code)
        # A cause of our own says it all: its last line was written before it froze.
        tail = "" if cause else _last_meaningful(process.log.tail)
        process.last_error = f"{reason}: {tail}" if tail else reason
        if not process.wanted:
            process.log.write_line(f"--- msctl: {process.name} {reason}")
            process.state = ProcessState.STOPPED
            return f"{process.name}: stopped"
        meaning = process.final_exits.get(code)
        if meaning is not None:
            # Deterministic: every restart would print the same error again, for half a
            # minute of backoff, and hide it among its copies.
            process.state = ProcessState.FAILED
            process.restart_times.clear()
            process.backoff = 0.0
            process.last_error = (
                f"{process.last_error} (gave up after one try: code {code} means {meaning})"
            )
            process.log.write_line(
                f"--- msctl: {process.name} {reason}; not restarted: code {code} means {meaning}"
            )
            return f"{process.name}: FAILED ({process.last_error})"
        process.log.write_line(f"--- msctl: {process.name} {reason}")
        while process.restart_times and now - process.restart_times[0] > self.policy.window:
            process.restart_times.popleft()
        if len(process.restart_times) >= self.policy.max_restarts:
            process.state = ProcessState.FAILED
            process.last_error = (
                f"{process.last_error} (gave up after {len(process.restart_times)} restarts "
                f"in {self.policy.window:g} s)"
            )
            return f"{process.name}: FAILED ({process.last_error})"
        process.restart_times.append(now)
        process.backoff = min(
            self.policy.backoff_max,
            max(self.policy.backoff_initial, process.backoff * 2),
        )
        process.state = ProcessState.RESTARTING
        process.next_start = now + process.backoff
        return f"{process.name}: {reason}; restarting in {process.backoff:.2f} s"

    def mark_running(self, name: str) -> None:
        """The launcher saw every component of ``name`` healthy."""
        process = self.processes[name]
        if process.state is ProcessState.STARTING:
            process.state = ProcessState.RUNNING

    # ------------------------------------------------------------------ controlling
    def restart(self, name: str) -> None:
        """Stop then start one process at once (no backoff, restarts counted)."""
        process = self.processes[name]
        self._terminate([process])
        process.popen = None
        process.restarts += 1
        process.restart_times.clear()
        process.backoff = 0.0
        self.start(name)

    def rebuild(self, name: str, component: str) -> None:
        """Order process ``name`` to rebuild ``component`` alone, its siblings running on.

        Raises:
            ValueError: If the process cannot take the order (no orders pipe, not alive, or
                ``component`` is not one of its components), saying why.
        """
        process = self.processes[name]
        if component not in process.components:
            raise ValueError(f"process {name} does not run {component}")
        if process.orders_fd is None or process.pid is None:
            raise ValueError(f"process {name} is {process.state.value}: restart it whole")
        try:
            os.write(process.orders_fd, encode(REBUILD, component))
        except OSError as exc:
            raise ValueError(f"process {name} takes no orders now ({exc.strerror})") from exc
        process.log.write_line(f"--- msctl: rebuilding {component} alone in {name}")

    def stop(self, name: str) -> None:
        """Stop one process and keep it stopped."""
        process = self.processes[name]
        process.wanted = False
        process.next_start = None
        self._terminate([process])
        process.popen = None
        process.state = ProcessState.STOPPED

    def shutdown(self) -> None:
        """Stop everything: SIGINT, SIGTERM, SIGKILL to each process group.

        A FAILED process stays FAILED (it has nothing left to stop), so the last state file
        still says which process failed and why.
        """
        for process in self.processes.values():
            process.wanted = False
            process.next_start = None
        self._terminate(list(self.processes.values()))
        for process in self.processes.values():
            process.popen = None
            if process.state is not ProcessState.FAILED:
                process.state = ProcessState.STOPPED
            process.log.close()

    def _terminate(self, processes: list[ManagedProcess]) -> None:
        live = [p for p in processes if p.popen is not None and p.popen.poll() is None]
        for signum, wait in (
            (signal.SIGINT, self.shutdown_policy.after_sigint),
            (signal.SIGTERM, self.shutdown_policy.after_sigterm),
            (signal.SIGKILL, 2.0),
        ):
            for process in live:
                _signal_group(process.popen, signum)
                # A stopped (SIGSTOP) process handles nothing until continued.
                _signal_group(process.popen, signal.SIGCONT)
            deadline = time.monotonic() + wait
            while live and time.monotonic() < deadline:
                live = [p for p in live if p.popen.poll() is None]
                time.sleep(0.02)
            if not live:
                break
        for process in processes:
            if process.popen is not None:
                # Whatever the leader left behind in its group goes too.
                _signal_group(process.popen, signal.SIGKILL)
                with contextlib.suppress(subprocess.TimeoutExpired):
                    process.popen.wait(timeout=1.0)
            if process.pump is not None:
                process.pump.join(timeout=1.0)
            _close_heartbeat(process)
            process.state_before_silence = None

    # ------------------------------------------------------------------ reporting
    def snapshot(self, now: float | None = None) -> list[ProcessRow]:
        """Every process's state, as the rows of a run document (``ps``, the state file)."""
        now = time.monotonic() if now is None else now
        return [
            ProcessRow(
                name=p.name,
                state=p.state.value,
                pid=p.pid,
                pgid=p.pid,
                uptime=round(p.uptime(now), 1),
                restarts=p.restarts,
                last_error=p.last_error,
                # Seconds since its last heartbeat (None: it has none, or none yet).
                heartbeat_age=(
                    round(now - p.last_beat, 1)
                    if p.last_beat is not None and p.pid is not None
                    else None
                ),
                log=str(p.log.path),
                log_lines_lost=p.log.dropped,
                components=list(p.components),
            )
            for p in self.processes.values()
        ]


def _read_beats(process: ManagedProcess) -> bool:
    """Drain a process's heartbeat pipe; whether it held at least one beat."""
    if process.beat_fd is None:
        return False
    beaten = False
    with contextlib.suppress(BlockingIOError, OSError):
        while True:
            data = os.read(process.beat_fd, 4096)
            if not data:
                break  # every writer closed: its exit is noticed on its own
            beaten = True
    return beaten


def _close_heartbeat(process: ManagedProcess) -> None:
    """Close our ends of its heartbeat and orders pipes."""
    for fd in (process.beat_fd, process.orders_fd):
        if fd is not None:
            with contextlib.suppress(OSError):
                os.close(fd)
    process.beat_fd = process.orders_fd = None
    process.last_beat = None


def _signal_group(popen: Child, signum: int) -> None:
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(popen.pid, signum)


def _describe_exit(code: int) -> str:
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exited with code {code}"


def _last_meaningful(lines: deque[str]) -> str:
    for line in reversed(lines):
        text = line.strip()
        meaningful = text and not text.startswith("--- msctl:")
        if meaningful and ("error" in text.lower() or "Traceback" in text):
            return text[-300:]
    for line in reversed(lines):
        text = line.strip()
        if text and not text.startswith("--- msctl:"):
            return text[-300:]
    return ""
