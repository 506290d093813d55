"""The supervisor survives what is sent to it, and there is only ever one per MSCTL_HOME.

- Requests (issue 10, finding 4): a 10 KB nested ``[[[[…]]]]`` argument once crashed the
  supervisor with a RecursionError and stopped the whole assembly. Arguments are bounded in
  size (64 KiB) and depth (32), and whatever handling a request raises is an error reply.
- Single instance (finding 5): two ``msctl up --detach`` started together both came up, two
  sets of components on the same topics, and ``msctl down`` stopped one set. ``msctl up``
  now holds an exclusive lock in ``MSCTL_HOME/run`` for the supervisor's life.

The end-to-end tests run the real ``msctl`` against the one-limb ``minimal`` assembly,
simulated, on a random loopback port, with a temporary MSCTL_HOME. :class:`Home` is shared
with the disk-fault and frozen-process tests.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from conftest import free_port, resolved_assembly, wait_until

from components.comm.session import SessionSettings
from components.supervision.contract import (
    AGENT_SRV,
    MAX_ARGS_BYTES,
    RequestError,
    encode_args,
    host_namespace,
)
from components.supervision.protocol import parse_request
from msctl.launcher.state import RunLock, group_alive

HOST = "e2e-laptop"  # none of the assembly's computers: off-robot, simulated


@dataclass
class Home:
    """One temporary MSCTL_HOME and router endpoint, and every process group seen there."""

    path: Path
    endpoint: str
    env: dict[str, str]
    groups: set[int] = field(default_factory=set)

    @classmethod
    def make(cls, path: Path) -> Home:
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        env = {
            **{k: v for k, v in os.environ.items() if not k.startswith(("MSCTL_", "ZENOH_"))},
            "MSCTL_HOME": str(path),
            "MSCTL_HOST": HOST,
            "MSCTL_ZENOH_CONNECT": endpoint,
            "MSCTL_ZENOH_LISTEN": "tcp/127.0.0.1:0",
            "MSCTL_ZENOH_MULTICAST": "0",
            "PYTHONPATH": str(Path(__file__).parents[1]),
        }
        return cls(path, endpoint, env)

    def command(self, *args: str) -> list[str]:
        """The argv of ``msctl ARGS``."""
        return [sys.executable, "-m", "msctl", *args]

    def msctl(self, *args: str, timeout: float = 90.0) -> subprocess.CompletedProcess:
        """Run ``msctl ARGS`` to completion."""
        return subprocess.run(
            self.command(*args), env=self.env, capture_output=True, text=True, timeout=timeout
        )

    def state(self) -> dict[str, Any]:
        """The state file, remembering every process group it names."""
        document = json.loads((self.path / "run" / "state.json").read_text())
        self.remember(document)
        return document

    def remember(self, document: dict[str, Any]) -> None:
        """Note the process groups of a run document, to kill whatever is left at the end."""
        for process in document.get("processes", []):
            if process.get("pgid"):
                self.groups.add(process["pgid"])
        if isinstance(document.get("supervisor_pid"), int):
            self.groups.add(document["supervisor_pid"])

    def ps(self) -> dict[str, Any]:
        """``msctl ps --json``."""
        result = self.msctl("ps", "--json", timeout=60.0)
        assert result.returncode == 0, result.stdout + result.stderr
        return json.loads(result.stdout)

    def components(self) -> dict[str, dict[str, Any]]:
        """``msctl ps --json``'s components by name."""
        return {c["name"]: c for c in self.ps()["components"]}

    def processes(self) -> dict[int, str]:
        """Every live process started for this MSCTL_HOME (from ``/proc``): pid -> cmdline."""
        marker = f"MSCTL_HOME={self.path}".encode()
        found = {}
        for entry in Path("/proc").glob("[0-9]*"):
            try:
                if marker not in (entry / "environ").read_bytes().split(b"\0"):
                    continue
                status = (entry / "stat").read_text().rsplit(")", 1)[1].split()[0]
                cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode()
            except (OSError, IndexError):
                continue
            if status != "Z" and int(entry.name) != os.getpid():
                found[int(entry.name)] = cmdline
        return found

    def clean_up(self) -> None:
        """``msctl down``, then SIGKILL whatever of msctl's is left of every group seen."""
        with contextlib.suppress(Exception):
            self.state()
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.msctl("down", timeout=60.0)
        for pgid in self.groups:
            if group_alive(pgid):
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(pgid, signal.SIGKILL)


