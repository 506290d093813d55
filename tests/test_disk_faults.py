"""A full disk never kills the supervisor (issue 10, finding 6).

Before: ENOSPC in a log thread killed ``msctl up``'s supervisor and every component with it;
component logs were lost silently before that, and state.json stayed "running". Now the log
writer drops lines and counts them, the supervisor warns once (its events, ``msctl ps``) and
keeps supervising, a state file that cannot be written is reported, not fatal, and once the
disk has room again the log says how many lines were lost.

The full disk is real: ``/dev/full`` for the log writer alone, and a 2 MiB tmpfs mounted as
MSCTL_HOME inside ``unshare -m`` for a running assembly.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from conftest import free_port, wait_until

from msctl.launcher.supervisor import RotatingLog, Supervisor

ROOT = Path(__file__).resolve().parents[1]


def test_a_log_on_a_full_disk_drops_and_counts_lines_and_never_raises(tmp_path: Path) -> None:
    full = tmp_path / "limb1.log"
    full.symlink_to("/dev/full")  # every write: ENOSPC
    log = RotatingLog(full, tail=5)
    for i in range(10):
        log.write_line(f"line {i}")
    assert log.dropped == 10 and log.fault == os.strerror(28)
    assert list(log.tail) == [f"line {i}" for i in range(5, 10)]  # still kept in memory
    log.close()


def test_the_supervisor_warns_once_per_fault_and_says_when_it_is_over(tmp_path: Path) -> None:
    supervisor = Supervisor(tmp_path, run="test")
    process = supervisor.add("limb1", [sys.executable, "-c", "pass"])
    good = process.log.path
    process.log.close()
    full = tmp_path / "full.log"
    full.symlink_to("/dev/full")
    process.log = RotatingLog(full)
    for i in range(3):
        process.log.write_line(f"lost {i}")
    events = supervisor.poll()
    assert len(events) == 1 and "cannot write its log" in events[0], events
    assert "No space left on device" in events[0] and "still supervising" in events[0]
    assert supervisor.poll() == []  # once, not at every poll
    assert supervisor.faults() == [f"log of limb1: {os.strerror(28)}; 3 lines lost"]
    assert {p.name: p for p in supervisor.snapshot()}["limb1"].log_lines_lost == 3

    # Room again: the next line goes through, preceded by how many were lost.
    process.log._fd = os.open(good, os.O_WRONLY | os.O_APPEND)  # the disk was freed
    process.log.write_line("back")
    events = supervisor.poll()
    assert events == ["limb1: its log is written again (3 lines lost in all)"]
    assert supervisor.faults() == []
    text = good.read_text().splitlines()
    assert text[-2].endswith("--- msctl: 3 log lines lost: No space left on device")
    assert text[-1].endswith(" back")
    process.log.close()


def _unshare_works() -> bool:
    if shutil.which("unshare") is None:
        return False
    probe = subprocess.run(
        ["unshare", "-m", "sh", "-c", "mount -t tmpfs -o size=64k tmpfs /mnt"],
        capture_output=True,
        check=False,
    )
    return probe.returncode == 0


@pytest.mark.e2e
@pytest.mark.skipif(not _unshare_works(), reason="needs mount namespaces (unshare -m)")
def test_an_assembly_on_a_full_disk_keeps_running_and_says_so(tmp_path: Path) -> None:
    home, signals = tmp_path / "home", tmp_path / "signals"
    home.mkdir()
    signals.mkdir()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    env = {
        **os.environ,
        "MSCTL_HOST": "test-laptop",
        "MSCTL_HOME": str(home),
        "MSCTL_ZENOH_CONNECT": endpoint,
        "MSCTL_ZENOH_LISTEN": "tcp/127.0.0.1:0",
        "MSCTL_ZENOH_MULTICAST": "0",
        "PYTHONPATH": str(ROOT),
    }
    msctl = f"{sys.executable} -m msctl"
    # Inside its own mount namespace: MSCTL_HOME is a 2 MiB tmpfs that only this script (and
    # the supervisor it starts) sees. It steps on files in `signals`, outside the tmpfs.
    script = textwrap.dedent(
        f"""
        set -e
        mount -t tmpfs -o size=2m tmpfs "$MSCTL_HOME"
        {msctl} up minimal --detach --timeout 90 > {signals}/up.out 2>&1
        touch {signals}/up
        head -c 4M /dev/zero > "$MSCTL_HOME/filler" 2>/dev/null || true
        touch {signals}/full
        while [ ! -e {signals}/free ]; do sleep 0.1; done
        rm "$MSCTL_HOME/filler"
        touch {signals}/freed
        while [ ! -e {signals}/down ]; do sleep 0.1; done
        cp "$MSCTL_HOME"/run/logs/limb1.log {signals}/limb1.log
        {msctl} down > {signals}/down.out 2>&1
        """
    )
    inside = subprocess.Popen(
        ["unshare", "-m", "sh", "-c", script], env=env, stdout=subprocess.PIPE, text=True
    )

    def ps() -> dict:
        result = subprocess.run(
            [sys.executable, "-m", "msctl", "ps", "--json"],
            env=env,
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
        assert result.returncode == 0, result.stderr
        return json.loads(result.stdout)

    try:
        wait_until(lambda: (signals / "full").exists() or inside.poll() is not None, 180.0)
        assert inside.poll() is None, (signals / "up.out").read_text()
        # A restart makes the supervisor write its log and its state file on the full disk.
        restart = subprocess.run(
            [sys.executable, "-m", "msctl", "restart", "limb1/joint_manager"],
            env=env,
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
        assert restart.returncode == 0, restart.stderr
        notes = wait_until(
            lambda: [n for n in ps()["notes"] if "No space left on device" in n] or None,
            60.0,
            interval=0.5,
        )
        assert any("state file" in n for n in notes) or any("log of" in n for n in notes), notes
        # Still supervising: the restarted process comes back up, nothing else died.
        wait_until(
            lambda: all(c["state"] == "running" for c in ps()["components"]) or None,
            90.0,
            interval=0.5,
        )
        (signals / "free").touch()
        wait_until(lambda: (signals / "freed").exists(), 30.0)
        wait_until(lambda: not ps()["notes"] or None, 30.0, interval=0.5)  # the warning is over
        (signals / "down").touch()
        assert inside.wait(timeout=120) == 0, (signals / "down.out").read_text()
        log = (signals / "limb1.log").read_text()
        # Each line of the restart is in the file (tmpfs fills by pages: the log's last page
        # may still have had room), or its loss is said there.
        assert log.count("--- msctl: starting limb1") == 2 or (
            "log lines lost: No space left on device" in log
        ), log[-2000:]
    finally:
        for name in ("free", "down"):
            (signals / name).touch()
        if inside.poll() is None:
            try:
                inside.wait(timeout=60)
            except subprocess.TimeoutExpired:
                inside.kill()
