"""The workspace of a robot computer: its repositories and the packages built from them.

The paper's orchestrator prepares a robot in three actions, update, build and start; this
package holds the first two:

- :mod:`msctl.workspace.repos`: ``.repos`` files (vcstool's format) and experiment overlays,
  merged into one list of repositories;
- :mod:`msctl.workspace.git` and :mod:`msctl.workspace.update`: ``msctl update``, putting
  every repository on its version, refusing per repository whatever would lose work;
- :mod:`msctl.workspace.packages` and :mod:`msctl.workspace.build`: ``msctl build``, a doit
  task graph over the workspace's packages, incremental, offline from a wheelhouse
  (:mod:`msctl.workspace.wheelhouse`);
- :mod:`msctl.workspace.remote`: both, asked of every robot computer's agent.

Nothing here imports zenoh, so ``msctl update`` and ``msctl build`` work on a computer
with no data plane at all.
"""

from __future__ import annotations

import fcntl
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from msctl.errors import InputError, MsctlError

#: The environment variable naming the default workspace directory.
WORKSPACE_ENV = "MSCTL_WORKSPACE"
#: msctl's own files inside a workspace (build state, logs, the files of the last update).
STATE_DIR = ".msctl"


def workspace_dir(given: Path | None = None) -> Path:
    """The workspace directory: ``given``, else ``$MSCTL_WORKSPACE``, else the current one.

    Raises:
        InputError: If the directory named does not exist or is not a directory.
    """
    if given is None:
        env = os.environ.get(WORKSPACE_ENV)
        given = Path(env) if env else Path.cwd()
    path = given.expanduser().absolute()
    if path.exists() and not path.is_dir():
        raise InputError(f"workspace {path} is not a directory", hint="pass --workspace DIR")
    return path


def state_dir(workspace: Path) -> Path:
    """``<workspace>/.msctl``: where msctl keeps what it knows about the workspace."""
    return workspace / STATE_DIR


@contextmanager
def workspace_lock(workspace: Path, what: str) -> Iterator[None]:
    """Hold ``<workspace>/.msctl/<what>.lock`` for the length of one ``update`` or ``build``.

    Two updates of one workspace at once would race on the same clones (two builds, on the
    same build state): the second is refused, naming the first.

    Raises:
        MsctlError: If another process holds the lock.
    """
    lock_dir = state_dir(workspace)
    lock_dir.mkdir(parents=True, exist_ok=True)
    path = lock_dir / f"{what}.lock"
    with open(path, "a+") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.seek(0)
            holder = handle.read().strip() or "?"
            raise MsctlError(
                f"another `msctl {what}` runs in {workspace} (pid {holder})",
                hint="wait for it to finish, then run this again",
            ) from None
        handle.seek(0)
        handle.truncate()
        handle.write(str(os.getpid()))
        handle.flush()
        try:
            yield
        finally:
            handle.seek(0)
            handle.truncate()
            fcntl.flock(handle, fcntl.LOCK_UN)
