"""Writing the resolved assembly so a reader never sees half of it.

Every file goes into a fresh directory next to the target (``$MSCTL_HOME/.assembly-XXXX``);
``$MSCTL_HOME/assembly`` is then a symlink switched to it with one ``os.replace``, which is
atomic: a reader sees the old resolution or the new one, never a mix, and a failure before the
switch leaves the old one untouched.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from components.assembly import LOCK_NAME, MJCF_NAME, URDF_NAME, encode_lock

#: Leftover staging directories older than this are removed (a crashed run's debris).
_STALE_SECONDS = 300.0


def write_resolution(target: Path, resolution: Any, mjcf: bool = True) -> Path:
    """Atomically write a resolution's lock file and URDF (and MJCF, unless ``mjcf`` is
    False: generating it costs MuJoCo's import) into directory ``target``."""
    files = {URDF_NAME: resolution.urdf, LOCK_NAME: encode_lock(resolution.lock)}
    if mjcf:
        files[MJCF_NAME] = resolution.mjcf()
    return write_assembly(target, files)


def write_assembly(target: Path, files: Mapping[str, str]) -> Path:
    """Atomically replace directory ``target`` by one holding ``files`` (name -> text).

    Returns:
        ``target``.
    """
    state = target.parent
    state.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{target.name}-", dir=state))
    try:
        # The lock goes last: even inside the staging directory, it only exists once every
        # artifact it names does.
        for name in sorted(files, key=lambda n: n == LOCK_NAME):
            _write(staging / name, files[name])
        os.chmod(staging, 0o755)
        link = state / f".{target.name}-link-{os.getpid()}-{time.monotonic_ns()}"
        os.symlink(staging.name, link)
        previous: Path | None = None
        if target.is_symlink():
            previous = state / os.readlink(target)
        elif target.exists():
            # A real directory (written by hand or an older msctl): move it aside first, since
            # a symlink cannot replace a directory in one step.
            previous = state / f".{target.name}-old-{os.getpid()}-{time.monotonic_ns()}"
            os.replace(target, previous)
        os.replace(link, target)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    if previous is not None and previous.name.startswith(f".{target.name}-"):
        shutil.rmtree(previous, ignore_errors=True)
    _sweep(state, target.name, keep=staging.name)
    return target


def write_file(path: Path, text: str) -> None:
    """Atomically write one file (temp file in the same directory, then rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}-", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
        # mkstemp makes the file private (0600); give it the mode a plain write would have.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _write(path: Path, text: str) -> None:
    # No fsync: readers are protected by the atomic switch; after a power cut the operator
    # resolves again in well under a second, which beats paying milliseconds on every run.
    with path.open("w", encoding="utf-8") as fh:
        fh.write(text)


def _sweep(state: Path, name: str, keep: str) -> None:
    now = time.time()
    for entry in state.glob(f".{name}-*"):
        if entry.name == keep:
            continue
        try:
            if now - entry.lstat().st_mtime < _STALE_SECONDS:
                continue  # maybe another msctl assemble still staging
            if entry.is_symlink() or entry.is_file():
                entry.unlink()
            else:
                shutil.rmtree(entry, ignore_errors=True)
        except OSError:
            pass
