"""The bags a computer keeps, served to the ground station over the fleet: ``msctl bag pull``'s
robot side.

Every bag a computer records for itself (a robot computer's own data archiver, see the
template's ``[recording] robots``) is a directory under ``$MSCTL_HOME/bags``: its *shelf*.
The computer's agent answers two requests about it, on the same service as ``ps`` (so the
same access control guards them: only operators, through their ground station):

- ``bags``: every bag on the shelf, each file with its size, whether it is complete, and the
  SHA-256 of each complete file (what the ground checks its copy against);
- ``bag_read``: ``size`` bytes of one file from ``offset``, base64 in the JSON answer.

Nothing outside the shelf is ever read: a path is a bag name and a file name, both plain
names, and what they resolve to (symbolic links followed) must still be under the shelf; any
other path is refused, naming it.

An MCAP file is complete once its writer finished it: it then ends with the MCAP magic
(the footer's). A file still being recorded (or cut short by a crash, which ``msctl bag
recover`` completes) does not, and is listed as incomplete: a pull leaves it for later. Its
SHA-256 is not computed: it would be stale at once. One left unwritten for
:data:`STALE_SECONDS` is *abandoned* (its recorder was killed, or the power lost): it will not
change, so it is hashed and served as it is, and the ground completes its copy with ``msctl
bag recover``.
"""

from __future__ import annotations

import base64
import hashlib
import os
import re
import time
from pathlib import Path
from typing import Any

from components.paths import state_dir
from components.supervision.contract import RequestError

#: The verbs an agent answers about its shelf.
VERBS = ("bags", "bag_read")
#: The most bytes one ``bag_read`` returns: about 350 KB of JSON once in base64, a reply the
#: agent's loop builds in a few milliseconds.
MAX_READ = 256 * 1024
#: The last bytes of a finished MCAP file (the footer's magic).
MCAP_MAGIC = b"\x89MCAP0\r\n"
#: A bag or file name the shelf serves: what the recorder makes (``limb1_data_archiver_
#: 2026_11_27-21_30_00``, ``..._0.mcap``, ``metadata.yaml``), never a path.
PLAIN_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,199}$")

#: Seconds an unfinished MCAP file must go unwritten to count as abandoned: a recorder
#: writes out its chunks at least every second while anything is recorded.
STALE_SECONDS = 10.0

#: SHA-256 of complete files by (path, size, modification time): a finished file never
#: changes, so each is hashed once per agent, not at every listing.
_digests: dict[tuple[str, int, int], str] = {}


def shelf_dir() -> Path:
    """``$MSCTL_HOME/bags``: where this computer's bags are, and the only place served."""
    return state_dir() / "bags"


def is_plain(name: str) -> bool:
    """Whether ``name`` is one plain bag or file name (no separator, not ``.`` or ``..``)."""
    return bool(PLAIN_NAME.match(name)) and name not in (".", "..")


def complete(path: Path, size: int) -> bool:
    """Whether a bag file is finished: an MCAP file ends with the MCAP magic; any other file
    of a bag (``metadata.yaml``, rewritten whole and atomically) is always whole."""
    if path.suffix != ".mcap":
        return True
    if size < len(MCAP_MAGIC):
        return False
    with path.open("rb") as stream:
        stream.seek(size - len(MCAP_MAGIC))
        return stream.read(len(MCAP_MAGIC)) == MCAP_MAGIC


def sha256_of(path: Path) -> str:
    """The SHA-256 (hex) of a file, read in 1 MiB pieces."""
    digest = hashlib.sha256()
    with path.open("rb") as stream:
        while piece := stream.read(1024 * 1024):
            digest.update(piece)
    return digest.hexdigest()


def _digest(path: Path, stat: os.stat_result) -> str:
    key = (str(path), stat.st_size, stat.st_mtime_ns)
    found = _digests.get(key)
    if found is None:
        found = _digests[key] = sha256_of(path)
    return found


