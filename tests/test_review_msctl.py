"""Regressions found reviewing the operator side (``msctl``), each on the real command in a
subprocess where the fault showed: a random loopback port, an ``MSCTL_HOME`` of its own."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import free_port, wait_until

from msctl.launcher.state import process_group_alive

pytestmark = pytest.mark.e2e


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


@pytest.fixture
def home(tmp_path: Path) -> Iterator[Home]:
    current = Home(tmp_path)
    try:
        yield current
    finally:
        current.kill_everything()


def _healthy(home: Home) -> bool:
    document = home.state()
    return bool(
        document
        and document.get("state") == "running"
        and document["components"]
        and all(c["state"] == "running" for c in document["components"])
    )


def test_foreground_up_stops_everything_on_sighup(home: Home) -> None:
    # An SSH link that drops sends SIGHUP to a foreground `msctl up`: it died at once and left
    # every component's process group running, the state file naming a dead supervisor.
    proc = home.popen("up", "minimal")
    try:
        wait_until(lambda: _healthy(home), timeout=60.0, what="minimal healthy")
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


def test_agent_stops_cleanly_on_sighup(home: Home) -> None:
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


def test_down_after_the_supervisor_died_kills_what_it_left_and_says_so(home: Home) -> None:
    # A supervisor SIGKILLed (OOM killer, power blip of a terminal): `ps` went on showing every
    # component "running" from the state file, and `down` said "nothing is running on this
    # computer" while it killed the groups left behind, leaving the state file "running".
    result = home.msctl("up", "minimal", "--detach", timeout=90.0)
    assert result.returncode == 0, result.stderr
    document = home.state()
    groups = {p["name"]: p["pgid"] for p in document["processes"] if p["pgid"]}
    os.kill(document["supervisor_pid"], signal.SIGKILL)
    wait_until(lambda: not process_group_alive(document["supervisor_pid"]), what="supervisor gone")

    ps = home.msctl("ps", "--json")
    assert ps.returncode == 0, ps.stderr
    listed = json.loads(ps.stdout)
    assert listed["components"]
    assert not [c["name"] for c in listed["components"] if c["state"] == "running"]
    assert any("msctl down" in note for note in listed["notes"]), listed["notes"]

    down = home.msctl("down", timeout=30.0)
    assert down.returncode == 0, down.stderr
    assert "nothing is running" not in down.stderr
    assert "killed" in down.stderr and "limb1" in down.stderr, down.stderr
    for name, pgid in groups.items():
        assert not process_group_alive(pgid), f"{name} (group {pgid}) left after down"
    assert home.state()["state"] == "stopped"
    after = json.loads(home.msctl("ps", "--json").stdout)
    assert not [c["name"] for c in after["components"] if c["state"] == "running"]


def test_unknown_component_is_not_found_exit_4(home: Home) -> None:
    # `msctl restart/stop/logs NAME` of a name nothing runs: exit 1 (restart, stop) or 3 (logs,
    # "cannot get the log ... from <host>", as if the network failed) instead of 4, not found.
    result = home.msctl("up", "minimal", "--detach", timeout=90.0)
    assert result.returncode == 0, result.stderr
    try:
        for verb in ("restart", "stop", "logs"):
            answer = home.msctl(verb, "limb9/joint_manager")
            assert answer.returncode == 4, (verb, answer.returncode, answer.stderr)
            assert "limb9/joint_manager" in answer.stderr and "msctl ps" in answer.stderr
            assert "limb1/joint_manager" in answer.stderr  # what does run
            assert answer.stdout == ""
        ok = home.msctl("restart", "limb1/joint_manager")
        assert ok.returncode == 0, ok.stderr
    finally:
        assert home.msctl("down", timeout=30.0).returncode == 0


def test_logs_of_a_component_with_no_network_names_the_component(home: Home) -> None:
    # Nothing ran here and no router: the one line named only the router, not what was asked.
    answer = home.msctl("logs", "limb1/joint_manager")
    assert answer.returncode == 3, answer.stderr
    assert "no log for 'limb1/joint_manager' on this computer" in answer.stderr
    assert "no Zenoh router reachable" in answer.stderr


def test_the_embedded_router_is_restarted_not_stopped_through_the_control_service(
    home: Home,
) -> None:
    # `msctl stop router` stopped the router that carries every request: the reply was lost
    # (exit 3) and nothing could reach the supervisor again, not even `msctl restart router`.
    # `msctl restart router` did restart it, but its reply was lost the same way (exit 3).
    result = home.msctl("up", "minimal", "--detach", timeout=90.0)
    assert result.returncode == 0, result.stderr
    try:
        first = {p["name"]: p["pid"] for p in home.state()["processes"]}["router"]
        stop = home.msctl("stop", "router")
        assert stop.returncode == 1, stop.stderr
        assert "msctl restart router" in stop.stderr and "msctl down" in stop.stderr
        restart = home.msctl("restart", "router")
        assert restart.returncode == 0, restart.stderr
        assert "router" in restart.stderr
        wait_until(
            lambda: (
                {p["name"]: p["pid"] for p in home.state()["processes"]}["router"]
                not in (None, first)
            ),
            timeout=10.0,
            what="a new router process",
        )
        wait_until(
            lambda: home.msctl("restart", "limb1/joint_manager").returncode == 0,
            timeout=20.0,
            what="requests reach the supervisor again",
        )
    finally:
        assert home.msctl("down", timeout=30.0).returncode == 0
