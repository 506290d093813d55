"""Launcher pieces with tiny real subprocesses: restart policy, stop/restart, shutdown
escalation, process groups, log rotation; host plans; control request refusals.

Every supervised process here is a ``python -c`` script in its own process group; each test
shuts its supervisor down, and the fixture kills whatever group is left.
"""

from __future__ import annotations

import os
import re
import signal
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import wait_until
from supervisor_rig import quick_supervisor

from components import kinds
from components.assembly import ResolvedAssembly, from_document
from components.build import buildable
from components.supervision.contract import RequestError, host_namespace
from components.supervision.protocol import parse_request
from msctl.assembler import resolve
from msctl.launcher.plan import plan_host
from msctl.launcher.supervisor import (
    ProcessState,
    RestartPolicy,
    RotatingLog,
    ShutdownPolicy,
    Supervisor,
)

PY = sys.executable

CRASH = "import sys; print('starting'); print('error: boom 42', file=sys.stderr); sys.exit(3)"
SLEEP = "import time; print('ready', flush=True); time.sleep(60)"
# Records each polite signal it gets and keeps running: only SIGKILL ends it.
STUBBORN = """
import signal, sys, time
path = sys.argv[1]
def note(signum, frame):
    with open(path, "a") as f:
        f.write(signal.Signals(signum).name + "\\n")
signal.signal(signal.SIGINT, note)
signal.signal(signal.SIGTERM, note)
print("ready", flush=True)
while True:
    time.sleep(0.05)
"""
# A leader that starts a grandchild (same process group) and says its pid.
PARENT = """
import subprocess, sys, time
child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
print("grandchild", child.pid, flush=True)
if sys.argv[1] == "exit":
    sys.exit(1)
time.sleep(60)
"""

SIMULATOR_COMPONENT = kinds.get("simulator").component_name


def group_gone(pgid: int) -> bool:
    """No process of group ``pgid`` is left (a zombie awaiting its reaper counts as gone)."""
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return True
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == pgid and fields[0] != "Z":
            return False
    return True


