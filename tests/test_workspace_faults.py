"""``msctl build`` and ``msctl update`` against what goes wrong in the field: a package that
never ends, a build stopped by a signal, a state file a power cut truncated, a typo in
``depends``, a lock file that cannot be written.

Real ``msctl`` subprocesses, real process groups, real git remotes (``file://``); the
packages are command packages running this Python, so no pip and no index.
"""

from __future__ import annotations

import fcntl
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import wait_until
from workspace_rigs import Remote, repos_text

from msctl.errors import InputError
from msctl.workspace.packages import find_packages

pytestmark = pytest.mark.timeout(300)

#: A build step that starts a grandchild (``sleep 300``, its pid written down) and then
#: waits for it; at SIGTERM it takes a moment to end (as a compiler flushing would), then
#: says it is gone. The grandchild ignores nothing: only its process group's end stops it.
LINGERING = """\
import pathlib, signal, subprocess, sys, time
marks = pathlib.Path(sys.argv[1])
child = subprocess.Popen(["sleep", "300"])
(marks / "grandchild.pid").write_text(str(child.pid))
def ending(_n, _f):
    (marks / "terminating").write_text("")
    time.sleep(0.5)
    (marks / "gone").write_text("")
    sys.exit(1)
signal.signal(signal.SIGTERM, ending)
(marks / "started").write_text("")
child.wait()
"""
#: A build step that counts its runs.
COUNTING = """\
import pathlib, sys
runs = pathlib.Path(sys.argv[1])
runs.write_text(str(int(runs.read_text()) + 1) if runs.exists() else "1")
"""


def _command_package(ws: Path, name: str, script: str, *args: str, depends: tuple = ()) -> Path:
    folder = ws / name
    folder.mkdir(parents=True)
    (folder / "run.py").write_text(script)
    argv = [sys.executable, "run.py", *args]
    (folder / "msctl-build.toml").write_text(
        f"name = {json.dumps(name)}\ndepends = {json.dumps(list(depends))}\n"
        f"commands = [{json.dumps(argv)}]\n"
    )
    return folder


def _env(tmp_path: Path) -> dict[str, str]:
    return {**os.environ, "MSCTL_HOME": str(tmp_path / "home"), "COLUMNS": "200"}


def _msctl(tmp_path: Path, *args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "msctl", *args],
        env=_env(tmp_path),
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie waiting for a reaper does not)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, IndexError):
        return False
    return state not in ("Z", "X")


def _lock_free(ws: Path) -> bool:
    path = ws / ".msctl" / "build.lock"
    with open(path, "a+") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return False
        fcntl.flock(handle, fcntl.LOCK_UN)
        return True


@pytest.fixture
def grandchildren() -> list[int]:
    """Pids a test's build steps started: killed at the end whatever happened."""
    pids: list[int] = []
    yield pids
    for pid in pids:
        if _alive(pid):
            os.kill(pid, signal.SIGKILL)


