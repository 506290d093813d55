"""Where a run keeps its state on this computer, so ``msctl ps``, ``logs`` and ``down`` work
from any shell even when the network is gone.

Layout: ``$MSCTL_HOME/run/state.json`` (the supervisor rewrites it atomically twice a
second) and ``$MSCTL_HOME/run/logs/<process>.log`` (+ rotated ``.1`` .. ``.3``).
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import time
from pathlib import Path
from typing import Any

from components.paths import state_dir
from msctl.errors import MsctlError


def run_dir() -> Path:
    """``$MSCTL_HOME/run``."""
    return state_dir() / "run"


def state_path() -> Path:
    """The state file of this computer's supervisor."""
    return run_dir() / "state.json"


def log_dir() -> Path:
    """Where process logs are written."""
    return run_dir() / "logs"


def lock_path() -> Path:
    """The lock a supervisor of this MSCTL_HOME holds for its whole life."""
    return run_dir() / "up.lock"


class HomeNotWritable(MsctlError):
    """MSCTL_HOME (or a directory under it) cannot be written: read-only, full, not ours."""

    exit_code = 3


def home_not_writable(path: Path, exc: OSError) -> HomeNotWritable:
    """The error for a directory under MSCTL_HOME that cannot be written, naming it."""
    reason = exc.strerror or type(exc).__name__
    full = exc.errno in (errno.ENOSPC, errno.EDQUOT)
    return HomeNotWritable(
        f"cannot write to {path}: {reason}",
        hint=(
            "free some space on its disk"
            if full
            else "msctl keeps its run state in MSCTL_HOME: point MSCTL_HOME at a writable "
            "directory, or make this one writable"
        ),
    )


class AlreadyRunning(MsctlError):
    """Another supervisor holds this MSCTL_HOME's run lock."""

    exit_code = 3


class RunLock:
    """The exclusive lock of this MSCTL_HOME's run (``flock`` on :func:`lock_path`).

    Whoever holds it is the one supervisor of this computer's run: a foreground ``msctl up``,
    a detached one (the parent takes it, the supervisor it starts inherits the descriptor
    and keeps it to its end), or an agent while it runs a part. The kernel drops it when its
    last holder exits, however it ends: no stale lock to clean after a crash. The file also
    says who holds it (pid, since when, what), for the refusal of the next one.
    """

    def __init__(self, fd: int, path: Path) -> None:
        self.fd = fd
        self.path = path
        self.holder: dict[str, Any] = {"pid": os.getpid(), "started": time.time()}

    @classmethod
    def acquire(cls, **holder: Any) -> RunLock:
        """Take the lock without waiting, and note ``holder`` (what runs) in it.

        Raises:
            AlreadyRunning: If another process holds it, naming that process.
            HomeNotWritable: If the run directory cannot be created or written.
        """
        path = lock_path()
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise home_not_writable(path.parent, exc) from exc
        try:
            _flock_soon(fd)
        except BlockingIOError:
            other = _read_holder(fd)
            os.close(fd)
            raise AlreadyRunning(
                describe_holder(other),
                hint="see it with `msctl ps`, stop it with `msctl down`",
            ) from None
        except OSError as exc:
            os.close(fd)
            raise home_not_writable(path.parent, exc) from exc
        lock = cls(fd, path)
        lock.note(**holder)
        return lock

    @classmethod
    def adopt(cls, fd: int, **holder: Any) -> RunLock:
        """Keep a lock inherited from the process that took it (a detached ``msctl up``)."""
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # ours already: never waits
        lock = cls(fd, lock_path())
        lock.holder = {**_read_holder(fd, tries=1), "pid": os.getpid()}
        lock.note(**holder)
        return lock

    def note(self, **holder: Any) -> None:
        """Say in the lock file who holds it (best effort: a full disk does not matter)."""
        self.holder.update(holder)
        data = json.dumps(self.holder).encode()
        try:
            os.pwrite(self.fd, data, 0)
            os.ftruncate(self.fd, len(data))
        except OSError:
            pass

    def release(self) -> None:
        """Let the lock go (idempotent)."""
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1


def _flock_soon(fd: int, patience: float = 0.2) -> None:
    """Take the lock exclusively, waiting at most ``patience`` seconds.

    A holder keeps it for a whole run; a command that only asks whether a run holds it
    (:func:`run_lock_holder`) holds it for microseconds, and must not be taken for one.

    Raises:
        BlockingIOError: If it is still held after ``patience``.
    """
    deadline = time.monotonic() + patience
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return
        except BlockingIOError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.01)


def run_lock_holder() -> dict[str, Any] | None:
    """Who holds this MSCTL_HOME's run lock, when another process does (else ``None``).

    An ``msctl up`` holds it from its first moment, long before its state file says it runs
    (that is written once its processes have started): the lock is what tells a run that is
    still starting. The holder's own process (an ``msctl up TEMPLATE`` resolving before it
    starts) is not another.
    """
    try:
        fd = os.open(lock_path(), os.O_RDONLY)
    except OSError:
        return None  # never taken here, or unreadable: nothing to go by
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _read_holder(fd)
            return None if holder.get("pid") == os.getpid() else holder or {"pid": None}
        except OSError:
            return None
        return None
    finally:
        os.close(fd)


