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
    """Whether the supervisor that wrote ``document`` is still running."""
    if not document or document.get("state") == "stopped":
        return False
    pid = document.get("supervisor_pid")
    return isinstance(pid, int) and _signal_reaches(os.kill, pid)


def group_alive(pgid: int) -> bool:
    """Whether any process of the process group ``pgid`` is left."""
    return _signal_reaches(os.killpg, pgid)


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
