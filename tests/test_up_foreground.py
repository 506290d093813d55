"""A foreground ``msctl up`` (no ``--detach``) on a simulated Dragon, end to end (issue 18).

- Point 15: a deterministic failure is printed once. Every worker refusing
  ``MSCTL_TRANSPORT=rclpy`` on a computer without ROS 2 printed the same long cause once per
  process, five or six times on one line; processes failing alike are now named together
  before their one cause, and the command ends at once (exit 3), never running its ``--for``.
- Point 18: a Ctrl-C while it is still starting stops it within moments (it took 13 s: the
  launcher waited for the router, opened its session, then gave every interrupted worker 2 s),
  exits 130 with one line, and leaves no ``KeyboardInterrupt`` traceback in any log (every
  worker interrupted while Python started, imported or built printed one, and so did the
  ``glfw`` probe MuJoCo's import starts in the simulator's process group).

Each test runs the real command in a subprocess with its own MSCTL_HOME and router port.
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import free_port, wait_until

from components.supervision.protocol import ProcessRow
from msctl.commands.up import _failure_error
from msctl.launcher import boot, state

ROOT = Path(__file__).resolve().parents[1]

#: The Dragon's processes on a computer that is none of its own (all simulated).
DRAGON_PROCESSES = {"router", "sim", "limb1", "limb2", "wheel1", "wheel2"}

#: Seconds a Ctrl-C may take to stop everything here: generous, for a loaded machine (on a
#: quiet one it takes about a second; the figure is printed).
STOP_BOUND = 15.0

#: What no log may hold after a Ctrl-C: Python's traceback of an interrupted program, and its
#: own when it is interrupted before it runs a line (while importing ``site``).
TRACEBACK_SIGNS = ("Traceback", "KeyboardInterrupt", "Fatal Python error")


class Foreground:
    """One MSCTL_HOME and router port, and the foreground ``msctl up`` running in it.

    Args:
        home: Its MSCTL_HOME.
    """

    def __init__(self, home: Path) -> None:
        self.home = home
        self.address = f"127.0.0.1:{free_port()}"
        self.env = {
            **{k: v for k, v in os.environ.items() if not k.startswith(("MSCTL_", "ZENOH_"))},
            "MSCTL_HOME": str(home),
            "MSCTL_HOST": "test-laptop",  # none of the Dragon's computers: all simulated
            "MSCTL_ZENOH_CONNECT": f"tcp/{self.address}",
            "MSCTL_ZENOH_LISTEN": "tcp/127.0.0.1:0",
            "MSCTL_ZENOH_MULTICAST": "0",
            "PYTHONPATH": str(ROOT),
        }
        self.proc: subprocess.Popen[str] | None = None
        self.lines: list[str] = []
        self._reader: threading.Thread | None = None

    def start(self, *args: str, **env: str) -> subprocess.Popen[str]:
        """Start ``msctl ARGS`` in a session of its own (a terminal's foreground job), its
        stderr read line by line as it comes."""
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "msctl", *args],
            env={**self.env, **env},
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,
            cwd=ROOT,
        )
        self._reader = threading.Thread(target=self._read, args=(self.proc,), daemon=True)
        self._reader.start()
        return self.proc

    def _read(self, proc: subprocess.Popen[str]) -> None:
        assert proc.stderr is not None
        for line in proc.stderr:
            self.lines.append(line.rstrip("\n"))

    def said(self, text: str) -> bool:
        """Whether a line of its stderr so far holds ``text``."""
        return any(text in line for line in list(self.lines))

    def stderr(self) -> str:
        """Its whole stderr, once it has exited."""
        if self._reader is not None:
            self._reader.join(timeout=10.0)
        return "\n".join(self.lines)

    def interrupt(self) -> None:
        """Ctrl-C as a terminal sends it: SIGINT to the foreground job's process group."""
        assert self.proc is not None
        os.killpg(self.proc.pid, signal.SIGINT)

    def log_dir(self) -> Path:
        """Where its supervisor writes the process logs (as msctl finds them)."""
        with _msctl_home(self.home):
            return state.log_dir()

    def logs_saying(self, text: str) -> set[str]:
        """The processes whose log holds ``text`` (by their log's name)."""
        found = set()
        for log in self.log_dir().glob("*.log"):
            with contextlib.suppress(OSError):
                if text in log.read_text(errors="replace"):
                    found.add(log.stem)
        return found

    def state(self) -> dict[str, Any] | None:
        """Its state file, if written."""
        with _msctl_home(self.home):
            path = state.state_path()
        try:
            return json.loads(path.read_text())
        except (OSError, ValueError):
            return None

    def leftovers(self) -> list[str]:
        """Command lines of live processes it started: every worker names this home's lock
        file, the embedded router this port."""
        found = []
        for entry in Path("/proc").glob("[0-9]*"):
            try:
                if (entry / "stat").read_text().rsplit(")", 1)[1].split()[0] == "Z":
                    continue  # a zombie awaiting its reaper has ended
                cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode()
            except (OSError, IndexError):
                continue
            if str(self.home) in cmdline or self.address in cmdline:
                found.append(f"{entry.name}: {cmdline}")
        return found

    def clean_up(self) -> None:
        """Whatever it left running is killed (a failing test must not leak a Dragon)."""
        if self.proc is not None and self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(timeout=30.0)
        for line in self.leftovers():
            with contextlib.suppress(ProcessLookupError, ValueError):
                os.killpg(int(line.split(":", 1)[0]), signal.SIGKILL)


@contextlib.contextmanager
def _msctl_home(home: Path) -> Iterator[None]:
    """MSCTL_HOME set to ``home`` meanwhile (msctl's paths read it when called)."""
    previous = os.environ.get("MSCTL_HOME")
    os.environ["MSCTL_HOME"] = str(home)
    try:
        yield
    finally:
        if previous is None:
            os.environ.pop("MSCTL_HOME", None)
        else:
            os.environ["MSCTL_HOME"] = previous


@pytest.fixture
def foreground(tmp_path: Path) -> Iterator[Foreground]:
    current = Foreground(tmp_path / "home")
    try:
        yield current
    finally:
        current.clean_up()


# ------------------------------------------------------------------------------ point 18
@pytest.mark.e2e
@pytest.mark.parametrize("moment", ["announced", "spawned", "building"])
def test_ctrl_c_while_starting_stops_at_once_with_one_line_and_no_traceback(
    foreground: Foreground, moment: str
) -> None:
    """Ctrl-C at three moments of the start: as the command announces what it starts, once
    every process is spawned (each still in Python's start-up or its imports), and once a
    worker builds its components."""
    proc = foreground.start("up", "dragon", "--for", "600")
    # The line it prints as it starts the router and the processes.
    wait_until(lambda: foreground.said("components in"), timeout=120.0, what="the start")
    if moment == "spawned":
        wait_until(
            lambda: foreground.logs_saying("--- msctl: starting") >= DRAGON_PROCESSES,
            timeout=60.0,
            what="every process spawned",
        )
    elif moment == "building":
        wait_until(
            lambda: foreground.logs_saying("INFO msctl.worker: built "),
            timeout=120.0,
            what="a worker building",
        )
    interrupted = time.monotonic()
    foreground.interrupt()
    try:
        code = proc.wait(timeout=STOP_BOUND)
    except subprocess.TimeoutExpired:
        raise AssertionError(
            f"msctl up still running {STOP_BOUND:g} s after Ctrl-C:\n" + foreground.stderr()
        ) from None
    took = time.monotonic() - interrupted
    print(f"\nCtrl-C ({moment}) -> msctl up exited in {took:.2f} s")
    stderr = foreground.stderr()
    assert " up in " not in stderr, "it was up before the Ctrl-C: nothing was tested"
    # Interrupted before it did what it was asked: 130 and one line, as every msctl command.
    assert code == 130, stderr
    assert stderr.splitlines()[-1] == "interrupted", stderr
    assert "dragon stopped on test-laptop" in stderr
    assert "Traceback" not in stderr
    logs = sorted(foreground.log_dir().glob("*.log"))
    if moment != "announced":  # (announced: it may stop before it started anything)
        assert {log.stem for log in logs} >= DRAGON_PROCESSES, logs
    for log in logs:
        text = log.read_text(errors="replace")
        for sign in TRACEBACK_SIGNS:
            assert sign not in text, f"{log.name}:\n{text}"
    document = foreground.state()
    assert document is not None and document["state"] == "stopped"
    assert not [p for p in document["processes"] if p["pid"] is not None], document
    assert not foreground.leftovers()


@pytest.mark.e2e
def test_a_booted_process_interrupted_before_its_first_line_ends_quietly(tmp_path: Path) -> None:
    """What the launcher starts, it starts through :mod:`msctl.launcher.boot` with SIGINT held:
    a SIGINT while the interpreter still starts (which printed "Fatal Python error:
    init_import_site" and a traceback) waits, then ends it, silently, before the program runs.
    """
    (tmp_path / "never_reached.py").write_text("print('ran')\n")
    env = {**os.environ, "PYTHONPATH": f"{tmp_path}{os.pathsep}{ROOT}"}
    with boot.held_sigint():
        proc = subprocess.Popen(
            boot.argv("never_reached"),
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,
        )
        os.killpg(proc.pid, signal.SIGINT)  # before it can have run a line
    out, err = proc.communicate(timeout=60.0)
    assert proc.returncode == -signal.SIGINT, err
    assert (out, err) == ("", "")


@pytest.mark.e2e
def test_boot_runs_the_module_as_main_with_its_arguments(tmp_path: Path) -> None:
    (tmp_path / "echo_args.py").write_text(
        "import signal, sys\n"
        "print(__name__, sys.argv[1:], signal.getsignal(signal.SIGINT) is signal.SIG_DFL)\n"
    )
    env = {**os.environ, "PYTHONPATH": f"{tmp_path}{os.pathsep}{ROOT}"}
    result = subprocess.run(
        boot.argv("echo_args", "--lock", "x", "-v"),
        env=env,
        capture_output=True,
        text=True,
        timeout=60.0,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "__main__ ['--lock', 'x', '-v'] True"


def test_a_booted_process_that_crashes_in_native_code_leaves_its_traceback(tmp_path: Path) -> None:
    # A segfault (Zenoh's, MuJoCo's) showed only as exit -11; the log now says where it was.
    (tmp_path / "crashes.py").write_text(
        "import ctypes\n\ndef where_it_crashed():\n    ctypes.string_at(0)\n\nwhere_it_crashed()\n"
    )
    env = {**os.environ, "PYTHONPATH": f"{tmp_path}{os.pathsep}{ROOT}"}
    env.pop("PYTHONFAULTHANDLER", None)
    result = subprocess.run(
        boot.argv("crashes"), env=env, capture_output=True, text=True, timeout=60.0, check=False
    )
    assert result.returncode == -signal.SIGSEGV, result.stderr
    assert "Fatal Python error: Segmentation fault" in result.stderr
    assert "where_it_crashed" in result.stderr


# ------------------------------------------------------------------------------ point 15
@pytest.mark.e2e
@pytest.mark.skipif(
    importlib.util.find_spec("rclpy") is not None, reason="rclpy is importable: it would run"
)
def test_a_cause_every_process_shares_is_printed_once(foreground: Foreground) -> None:
    proc = foreground.start("up", "dragon", "--for", "600", MSCTL_TRANSPORT="rclpy")
    try:
        # Ending at once: never its --for.
        code = proc.wait(timeout=300.0)
    except subprocess.TimeoutExpired:
        raise AssertionError("msctl up kept running:\n" + foreground.stderr()) from None
    stderr = foreground.stderr()
    cause = "MSCTL_TRANSPORT=rclpy needs a ROS 2 install"
    assert code == 3, stderr
    assert stderr.count(cause) == 1, stderr
    assert " up in " not in stderr
    # Its last line says it all: which processes failed (with how), and the cause.
    last = stderr.strip().splitlines()[-1]
    assert last.startswith("error: ") and cause in last, last
    assert "exited with code 3" in last and "gave up after one try" in last, last
    failed = [p for p in foreground.state()["processes"] if p["state"] == "failed"]
    assert failed, foreground.state()
    for process in failed:
        assert cause in process["last_error"]
        assert process["name"] in last, (process["name"], last)
    assert "log" in last and "msctl logs" in last, last
    assert not foreground.leftovers()


def _failed(name: str, components: list[str], cause: str) -> ProcessRow:
    """A FAILED process as a run document holds it."""
    return ProcessRow(
        name=name,
        state="failed",
        components=components,
        last_error=cause,
        log=f"/home/run/logs/{name}.log",
    )


def test_processes_failing_alike_are_named_together_before_their_one_cause() -> None:
    alike = "exited with code 3: error: MSCTL_TRANSPORT=rclpy needs a ROS 2 install"
    own = "exited with code 3: error: cannot build limb1/joint_manager: param x"
    error = _failure_error(
        [
            _failed("sim", ["sim/simulator"], alike),
            _failed("limb1", ["limb1/joint_manager", "limb1/health_monitor"], own),
            _failed("wheel1", ["wheel1/joint_manager", "wheel1/health_monitor"], alike),
        ]
    )
    text = str(error)
    assert text.count("MSCTL_TRANSPORT") == 1, text
    assert f"processes sim, wheel1 (3 components) failed, each: {alike}" in text
    # A cause naming its component still names it, and its own process.
    assert f"limb1/joint_manager (process limb1) failed: {own}" in text
    assert error.exit_code == 3


# Issue 18, point 15: a setting every worker refuses.
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
