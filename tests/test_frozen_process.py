"""A frozen component process is noticed, then killed and restarted (issue 10, finding 7).

Before: a worker stopped with SIGSTOP kept its pid and its sockets, so ``msctl ps`` said
"running" (25 s and counting) while its nodes were gone from the graph. Now each worker's
executor loop beats a pipe the supervisor reads (``components/executor/heartbeat.py``): the
supervisor marks a silent process ``unresponsive`` after 1 s, and after a grace period
(``--kill-unresponsive-after``, 5 s by default) SIGKILLs and restarts it as for a crash.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import wait_until
from test_supervisor_hardening import Home, all_running

from components.executor.heartbeat import FD_ENV, Heartbeat
from msctl.launcher.supervisor import (
    LivenessPolicy,
    ProcessState,
    RestartPolicy,
    ShutdownPolicy,
    Supervisor,
)

#: A stand-in worker: beats its heartbeat as the executor loop does, forever.
BEATING = """
import time
from components.executor.heartbeat import Heartbeat
heartbeat = Heartbeat.from_env()
print("beating" if heartbeat else "no heartbeat", flush=True)
while True:
    heartbeat.beat()
    time.sleep(0.05)
"""


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_a_heartbeat_beats_at_most_every_period_and_never_blocks() -> None:
    reader, writer = os.pipe()
    clock = FakeClock()
    heartbeat = Heartbeat(writer, period=0.25, clock=clock)
    try:
        os.set_blocking(reader, False)
        for _ in range(10):
            heartbeat.beat()
        assert os.read(reader, 100) == b"."
        clock.now += 0.3
        heartbeat.beat()
        assert os.read(reader, 100) == b"."
        # A supervisor that stopped reading: the pipe fills, the loop never waits on it.
        for _ in range(200_000):
            clock.now += 1.0
            heartbeat.beat()
        assert heartbeat.fd == writer
        # The supervisor gone (reader closed): beating stops quietly.
        os.close(reader)
        clock.now += 1.0
        heartbeat.beat()
        assert heartbeat.fd == -1
    finally:
        heartbeat.close()


def test_the_heartbeat_is_taken_from_the_environment_once(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    reader, writer = os.pipe()
    try:
        monkeypatch.setenv(FD_ENV, str(writer))
        heartbeat = Heartbeat.from_env()
        assert heartbeat is not None and heartbeat.fd == writer
        assert FD_ENV not in os.environ  # nothing the worker starts inherits it
        assert not os.get_inheritable(writer)
        assert Heartbeat.from_env() is None
        monkeypatch.setenv(FD_ENV, "not a number")
        assert Heartbeat.from_env() is None
        heartbeat.close()
    finally:
        os.close(reader)


def test_the_executor_loop_beats_while_it_runs(session_settings: Any) -> None:
    from components.executor.executor import Executor

    reader, writer = os.pipe()
    os.set_blocking(reader, False)
    try:
        with Executor(session_settings, heartbeat=Heartbeat(writer, period=0.05)) as executor:
            executor.run(duration=1.0)  # idle: no core, no timer, yet it beats
        beats = os.read(reader, 1000)
    finally:
        os.close(reader)
    assert len(beats) >= 4, beats


#: The grace period the end-to-end run is given: long enough for a ``msctl ps`` on a loaded
#: machine (several seconds each) to see the process unresponsive before it is killed.
GRACE = 20.0


@pytest.fixture
def minimal(tmp_path: Path) -> Iterator[Home]:
    """``msctl up minimal --detach`` in a fresh MSCTL_HOME, every component healthy."""
    current = Home.make(tmp_path / "home")
    current.env["MSCTL_KILL_UNRESPONSIVE_AFTER"] = str(GRACE)  # the option's variable
    try:
        result = current.msctl("up", "minimal", "--detach", timeout=120.0)
        current.state()
        assert result.returncode == 0, result.stdout + result.stderr
        yield current
    finally:
        current.clean_up()


@pytest.fixture
def supervisor(tmp_path: Path) -> Iterator[Supervisor]:
    """A supervisor with short liveness bounds; every group it started is killed at the end."""
    sup = Supervisor(
        tmp_path / "logs",
        RestartPolicy(backoff_initial=0.05, backoff_max=0.2),
        ShutdownPolicy(after_sigint=0.5, after_sigterm=0.5),
        LivenessPolicy(unresponsive_after=1.0, kill_after=2.0),
    )
    pgids: set[int] = set()
    original = sup._spawn

    def spawn(process: Any) -> None:
        original(process)
        if process.popen is not None:
            pgids.add(process.popen.pid)

    sup._spawn = spawn  # type: ignore[method-assign]
    try:
        yield sup
    finally:
        sup.shutdown()
        for pgid in pgids:
            try:
                os.killpg(pgid, signal.SIGKILL)
            except ProcessLookupError:
                pass


def poll_until(sup: Supervisor, predicate: Any, what: str, timeout: float = 30.0) -> list[str]:
    """Poll the supervisor until ``predicate()``; returns the events seen meanwhile."""
    events: list[str] = []

    def done() -> bool:
        events.extend(sup.poll())
        return bool(predicate())

    wait_until(done, timeout=timeout, what=what, interval=0.05)
    return events


@pytest.mark.e2e
def test_a_stopped_process_is_unresponsive_then_killed_and_restarted(
    supervisor: Supervisor,
) -> None:
    process = supervisor.add(
        "limb1",
        [sys.executable, "-c", BEATING],
        env={"PYTHONPATH": str(Path(__file__).parents[1])},
        components=["limb1/joint_manager"],
        heartbeat=True,
    )
    silent = supervisor.add("router", [sys.executable, "-c", "import time; time.sleep(600)"])
    supervisor.start_all()
    poll_until(supervisor, lambda: process.last_beat is not None, "a first beat")
    supervisor.mark_running("limb1")
    first = process.pid
    assert first is not None

    # Stopped, then continued within the grace period: unresponsive, then running again.
    os.killpg(first, signal.SIGSTOP)
    events = poll_until(
        supervisor, lambda: process.state is ProcessState.UNRESPONSIVE, "unresponsive"
    )
    assert any("limb1: unresponsive (no heartbeat for" in e for e in events), events
    assert supervisor.snapshot()[0].state == "unresponsive"
    os.killpg(first, signal.SIGCONT)
    events = poll_until(supervisor, lambda: process.state is ProcessState.RUNNING, "running")
    assert "limb1: responsive again" in events and process.pid == first

    # Stopped for good: killed and restarted as for a crash, counted in restarts.
    os.killpg(first, signal.SIGSTOP)
    events = poll_until(
        supervisor,
        lambda: process.pid not in (None, first) and process.state is ProcessState.STARTING,
        "a new process",
    )
    assert any("killed; restarting in" in e for e in events), events
    assert process.restarts == 1
    assert process.last_error.startswith("unresponsive (no heartbeat for")
    assert "unresponsive (no heartbeat for" in process.log.path.read_text()
    # A process without a heartbeat (the router) is never judged by one.
    assert silent.state is ProcessState.STARTING and silent.pid is not None


@pytest.mark.e2e
def test_a_frozen_worker_shows_unresponsive_in_ps_then_is_restarted(minimal: Home) -> None:
    home = minimal
    before = home.state()
    limb1 = next(p for p in before["processes"] if p["name"] == "limb1")
    frozen = limb1["pid"]
    assert limb1["heartbeat_age"] is not None, limb1

    stopped_at = time.monotonic()
    os.killpg(frozen, signal.SIGSTOP)

    def unresponsive() -> dict[str, Any] | None:
        components = home.components()
        states = {c["state"] for n, c in components.items() if n.startswith("limb1/")}
        return components if states == {"unresponsive"} else None

    components = wait_until(unresponsive, timeout=GRACE, what="ps shows limb1 unresponsive")
    noticed = time.monotonic() - stopped_at
    assert all(c["pid"] == frozen for n, c in components.items() if n.startswith("limb1/"))
    assert components["sim/simulator"]["state"] == "running"
    table = home.msctl("ps", timeout=60.0)
    assert "unresponsive" in table.stdout

    def restarted() -> dict[str, Any] | None:
        components = home.components()
        limb = [c for n, c in components.items() if n.startswith("limb1/")]
        fresh = all(c["pid"] not in (None, frozen) and c["restarts"] == 1 for c in limb)
        return components if fresh and all_running(components) else None

    components = wait_until(restarted, timeout=180.0, what="limb1 restarted and running")
    back = time.monotonic() - stopped_at
    error = components["limb1/joint_manager"]["last_error"]
    assert error.startswith("unresponsive (no heartbeat for"), error
    log = (home.path / "run" / "supervisor.log").read_text()
    assert "limb1: unresponsive (no heartbeat for" in log
    assert f"killed and restarted if still silent in {GRACE:g} s" in log
    print(json.dumps({"unresponsive_in_ps_s": round(noticed, 2), "running_again_s": round(back)}))
