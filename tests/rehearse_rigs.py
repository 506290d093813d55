"""A rehearsal of ``dragon`` for the cross-computer tests, and commands run on its computers.

``msctl rehearse up dragon`` makes hl-limb-01/02 and hl-wheel-01/02 (robot computers) and
ground1 (the ground station), one network namespace each; :class:`Stage` runs ``msctl`` on
the rehearsing machine and any command as one of those computers (``msctl rehearse exec
HOST -- ...``), each test run in its own ``MSCTL_HOME``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

from msctl.rehearse.computers import privileges_problem


def _root_mode_problem() -> str | None:
    if os.geteuid() != 0:
        # Without root a rehearsal runs in user namespaces (tests/test_rehearse_userns_e2e.py):
        # these tests look at the system's own /run/netns and /etc/netns.
        return "these tests rehearse as root (CI does); user namespaces have their own tests"
    return privileges_problem()


#: Skips a test of a rehearsal run as root, saying why.
ROOT_REHEARSAL = pytest.mark.skipif(
    _root_mode_problem() is not None, reason=str(_root_mode_problem())
)

#: Dragon's modules and the robot computer each runs on.
ROBOTS = {
    "limb1": "hl-limb-01",
    "limb2": "hl-limb-02",
    "wheel1": "hl-wheel-01",
    "wheel2": "hl-wheel-02",
}
#: Dragon's ground station, where the operator works.
GROUND = "ground1"


class Stage:
    """A rehearsal of ``dragon`` in its own MSCTL_HOME, and commands run on its computers.

    Args:
        home: The rehearsing machine's ``MSCTL_HOME`` (the rehearsal lives under it).
        env: More environment for every command, and so for every computer's agent, which
            ``msctl rehearse up`` starts with its own environment (``MSCTL_WHEELHOUSE``).
    """

    def __init__(self, home: Path, env: Mapping[str, str] | None = None) -> None:
        self.home = home
        self.env = {
            k: v for k, v in os.environ.items() if not k.startswith(("MSCTL_", "COLUMNS", "LINES"))
        }
        self.env.update({"MSCTL_HOME": str(home), "COLUMNS": "200"})
        self.env.update(env or {})

    def computer_home(self, host: str) -> Path:
        """The ``MSCTL_HOME`` of computer ``host``."""
        return self.home / "rehearse" / "computers" / host

    def msctl(self, *args: str, timeout: float = 120.0) -> subprocess.CompletedProcess[str]:
        """``msctl ARGS`` on this (the rehearsing) machine."""
        return subprocess.run(
            [sys.executable, "-m", "msctl", *args],
            env=self.env,
            capture_output=True,
            text=True,
            timeout=timeout,
            stdin=subprocess.DEVNULL,
            check=False,
        )

    def on(self, host: str, *argv: str, timeout: float = 120.0) -> subprocess.CompletedProcess[str]:
        """``msctl ARGV`` run as computer ``host``."""
        return self.run(host, "msctl", *argv, timeout=timeout)

    def run(
        self, host: str, *argv: str, timeout: float = 120.0
    ) -> subprocess.CompletedProcess[str]:
        """Any command run as computer ``host`` (its namespace and environment)."""
        return self.msctl("rehearse", "exec", host, "--", *argv, timeout=timeout)

    def spawn(self, host: str, *argv: str) -> subprocess.Popen[str]:
        """``msctl ARGV`` started as computer ``host`` (the pid is msctl's: exec all the way)."""
        return self.start(host, "msctl", *argv)

    def start(self, host: str, *argv: str) -> subprocess.Popen[str]:
        """Any command started as computer ``host`` (the pid is the command's)."""
        return subprocess.Popen(
            [sys.executable, "-m", "msctl", "rehearse", "exec", host, "--", *argv],
            env=self.env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            stdin=subprocess.DEVNULL,
            text=True,
        )

    def status(self) -> dict[str, Any]:
        """``msctl rehearse status --json``."""
        done = self.msctl("rehearse", "status", "--json")
        assert done.returncode == 0, done.stderr
        return json.loads(done.stdout)


@contextmanager
def rehearsed(stage: Stage, *more: str, timeout: float = 600.0) -> Iterator[Stage]:
    """``msctl rehearse up dragon --link wifi --detach MORE`` for the block, then ``msctl
    rehearse down``, also on failure; the down must leave none of its namespaces."""
    from msctl.rehearse.computers import namespaces
    from msctl.rehearse.rehearsal import namespace_prefix

    # Its --timeout is one budget for every step: a loaded CI machine with two rehearsals at
    # once needs minutes, so it gets nearly all of this wait.
    budget = f"{timeout - 60:g}"
    up = stage.msctl(
        "rehearse", "up", "dragon", "--link", "wifi", "--detach", "--timeout", budget, *more,
        timeout=timeout,
    )  # fmt: skip
    try:
        assert up.returncode == 0, up.stderr
        yield stage
    finally:
        down = stage.msctl("rehearse", "down", timeout=180)
        prefix = namespace_prefix(stage.home / "rehearse")
        assert down.returncode == 0, down.stderr
        assert not [n for n in namespaces() if n.startswith(prefix)], "namespaces left behind"