def all_running(components: dict[str, dict[str, Any]]) -> bool:
    """Every component running (and there are some)."""
    return bool(components) and all(c["state"] == "running" for c in components.values())


@pytest.fixture
def home(tmp_path: Path) -> Iterator[Home]:
    """A fresh MSCTL_HOME with ``minimal`` resolved in it; cleaned up at the end."""
    current = Home.make(tmp_path / "home")
    try:
        yield current
    finally:
        current.clean_up()


@pytest.fixture
def minimal_up(home: Home) -> Home:
    """``msctl up minimal --detach``, every component healthy."""
    result = home.msctl("up", "minimal", "--detach", timeout=120.0)
    home.state()
    assert result.returncode == 0, result.stdout + result.stderr
    return home


class RawClient:
    """A bare AgentRequest client of one host's supervisor: sends exactly what it is given."""

    def __init__(self, endpoint: str, host: str = HOST) -> None:
        from components.comm.node import Node
        from components.comm.session import open_session
        from components.comm.types import registry

        self.session = open_session(
            SessionSettings(mode="client", connect=(endpoint,), listen=(), multicast=False)
        )
        self.node = Node(self.session, "hardening_test", "/test")
        self.client = self.node.client(f"{host_namespace(host)}/request", AGENT_SRV)
        self._request = registry().msg_class(self.client.parts.request)

    def call(self, verb: str, args: str, timeout: float = 20.0) -> Any:
        return self.client.call(self._request(verb=verb, args=args), timeout=timeout)

    def close(self) -> None:
        self.client.close()
        self.node.close()
        self.session.close()


# ------------------------------------------------------------------------------ requests
def test_the_dragon_x4_up_request_fits_the_bound(tmp_path: Path) -> None:
    """The bound was measured against the largest shipped assembly a ground station sends."""
    assembly = resolved_assembly(tmp_path, "dragon_x4")
    document = json.loads(assembly.lock_path.read_text())
    text = encode_args({"assembly": document, "sim": None, "speed": 1.0})
    assert MAX_ARGS_BYTES == 64 * 1024
    assert len(text) < 0.75 * MAX_ARGS_BYTES, len(text)
    assert parse_request("up", text).args["assembly"] == document


@pytest.mark.parametrize(
    ("args", "why"),
    [
        ("[" * 5000 + "]" * 5000, "nest deeper than 32"),  # the finding's 10 KB
        ('{"a":' * 40 + "1" + "}" * 40, "nest deeper than 32"),
        ('{"assembly": "' + "x" * MAX_ARGS_BYTES + '"}', f"at most {MAX_ARGS_BYTES}"),
        # Counted in bytes: 30,000 characters of 3 bytes each.
        ('{"assembly": "' + "\u20ac" * 30_000 + '"}', f"at most {MAX_ARGS_BYTES}"),
    ],
)
def test_oversized_or_deep_arguments_are_refused_before_parsing(args: str, why: str) -> None:
    with pytest.raises(RequestError, match=why):
        parse_request("up", args)


