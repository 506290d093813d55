"""Writing joint zero offsets back into a unit's calibration TOML, touching nothing else.

Only ``zero_offset`` values in ``[joints.<raw joint name>]`` tables are edited, line by line,
so comments, key order and every other table survive. A missing key is inserted under its
table header; a missing table is appended (with the joint's ``direction``). The result is
checked by parsing both versions with :mod:`tomllib`: it must equal the original with exactly
the requested values changed, otherwise nothing is written. The write is atomic (temporary
file in the same directory, then :func:`os.replace`), so a crash leaves the old file whole.
Before it, a timestamped copy of the old file can be kept beside it
(``<unit>.toml.<UTC time>.bak``; restoring is copying it back), written atomically too.

No TOML writer is a dependency; the calibration schema is small enough that a careful
updater is less risk than a full emitter that would reformat the operator's file.
"""

from __future__ import annotations

import copy
import math
import os
import re
import tempfile
import tomllib
from collections.abc import Mapping
from datetime import UTC, datetime
from pathlib import Path

from components.errors import ConfigError

_BARE_KEY = re.compile(r"^[A-Za-z0-9_-]+$")
# A table or array-of-tables header line; a header contains no comma, unlike an array row.
_HEADER = re.compile(r"^\s*\[\[?[^\],]*\]\]?\s*(?:#.*)?$")
_ZERO_OFFSET = re.compile(r"^(\s*zero_offset\s*=\s*)([^#]*?)(\s*(?:#.*)?)$")


class CalibrationFileError(ConfigError):
    """The calibration file cannot be updated; the message names the file and the fix."""


def _joint_header(joint: str) -> re.Pattern[str]:
    name = re.escape(joint)
    return re.compile(rf"""^\s*\[\s*joints\s*\.\s*(?:{name}|"{name}"|'{name}')\s*\]\s*(?:#.*)?$""")


def _key(joint: str) -> str:
    return joint if _BARE_KEY.match(joint) else '"' + joint.replace('"', '\\"') + '"'


def _number(value: float) -> str:
    if not math.isfinite(value):
        raise CalibrationFileError(f"zero_offset must be finite, not {value}")
    # repr is the shortest text that reads back to the same float, and is valid TOML.
    return repr(float(value))


def updated_text(
    text: str,
    offsets: Mapping[str, float],
    directions: Mapping[str, int] | None = None,
    source: str = "<calibration>",
) -> str:
    """Return ``text`` with ``[joints.<name>] zero_offset`` set for each joint in ``offsets``.

    Args:
        text: The calibration file's current content.
        offsets: Raw joint name -> new zero offset (raw units: rad or m).
        directions: Raw joint name -> direction, written only when a table is created.
        source: File name for error messages.

    Raises:
        CalibrationFileError: If the text is not valid TOML, or the joint is described in a
            form this updater does not edit (e.g. an inline table), so the result would not
            be the original with only those values changed.
    """
    directions = directions or {}
    try:
        before = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise CalibrationFileError(f"{source} is not valid TOML ({exc}); fix it first") from exc
    lines = text.splitlines(keepends=True)
    newline = "\r\n" if lines and lines[0].endswith("\r\n") else "\n"
    appended: list[str] = []
    for joint, value in offsets.items():
        number = _number(value)
        header = _joint_header(joint)
        start = next((i for i, line in enumerate(lines) if header.match(line.rstrip("\r\n"))), None)
        if start is None:
            appended += [
                newline,
                f"[joints.{_key(joint)}]{newline}",
                f"zero_offset = {number}{newline}",
                f"direction = {int(directions.get(joint, 1))}{newline}",
            ]
            continue
        end = next(
            (i for i in range(start + 1, len(lines)) if _HEADER.match(lines[i].rstrip("\r\n"))),
            len(lines),
        )
        for i in range(start + 1, end):
            body = lines[i].rstrip("\r\n")
            found = _ZERO_OFFSET.match(body)
            if found:
                ending = lines[i][len(body) :]
                lines[i] = f"{found.group(1)}{number}{found.group(3)}{ending}"
                break
        else:
            lines.insert(start + 1, f"zero_offset = {number}{newline}")
    if appended and lines and not lines[-1].endswith(("\n", "\r")):
        lines[-1] += newline
    result = "".join(lines + appended)

    expected = copy.deepcopy(before)
    for joint, value in offsets.items():
        table = expected.setdefault("joints", {}).setdefault(joint, {})
        if "direction" not in table and not _has_joint(before, joint):
            table["direction"] = int(directions.get(joint, 1))
        table["zero_offset"] = float(value)
    try:
        after = tomllib.loads(result)
    except tomllib.TOMLDecodeError as exc:
        raise CalibrationFileError(
            f"cannot update {source}: the joints are not all written as "
            f"'[joints.<name>]' tables with a 'zero_offset = <number>' line ({exc})"
        ) from exc
    if after != expected:
        raise CalibrationFileError(
            f"cannot update {source}: the edit would change more than the zero offsets "
            f"of {sorted(offsets)}; write each joint as a '[joints.<name>]' table"
        )
    return result