def _read_holder(fd: int, tries: int = 20) -> dict[str, Any]:
    """What the lock's holder wrote in it (``{}`` if nothing readable yet)."""
    for _ in range(tries):  # the holder may be between its two writes
        try:
            document = json.loads(os.pread(fd, 65536, 0) or b"null")
        except (OSError, ValueError):
            document = None
        if isinstance(document, dict):
            return document
        time.sleep(0.02)
    return {}


def describe_holder(holder: dict[str, Any]) -> str:
    """One line naming the holder of the run lock: what it runs, its pid, since when."""
    what = holder.get("template") or "an assembly"
    by = holder.get("by") or "msctl up"
    where = f" on {holder['host']}" if holder.get("host") else ""
    pid = holder.get("pid")
    started = holder.get("started")
    since = ""
    if isinstance(started, int | float):
        ago = max(0.0, time.time() - started)
        since = f", started {time.strftime('%Y-%m-%d %H:%M:%S', time.localtime(started))}"
        since += f", {ago:.0f} s ago"
    return (
        f"{what} is already up{where} (pid {pid}: {by}{since}); one supervisor "
        f"per MSCTL_HOME ({state_dir()})"
    )


def write_state(document: Any) -> None:
    """Replace the state file atomically (a reader never sees half a file).

    Args:
        document: The run's :class:`~components.supervision.protocol.RunDocument` (written
            as msgspec encodes it, the same JSON as its ``ps`` answer), or those fields as a
            dict (``down`` marking a dead supervisor's run stopped).
    """
    if not isinstance(document, dict):
        import msgspec  # only a supervisor writes a struct: `msctl ps` only reads the file

        document = msgspec.to_builtins(document)
    path = state_path()
    path.parent.mkdir(parents=True, exist_ok=True)
    import tempfile  # 3 ms: only the supervisor writes state; `msctl ps` only reads it

    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".state.", suffix=".json")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as handle:
            json.dump(document, handle, indent=1)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def read_state() -> dict[str, Any] | None:
    """The state file, or ``None`` if no run ever wrote one (or it is unreadable)."""
    try:
        return json.loads(state_path().read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def supervisor_alive(document: dict[str, Any] | None) -> bool:
    """Whether the supervisor that wrote ``document`` is still running (a zombie is not:
    a killed detached supervisor waits for init to reap it, which some never do)."""
    if not document or document.get("state") == "stopped":
        return False
    pid = document.get("supervisor_pid")
    return (
        isinstance(pid, int)
        and _signal_reaches(os.kill, pid)
        and _stat(pid) != "Z"
        and _is_msctl(Path(f"/proc/{pid}"))
    )


def process_group_alive(pgid: int, ours_only: bool = False) -> bool:
    """Whether any process of group ``pgid`` is left (zombies awaiting a reaper do not count).

    Args:
        pgid: The process group.
        ours_only: Count only msctl's own processes (a stale state file's ids may have been
            reused by strangers after a reboot).
    """
    if not _signal_reaches(os.killpg, pgid):
        return False
    try:
        entries = list(Path("/proc").glob("[0-9]*"))
    except OSError:
        return True
    if not entries:
        return True  # no /proc to look into: trust the signal
    for entry in entries:
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if (
            len(fields) > 2
            and fields[2] == str(pgid)
            and fields[0] != "Z"
            and (not ours_only or _is_msctl(entry))
        ):
            return True
    return False


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie waiting to be reaped has exited)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return True


def group_alive(pgid: int) -> bool:
    """Whether any of msctl's processes of the process group ``pgid`` is left."""
    return process_group_alive(pgid, ours_only=True)


# What every process msctl starts has on its command line: the CLI, a component worker, the
# embedded router. A state file outlives a reboot; its ids may then belong to strangers.
_OUR_MARKERS = (b"msctl", b"components.executor.worker")


def _is_msctl(proc_dir: Path) -> bool:
    """Whether the process behind ``/proc/<pid>`` is one of msctl's (True if unreadable)."""
    try:
        cmdline = (proc_dir / "cmdline").read_bytes()
    except OSError:
        return True  # cannot tell: keep the old behaviour rather than ignore a live run
    return any(marker in cmdline for marker in _OUR_MARKERS)


def _stat(pid: int) -> str:
    """A process's state letter from ``/proc`` ("" when it cannot tell)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return ""


def groups_left(document: dict[str, Any]) -> list[str]:
    """Names of the processes of a run document whose process group still has a process."""
    return [
        p["name"] for p in document.get("processes", []) if p.get("pgid") and group_alive(p["pgid"])
    ]


def _signal_reaches(send: Any, target: int) -> bool:
    try:
        send(target, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # it exists, owned by someone else
    return True
