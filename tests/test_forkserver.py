"""The fork server (msctl.launcher.forkserver): a forked worker is what a spawned one was.

Real processes throughout: a real server (its real imports), real forks, real signals. The
worker is a small module written for the test (``probe_worker``), run through the server as
the launcher runs ``components.executor.worker``.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import wait_until

from msctl.launcher import boot
from msctl.launcher.forkserver import ForkedProcess, ForkServer, ForkServerError
from msctl.launcher.supervisor import ProcessState, RestartPolicy, Supervisor

PROBE = """
import json, os, signal, sys, time

def main():
    mode = sys.argv[1]
    if mode == "report":
        os.write(int(os.environ["MSCTL_HEARTBEAT_FD"]), b".")
        blocked = signal.pthread_sigmask(signal.SIG_BLOCK, set())
        print(json.dumps({
            "pid": os.getpid(), "ppid": os.getppid(), "pgid": os.getpgid(0),
            "cwd": os.getcwd(), "marker": os.environ.get("PROBE_MARKER"),
            "argv": sys.argv[1:], "name": __name__,
            "fds": sorted(int(f) for f in os.listdir("/proc/self/fd")),
            "heartbeat_fd": int(os.environ["MSCTL_HEARTBEAT_FD"]),
            "sigint_blocked": signal.SIGINT in blocked,
            "sigint_default": signal.getsignal(signal.SIGINT) == signal.SIG_DFL,
            "threads": len(os.listdir("/proc/self/task")),
            "stdin": os.readlink("/proc/self/fd/0"),
        }), flush=True)
        print("to stderr", file=sys.stderr, flush=True)
        sys.exit(int(sys.argv[2]))
    if mode == "sleep":
        print("sleeping", flush=True)
        time.sleep(600)
    if mode == "interrupt":
        raise KeyboardInterrupt
    if mode == "imports":
        from components import kinds
        wanted = sys.argv[2].split(",")
        print(json.dumps({
            "kinds_loaded": kinds._kinds is not None,
            "missing": [m for m in wanted if m not in sys.modules],
        }), flush=True)
    if mode == "types":
        from components.comm import types
        built = types.registry.cache_info().currsize == 1  # before this process asked
        made = sorted(types.registry()._store.fielddefs)
        print(json.dumps({"built": built, "made": made}), flush=True)

if __name__ == "__main__":
    main()
