"""Where a run keeps its state on this computer, so ``msctl ps``, ``logs`` and ``down`` work
from any shell even when the network is gone.

Layout: ``$MSCTL_HOME/run/state.json`` (the supervisor rewrites it atomically twice a
second) and ``$MSCTL_HOME/run/logs/<process>.log`` (+ rotated ``.1`` .. ``.3``).
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

from components.assembly import state_dir


def run_dir() -> Path:
    """``$MSCTL_HOME/run``."""
    return state_dir() / "run"


def state_path() -> Path:
    """The state file of this computer's supervisor."""
    return run_dir() / "state.json"


def log_dir() -> Path:
    """Where process logs are written."""
    return run_dir() / "logs"


def write_state(document: dict[str, Any]) -> None:
    """Replace the state file atomically (a reader never sees half a file)."""
    path = state_path()
    path.parent.mkdir(parents=True, exist_ok=True)
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