def test_whatever_handling_a_request_raises_is_answered_as_an_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A RecursionError (or any bug) in a handler is an error reply, and the loop goes on."""
    from msctl.launcher.plan import HostPlan
    from msctl.launcher.run import Launch

    monkeypatch.setenv("MSCTL_HOME", str(tmp_path))
    launch = Launch(
        assembly=SimpleNamespace(template="minimal"),  # type: ignore[arg-type]
        plan=HostPlan(host=HOST, simulated=True, off_robot=True),
        settings=SessionSettings(mode="peer", connect=(), listen=(), multicast=False),
    )

    def broken(verb: str, args: dict[str, Any]) -> Any:
        raise RecursionError("maximum recursion depth exceeded")

    monkeypatch.setattr(launch, "_do", broken)
    replies: list[Any] = []
    pending = SimpleNamespace(request=SimpleNamespace(verb="ps", args=""), reply=replies.append)
    launch._answer(pending)
    assert len(replies) == 1 and not replies[0].success
    assert "RecursionError" in replies[0].message and HOST in replies[0].message
    assert any("RecursionError" in event for event in launch.events)

    # A reply that cannot be sent (the caller gone) is noted, not raised.
    def unsendable(response: Any) -> None:
        raise ConnectionError("the caller is gone")

    monkeypatch.setattr(launch, "_do", lambda verb, args: {"host": HOST})
    launch._answer(SimpleNamespace(request=SimpleNamespace(verb="ps", args=""), reply=unsendable))
    assert any("could not answer" in event for event in launch.events)


def test_a_slow_doctor_is_answered_off_the_loop_which_goes_on_answering(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """doctor (seconds of certificate checks and graph listing; tens on a starved machine)
    runs on a thread of its own: the loop answers ps meanwhile (it supervises in the same
    turns), and doctors asked again while one runs are answered by one more run, not a queue
    of them."""
    import threading

    from msctl.launcher.plan import HostPlan
    from msctl.launcher.run import Launch

    monkeypatch.setenv("MSCTL_HOME", str(tmp_path))
    launch = Launch(
        assembly=SimpleNamespace(template="minimal"),  # type: ignore[arg-type]
        plan=HostPlan(host=HOST, simulated=True, off_robot=True),
        settings=SessionSettings(mode="peer", connect=(), listen=(), multicast=False),
    )
    release = threading.Event()
    runs: list[str] = []

    def slow_doctor(verb: str, args: dict[str, Any]) -> Any:
        if verb == "doctor":
            runs.append(threading.current_thread().name)
            assert release.wait(60), "the test never released the doctor"
            return {"host": HOST, "run": len(runs)}
        return {"host": HOST, "verb": verb}

    monkeypatch.setattr(launch, "_do", slow_doctor)
    replies: dict[str, list[Any]] = {}

    def asked(verb: str, name: str) -> SimpleNamespace:
        return SimpleNamespace(
            request=SimpleNamespace(verb=verb, args=""), reply=replies.setdefault(name, []).append
        )

    launch._answer(asked("doctor", "first"))  # returns at once: the doctor runs elsewhere
    wait_until(lambda: runs, timeout=30, what="the first doctor running")
    launch._answer(asked("ps", "ps"))  # answered now, on the loop, while the doctor runs
    assert [json.loads(r.payload)["verb"] for r in replies["ps"]] == ["ps"]
    for again in ("second", "third"):  # asked again while the first runs
        launch._answer(asked("doctor", again))
    assert not replies["first"] and runs == ["msctl-off-loop"]
    release.set()
    wait_until(
        lambda: all(replies.get(n) for n in ("first", "second", "third")),
        timeout=30,
        what="every doctor answered",
    )
    answered = {n: json.loads(replies[n][0].payload)["run"] for n in ("first", "second", "third")}
    assert answered == {"first": 1, "second": 2, "third": 2}  # two runs for three requests
    assert all(len(replies[n]) == 1 and replies[n][0].success for n in answered)


@pytest.mark.e2e
def test_hostile_requests_get_error_replies_and_the_assembly_keeps_running(
    minimal_up: Home,
) -> None:
    home = minimal_up
    before = home.state()
    pids = {p["name"]: p["pid"] for p in before["processes"]}
    hostile = [
        ("ps", "[" * 5000 + "]" * 5000, "nest deeper than 32"),
        ("ps", '{"a":' * 3000 + "1" + "}" * 3000, "nest deeper than 32"),
        ("logs", '{"component": ' + "[" * 5000 + "]" * 5000 + "}", "nest deeper than 32"),
        ("up", '{"assembly": {"x": "' + "y" * (70 * 1024) + '"}}', f"at most {MAX_ARGS_BYTES}"),
        ("reboot", "{}", "unknown verb"),
        ("", "", "unknown verb"),
        ("ps", "\x00garbage\xff{{{", "not JSON"),
        ("ps", "[1, 2", "not JSON"),
        ("logs", '{"lines": 1e999}', "lines must be"),
        ("restart", '{"component": "nobody"}', "no component or process 'nobody'"),
        ("up", '{"assembly": {}}', "already runs minimal"),
    ]
    client = RawClient(home.endpoint)
    try:
        for verb, args, why in hostile:
            response = client.call(verb, args)
            assert not response.success, (verb, args[:40])
            assert why in response.message, (verb, args[:40], response.message)
        # Still answering, with the same processes.
        response = client.call("ps", "{}")
        assert response.success
        assert json.loads(response.payload)["supervisor_pid"] == before["supervisor_pid"]
    finally:
        client.close()
    components = home.components()
    assert all_running(components), components
    after = home.state()
    assert after["supervisor_pid"] == before["supervisor_pid"]
    assert {p["name"]: p["pid"] for p in after["processes"]} == pids


# ------------------------------------------------------------------------------ one supervisor
def test_up_is_refused_while_the_run_lock_is_held_naming_the_holder(
    home: Home, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Refused before it resolves or reads anything, naming what holds the lock."""
    monkeypatch.setenv("MSCTL_HOME", str(home.path))
    lock = RunLock.acquire(template="dragon", host="gl-pi-01", by="msctl up --detach")
    try:
        result = home.msctl("up", "minimal", "--detach", timeout=60.0)
    finally:
        lock.release()
    message = " ".join(result.stderr.split())
    assert result.returncode == 3, message
    assert "internal error" not in message
    assert f"dragon is already up on gl-pi-01 (pid {os.getpid()}: msctl up --detach" in message
    assert "started " in message and "msctl down" in message, message
    assert not (home.path / "assembly").exists()  # nothing was resolved over the first run's
    # Released (as a dead holder's is, by the kernel): the next one may take it.
    RunLock.acquire(template="minimal").release()