def _has_joint(document: Mapping, joint: str) -> bool:
    joints = document.get("joints")
    return isinstance(joints, Mapping) and joint in joints


def backup_name(target: Path, when: datetime) -> Path:
    """Where a backup of ``target`` taken at ``when`` goes: beside it, named
    ``<name>.<UTC time, microseconds>.bak`` (never ``*.toml``, so nothing loads it as a unit)."""
    stamp = when.astimezone(UTC).strftime("%Y%m%dT%H%M%S.%fZ")
    return target.with_name(f"{target.name}.{stamp}.bak")


def _atomic_write(target: Path, text: str, mode: int) -> None:
    """Write ``text`` to a temporary file beside ``target``, then rename it over ``target``.

    Raises:
        OSError: If writing or renaming fails (the temporary file is removed).
    """
    fd, temp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="") as handle:
            handle.write(text)
            handle.flush()
            os.fsync(handle.fileno())
        os.chmod(temp, mode)
        os.replace(temp, target)
    except OSError:
        Path(temp).unlink(missing_ok=True)
        raise


def write_zero_offsets(
    path: str | os.PathLike[str],
    offsets: Mapping[str, float],
    directions: Mapping[str, int] | None = None,
    backup: bool = False,
) -> Path | None:
    """Atomically update the zero offsets of a unit calibration file (see :func:`updated_text`).

    Args:
        path: The unit calibration file.
        offsets: Raw joint name -> new zero offset.
        directions: Raw joint name -> direction, for joints the file has no table for.
        backup: First keep a copy of the file as it was, beside it (:func:`backup_name`).

    Returns:
        The backup's path, or ``None`` without ``backup``.

    Raises:
        CalibrationFileError: If the file is missing, unreadable, not valid TOML or not
            editable as described, or the backup cannot be written; the file is then left
            as it was.
    """
    target = Path(path)
    try:
        # newline="" keeps CRLF files CRLF.
        with open(target, encoding="utf-8", newline="") as handle:
            text = handle.read()
        mode = target.stat().st_mode & 0o7777
    except OSError as exc:
        raise CalibrationFileError(
            f"cannot read calibration file {target}: {exc.strerror or exc}"
        ) from exc
    result = updated_text(text, offsets, directions, source=str(target))
    saved = None
    if backup:
        saved = backup_name(target, datetime.now(UTC))
        try:
            _atomic_write(saved, text, mode)
        except OSError as exc:
            raise CalibrationFileError(
                f"cannot keep a backup of {target} as {saved.name}: {exc}; nothing changed"
            ) from exc
    try:
        _atomic_write(target, result, mode)
    except OSError as exc:
        raise CalibrationFileError(f"cannot write calibration file {target}: {exc}") from exc
    return saved