def test_timeout_stops_a_package_and_what_it_started_without_all(
    tmp_path: Path, grandchildren: list[int]
) -> None:
    ws, marks = tmp_path / "ws", tmp_path / "marks"
    marks.mkdir()
    _command_package(ws, "limb_firmware", LINGERING, str(marks))
    _command_package(ws, "wheel_firmware", COUNTING, str(tmp_path / "runs"))
    process = subprocess.Popen(
        [sys.executable, "-m", "msctl", "build", "-w", "ws", "--timeout", "3"],
        env=_env(tmp_path),
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        pid = int(wait_until(lambda: _read(marks / "grandchild.pid"), 120, "the step started"))
        grandchildren.append(pid)
        _, stderr = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert process.returncode == 1, stderr
    said = " ".join(stderr.split())
    assert "limb_firmware took longer than --timeout 3 s: stopped it" in said
    assert "failed: limb_firmware" in said
    # What the step started is gone when msctl returns; the other package was built.
    assert not _alive(pid)
    assert (tmp_path / "runs").read_text() == "1"


def test_timeout_must_be_positive(tmp_path: Path) -> None:
    result = _msctl(tmp_path, "build", "-w", str(tmp_path), "--timeout", "0")
    assert result.returncode == 2
    assert "--timeout must be a number of seconds above 0" in result.stderr


def _read(path: Path) -> str:
    try:
        return path.read_text()
    except FileNotFoundError:
        return ""


@pytest.mark.parametrize(("number", "code"), [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_signal_stops_the_steps_then_releases_the_lock(
    tmp_path: Path, grandchildren: list[int], number: int, code: int
) -> None:
    ws, marks = tmp_path / "ws", tmp_path / "marks"
    marks.mkdir()
    _command_package(ws, "limb_firmware", LINGERING, str(marks))
    process = subprocess.Popen(
        [sys.executable, "-m", "msctl", "build", "-w", "ws"],
        env=_env(tmp_path),
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        wait_until(lambda: (marks / "started").exists(), 120, "the build step started")
        pid = int((marks / "grandchild.pid").read_text())
        grandchildren.append(pid)
        assert not _lock_free(ws)
        process.send_signal(number)

        def step_ended_when_lock_freed() -> tuple[bool] | None:
            # Read as soon as the lock is seen free: the step must have ended already.
            return ((marks / "gone").exists(),) if _lock_free(ws) else None

        (ended,) = wait_until(step_ended_when_lock_freed, 60, "the build lock released")
        assert ended, "the build lock was released while its step still ran"
        _, stderr = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert process.returncode == code, stderr
    said = " ".join(stderr.split())
    name = signal.Signals(number).name
    assert f"build stopped: msctl build got {name}; its running steps were ended" in said
    assert "limb_firmware" in said
    assert "Traceback" not in stderr
    assert not _alive(pid)


def test_a_corrupt_build_state_is_rebuilt_saying_so(tmp_path: Path) -> None:
    ws, runs = tmp_path / "ws", tmp_path / "runs"
    _command_package(ws, "limb_firmware", COUNTING, str(runs))
    first = _msctl(tmp_path, "build", "-w", "ws")
    assert first.returncode == 0, first.stderr
    state = ws / ".msctl" / "build" / "doit.json"
    # What a power cut during doit's in-place rewrite leaves: the first half of the file.
    text = state.read_text()
    state.write_text(text[: len(text) // 2])
    second = _msctl(tmp_path, "build", "-w", "ws")
    assert second.returncode == 0, second.stderr
    notes = [line for line in second.stderr.splitlines() if "build state" in line]
    assert len(notes) == 1 and "unreadable" in notes[0], second.stderr
    assert "rebuilt from the packages" in " ".join(second.stderr.split())
    assert "Traceback" not in second.stderr
    assert runs.read_text() == "2"
    third = _msctl(tmp_path, "build", "-w", "ws", "--json")
    assert third.returncode == 0, third.stderr
    assert json.loads(third.stdout)["nothing_done"] is True
    assert "build state" not in third.stderr
    state.write_bytes(b"\xff\xfe garbage")
    fourth = _msctl(tmp_path, "build", "-w", "ws", "--json")
    assert fourth.returncode == 0, fourth.stderr
    assert json.loads(fourth.stdout)["notes"][0].startswith(f"build state {state} was unreadable")
    assert runs.read_text() == "3"


def test_an_unknown_dependency_of_a_command_package_is_refused(tmp_path: Path) -> None:
    ws = tmp_path / "ws"
    _command_package(ws, "limb_msgs", COUNTING, str(tmp_path / "runs"))
    folder = _command_package(
        ws, "limb_firmware", COUNTING, str(tmp_path / "runs"), depends=("limb_msg",)
    )
    with pytest.raises(InputError) as caught:
        find_packages(ws)
    message = str(caught.value)
    assert str(folder / "msctl-build.toml") in message
    assert "'limb_firmware' depends on 'limb_msg'" in message
    assert "did you mean 'limb_msgs'?" in message
    result = _msctl(tmp_path, "build", "-w", "ws")
    assert result.returncode == 2
    assert "depends on 'limb_msg', which is no package of the workspace" in " ".join(
        result.stderr.split()
    )
    assert not (tmp_path / "runs").exists()


def test_update_refuses_an_unwritable_lock_before_updating(tmp_path: Path) -> None:
    limb = Remote(tmp_path, "limb")
    (tmp_path / "ws").mkdir()
    (tmp_path / "ws" / "workspace.repos").write_text(repos_text({"src/limb": (limb.url, "main")}))
    (tmp_path / "a-file").write_text("")
    for lock, why in [
        ("a-file/exact.repos", "is not a directory"),
        ("/proc/exact.repos", "cannot be written"),
        ("ws", "is a directory"),
    ]:
        result = _msctl(tmp_path, "update", "-w", "ws", "--lock", lock)
        assert result.returncode == 2, result.stderr
        said = " ".join(result.stderr.split())
        assert f"--lock {lock}" in said and why in said, said
        assert "Traceback" not in result.stderr
        assert not (tmp_path / "ws" / "src" / "limb").exists(), "the update ran"
    fine = _msctl(tmp_path, "update", "-w", "ws", "--lock", "locks/exact.repos")
    assert fine.returncode == 0, fine.stderr
    assert (tmp_path / "locks" / "exact.repos").is_file()
