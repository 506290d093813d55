"""Issue 18, the actions a newcomer meets with nothing running: each a real ``msctl``
subprocess, end to end (points 4, 5, 6, 10, 12, 17).

The running assembly's side (points 9 and 11) is in ``test_newcomer_actions_running.py``,
the foreground ``msctl up`` (points 15 and 18) in ``test_newcomer_actions_up.py``.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import free_port, wait_until

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


# ------------------------------------------------------------------------------ point 11
def test_assembling_while_an_up_is_still_starting_is_refused_and_the_lock_file_kept(
    tmp_path: Path, nowhere: dict[str, str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from msctl.launcher.state import RunLock

    assert msctl("assemble", "minimal", env=nowhere).returncode == 0
    lock_file = tmp_path / "home" / "assembly" / "assembly.lock.json"
    before = lock_file.read_bytes()
    # An `msctl up` holds the run lock from its first moment; its state file comes only
    # once its processes have started (and read the lock file): hold the lock as it does.
    monkeypatch.setenv("MSCTL_HOME", nowhere["MSCTL_HOME"])
    run = RunLock.acquire(template="minimal", host="test-laptop", by="msctl up")
    try:
        result = msctl("assemble", "dragon", env=nowhere)
        assert result.returncode == 2, result.stderr
        line = one_line(result)
        assert f"assembly minimal is starting (pid {os.getpid()}: msctl up" in line, line
        assert "would replace the lock file under it" in line and "msctl down" in line, line
        assert lock_file.read_bytes() == before
        # The same lock refuses a second `up` (the check above did not take it over).
        again = msctl("up", "minimal", "--for", "1", env=nowhere)
        assert again.returncode == 3 and "minimal is already up" in again.stderr, again.stderr
    finally:
        run.release()
    assert msctl("assemble", "dragon", env=nowhere).returncode == 0
    assert lock_file.read_bytes() != before


# ------------------------------------------------------------------------------ point 5
def test_down_all_with_only_idle_agents_says_nothing_is_running(
    tmp_path: Path, zenoh_env: dict[str, str]
) -> None:
    operator = {**zenoh_env, "MSCTL_HOME": str(tmp_path / "ground"), "MSCTL_HOST": "ground1"}
    with (tmp_path / "agent.log").open("w") as log:
        agent = subprocess.Popen(
            [sys.executable, "-m", "msctl", "agent"],
            env={
                **os.environ,
                **zenoh_env,
                "MSCTL_HOME": str(tmp_path / "limb"),
                "MSCTL_HOST": "hl-limb-01",
            },
            stdin=subprocess.DEVNULL,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            cwd=ROOT,
        )
    try:

        def agent_answers() -> bool:
            result = msctl("ps", "--json", env=operator)
            return result.returncode == 0 and "hl-limb-01" in json.loads(result.stdout)["hosts"]

        wait_until(agent_answers, 60.0, "the agent answering ps", interval=0.5)
        result = msctl("down", "--all", env=operator)
        assert result.returncode == 0, result.stderr
        # Nothing was stopped: no "stopping" for an agent that ran nothing.
        assert "stopping" not in result.stderr, result.stderr
        assert one_line(result) == "nothing is running: the agents of hl-limb-01 run nothing"
    finally:
        agent.send_signal(signal.SIGTERM)
        assert agent.wait(timeout=30) == 0, (tmp_path / "agent.log").read_text()
