"""The unit picker: when several units fit a slot and nothing chooses for the operator, a
terminal gets a numbered list and a prompt (the real ``msctl`` on a pseudo-terminal)."""

from __future__ import annotations

import json
import os
import pty
import select
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

import assemblies


def _read_until(fd: int, needle: bytes, timeout: float) -> bytes:
    seen = b""
    deadline = time.monotonic() + timeout
    while needle not in seen:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise AssertionError(f"{needle!r} never appeared; the terminal showed:\n{seen!r}")
        ready, _, _ = select.select([fd], [], [], remaining)
        if ready:
            try:
                seen += os.read(fd, 4096)
            except OSError:  # the child closed the terminal
                break
    return seen


@pytest.mark.e2e
def test_terminal_operator_picks_a_unit_from_the_list(tmp_path: Path) -> None:
    # The shipped templates name a default unit for every slot; take it away from one.
    data = tmp_path / "assemblies"
    shutil.copytree(Path(assemblies.__file__).parent, data)
    minimal = data / "minimal.toml"
    minimal.write_text(minimal.read_text().replace('default = "hlv1-limb-01"\n', ""))
    env = {
        **os.environ,
        "MSCTL_ASSEMBLIES_DIR": str(data),
        "MSCTL_HOME": str(tmp_path / "home"),
        "TERM": "dumb",
        "COLUMNS": "120",
    }
    leader, follower = pty.openpty()
    child = subprocess.Popen(
        [sys.executable, "-m", "msctl", "assemble", "minimal"],
        stdin=follower,
        stdout=follower,
        stderr=follower,
        env=env,
        close_fds=True,
    )
    os.close(follower)
    try:
        shown = _read_until(leader, b"unit for limb1", timeout=60.0)
        listed = [line for line in shown.decode(errors="replace").splitlines() if ") " in line]
        assert len(listed) >= 2, shown  # every H-line and G-line limb fits this slot
        second = listed[1].split(") ", 1)[1].split()[0]
        os.write(leader, b"2\n")
        _read_until(leader, b"resolved minimal", timeout=60.0)
        assert child.wait(timeout=30) == 0
    finally:
        if child.poll() is None:
            child.kill()
        os.close(leader)
    lock = json.loads((tmp_path / "home" / "assembly" / "assembly.lock.json").read_text())
    assert lock["units"] == {"limb1": second}
