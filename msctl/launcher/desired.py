"""What this computer's agent was last asked to run, kept on disk so a reboot does not lose it.

An ``up`` the agent accepts (from ``msctl up --all``) is written to
``$MSCTL_HOME/agent/desired.json``: the resolved assembly document as it was sent, the
simulation flag and speed, and when it was asked. A ``down`` (of this host, or ``down
--all``) removes it. When the agent starts (at boot, or after a power cut) and finds it, it
brings the same part back up by itself; a deliberate down is never undone, since it left no
file behind.

The file is written atomically (a temporary file in the same directory, flushed to disk,
renamed over the old one, then the directory flushed), so a power cut leaves the old file
or the new one, never half of one. It carries a digest of the document: a file cut or
edited by hand, or one written for another computer, is refused whole (:class:`DesiredStateError`,
naming the file and what to do), never acted on.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import tempfile
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

from msctl.errors import MsctlError
from msctl.launcher import state

#: The file's name in the agent's directory.
FILE_NAME = "desired.json"
#: What the file says it is, and the layout's version.
FORMAT = "msctl-desired-state"
VERSION = 1


class DesiredStateError(MsctlError):
    """A desired-state file that cannot be acted on (unreadable, cut, edited, another host's)."""


def digest(document: Mapping[str, Any]) -> str:
    """SHA-256 of the document's canonical JSON (sorted keys, no spaces)."""
    text = json.dumps(document, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


@dataclass(frozen=True)
class DesiredState:
    """What ``up --all`` asked this computer to run.

    Attributes:
        host: The computer it was asked of (``MSCTL_HOST``).
        template: The assembly's template (``dragon``), for messages.
        assembly: The resolved assembly document, as the ``up`` request carried it.
        sim: The request's simulation flag (``None``: simulate where no hardware is).
        speed: The simulation speed asked.
        asked_at: When the ``up`` was accepted (Unix seconds).
    """

    host: str
    template: str
    assembly: Mapping[str, Any]
    sim: bool | None
    speed: float
    asked_at: float

    def to_json(self) -> dict[str, Any]:
        """The file's content."""
        return {
            "format": FORMAT,
            "version": VERSION,
            "host": self.host,
            "template": self.template,
            "sim": self.sim,
            "speed": self.speed,
            "asked_at": self.asked_at,
            "digest": digest(self.assembly),
            "assembly": self.assembly,
        }

    @classmethod
    def from_json(cls, data: Any) -> DesiredState:
        """Read the file's content back.

        Raises:
            ValueError: Naming what is wrong (a field missing or of the wrong type, another
                format or version, a document that does not match its digest).
        """
        if not isinstance(data, dict):
            raise ValueError(f"it holds a JSON {type(data).__name__}, not an object")
        if data.get("format") != FORMAT:
            raise ValueError(f"its 'format' is {data.get('format')!r}, not {FORMAT!r}")
        if data.get("version") != VERSION:
            raise ValueError(
                f"its 'version' is {data.get('version')!r}; this msctl reads {VERSION}"
            )
        for key, kind in (("host", str), ("template", str), ("assembly", dict), ("digest", str)):
            if not isinstance(data.get(key), kind):
                raise ValueError(f"its {key!r} is missing or not a {kind.__name__}")
        sim = data.get("sim")
        if sim is not None and not isinstance(sim, bool):
            raise ValueError(f"its 'sim' is {sim!r}, not true, false or null")
        speed, asked_at = data.get("speed"), data.get("asked_at")
        for key, value in (("speed", speed), ("asked_at", asked_at)):
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(f"its {key!r} is {value!r}, not a number")
        if digest(data["assembly"]) != data["digest"]:
            raise ValueError("its assembly does not match its digest (cut short, or edited)")
        return cls(
            host=data["host"],
            template=data["template"],
            assembly=data["assembly"],
            sim=sim,
            speed=float(speed),  # type: ignore[arg-type]
            asked_at=float(asked_at),  # type: ignore[arg-type]
        )


def _what_to_do(path: Path) -> str:
    return (
        f"the agent starts nothing from it: run `msctl up --all` (or `msctl down --all`) from "
        f"the ground station to replace it, or remove {path}"
    )


def read(path: Path, host: str) -> DesiredState | None:
    """The desired state kept in ``path`` for ``host``, or ``None`` if there is none.

    Raises:
        DesiredStateError: If the file is there but cannot be acted on: unreadable, not
            JSON, not a desired state, cut short or edited, or written for another computer
            (its home copied from one to another). The message names the file and what to do.
    """
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return None
    except (OSError, UnicodeDecodeError) as exc:
        raise DesiredStateError(f"cannot read {path}: {exc}", hint=_what_to_do(path)) from None
    try:
        state = DesiredState.from_json(json.loads(text))
    except ValueError as exc:  # json.JSONDecodeError is one
        raise DesiredStateError(
            f"{path} is not a desired state msctl wrote: {exc}", hint=_what_to_do(path)
        ) from None
    if state.host != host:
        raise DesiredStateError(
            f"{path} was written for {state.host}, not for this computer ({host}): a home "
            "copied from another computer?",
            hint=_what_to_do(path),
        )
    return state


def write(path: Path, state: DesiredState) -> None:
    """Replace ``path`` with ``state``, atomically and durably (see the module docstring).

    Raises:
        OSError: If it cannot be written (the old file, if any, is then left as it was).
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as handle:
            json.dump(state.to_json(), handle, indent=1)
            handle.flush()
            os.fsync(handle.fileno())  # the content is on disk before the name points at it
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    _sync_directory(path.parent)  # and the rename itself survives a power cut


def remove(path: Path) -> bool:
    """Remove the desired state (a ``down`` was asked); whether there was one.

    Raises:
        OSError: If it is there and cannot be removed.
    """
    try:
        path.unlink()
    except FileNotFoundError:
        return False
    _sync_directory(path.parent)
    return True


def _sync_directory(directory: Path) -> None:
    """Flush a directory's entries (a rename or unlink) to disk, where the system allows."""
    with contextlib.suppress(OSError):  # some filesystems refuse to open a directory
        fd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


class _Kept(NamedTuple):
    """Whether an ``up`` was kept on disk, and if not, why (said in its answer)."""

    ok: bool
    reason: str = ""

    def __bool__(self) -> bool:
        return self.ok


def _process_start() -> float:
    """When this process started (Unix seconds); now, if the system does not say."""
    try:
        import psutil

        return float(psutil.Process().create_time())
    except Exception:  # no /proc to read: the agent's own start is near enough
        return time.time()


def _previous_run() -> tuple[dict[str, Any] | None, bool]:
    """This computer's last run as its state file keeps it, and whether it was written since
    the computer booted (after a reboot its process ids mean nothing any more)."""
    previous = state.read_state()
    if previous is None:
        return None, False
    try:
        import psutil

        written = state.state_path().stat().st_mtime
        return previous, written >= psutil.boot_time()
    except Exception:  # cannot tell: treat it as this boot's (its processes are checked)
        return previous, True


def _why_back(previous: Mapping[str, Any] | None, this_boot: bool) -> str:
    """What brought the agent back, as far as this computer can tell (for the operator)."""
    if previous is not None and not this_boot:
        return "rebooted"
    if previous is not None and previous.get("state") == "stopped":
        return "restarted its agent"  # its run was stopped in order: no power was lost
    if previous is not None:
        return "rebooted or lost power"  # its run ended with no down and nothing is left
    return "restarted"
