"""Issue 18, the actions a newcomer meets with nothing running: each a real ``msctl``
subprocess, end to end (points 4, 5, 6, 10, 12, 17).

The running assembly's side (points 9 and 11) is in ``test_newcomer_actions_running.py``,
the foreground ``msctl up`` (points 15 and 18) in ``test_newcomer_actions_up.py``.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import free_port

pytestmark = pytest.mark.e2e

ROOT = Path(__file__).resolve().parents[1]


def msctl(*args: str, env: dict[str, str], timeout: float = 60.0) -> subprocess.CompletedProcess:
    """One ``msctl`` command, run as the operator runs it."""
    return subprocess.run(
        [sys.executable, "-m", "msctl", *args],
        capture_output=True,
        text=True,
        env={**os.environ, **env},
        timeout=timeout,
        check=False,
        cwd=ROOT,
    )


def one_line(result: subprocess.CompletedProcess) -> str:
    """The one line a failing command printed."""
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, result.stderr
    return lines[0]


@pytest.fixture
def nowhere(tmp_path: Path) -> dict[str, str]:
    """A home, and a router endpoint where nothing listens."""
    return {
        "MSCTL_HOME": str(tmp_path / "home"),
        "MSCTL_HOST": "test-laptop",
        "MSCTL_ZENOH_CONNECT": f"tcp/127.0.0.1:{free_port()}",
        "MSCTL_ZENOH_LISTEN": "tcp/127.0.0.1:0",
        "MSCTL_ZENOH_MULTICAST": "0",
    }


# ------------------------------------------------------------------------------ point 12
def test_run_with_no_router_fails_at_the_refusal_as_topic_list_does(
    tmp_path: Path, nowhere: dict[str, str]
) -> None:
    script = tmp_path / "noop.py"
    script.write_text("async def main(robot):\n    pass\n")
    endpoint = nowhere["MSCTL_ZENOH_CONNECT"]
    result = msctl("run", str(script), "--timeout", "60", env=nowhere)
    assert result.returncode == 3, result.stderr
    line = one_line(result)
    # The refused connection itself, as `msctl topic list` knows it: no wait for an answer
    # that cannot come ("within 2 s" was a wait of its own, after the refusal).
    assert f"no Zenoh router or peer reachable at {endpoint} (connection refused)" in line, line
    assert "within" not in line, line
    listed = msctl("topic", "list", env=nowhere)
    assert listed.returncode == result.returncode == 3, listed.stderr
