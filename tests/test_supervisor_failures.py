"""Deterministic failures are not retried: a component worker that exits 2 (bad arguments) or 3
(a component cannot be built or configured) is FAILED at once with its last stderr line as the
reason, printed once; crashes (exit 1, other codes, signals) keep backoff-and-retry.

First with tiny ``python -c`` stand-ins for the worker under a real :class:`Supervisor`, then end
to end: the real ``msctl up`` (foreground and ``--detach``) on a resolved Dragon whose limb1
joint manager holds a parameter its builder refuses.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import free_port, resolved_assembly, wait_until
from supervisor_rig import quick_supervisor

from msctl.launcher.run import WORKER_FINAL_EXITS
from msctl.launcher.state import group_alive, process_group_alive
from msctl.launcher.supervisor import ProcessState, Supervisor

PY = sys.executable

CAUSE = "error: cannot build limb1/joint_manager: param watchdog_timeout must be a number"

#: A stand-in for the component worker: notes each start in the file ``argv[1]``, logs a line,
#: prints ``argv[3]`` to stderr and ends with ``argv[2]`` (an exit code, or ``SIGKILL``).
WORKER = """
import os, signal, sys
with open(sys.argv[1], "a") as starts:
    starts.write("start\\n")
print("INFO msctl.worker: built limb1/health_monitor (health_monitor)", file=sys.stderr)
print(sys.argv[3], file=sys.stderr, flush=True)
if sys.argv[2] == "SIGKILL":
    os.kill(os.getpid(), signal.SIGKILL)