def pid_gone(pid: int) -> bool:
    """``pid`` is dead (or a zombie)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return True
    return state == "Z"


@pytest.fixture
def supervisor(tmp_path: Path) -> Iterator[Supervisor]:
    """A supervisor with quick backoff; everything it started is killed at teardown."""
    with quick_supervisor(tmp_path / "logs", backoff_max=1.0) as sup:
        yield sup


def poll_until(sup: Supervisor, predicate, timeout: float = 5.0) -> list[str]:
    """Poll the supervisor until ``predicate()``; returns the events seen meanwhile."""
    events: list[str] = []

    def check():
        events.extend(sup.poll())
        return predicate()

    wait_until(check, timeout=timeout)
    return events


def log_has(sup: Supervisor, name: str, line: str) -> bool:
    """The process printed exactly ``line`` (its command line, also logged, does not count)."""
    return line in sup.processes[name].log.tail


# ------------------------------------------------------------------------------ restart policy
@pytest.mark.e2e
def test_crash_loop_backs_off_doubling_then_fails_with_the_last_error(supervisor) -> None:
    process = supervisor.add("crasher", [PY, "-c", CRASH], components=["x/crasher"])
    supervisor.start("crasher")
    backoffs: list[float] = []
    starts: list[float] = []
    deadline = time.monotonic() + 10.0
    while process.state is not ProcessState.FAILED:
        assert time.monotonic() < deadline, f"never FAILED: {process.state} {process.last_error}"
        for event in supervisor.poll():
            if "restarting in" in event:
                backoffs.append(process.backoff)
            if "restarted" in event:
                starts.append(time.monotonic())
        time.sleep(0.01)
    assert backoffs == [0.05, 0.1, 0.2]
    assert process.restarts == 3
    assert process.pid is None
    assert "exited with code 3" in process.last_error
    assert "error: boom 42" in process.last_error  # the line that says why, not the last one
    assert "gave up after 3 restarts" in process.last_error
    snapshot = {p.name: p for p in supervisor.snapshot()}["crasher"]
    assert snapshot.state == "failed" and snapshot.last_error == process.last_error
    log = Path(snapshot.log).read_text()
    unstamped = [line[24:] for line in log.splitlines()]  # each line has its time in front
    assert unstamped.count("error: boom 42") == 4 and "exited with code 3" in log
    # A FAILED process stays down.
    time.sleep(0.3)
    supervisor.poll()
    assert process.state is ProcessState.FAILED and process.popen is None


@pytest.mark.e2e
def test_restarts_outside_the_window_are_forgotten(tmp_path: Path) -> None:
    sup = Supervisor(
        tmp_path, RestartPolicy(max_restarts=1, window=0.3, backoff_initial=0.01, backoff_max=0.01)
    )
    # Lives 0.4 s, longer than the window: each crash finds the previous restart forgotten.
    process = sup.add("crasher", [PY, "-c", "import time, sys; time.sleep(0.4); sys.exit(1)"])
    sup.start("crasher")
    try:
        poll_until(sup, lambda: process.restarts >= 3, timeout=8.0)
        assert process.state is not ProcessState.FAILED
    finally:
        sup.shutdown()


@pytest.mark.e2e
def test_backoff_resets_once_alive_long_enough_even_without_components(tmp_path: Path) -> None:
    sup = Supervisor(tmp_path, RestartPolicy(backoff_initial=0.05, stable_after=0.3))
    process = sup.add("router", [PY, "-c", SLEEP])  # no components: never marked RUNNING
    sup.start("router")
    try:
        os.killpg(process.popen.pid, signal.SIGKILL)
        poll_until(sup, lambda: process.restarts == 1 and process.pid is not None)
        assert process.backoff == 0.05 and process.state is ProcessState.STARTING
        poll_until(sup, lambda: process.backoff == 0.0, timeout=3.0)
    finally:
        sup.shutdown()


@pytest.mark.e2e
def test_stop_keeps_it_stopped(supervisor) -> None:
    process = supervisor.add("sleeper", [PY, "-c", SLEEP])
    supervisor.start("sleeper")
    wait_until(lambda: log_has(supervisor, "sleeper", "ready"))
    pgid = process.pid
    assert pgid is not None
    supervisor.stop("sleeper")
    assert process.state is ProcessState.STOPPED and process.pid is None
    assert group_gone(pgid)
    deadline = time.monotonic() + 0.6
    while time.monotonic() < deadline:
        assert supervisor.poll() == []
        time.sleep(0.02)
    assert process.state is ProcessState.STOPPED and process.popen is None
    assert process.restarts == 0
    supervisor.start("sleeper")  # and it starts again when asked
    assert process.state is ProcessState.STARTING and process.pid is not None


@pytest.mark.e2e
def test_start_of_a_live_process_starts_no_second_copy(supervisor) -> None:
    # `start` (an AgentRequest verb) of a running process spawned a second copy and dropped
    # the first from view: two workers driving the same motors, and one left after `down`.
    process = supervisor.add("sleeper", [PY, "-c", SLEEP])
    supervisor.start("sleeper")
    wait_until(lambda: log_has(supervisor, "sleeper", "ready"))
    first = process.pid
    assert first is not None
    supervisor.start("sleeper")
    assert process.pid == first
    supervisor.shutdown()
    assert group_gone(first)


@pytest.mark.e2e
def test_restart_replaces_the_process_and_counts(supervisor) -> None:
    process = supervisor.add("sleeper", [PY, "-c", SLEEP])
    supervisor.start("sleeper")
    wait_until(lambda: log_has(supervisor, "sleeper", "ready"))
    first = process.pid
    assert first is not None
    supervisor.mark_running("sleeper")
    supervisor.restart("sleeper")
    assert process.restarts == 1
    assert process.state is ProcessState.STARTING
    assert process.pid not in (None, first)
    assert group_gone(first)
    supervisor.restart("sleeper")
    assert process.restarts == 2
    supervisor.poll()
    assert process.state is ProcessState.STARTING  # a requested restart is no crash


@pytest.mark.e2e
def test_killed_process_is_restarted_as_starting(supervisor) -> None:
    process = supervisor.add("sleeper", [PY, "-c", SLEEP])
    supervisor.start("sleeper")
    supervisor.mark_running("sleeper")
    first = process.pid
    assert first is not None
    os.killpg(first, signal.SIGKILL)
    events = poll_until(supervisor, lambda: process.restarts == 1 and process.pid is not None)
    assert any("killed by SIGKILL" in e for e in events)
    assert process.state is ProcessState.STARTING
    assert "killed by SIGKILL" in process.last_error


# ------------------------------------------------------------------------------ shutdown
@pytest.mark.e2e
def test_shutdown_escalates_sigint_sigterm_sigkill_within_the_policy(tmp_path: Path) -> None:
    policy = ShutdownPolicy()  # the real one
    sup = Supervisor(tmp_path / "logs", shutdown=policy)
    signals = tmp_path / "signals.txt"
    process = sup.add("stubborn", [PY, "-c", STUBBORN, str(signals)])
    sup.start("stubborn")
    try:
        wait_until(lambda: log_has(sup, "stubborn", "ready"))
        pgid = process.pid
        assert pgid is not None
        started = time.monotonic()
        sup.shutdown()
        elapsed = time.monotonic() - started
    finally:
        if process.popen is not None:
            os.killpg(process.popen.pid, signal.SIGKILL)
    assert signals.read_text().split() == ["SIGINT", "SIGTERM"]
    budget = policy.after_sigint + policy.after_sigterm
    # It waited out each step; the upper bound only says it did not hang (a busy machine).
    assert budget - 0.1 <= elapsed < budget + 30.0, elapsed
    assert group_gone(pgid)
    assert process.state is ProcessState.STOPPED


@pytest.mark.e2e
def test_polite_process_stops_at_sigint_at_once(supervisor) -> None:
    process = supervisor.add("sleeper", [PY, "-c", SLEEP])
    supervisor.start("sleeper")
    wait_until(lambda: log_has(supervisor, "sleeper", "ready"))
    popen = process.popen
    assert popen is not None
    supervisor.shutdown()
    # Ended by the SIGINT itself (Python dies of it), never escalated to SIGTERM or SIGKILL.
    assert popen.returncode == -signal.SIGINT
    assert process.state is ProcessState.STOPPED


@pytest.mark.e2e
@pytest.mark.parametrize("how", ["shutdown", "exit"])
def test_grandchildren_go_with_their_group(supervisor, how: str) -> None:
    """Shutdown kills the whole group; so does the leader dying on its own (no orphans)."""
    process = supervisor.add("parent", [PY, "-c", PARENT, how])
    supervisor.start("parent")
    pgid = process.popen.pid
    line = wait_until(
        lambda: next((x for x in process.log.tail if x.startswith("grandchild ")), None)
    )
    grandchild = int(line.split()[1])
    assert os.getpgid(grandchild) == pgid
    if how == "shutdown":
        supervisor.shutdown()
    else:
        poll_until(supervisor, lambda: process.restarts >= 1)
    wait_until(lambda: pid_gone(grandchild), timeout=3.0)
    assert group_gone(pgid)


# ------------------------------------------------------------------------------ logs
def test_log_rotates_past_max_bytes_and_keeps_the_tail(tmp_path: Path) -> None:
    path = tmp_path / "logs" / "limb1.log"
    log = RotatingLog(path, max_bytes=200, backups=2, tail=5)
    lines = [f"line {i:03d} " + "x" * 10 for i in range(60)]  # 20 bytes each
    for line in lines:
        log.write_line(line)
    log.close()
    log.close()  # idempotent
    rotated = [path.with_name(f"limb1.log.{i}") for i in (1, 2)]
    assert path.exists() and all(p.exists() for p in rotated)
    assert not path.with_name("limb1.log.3").exists()
    for p in (path, *rotated):
        assert p.stat().st_size <= 200 + 45  # one stamped line past the size at most
    # Newest in the live file, older ones in .1 then .2, none repeated, order kept.
    kept = rotated[1].read_text().splitlines() + rotated[0].read_text().splitlines()
    kept += path.read_text().splitlines()
    assert [line[24:] for line in kept] == lines[-len(kept) :]
    assert list(log.tail) == lines[-5:]
    assert [line[24:] for line in log.recent] == lines[-5:]


def test_every_log_line_is_stamped_and_each_run_marked(tmp_path: Path) -> None:
    for run in ("first", "second"):
        supervisor = Supervisor(tmp_path, run=f"msctl up minimal ({run})")
        process = supervisor.add("limb1", [PY, "-c", "pass"])
        process.log.write_line("Traceback (most recent call last):")
        process.log.write_line("2026-11-23 01:02:03,456 INFO msctl.worker: built limb1")
        process.log.close()
    lines = (tmp_path / "limb1.log").read_text().splitlines()
    stamped = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d[.,]\d{3} ")
    assert all(stamped.match(line) for line in lines), lines
    marks = [line for line in lines if "=====" in line]
    assert len(marks) == 2 and "msctl up minimal (first) started" in marks[0]
    assert "(second)" in marks[1] and lines.index(marks[1]) == 3
    # A line that has its own time (Python logging) is not stamped twice.
    assert lines[2] == "2026-11-23 01:02:03,456 INFO msctl.worker: built limb1"


@pytest.mark.e2e
def test_supervised_output_goes_to_the_process_log(supervisor) -> None:
    process = supervisor.add("limb1", [PY, "-c", CRASH])
    supervisor.start("limb1")
    poll_until(supervisor, lambda: process.restarts >= 1)
    text = process.log.path.read_text()
    assert process.log.path.name == "limb1.log"
    assert "--- msctl: starting limb1" in text and "starting\n" in text


# ------------------------------------------------------------------------------ plans
@pytest.fixture(scope="module")
def dragon() -> ResolvedAssembly:
    return from_document(resolve("dragon").document)


@pytest.fixture(scope="module")
def two_dragons() -> ResolvedAssembly:
    return from_document(resolve("two_dragons").document)


def test_off_robot_runs_everything_with_the_simulator_and_no_motor_interface(dragon) -> None:
    plan = plan_host(dragon, "a-laptop")
    assert plan.off_robot and plan.simulated
    names = [p.name for p in plan.processes]
    assert names[0] == "sim"
    assert set(names) == {
        "sim",
        "limb1",
        "limb2",
        "wheel1",
        "wheel2",
        "gc1_human_operator",
        "gc1_data_monitor",
    }
    kinds = {c.kind for c in plan.components}
    assert "motor_interface" not in kinds
    assert [c.name for c in plan.processes[0].components] == [SIMULATOR_COMPONENT]
    started = {c.name for c in plan.components}
    assert {"limb1/joint_manager", "wheel2/health_monitor"} <= started
    not_built = dict(plan.not_built)
    # Motor interfaces are replaced, not missing; every other planned component is either
    # started or listed as not built, never both.
    assert not any(k == "motor_interface" for k in not_built.values())
    robot_side = {c.name for c in dragon.components if c.kind != "motor_interface"}
    assert robot_side == (started - {SIMULATOR_COMPONENT}) | set(not_built)
    assert not started & set(not_built)
    # Not built means exactly: no builder for the kind in the code yet.
    assert all(not buildable(kind) for kind in not_built.values())
    assert all(buildable(c.kind) for c in plan.components)
    jm = next(c for c in plan.components if c.name == "limb1/joint_manager")
    assert (jm.namespace, jm.node_fqn, jm.first_output) == (
        "/limb1",
        "/limb1/joint_manager",
        "/limb1/diagnostics",
    )


def test_off_robot_real_keeps_motor_interfaces_and_no_simulator(dragon) -> None:
    plan = plan_host(dragon, "a-laptop", sim=False)
    assert plan.off_robot and not plan.simulated
    kinds = [c.kind for c in plan.components]
    assert kinds.count("motor_interface") == 4
    assert "simulator" not in kinds
    assert "sim" not in [p.name for p in plan.processes]


def test_robot_host_runs_only_its_own_components(dragon) -> None:
    host = dragon.module("limb1").host
    plan = plan_host(dragon, host)
    assert not plan.off_robot and not plan.simulated
    assert [p.name for p in plan.processes] == ["limb1"]
    mine = {c.name for c in dragon.components_on(host)}
    started = {c.name for c in plan.components}
    assert started | {n for n, _ in plan.not_built} == mine
    assert "limb1/motor_interface" in started
    assert all(c.namespace == "/limb1" for c in plan.components)


def test_robot_host_forced_to_sim_swaps_its_motor_interface(dragon) -> None:
    plan = plan_host(dragon, dragon.module("limb1").host, sim=True)
    assert not plan.off_robot and plan.simulated
    kinds = [c.kind for c in plan.components]
    assert "motor_interface" not in kinds and kinds[0] == "simulator"


def test_host_defaults_to_msctl_host(dragon, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MSCTL_HOST", dragon.module("wheel2").host)
    assert [p.name for p in plan_host(dragon).processes] == ["wheel2"]


def test_two_dragons_groups_by_module_and_station_and_reports_not_built(two_dragons) -> None:
    plan = plan_host(two_dragons, "a-laptop")
    assert len(two_dragons.components) == 60
    motor_interfaces = sum(c.kind == "motor_interface" for c in two_dragons.components)
    accounted = len(plan.components) - 1 + len(plan.not_built) + motor_interfaces
    assert accounted == 60
    processes = {p.name for p in plan.processes}
    modules = ("limb1", "limb2", "wheel1", "wheel2")
    assert {f"d{d}_{m}" for d in (1, 2) for m in modules} <= processes
    for process in plan.processes:
        # One process per module (its namespace), one for the simulator.
        assert len({c.namespace for c in process.components}) == 1
    for name, kind in plan.not_built:
        assert not buildable(kind), name


# ------------------------------------------------------------------------------ control
@pytest.mark.parametrize(
    ("verb", "args", "why"),
    [
        ("reboot", "{}", "unknown verb 'reboot'"),
        ("", "{}", "unknown verb"),
        ("restart", "{component: x}", "not JSON"),
        ("restart", '["limb1"]', "must be a JSON object"),
        ("ps", '{"component": "limb1"}', "ps takes no argument component"),
        ("restart", '{"component": "x", "cmd": "rm -rf /"}', "takes no argument cmd"),
        ("restart", '{"component": 3}', "component must be"),
        ("restart", '{"component": "' + "a" * 200 + '"}', "component must be"),
        ("logs", '{"lines": 0}', "lines must be"),
        ("logs", '{"lines": "10"}', "lines must be"),
        ("logs", '{"lines": 10001}', "lines must be"),
        ("up", '{"speed": 0}', "speed must be"),
        ("up", '{"speed": 1000}', "speed must be"),
        ("up", '{"sim": "yes"}', "sim must be"),
        ("up", '{"assembly": "/etc/passwd"}', "assembly must be"),
    ],
)
def test_parse_request_refuses(verb: str, args: str, why: str) -> None:
    with pytest.raises(RequestError, match=why.replace("(", r"\(")):
        parse_request(verb, args)


def test_parse_request_accepts() -> None:
    assert parse_request("ps", "").args == {}
    assert parse_request("ps", "  ").args == {}
    assert parse_request("restart", '{"component": "limb1/joint_manager"}').args == {
        "component": "limb1/joint_manager"
    }
    assert parse_request("logs", '{"lines": 20}').args == {"lines": 20}
    request = parse_request("up", '{"sim": null, "speed": 2.5, "assembly": {}}')
    assert request.verb == "up" and request.args["speed"] == 2.5


def test_host_namespace_is_a_ros_name() -> None:
    assert host_namespace("hl-limb-01") == "/msctl/hl_limb_01"
    assert host_namespace("1robot.local") == "/msctl/h_1robot_local"


def test_ground_station_components_run_one_process_per_role() -> None:
    """A station's components group one process per role (kind), except a kind that asks
    for a process each (an autonomous operator); the modules one per module."""
    two = from_document(resolve("two_dragons").document)
    station_kinds = {k.name for k in kinds.placed(kinds.Placement.STATION)}
    plan = plan_host(two, "a-laptop")
    ground = [p for p in plan.processes if {c.kind for c in p.components} <= station_kinds]
    assert ground, "two_dragons has ground stations"
    for process in ground:
        roles = {c.kind for c in process.components}
        stations = {c.name.split("/")[0] for c in process.components}
        assert len(roles) == 1 and len(stations) == 1, process
        role = roles.pop()
        if kinds.get(role).own_process:
            (component,) = process.components
            assert process.name == component.name.replace("/", "_")
        else:
            assert process.name == f"{stations.pop()}_{role}"
    modules = {c.module for c in two.components if c.module}
    assert {p.name for p in plan.processes} >= modules


@pytest.mark.e2e
def test_a_stale_state_file_never_blocks_up_nor_kills_strangers(tmp_path: Path) -> None:
    """After a reboot the state file's ids may belong to other programs: `up` must not be
    refused because of them, and `down` must not kill them."""
    import json
    import subprocess

    from msctl.launcher import state

    stranger = subprocess.Popen(["sleep", "30"], start_new_session=True)
    try:
        home = tmp_path / "home"
        (home / "run").mkdir(parents=True)
        document = {
            "host": "robot",
            "template": "dragon",
            "state": "running",
            "supervisor_pid": stranger.pid,
            "processes": [{"name": "limb1", "pgid": stranger.pid, "pid": stranger.pid}],
            "components": [],
        }
        (home / "run" / "state.json").write_text(json.dumps(document))
        assert not state.supervisor_alive(document)
        assert not state.group_alive(stranger.pid)
        down = subprocess.run(
            [sys.executable, "-m", "msctl", "down"],
            env={**os.environ, "MSCTL_HOME": str(home)},
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert down.returncode == 0, down.stderr
        assert stranger.poll() is None, "msctl down killed a process that is not msctl's"
    finally:
        stranger.kill()
        stranger.wait()


def test_at_once_runs_every_call_together_keeps_the_order_and_raises_what_failed() -> None:
    import threading

    from msctl.launcher.fanout import at_once

    # Each call waits for all the others: one after another, the barrier would break.
    together = threading.Barrier(4, timeout=30.0)

    def answer(host: str) -> str:
        together.wait()
        return host.upper()

    assert at_once(answer, ["a", "b", "c", "d"]) == ["A", "B", "C", "D"]
    assert at_once(answer, []) == []

    ended: list[str] = []

    def fail_one(host: str) -> str:
        if host == "b":
            raise ValueError("b refused")
        ended.append(host)
        return host

    with pytest.raises(ValueError, match="b refused"):
        at_once(fail_one, ["a", "b", "c"])
    assert sorted(ended) == ["a", "c"]  # the others still ran to their end