@pytest.mark.e2e
def test_two_ups_started_together_one_is_refused_naming_the_first_and_down_leaves_nothing(
    home: Home,
) -> None:
    ups = [
        subprocess.Popen(
            home.command("up", "minimal", "--detach"),
            env=home.env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for _ in range(2)
    ]
    outputs = [up.communicate(timeout=120.0) for up in ups]
    home.state()
    codes = sorted(up.returncode for up in ups)
    assert codes == [0, 3], outputs
    winner, loser = (0, 1) if ups[0].returncode == 0 else (1, 0)
    refusal = " ".join(outputs[loser][1].split())
    supervisor = home.state()["supervisor_pid"]
    # The first is named: the `up` that took the lock, or the supervisor it handed it to.
    assert "minimal is already up on e2e-laptop" in refusal, refusal
    assert f"(pid {ups[winner].pid}:" in refusal or f"(pid {supervisor}:" in refusal, refusal
    # One set of processes: one supervisor, one router, one worker per process of the plan.
    running = home.processes()
    supervisors = [pid for pid, cmd in running.items() if " msctl up " in f" {cmd}"]
    assert supervisors == [supervisor], running
    workers = [cmd for cmd in running.values() if "components.executor.worker" in cmd]
    assert len(workers) == 2, running  # sim and limb1
    assert all_running(home.components())
    down = home.msctl("down", timeout=60.0)
    assert down.returncode == 0, down.stderr
    assert "nothing left" in down.stderr
    wait_until(lambda: not home.processes(), timeout=15.0, what="no process of the run left")
