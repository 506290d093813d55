"""One ``MSCTL_HOME`` and router endpoint for tests that run the real ``msctl`` in a
subprocess and must leave no process behind (the ``home`` fixture kills every process group
it saw started, also on failure)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import free_port


class Home:
    """One MSCTL_HOME and router endpoint; remembers every process group it saw started."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.env = {
            **{k: v for k, v in os.environ.items() if not k.startswith(("MSCTL_", "ZENOH_"))},
            "MSCTL_HOME": str(root),
            "MSCTL_HOST": "review-laptop",  # none of the assembly's computers: simulated
            "MSCTL_ZENOH_CONNECT": f"tcp/127.0.0.1:{free_port()}",
            "MSCTL_ZENOH_LISTEN": "tcp/127.0.0.1:0",
            "MSCTL_ZENOH_MULTICAST": "0",
            "PYTHONPATH": str(Path(__file__).parents[1]),
        }
        self.pgids: set[int] = set()

    def msctl(self, *args: str, timeout: float = 60.0, **env: str) -> subprocess.CompletedProcess:
        return subprocess.run(
            [sys.executable, "-m", "msctl", *args],
            env={**self.env, **env},
            capture_output=True,
            text=True,
            timeout=timeout,
        )

    def popen(self, *args: str, **env: str) -> subprocess.Popen:
        proc = subprocess.Popen(
            [sys.executable, "-m", "msctl", *args],
            env={**self.env, **env},
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,
        )
        self.pgids.add(proc.pid)
        return proc

    def state(self) -> dict | None:
        try:
            document = json.loads((self.root / "run" / "state.json").read_text())
        except (OSError, ValueError):
            return None
        for process in document.get("processes", []):
            if process.get("pgid"):
                self.pgids.add(process["pgid"])
        return document

    def kill_everything(self) -> None:
        self.state()
        for pgid in self.pgids:
            try:
                os.killpg(pgid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        # An `up --detach` the test's own bound killed may have started processes its state
        # file never named (seen: two assemblies' workers left running for an hour after a
        # loaded run): every process whose command line or environment names this home goes.
        home = str(self.root).encode()
        own = b"MSCTL_HOME=" + home + b"\0"
        for proc in Path("/proc").iterdir():
            if not proc.name.isdigit() or int(proc.name) == os.getpid():
                continue
            try:
                command = (proc / "cmdline").read_bytes()
                environment = (proc / "environ").read_bytes()
            except OSError:
                continue  # gone meanwhile, or not ours to read
            if home + b"/" in command or own in environment:
                try:
                    os.kill(int(proc.name), signal.SIGKILL)
                except ProcessLookupError:
                    pass


@pytest.fixture
def home(tmp_path: Path) -> Iterator[Home]:
    current = Home(tmp_path)
    try:
        yield current
    finally:
        current.kill_everything()


def healthy(home: Home) -> bool:
    """Whether the home's assembly runs with every component running."""
    document = home.state()
    return bool(
        document
        and document.get("state") == "running"
        and document["components"]
        and all(c["state"] == "running" for c in document["components"])
    )