"""


@pytest.fixture(scope="module")
def probe_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("probe")
    (directory / "probe_worker.py").write_text(textwrap.dedent(PROBE))
    (directory / "slow_at_import.py").write_text(
        "import os, pathlib, time\n"
        "pathlib.Path(os.environ['SLOW_FLAG']).write_text('importing')\n"
        "time.sleep(2.0)\n"
    )
    (directory / "threads_at_import.py").write_text(
        "import threading, time\n"
        "threading.Thread(target=time.sleep, args=(600,), daemon=True).start()\n"
    )
    return directory


def _start(probe_dir: Path, preload: list[str] = ()) -> ForkServer:
    """A server that can import the probe (its PYTHONPATH is read as it starts)."""
    previous = os.environ.get("PYTHONPATH")
    os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [str(probe_dir), previous]))
    try:
        return ForkServer.start(
            list(preload), probe_dir / "forkserver.log", tag="probe-run", room=400
        )
    finally:
        if previous is None:
            del os.environ["PYTHONPATH"]
        else:
            os.environ["PYTHONPATH"] = previous


@pytest.fixture(scope="module")
def server(probe_dir: Path) -> Iterator[ForkServer]:
    started = _start(probe_dir)
    try:
        assert started.wait_ready(120.0), started.failure
        yield started
    finally:
        started.close()


def _spawn(server: ForkServer, *args: str, **env: str) -> tuple[ForkedProcess, int]:
    """Fork the probe with a heartbeat pipe; returns it and our read end of the pipe."""
    read_end, write_end = os.pipe()
    try:
        with boot.held_sigint():  # as the supervisor spawns
            child = server.spawn(
                boot.argv("probe_worker", *args),
                {**os.environ, **env, "MSCTL_HEARTBEAT_FD": str(write_end)},
                {"MSCTL_HEARTBEAT_FD": write_end},
                name="probe",
            )
    finally:
        os.close(write_end)
    return child, read_end


def test_a_forked_worker_gets_its_group_pipes_environment_and_exit_code(
    server: ForkServer, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    child, heartbeat = _spawn(server, "report", "3", PROBE_MARKER="only-in-this-request")
    try:
        assert child.wait(timeout=60.0) == 3
        assert child.stdout is not None
        lines = child.stdout.read().splitlines()
        report = json.loads(lines[0])
        assert lines[1] == "to stderr"  # stderr goes down the same pipe
        assert os.read(heartbeat, 16) == b"."  # its heartbeat pipe reaches us
    finally:
        os.close(heartbeat)
    assert report["pid"] == child.pid == report["pgid"]  # its own process group
    assert report["ppid"] == server.popen.pid  # forked, not a new interpreter
    assert report["marker"] == "only-in-this-request"
    assert report["cwd"] == str(tmp_path)
    assert report["argv"] == ["report", "3"]
    assert report["name"] == "__main__"
    assert report["sigint_default"] and not report["sigint_blocked"]
    assert report["threads"] == 1
    assert report["stdin"] == os.devnull
    # Nothing of the server's (its control socket): 0-2, its heartbeat, and the descriptor
    # listing /proc/self/fd.
    assert {0, 1, 2, report["heartbeat_fd"]} < set(report["fds"])
    assert len(report["fds"]) == 5, report["fds"]


def test_only_its_own_descriptors_reach_a_forked_worker(server: ForkServer) -> None:
    # A second child, forked while the first still runs, gets none of the first's pipes.
    first, first_beat = _spawn(server, "sleep")
    try:
        second, second_beat = _spawn(server, "report", "0")
        try:
            assert second.wait(timeout=60.0) == 0
            assert second.stdout is not None
            report = json.loads(second.stdout.readline())
        finally:
            os.close(second_beat)
        # 0-2, its heartbeat, and the listing's own descriptor of /proc/self/fd.
        assert len(report["fds"]) == 5, report["fds"]
    finally:
        os.killpg(first.pid, signal.SIGKILL)
        first.wait(timeout=30.0)
        os.close(first_beat)


def test_ps_shows_a_forked_worker_by_its_own_command_line(server: ForkServer) -> None:
    child, heartbeat = _spawn(server, "sleep")
    try:
        assert child.stdout is not None
        assert child.stdout.readline().strip() == "sleeping"
        shown = Path(f"/proc/{child.pid}/cmdline").read_bytes().rstrip(b"\0").split(b"\0")
        assert [a.decode() for a in shown] == boot.argv("probe_worker", "sleep")
        assert Path(f"/proc/{child.pid}/comm").read_text().strip() == "probe"
        assert b"forkserver" in Path(f"/proc/{server.popen.pid}/cmdline").read_bytes()
    finally:
        os.killpg(child.pid, signal.SIGKILL)
        child.wait(timeout=30.0)
        os.close(heartbeat)


def test_a_sigint_before_its_module_handles_one_ends_it_quietly(server: ForkServer) -> None:
    child, heartbeat = _spawn(server, "sleep")
    try:
        assert child.stdout is not None
        assert child.stdout.readline().strip() == "sleeping"
        os.killpg(child.pid, signal.SIGINT)
        assert child.wait(timeout=30.0) == -signal.SIGINT
        assert child.stdout.read() == ""  # no traceback
    finally:
        os.close(heartbeat)


def test_kills_and_an_uncaught_keyboard_interrupt_end_as_for_a_spawned_worker(
    server: ForkServer,
) -> None:
    child, heartbeat = _spawn(server, "sleep")
    os.close(heartbeat)
    assert child.stdout is not None
    assert child.stdout.readline().strip() == "sleeping"
    with pytest.raises(subprocess.TimeoutExpired):
        child.wait(timeout=0.2)
    assert child.poll() is None
    os.killpg(child.pid, signal.SIGKILL)
    assert child.wait(timeout=30.0) == -signal.SIGKILL
    # As `python -m` ends on one: by SIGINT, after the traceback.
    interrupted, heartbeat = _spawn(server, "interrupt")
    os.close(heartbeat)
    assert interrupted.wait(timeout=30.0) == -signal.SIGINT
    assert interrupted.stdout is not None
    assert "KeyboardInterrupt" in interrupted.stdout.read()


def test_a_forked_worker_finds_the_message_types_made(server: ForkServer) -> None:
    # Made once in the server: every worker parsed the definitions and compiled the codecs.
    child, heartbeat = _spawn(server, "types")
    os.close(heartbeat)
    assert child.wait(timeout=60.0) == 0
    assert child.stdout is not None
    report = json.loads(child.stdout.read())
    assert report["built"]
    for name in (
        "sensor_msgs/msg/JointState",
        "diagnostic_msgs/msg/DiagnosticArray",
        "std_srvs/srv/Trigger_Request",
    ):
        assert name in report["made"], report["made"]


def test_what_a_kind_imports_once_running_is_imported_before_its_worker_is_forked(
    probe_dir: Path,
) -> None:
    # Each worker imported psutil (a health monitor), the MCAP writer (an archiver), the
    # kind registry's entry points: 10-25 ms of CPU each, in 23 workers at once.
    from components import kinds
    from msctl.launcher.forkserver import preload_for

    chosen = ["health_monitor", "data_archiver", "joint_manager", "autonomous_operator"]
    preload = preload_for(chosen)
    assert len(preload) == len(set(preload))
    for kind in chosen:
        assert set(kinds.get(kind).preload) <= set(preload)
    assert "components.overrides" in preload  # an extension of the joint manager's
    assert "components.autonomous_operator.operators.guardian" in preload  # a subpackage's
    server = _start(probe_dir, preload)
    try:
        assert server.wait_ready(120.0), server.failure
        wanted = ["psutil", "mcap.writer", "components.overrides.locked_joint", "zenoh.ext"]
        wanted += ["components.comm.topics", "components.autonomous_operator.operators.steering"]
        child, heartbeat = _spawn(server, "imports", ",".join(wanted))
        os.close(heartbeat)
        assert child.wait(timeout=60.0) == 0
        assert child.stdout is not None
        report = json.loads(child.stdout.read())
    finally:
        server.close()
    assert report == {"kinds_loaded": True, "missing": []}


def test_a_worker_given_up_on_while_the_server_imports_never_runs(
    probe_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Its pid came too late: the supervisor started it as a new interpreter instead, so
    # the forked copy must not run as well (it would drive the same hardware).
    flag = tmp_path / "slow-import-started"
    monkeypatch.setenv("SLOW_FLAG", str(flag))
    slow = _start(probe_dir)
    marker = f"abandoned-{os.getpid()}-{time.monotonic_ns()}"
    try:
        assert slow.wait_ready(120.0), slow.failure
        slow.preloads["late"] = ["slow_at_import"]
        read_end, write_end = os.pipe()
        try:
            with pytest.raises(ForkServerError, match="within"):
                slow.spawn(
                    boot.argv("probe_worker", "sleep", marker),
                    {**os.environ, "MSCTL_HEARTBEAT_FD": str(write_end)},
                    {"MSCTL_HEARTBEAT_FD": write_end},
                    name="late",
                    timeout=0.2,
                )
        finally:
            os.close(write_end)
            os.close(read_end)
        assert not slow.ready  # plain interpreters from now on
        wait_until(flag.exists, timeout=60.0, what="the slow import")
        time.sleep(4.0)  # the import ends, the server forks the worker, which finds nobody

        def running_marker() -> list[str]:
            found = []
            for entry in Path("/proc").glob("[0-9]*"):
                try:
                    if marker.encode() in (entry / "cmdline").read_bytes():
                        found.append(entry.name)
                except OSError:
                    continue
            return found

        assert not running_marker()
    finally:
        slow.close()


def test_only_boot_command_lines_are_forked(server: ForkServer) -> None:
    with pytest.raises(ForkServerError, match="not a boot command line"):
        server.spawn(["python", "-c", "pass"], dict(os.environ), {})
    assert server.ready  # refusing one is no reason to stop forking


def test_a_server_with_a_thread_after_importing_refuses_to_fork(probe_dir: Path) -> None:
    refusing = _start(probe_dir, ["threads_at_import"])
    try:
        assert not refusing.wait_ready(120.0)
        assert "2 threads" in refusing.failure
        with pytest.raises(ForkServerError, match="not ready"):
            refusing.spawn(boot.argv("probe_worker", "report", "0"), dict(os.environ), {})
    finally:
        refusing.close()
    assert refusing.popen.poll() is not None


def test_its_workers_outlive_a_dead_server_and_their_end_is_still_seen(probe_dir: Path) -> None:
    dying = _start(probe_dir)
    try:
        assert dying.wait_ready(120.0), dying.failure
        child, heartbeat = _spawn(dying, "sleep")
        os.close(heartbeat)
        assert child.stdout is not None
        assert child.stdout.readline().strip() == "sleeping"
        os.killpg(dying.popen.pid, signal.SIGKILL)
        dying.popen.wait(timeout=30.0)
        assert child.poll() is None  # still running: signals still reach it
        os.killpg(child.pid, signal.SIGKILL)
        # Its pidfd tells its end; its code died with the server (reaped by init).
        assert wait_until(lambda: child.poll() is not None, timeout=30.0) == 1
        with pytest.raises(ForkServerError):
            _spawn(dying, "report", "0")
        assert not dying.ready
    finally:
        dying.close()


# ---------------------------------------------------------------------------- supervisor
@pytest.fixture
def supervisor(tmp_path: Path) -> Iterator[Supervisor]:
    current = Supervisor(
        tmp_path / "logs", RestartPolicy(backoff_initial=0.05, max_restarts=3, window=60.0)
    )
    try:
        yield current
    finally:
        current.shutdown()


def test_the_supervisor_restarts_a_forked_crash_and_fails_a_final_exit(
    supervisor: Supervisor, server: ForkServer
) -> None:
    crash = supervisor.add(
        "crash", boot.argv("probe_worker", "report", "1"), heartbeat=True, forkserver=server
    )
    final = supervisor.add(
        "final",
        boot.argv("probe_worker", "report", "3"),
        heartbeat=True,
        forkserver=server,
        final_exits={3: "cannot be built"},
    )
    supervisor.start_all()
    assert crash.popen is not None and isinstance(crash.popen, ForkedProcess)

    def both_failed() -> bool:
        supervisor.poll()
        return crash.state is ProcessState.FAILED and final.state is ProcessState.FAILED

    wait_until(both_failed, timeout=60.0, what="the crash loop to give up")
    assert crash.restarts == 3
    assert "exited with code 1" in crash.last_error
    assert final.restarts == 0
    assert "code 3 means cannot be built" in final.last_error
    text = crash.log.path.read_text()
    assert text.count('"marker"') == 4  # each start's output reached its log
    assert "not forked" not in text


def test_the_supervisor_stops_a_forked_worker_and_its_group(
    supervisor: Supervisor, server: ForkServer
) -> None:
    sleeper = supervisor.add(
        "sleeper", boot.argv("probe_worker", "sleep"), heartbeat=True, forkserver=server
    )
    supervisor.start("sleeper")
    pid = sleeper.pid
    assert pid is not None and os.getpgid(pid) == pid
    wait_until(lambda: "sleeping" in sleeper.log.tail, timeout=60.0, what="the sleeper")
    started = time.monotonic()
    supervisor.stop("sleeper")
    assert time.monotonic() - started < supervisor.shutdown_policy.after_sigint + 5.0
    assert sleeper.state is ProcessState.STOPPED
    with pytest.raises(ProcessLookupError):
        os.killpg(pid, 0)


def test_the_supervisor_starts_new_interpreters_once_the_server_is_gone(
    supervisor: Supervisor, probe_dir: Path
) -> None:
    gone = _start(probe_dir)
    assert gone.wait_ready(120.0), gone.failure
    gone.close()
    process = supervisor.add(
        "plain",
        boot.argv("probe_worker", "report", "0"),
        {"PYTHONPATH": str(probe_dir)},
        heartbeat=True,
        forkserver=gone,
    )
    supervisor.start("plain")
    assert isinstance(process.popen, subprocess.Popen)
    wait_until(lambda: '"marker"' in "".join(process.log.tail), timeout=60.0, what="its report")
    report = json.loads(next(line for line in process.log.tail if '"marker"' in line))
    assert report["ppid"] == os.getpid()


# ---------------------------------------------------------------------------- msctl up
def _ppid(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])


def _servers_of(home: Path) -> list[int]:
    """Live fork servers whose command line names this home's lock file."""
    found = []
    for entry in Path("/proc").glob("[0-9]*"):
        try:
            cmdline = (entry / "cmdline").read_bytes()
            state = (entry / "stat").read_text().rsplit(")", 1)[1].split()[0]
        except (OSError, IndexError):
            continue
        ours = b"msctl.launcher.forkserver" in cmdline and str(home).encode() in cmdline
        if ours and state != "Z":
            found.append(int(entry.name))
    return found