sys.exit(int(sys.argv[2]))
"""


@pytest.fixture
def supervisor(tmp_path: Path) -> Iterator[Supervisor]:
    """A supervisor with quick backoff; every group it started is killed at teardown."""
    with quick_supervisor(tmp_path / "logs", backoff_max=0.2) as sup:
        yield sup


def add_worker(
    sup: Supervisor, tmp_path: Path, ending: str, final_exits: dict[int, str] | None
) -> tuple[Any, Path]:
    """Register a stand-in worker ending with ``ending``; returns it and its starts file."""
    starts = tmp_path / "starts.txt"
    process = sup.add(
        "limb1",
        [PY, "-c", WORKER, str(starts), ending, CAUSE + ", not 'soon'"],
        components=["limb1/joint_manager", "limb1/health_monitor"],
        final_exits=final_exits,
    )
    return process, starts


def poll_until_failed(sup: Supervisor, process: Any, timeout: float = 20.0) -> list[str]:
    """Poll until ``process`` is FAILED; returns every event seen meanwhile."""
    events: list[str] = []

    def failed() -> bool:
        events.extend(sup.poll())
        return process.state is ProcessState.FAILED

    wait_until(failed, timeout=timeout, what=f"{process.name} FAILED")
    return events


def start_count(starts: Path) -> int:
    return starts.read_text().count("start")


# ------------------------------------------------------------------------------ supervisor
@pytest.mark.e2e
@pytest.mark.parametrize("code", [2, 3])
def test_a_worker_exit_that_says_restarting_cannot_help_fails_at_once(
    supervisor: Supervisor, tmp_path: Path, code: int
) -> None:
    process, starts = add_worker(supervisor, tmp_path, str(code), WORKER_FINAL_EXITS)
    supervisor.start("limb1")
    events = poll_until_failed(supervisor, process)
    # Nothing is due, however late it is: a restart would have been planned by now.
    assert process.next_start is None
    assert supervisor.poll(now=time.monotonic() + 3600.0) == []
    assert process.state is ProcessState.FAILED and process.pid is None
    assert process.restarts == 0 and start_count(starts) == 1
    # The reason is the worker's last stderr line, said once, with what the code means.
    assert f"exited with code {code}: {CAUSE}, not 'soon'" in process.last_error
    assert process.last_error.count(CAUSE) == 1
    assert WORKER_FINAL_EXITS[code] in process.last_error
    assert "built limb1/health_monitor" not in process.last_error
    assert [e for e in events if "FAILED" in e] == [f"limb1: FAILED ({process.last_error})"]
    assert not any("restart" in e for e in events if "FAILED" not in e), events
    snapshot = {p.name: p for p in supervisor.snapshot()}["limb1"]
    assert snapshot.state == "failed" and snapshot.restarts == 0
    assert snapshot.last_error == process.last_error
    log = process.log.path.read_text()
    # Printed once (its command line, logged at the start, holds it too: count whole lines).
    assert [line[24:] for line in log.splitlines()].count(f"{CAUSE}, not 'soon'") == 1
    assert log.count("--- msctl: starting limb1") == 1
    assert f"not restarted: code {code} means" in log


@pytest.mark.e2e
@pytest.mark.parametrize("ending", ["1", "4", "SIGKILL"])
def test_a_crash_is_still_restarted_with_backoff_until_it_gives_up(
    supervisor: Supervisor, tmp_path: Path, ending: str
) -> None:
    process, starts = add_worker(supervisor, tmp_path, ending, WORKER_FINAL_EXITS)
    supervisor.start("limb1")
    backoffs: list[float] = []

    def failed() -> bool:
        for event in supervisor.poll():
            if "restarting in" in event:
                backoffs.append(process.backoff)
        return process.state is ProcessState.FAILED

    wait_until(failed, timeout=20.0, what="the crash loop to give up")
    assert backoffs == [0.05, 0.1, 0.2]
    assert process.restarts == 3 and start_count(starts) == 4
    assert "gave up after 3 restarts" in process.last_error
    reason = "killed by SIGKILL" if ending == "SIGKILL" else f"exited with code {ending}"
    assert reason in process.last_error and CAUSE in process.last_error


@pytest.mark.e2e
def test_a_process_without_final_exits_is_restarted_whatever_its_code(
    supervisor: Supervisor, tmp_path: Path
) -> None:
    """Exit 3 is the worker's word only: ``msctl router`` exits 3 on a network error, which
    may pass (the port of a router killed a moment ago), so it keeps being restarted."""
    process, starts = add_worker(supervisor, tmp_path, "3", None)
    supervisor.start("limb1")
    events: list[str] = []

    def restarted() -> bool:
        events.extend(supervisor.poll())
        return process.restarts >= 1

    wait_until(restarted, timeout=20.0, what="a restart after exit 3")
    assert any("exited with code 3; restarting in" in e for e in events), events
    wait_until(lambda: start_count(starts) >= 2, timeout=20.0, what="a second start")


@pytest.mark.e2e
def test_shutdown_leaves_a_failed_process_failed(supervisor: Supervisor, tmp_path: Path) -> None:
    process, _ = add_worker(supervisor, tmp_path, "3", WORKER_FINAL_EXITS)
    sleeper = supervisor.add("limb2", [PY, "-c", "import time; time.sleep(60)"])
    supervisor.start_all()
    poll_until_failed(supervisor, process)
    error = process.last_error
    supervisor.shutdown()
    # The last state file still says which process failed, and why.
    assert process.state is ProcessState.FAILED and process.last_error == error
    assert sleeper.state is ProcessState.STOPPED


# ------------------------------------------------------------------------------ msctl up
class Home:
    """One MSCTL_HOME holding a Dragon that cannot be built, and a random router port."""

    def __init__(self, root: Path, assembly: Path) -> None:
        self.root = root
        self.env = {
            **{k: v for k, v in os.environ.items() if not k.startswith(("MSCTL_", "ZENOH_"))},
            "MSCTL_HOME": str(root),
            "MSCTL_HOST": "failures-laptop",  # none of the Dragon's computers: simulated
            "MSCTL_ZENOH_CONNECT": f"tcp/127.0.0.1:{free_port()}",
            "MSCTL_ZENOH_LISTEN": "tcp/127.0.0.1:0",
            "MSCTL_ZENOH_MULTICAST": "0",
            "PYTHONPATH": str(Path(__file__).parents[1]),
        }
        shutil.copytree(assembly, root / "assembly")
        self.pgids: set[int] = set()

    def break_limb1_joint_manager(self) -> None:
        """Give limb1's joint manager a watchdog timeout its builder refuses (not a number)."""
        lock = self.root / "assembly" / "assembly.lock.json"
        document = json.loads(lock.read_text())
        component = next(c for c in document["components"] if c["name"] == "limb1/joint_manager")
        component["params"]["watchdog_timeout"] = "soon"
        lock.write_text(json.dumps(document))

    def msctl(self, *args: str, timeout: float = 90.0) -> subprocess.CompletedProcess:
        return subprocess.run(
            [sys.executable, "-m", "msctl", *args],
            env=self.env,
            capture_output=True,
            text=True,
            timeout=timeout,
        )

    def up(self, *args: str, timeout: float = 90.0) -> subprocess.CompletedProcess:
        """Run ``msctl up ARGS`` to completion, noting every process group its state file
        names meanwhile (a stopped run's file names none)."""
        out, err = self.root / "up.out", self.root / "up.err"
        with out.open("w") as stdout, err.open("w") as stderr:
            proc = subprocess.Popen(
                [sys.executable, "-m", "msctl", "up", *args],
                env=self.env,
                stdin=subprocess.DEVNULL,
                stdout=stdout,
                stderr=stderr,
                start_new_session=True,
            )
        try:
            deadline = time.monotonic() + timeout
            while proc.poll() is None and time.monotonic() < deadline:
                with contextlib.suppress(OSError, ValueError, KeyError):
                    self.state()
                time.sleep(0.05)
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        return subprocess.CompletedProcess(
            proc.args, proc.returncode, out.read_text(), err.read_text()
        )

    def state(self) -> dict[str, Any]:
        """The state file, remembering every process group it names."""
        document = json.loads((self.root / "run" / "state.json").read_text())
        self.pgids |= {p["pgid"] for p in document["processes"] if p.get("pgid")}
        return document

    def clean_up(self) -> None:
        if (self.root / "run" / "state.json").exists():
            self.state()
        self.msctl("down", timeout=30.0)
        for pgid in self.pgids:
            if group_alive(pgid):  # still msctl's: the ids of a finished run may be reused
                os.killpg(pgid, signal.SIGKILL)


