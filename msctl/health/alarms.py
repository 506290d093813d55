"""The alarm file: every level change ``msctl health`` saw, kept for ``msctl health --alarms``.

``$MSCTL_HOME/health/alarms.jsonl`` holds one JSON object per line: a session line when a
``msctl health`` (screen or ``--watch``) starts, then its alarms, each tagged with the
session. ``--alarms`` reads back the last session. Past :data:`ROTATE_BYTES` the file is
moved to ``alarms.jsonl.1`` when a session starts, so it never grows without bound.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from components.assembly import state_dir
from components.data_monitor.alarms import Alarm

FILE_NAME = "alarms.jsonl"
#: Size past which the file is rotated when a session starts.
ROTATE_BYTES = 4 * 1024 * 1024


def alarm_path() -> Path:
    """``$MSCTL_HOME/health/alarms.jsonl``."""
    return state_dir() / "health" / FILE_NAME


class AlarmLog:
    """Appends one session's alarms to the alarm file.

    Args:
        assembly: The assembly watched (written in the session line).
        source: Who records (``msctl health``, ``msctl health --watch``).
        path: The file (default :func:`alarm_path`).
    """

    def __init__(self, assembly: str, source: str, path: Path | None = None) -> None:
        self.path = path or alarm_path()
        self.session = f"{time.strftime('%Y%m%dT%H%M%S')}-{os.getpid()}"
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            if self.path.stat().st_size > ROTATE_BYTES:
                self.path.replace(self.path.with_name(FILE_NAME + ".1"))
        except FileNotFoundError:
            pass
        self._write(
            [
                {
                    "session": self.session,
                    "assembly": assembly,
                    "source": source,
                    "started": round(time.time(), 3),
                }
            ]
        )

    def append(self, alarms: Iterable[Alarm]) -> None:
        """Append alarms (one line each; a short write per batch)."""
        self._write([{"session": self.session, **a.to_json()} for a in alarms])

    def _write(self, records: list[dict]) -> None:
        if not records:
            return
        text = "".join(json.dumps(r, separators=(",", ":")) + "\n" for r in records)
        # O_APPEND: lines from two sessions writing at once never interleave mid-line.
        fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.write(fd, text.encode())
        finally:
            os.close(fd)


@dataclass(frozen=True)
class Session:
    """One recorded session: who, when, what it saw.

    Attributes:
        session: Its id.
        assembly: The assembly it watched.
        source: Who recorded it.
        started: Wall-clock seconds of its start.
        alarms: Its alarms, oldest first.
        skipped: Lines of it that could not be read.
    """

    session: str
    assembly: str
    source: str
    started: float
    alarms: tuple[Alarm, ...]
    skipped: int = 0

    def to_json(self) -> dict:
        """``{"session", "assembly", "source", "started", "alarms": [...]}``."""
        return {
            "session": self.session,
            "assembly": self.assembly,
            "source": self.source,
            "started": self.started,
            "alarms": [a.to_json() for a in self.alarms],
        }


def last_session(path: Path | None = None) -> Session | None:
    """The last session recorded in the alarm file; ``None`` if there is none.

    Lines that are not JSON or not alarms (a file cut by a crash, edited by hand) are skipped
    and counted in :attr:`Session.skipped`.

    Raises:
        OSError: If the file exists but cannot be read.
    """
    path = path or alarm_path()
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except FileNotFoundError:
        return None
    header: dict | None = None
    alarms: list[Alarm] = []
    skipped = 0
    for line in lines:
        try:
            record = json.loads(line)
        except ValueError:
            skipped += 1
            continue
        if not isinstance(record, dict):
            skipped += 1
            continue
        if "started" in record and "session" in record and "to" not in record:
            header, alarms, skipped = record, [], 0
            continue
        if header is None or record.get("session") != header.get("session"):
            continue  # another session's line, written while this one ran
        try:
            alarms.append(Alarm.from_json(record))
        except ValueError:
            skipped += 1
    if header is None:
        return None
    return Session(
        session=str(header.get("session")),
        assembly=str(header.get("assembly", "")),
        source=str(header.get("source", "")),
        started=float(header.get("started") or 0.0),
        alarms=tuple(alarms),
        skipped=skipped,
    )
