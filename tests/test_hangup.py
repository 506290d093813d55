"""A dropped SSH link sends SIGHUP: a foreground ``msctl up`` and an ``msctl agent`` started
in a terminal stop cleanly, leaving no process group behind (the real command in a
subprocess, a random loopback port, an ``MSCTL_HOME`` of its own)."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest
from conftest import wait_until
from home_rig import Home, healthy, home  # noqa: F401  (home: the fixture)

from msctl.launcher.state import process_group_alive

pytestmark = pytest.mark.e2e


def test_foreground_up_stops_everything_on_sighup(home: Home) -> None:  # noqa: F811
    # An SSH link that drops sends SIGHUP to a foreground `msctl up`: it died at once and left
    # every component's process group running, the state file naming a dead supervisor.
    proc = home.popen("up", "minimal")
    try:
        wait_until(lambda: healthy(home), timeout=60.0, what="minimal healthy")
        groups = {p["name"]: p["pgid"] for p in home.state()["processes"] if p["pgid"]}
        assert "router" in groups and "sim" in groups
        proc.send_signal(signal.SIGHUP)
        _, stderr = proc.communicate(timeout=20.0)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 0, stderr
    assert "minimal stopped" in stderr
    assert home.state()["state"] == "stopped"
    for name, pgid in groups.items():
        assert not process_group_alive(pgid), f"{name} (group {pgid}) outlived SIGHUP"


def test_agent_stops_cleanly_on_sighup(home: Home) -> None:  # noqa: F811
    # The same for an agent started in a terminal: its router (and any run) must not outlive it.
    proc = home.popen("agent", MSCTL_HOST="gl-pi-01")
    try:
        router = wait_until(
            lambda: next(
                (
                    int(p.parent.name)
                    for p in Path("/proc").glob("[0-9]*/cmdline")
                    if _ppid(p.parent) == proc.pid and b"router" in _read(p)
                ),
                None,
            ),
            timeout=30.0,
            what="the agent's router",
        )
        home.pgids.add(router)
        wait_until(
            lambda: home.msctl("ps", "--json", timeout=30.0).stdout.count("gl-pi-01") > 0,
            timeout=30.0,
            what="the agent answering ps",
        )
        proc.send_signal(signal.SIGHUP)
        _, stderr = proc.communicate(timeout=20.0)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 0, stderr
    assert "gl-pi-01: stopped" in stderr
    assert not process_group_alive(router), "the agent's router outlived SIGHUP"


def _read(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError:
        return b""


def _ppid(proc_dir: Path) -> int:
    try:
        return int((proc_dir / "stat").read_text().rsplit(")", 1)[1].split()[1])
    except (OSError, IndexError, ValueError):
        return -1