def listing(root: Path | None = None) -> dict[str, Any]:
    """Every bag on the shelf and its files: what ``bags`` answers.

    Returns:
        ``{"root": ..., "bags": [{"name", "recording", "files": [{"name", "size",
        "complete", "abandoned", "sha256"}]}]}``, bags and files by name; ``sha256`` is
        ``None`` for a file still being written, and ``recording`` says a bag has one.
    """
    root = shelf_dir() if root is None else root
    bags = []
    folders = sorted(p for p in root.iterdir() if p.is_dir()) if root.is_dir() else []
    for folder in folders:
        if not is_plain(folder.name) or folder.is_symlink():
            continue  # not something a recorder made: never served, so never listed
        files = []
        for path in sorted(folder.iterdir()):
            if not is_plain(path.name) or path.is_symlink() or not path.is_file():
                continue
            stat = path.stat()
            whole = complete(path, stat.st_size)
            # Unfinished and untouched for a while: its recorder was stopped too hard to
            # finish it (SIGKILL, power lost). It will not change: served as it is.
            abandoned = not whole and time.time() - stat.st_mtime > STALE_SECONDS
            files.append(
                {
                    "name": path.name,
                    "size": stat.st_size,
                    "complete": whole,
                    "abandoned": abandoned,
                    "sha256": _digest(path, stat) if whole or abandoned else None,
                }
            )
        recording = not all(f["complete"] or f["abandoned"] for f in files)
        bags.append({"name": folder.name, "recording": recording, "files": files})
    return {"root": str(root), "bags": bags}


def locate(path: Any, host: str, root: Path | None = None) -> Path:
    """The file a request's ``path`` (``<bag>/<file>``) names on the shelf.

    Raises:
        RequestError: If it is not two plain names, resolves outside the shelf, or is not a
            regular file there; the message names the path and the shelf.
    """
    root = shelf_dir() if root is None else root
    shown = repr(path)[:120]
    outside = (
        f"{shown} is not a bag file of {host}: only files of the bags under {root} are "
        "served, named <bag>/<file> as `msctl bag pull` lists them"
    )
    if not isinstance(path, str):
        raise RequestError(outside)
    parts = path.split("/")
    if len(parts) != 2 or not all(is_plain(p) for p in parts):
        raise RequestError(outside)
    target = root / parts[0] / parts[1]
    try:
        resolved = target.resolve(strict=True)
        inside = resolved.is_relative_to(root.resolve(strict=True))
    except (OSError, RuntimeError):
        raise RequestError(f"{host} has no bag file {path} under {root}") from None
    if not inside:
        raise RequestError(outside)
    if not resolved.is_file():
        raise RequestError(f"{path} on {host} is not a file")
    return resolved


def read(args: dict[str, Any], host: str, root: Path | None = None) -> dict[str, Any]:
    """``size`` bytes of a bag file from ``offset``: what ``bag_read`` answers.

    Returns:
        ``{"path", "offset", "file_size", "data"}``, ``data`` in base64 (fewer bytes than
        asked at the end of the file, none past it).

    Raises:
        RequestError: If the path is refused (:func:`locate`) or offset or size are not
            whole numbers in range.
    """
    offset, size = args.get("offset"), args.get("size")
    if not (isinstance(offset, int) and not isinstance(offset, bool) and offset >= 0):
        raise RequestError("bag_read's offset must be a whole number of bytes, 0 or more")
    if not (isinstance(size, int) and not isinstance(size, bool) and 0 < size <= MAX_READ):
        raise RequestError(f"bag_read's size must be a whole number of bytes, 1 to {MAX_READ}")
    path = locate(args.get("path"), host, root)
    with path.open("rb") as stream:
        file_size = os.fstat(stream.fileno()).st_size
        stream.seek(offset)
        data = stream.read(size)
    return {
        "path": args["path"],
        "offset": offset,
        "file_size": file_size,
        "data": base64.b64encode(data).decode("ascii"),
    }


def serve(verb: str, args: dict[str, Any], host: str) -> tuple[Any, str]:
    """Answer a shelf verb for the agent of ``host``: ``(payload, message)``.

    Raises:
        RequestError: For a refused path or bad arguments.
    """
    if verb == "bags":
        return listing(), "ok"
    if verb == "bag_read":
        return read(args, host), "ok"
    raise RequestError(f"{verb} is not a shelf request")  # pragma: no cover