@pytest.mark.e2e
@pytest.mark.parametrize("forked", [True, False])
def test_msctl_up_forks_its_workers_and_restarts_a_killed_one(tmp_path: Path, forked: bool) -> None:
    from running import Up

    home = tmp_path / "home"
    up = Up(home, "minimal", env={} if forked else {"MSCTL_FORKSERVER": "0"})
    try:
        document = json.loads((home / "run" / "state.json").read_text())
        supervisor = document["supervisor_pid"]
        workers = [p for p in document["processes"] if p["name"] != "router"]
        assert workers
        servers = _servers_of(home)
        assert len(servers) == (1 if forked else 0), servers
        for worker in workers:
            parent = _ppid(worker["pid"])
            assert parent == (servers[0] if forked else supervisor), worker
            assert (
                b"components.executor.worker" in Path(f"/proc/{worker['pid']}/cmdline").read_bytes()
            )
            # Its module runs once, as __main__ (runpy warns when it was imported before).
            log = (home / "run" / "logs" / f"{worker['name']}.log").read_text()
            assert "RuntimeWarning" not in log, log
        victim = workers[0]
        os.killpg(victim["pgid"], signal.SIGKILL)

        def restarted() -> dict | None:
            rows = json.loads((home / "run" / "state.json").read_text())["processes"]
            row = next(p for p in rows if p["name"] == victim["name"])
            if row["pid"] not in (None, victim["pid"]) and row["state"] == "running":
                return row
            return None

        row = wait_until(restarted, timeout=90.0, what=f"{victim['name']} restarted")
        assert row["restarts"] == 1
        assert _ppid(row["pid"]) == (servers[0] if forked else supervisor)
        os.killpg(row["pid"], 0)  # `msctl ps` shows a pid signals reach
    finally:
        up.down()
    wait_until(lambda: not _servers_of(home), timeout=30.0, what="the fork server gone")
