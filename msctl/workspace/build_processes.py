"""The processes and logs of a package's build steps.

Each step runs in a process group of its own, so a package's ``timeout`` or a stopped build
ends the step and every process it started; its output goes to the package's log, whose
last lines are shown with a failure. doit's own state file is checked here too.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
from pathlib import Path

#: Lines of a failed step's log shown with the failure.
LOG_TAIL = 15
#: Seconds a stopped step's processes have after SIGTERM before they get SIGKILL.
STOP_GRACE_S = 5.0


def signal_group(process: subprocess.Popen[bytes], number: int) -> None:
    """Send ``number`` to the process group a step leads (it may be gone already)."""
    try:
        os.killpg(process.pid, number)
    except (ProcessLookupError, PermissionError):
        pass


def end_group(process: subprocess.Popen[bytes]) -> None:
    """Make sure a stopped step and every process of its group are gone: it gets
    :data:`STOP_GRACE_S` after its SIGTERM, then SIGKILL; what its leader left behind (a
    ``sleep`` in a script whose shell exited at the SIGTERM) goes with it."""
    if process.poll() is None:
        signal_group(process, signal.SIGTERM)
        try:
            process.wait(STOP_GRACE_S)
        except subprocess.TimeoutExpired:
            signal_group(process, signal.SIGKILL)
            process.wait()
    # The leader is reaped; what is left of its group (if anything) goes too.
    signal_group(process, signal.SIGKILL)


def set_aside_unreadable(db: Path) -> str:
    """Set doit's state file aside when it cannot be read (doit rewrites it in place, so
    a power cut can leave it truncated), and say so; ``""`` when it is fine or absent.

    doit would stop every later build at it with a traceback; without it, doit knows
    nothing built and builds every package again, which is the state rebuilt.
    """
    try:
        text = db.read_text(encoding="utf-8")
    except FileNotFoundError:
        return ""
    except (OSError, UnicodeDecodeError) as exc:
        why = str(exc)
    else:
        try:
            if isinstance(json.loads(text), dict):
                return ""
            why = "not a JSON object"
        except ValueError as exc:
            why = f"not valid JSON ({exc})"
    aside = db.with_name(db.name + ".unreadable")
    os.replace(db, aside)
    return (
        f"build state {db} was unreadable ({why}): set aside as {aside.name}, and rebuilt "
        "from the packages (every package is built again)"
    )


def read_from(log: Path, offset: int) -> str:
    """What a step wrote to its package's log (from ``offset`` on)."""
    try:
        with log.open("rb") as handle:
            handle.seek(offset)
            return handle.read().decode("utf-8", errors="replace")
    except OSError:
        return ""


def tail(log: Path, lines: int = LOG_TAIL) -> str:
    try:
        text = log.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError:
        return "(no log)"
    return "\n".join(f"    {line}" for line in text[-lines:])