@pytest.fixture(scope="module")
def dragon_assembly(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The directory of a resolved Dragon (lock file, URDF, MJCF), copied into each home."""
    lock = Path(resolved_assembly(tmp_path_factory.mktemp("resolved"), "dragon").lock_path)
    return lock if lock.is_dir() else lock.parent


@pytest.fixture
def home(tmp_path: Path, dragon_assembly: Path) -> Iterator[Home]:
    current = Home(tmp_path / "home", dragon_assembly)
    current.break_limb1_joint_manager()
    try:
        yield current
    finally:
        current.clean_up()


def assert_reported_once(result: subprocess.CompletedProcess, home: Home) -> None:
    """Non-zero exit; the cause on stderr once, on its last line with the component and log."""
    assert result.returncode != 0, result.stderr
    cause = "param watchdog_timeout must be a number, not 'soon'"
    assert result.stderr.count("watchdog_timeout") == 1, result.stderr
    last = result.stderr.strip().splitlines()[-1]
    assert "limb1/joint_manager" in last and "process limb1" in last, last
    assert cause in last and "exited with code 3" in last, last
    assert str(home.root / "run" / "logs" / "limb1.log") in last, last
    assert "gave up after 3" not in result.stderr and "restarting" not in result.stderr


def assert_failed_without_restarts(home: Home) -> None:
    """limb1 FAILED at its first start (state file and ``ps``); the others never restarted."""
    processes = {p["name"]: p for p in home.state()["processes"]}
    limb1 = processes["limb1"]
    assert limb1["state"] == "failed" and limb1["restarts"] == 0, limb1
    assert "watchdog_timeout" in limb1["last_error"], limb1
    assert all(p["restarts"] == 0 for p in processes.values()), processes
    log = Path(limb1["log"]).read_text()
    assert log.count("--- msctl: starting limb1") == 1, log
    ps = home.msctl("ps", "--json", timeout=30.0)
    assert ps.returncode == 0, ps.stderr
    components = {c["name"]: c for c in json.loads(ps.stdout)["components"]}
    broken = components["limb1/joint_manager"]
    assert broken["state"] == "failed" and broken["restarts"] == 0 and broken["pid"] is None
    assert "watchdog_timeout" in broken["last_error"]


@pytest.mark.e2e
def test_foreground_up_fails_at_once_naming_the_component_and_its_cause(home: Home) -> None:
    result = home.up("--for", "20")
    assert_reported_once(result, home)
    # The rest of its process is named, without the cause again.
    assert "not started with it (process limb1)" in result.stderr
    assert "limb1/kinematics_manager" in result.stderr
    assert_failed_without_restarts(home)
    assert home.state()["state"] == "stopped"
    assert home.pgids, "no process group was seen in the state file"
    for pgid in home.pgids:
        assert not process_group_alive(pgid), pgid


@pytest.mark.e2e
def test_detached_up_fails_at_once_naming_the_component_and_its_cause(home: Home) -> None:
    result = home.up("--detach")
    assert_reported_once(result, home)
    assert_failed_without_restarts(home)
    # The detached supervisor stopped everything it started before the command returned.
    assert home.pgids, "no process group was seen in the state file"
    for pgid in home.pgids:
        assert not process_group_alive(pgid), pgid
