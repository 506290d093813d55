"""Where msctl keeps its state on this computer.

Apart from :mod:`components.assembly` (the lock file's schema, msgspec and the module
specs, about 50 ms to import) so that what only needs the directory -- the launcher's state
file read by every ``msctl ps`` -- does not load the schema.
"""

from __future__ import annotations

import os
from pathlib import Path


def state_dir() -> Path:
    """msctl's state directory: ``$MSCTL_HOME``, else ``$XDG_STATE_HOME/msctl``,
    else ``~/.local/state/msctl``."""
    home = os.environ.get("MSCTL_HOME")
    if home:
        return Path(home).expanduser()
    xdg = os.environ.get("XDG_STATE_HOME")
    if xdg:
        return Path(xdg).expanduser() / "msctl"
    return Path.home() / ".local" / "state" / "msctl"
