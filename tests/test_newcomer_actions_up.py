"""Issue 18, a foreground ``msctl up`` failing or interrupted, end to end (points 15, 18).

``tests/test_up_foreground.py`` holds the rest: Ctrl-C at three moments of the start, and
every worker refusing ``MSCTL_TRANSPORT=rclpy`` where rclpy cannot be imported (skipped where
it can: then nothing fails).
"""

from __future__ import annotations

import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
from test_up_foreground import Foreground

pytestmark = pytest.mark.e2e


@pytest.fixture
def foreground(tmp_path: Path) -> Iterator[Foreground]:
    current = Foreground(tmp_path / "home")
    try:
        yield current
    finally:
        current.clean_up()


# ------------------------------------------------------------------------------ point 15
def test_a_setting_every_worker_refuses_is_said_once_and_the_up_ends(
    foreground: Foreground,
) -> None:
    # Deterministic wherever it runs: every component process refuses the transport, a
    # bad argument (exit 2) that no restart would cure.
    proc = foreground.start("up", "dragon", "--for", "600", MSCTL_TRANSPORT="carrier-pigeon")
    try:
        code = proc.wait(timeout=300.0)  # ending at once: never its --for
    except subprocess.TimeoutExpired:
        raise AssertionError("msctl up kept running:\n" + foreground.stderr()) from None
    stderr = foreground.stderr()
    cause = "MSCTL_TRANSPORT='carrier-pigeon': use zenoh or rclpy"
    assert code == 3, stderr
    assert stderr.count(cause) == 1, stderr  # it was printed once per process, six times
    assert " up in " not in stderr, stderr
    last = stderr.strip().splitlines()[-1]
    assert last.startswith("error: ") and cause in last, last
    assert "gave up after one try" in last and "msctl logs" in last, last
    failed = [p for p in foreground.state()["processes"] if p["state"] == "failed"]
    assert failed, foreground.state()
    assert not foreground.leftovers()
