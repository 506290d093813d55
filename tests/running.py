"""A detached simulated assembly for end-to-end tests: ``msctl up TEMPLATE --detach`` in its
own MSCTL_HOME, behind its own router on a free loopback port, and ``msctl down`` after."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

from conftest import free_port

from components.comm.session import SessionSettings

ROOT = Path(__file__).resolve().parents[1]


class Up:
    """One detached simulated assembly (every host simulated: MSCTL_HOST is no robot).

    Args:
        home: Its MSCTL_HOME.
        template: The template to bring up.
        extra: More ``msctl up`` arguments.
        env: More environment variables for every command (``MSCTL_TRANSPORT``...).
        up_wait: Seconds ``msctl up --detach`` may take.
    """

    def __init__(
        self,
        home: Path,
        template: str,
        *extra: str,
        env: dict[str, str] | None = None,
        up_wait: float = 120.0,
    ) -> None:
        self.home = home
        self.template = template
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.env = {
            **os.environ,
            "MSCTL_HOME": str(home),
            "MSCTL_HOST": "test-laptop",  # none of the assembly's computers: simulated
            "MSCTL_ZENOH_CONNECT": self.endpoint,
            "MSCTL_ZENOH_LISTEN": "tcp/127.0.0.1:0",
            "MSCTL_ZENOH_MULTICAST": "0",
            "PYTHONPATH": str(ROOT),
            **(env or {}),
        }
        try:
            result = self.msctl("up", template, "--detach", "--speed", "1", *extra, timeout=up_wait)
        except subprocess.TimeoutExpired:
            # The detached supervisor outlives the command: stop it, or a whole assembly
            # runs on into every later test.
            self.kill_leftovers()
            raise
        if result.returncode != 0:
            self.kill_leftovers()
        assert result.returncode == 0, result.stdout + result.stderr

    def msctl(self, *args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
        """Run one msctl command against this assembly."""
        return subprocess.run(
            [sys.executable, "-m", "msctl", *args],
            env=self.env,
            capture_output=True,
            text=True,
            timeout=timeout,
            cwd=ROOT,
            check=False,
        )

    def settings(self) -> SessionSettings:
        """Session settings that join this assembly from outside, as a script or a command
        does (:meth:`SessionSettings.joining`): a client of its router only."""
        return SessionSettings(mode="client", connect=(self.endpoint,), multicast=False)

    def down(self) -> None:
        """``msctl down``, verified; whatever it could not stop is killed all the same, so a
        failed test leaves no assembly running into the next ones."""
        try:
            result = self.msctl("down", timeout=60.0)
        except subprocess.TimeoutExpired:
            self.kill_leftovers()
            raise
        if result.returncode != 0:
            self.kill_leftovers()
        assert result.returncode == 0, result.stdout + result.stderr

    def kill_leftovers(self) -> None:
        """SIGKILL the supervisor and every process group its state file names."""
        try:
            document = json.loads((self.home / "run" / "state.json").read_text())
        except (OSError, ValueError):
            return
        pids = [document.get("supervisor_pid")]
        pgids = [p.get("pgid") for p in document.get("processes", [])]
        for pid in filter(None, pids):
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
        for pgid in filter(None, pgids):
            with contextlib.suppress(OSError):
                os.killpg(pgid, signal.SIGKILL)
