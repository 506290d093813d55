"""What an operator reads when something is named wrong, mistyped, or interrupted.

In-process: the nearest-name suggestions and the assembler's errors. Subprocesses (e2e): the
help's metavars, Ctrl-C at any moment, ``msctl run`` failing fast with nothing up, an
``assemble`` while an ``up`` is starting, and ``down --all`` with only idle agents.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from conftest import free_port, wait_until

from msctl.errors import InputError, NotFoundError, did_you_mean, nearest

ROOT = Path(__file__).resolve().parents[1]


def test_nearest_keeps_only_names_about_as_close_as_the_best() -> None:
    types = ["std_msgs/msg/String", "std_msgs/msg/Int8", "std_msgs/msg/Char"]
    assert nearest("std_msgs/msg/Strin", types) == ["std_msgs/msg/String"]
    components = ["limb1/joint_manager", "limb2/joint_manager", "limb1/motor_interface"]
    assert nearest("limb1/joint_managr", components) == ["limb1/joint_manager"]
    assert nearest("zzz", types) == []
    assert did_you_mean("dragn", ["dragon", "minimal"]) == "did you mean 'dragon'?"
    assert did_you_mean("zzz", ["dragon"]) == ""


def test_mistyped_template_unit_and_slot_get_the_nearest_names() -> None:
    from msctl.assembler import data, resolve

    with pytest.raises(NotFoundError, match=r"did you mean 'dragon'\?"):
        data.load_template("dragn")
    with pytest.raises(NotFoundError, match=r"did you mean 'hlv1-limb-03'\?"):
        resolve("dragon", {"limb1": "hlv1-limb-3"})
    with pytest.raises(InputError, match=r"no slot 'limb' — did you mean 'limb1' or 'limb2'\?"):
        resolve("dragon", {"limb": "hlv1-limb-03"})
    with pytest.raises(NotFoundError, match=r"did you mean 'hl_limb_v1' or 'hl_limb_v2'\?"):
        data.load_module_type("hl_limb_v")


def _msctl(*args: str, env: dict[str, str] | None = None, timeout: float = 60.0):
    return subprocess.run(
        [sys.executable, "-m", "msctl", *args],
        capture_output=True,
        text=True,
        env={**os.environ, **(env or {})},
        timeout=timeout,
        check=False,
        cwd=ROOT,
    )


@pytest.mark.e2e
@pytest.mark.parametrize(
    "args", [("topic", "pub", "--help"), ("router", "--help"), ("assemble", "--help")]
)
def test_help_uses_plain_words_and_lines_that_fit(args: tuple[str, ...]) -> None:
    result = _msctl(*args, env={"COLUMNS": "80", "TERM": "dumb"})
    assert result.returncode == 0, result.stderr
    for word in ("<bool>", "<str>", "<list[str]>", "<float>", "<int>", "{"):
        assert word not in result.stdout.replace("{data: hello}", ""), (word, result.stdout)
    if args[0] == "assemble":
        # Every example command fits on its line, its description on the next.
        assert "\n msctl assemble dragon --use limb1=hlv1-limb-04 " in result.stdout
        assert "     swap one unit, keep the others" in result.stdout


@pytest.mark.e2e
def test_ctrl_c_while_the_commands_are_imported_is_one_line_and_130() -> None:
    # A Ctrl-C the moment `msctl router` imports its command module, deterministically.
    script = textwrap.dedent(
        """
        import os, signal, sys
        class Interrupt:
            def find_spec(self, name, path=None, target=None):
                if name == "msctl.commands.router":
                    os.kill(os.getpid(), signal.SIGINT)
                return None
        sys.meta_path.insert(0, Interrupt())
        sys.argv = ["msctl", "router", "--for", "0.1"]
        from msctl.cli import main
        main()
        """
    )
    result = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60, cwd=ROOT
    )
    assert result.returncode == 130, result.stderr
    assert result.stderr.strip() == "interrupted"


@pytest.mark.e2e
def test_ctrl_c_inside_a_command_is_one_line_and_130(tmp_path: Path) -> None:
    script = tmp_path / "stop.py"
    script.write_text("raise KeyboardInterrupt\n")
    result = _msctl("run", str(script))
    assert result.returncode == 130, result.stderr
    assert result.stderr.strip() == "interrupted"


@pytest.mark.e2e
def test_run_with_no_router_fails_fast_naming_the_endpoint(tmp_path: Path) -> None:
    script = tmp_path / "noop.py"
    script.write_text("async def main(robot):\n    pass\n")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    env = {
        "MSCTL_HOME": str(tmp_path / "home"),
        "MSCTL_ZENOH_CONNECT": endpoint,
        "MSCTL_ZENOH_LISTEN": "tcp/127.0.0.1:0",
        "MSCTL_ZENOH_MULTICAST": "0",
    }
    result = _msctl("run", str(script), env=env)
    assert result.returncode == 3, result.stderr
    assert f"no Zenoh router or peer reachable at {endpoint} (connection refused)" in result.stderr


@pytest.mark.e2e
def test_run_with_a_router_and_nothing_behind_it_says_nothing_runs(
    tmp_path: Path, zenoh_env: dict[str, str]
) -> None:
    script = tmp_path / "noop.py"
    script.write_text("async def main(robot):\n    pass\n")
    result = _msctl("run", str(script), env={**zenoh_env, "MSCTL_HOME": str(tmp_path / "h")})
    assert result.returncode == 3, result.stderr
    assert "no running assembly found on the data plane" in result.stderr
    assert "within 15 s" not in result.stderr


@pytest.mark.e2e
def test_urdf_output_into_a_missing_directory_is_refused(tmp_path: Path) -> None:
    env = {"MSCTL_HOME": str(tmp_path / "home")}
    assert _msctl("assemble", "minimal", env=env).returncode == 0
    target = tmp_path / "nonexistent" / "dir" / "x.urdf"
    result = _msctl("assemble", "urdf", "-o", str(target), env=env)
    assert result.returncode == 2, result.stderr
    assert f"no directory {target.parent}" in result.stderr
    assert not (tmp_path / "nonexistent").exists()


@pytest.mark.e2e
def test_up_with_nothing_resolved_says_what_to_run_once(tmp_path: Path) -> None:
    result = _msctl("up", "--for", "1", env={"MSCTL_HOME": str(tmp_path / "home")})
    assert result.returncode == 4, result.stderr
    line = result.stderr.strip()
    assert line.startswith("error: no resolved assembly at ") and "\n" not in line
    assert line.count("msctl assemble dragon") == 1, line
    assert " — " not in line, line  # no second hint repeating the first


@pytest.mark.e2e
def test_up_all_with_no_agent_says_no_host_was_started(
    tmp_path: Path, zenoh_env: dict[str, str]
) -> None:
    env = {**zenoh_env, "MSCTL_HOME": str(tmp_path / "home")}
    assert _msctl("assemble", "dragon", env=env).returncode == 0
    result = _msctl("up", "--all", "--sim", "--timeout", "5", env=env)
    assert result.returncode == 3, result.stderr
    assert "no host was started" in result.stderr, result.stderr
    assert "other hosts were started" not in result.stderr
    # Each of the template's computers is named as not answering.
    last = result.stderr.strip().splitlines()[-1]
    for host in ("hl-limb-01", "hl-limb-02", "hl-wheel-01", "hl-wheel-02", "ground1"):
        assert host in last, last


@pytest.mark.e2e
def test_down_all_with_nothing_running_is_done(tmp_path: Path, zenoh_env: dict[str, str]) -> None:
    home = {"MSCTL_HOME": str(tmp_path / "home")}
    # No router at all: no agent can run anything an operator reaches through it.
    alone = {
        **home,
        "MSCTL_ZENOH_CONNECT": f"tcp/127.0.0.1:{free_port()}",
        "MSCTL_ZENOH_LISTEN": "tcp/127.0.0.1:0",
        "MSCTL_ZENOH_MULTICAST": "0",
    }
    result = _msctl("down", "--all", env=alone)
    assert result.returncode == 0, result.stderr
    assert result.stderr.startswith("nothing is running"), result.stderr
    # A router, and no agent or supervisor behind it.
    result = _msctl("down", "--all", env={**zenoh_env, **home})
    assert result.returncode == 0, result.stderr
    assert "nothing is running" in result.stderr, result.stderr


@pytest.mark.e2e
def test_a_bad_session_variable_is_the_operators_error_naming_it(tmp_path: Path) -> None:
    env = {
        "MSCTL_HOME": str(tmp_path / "home"),
        "MSCTL_HOST": "test-laptop",
        "MSCTL_ZENOH_CONNECT": f"tcp/127.0.0.1:{free_port()}",
        "MSCTL_ZENOH_LISTEN": "garbage",
        "MSCTL_ZENOH_MULTICAST": "0",
    }
    result = _msctl("up", "minimal", "--for", "1", env=env)
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip().startswith("error: MSCTL_ZENOH_LISTEN: endpoint 'garbage'")
    assert "internal error" not in result.stderr


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


# Issue 18, point 12.
@pytest.mark.e2e
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


# Issue 18, point 11.
@pytest.mark.e2e
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


# Issue 18, point 5.
@pytest.mark.e2e
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


# Issue 18, point 8: every help in plain words.
_HELP_OF_EVERY_COMMAND = """
import contextlib, io, sys
from msctl.app import command

def walk(cmd, path):
    yield path
    for name, sub in sorted(getattr(cmd, "commands", {}).items()):
        yield from walk(sub, [*path, name])

for path in walk(command(None), []):
    buffer = io.StringIO()
    with contextlib.redirect_stdout(buffer):
        try:
            command(path).main([*path, "--help"], prog_name="msctl", standalone_mode=False)
        except SystemExit:
            pass
    print("@@@ msctl " + " ".join(path))
    print(buffer.getvalue())
"""

#: A Python type where a value's word belongs (typer's ``<bool>``, ``<list[str]>``...).
_PYTHON_METAVAR = re.compile(r"<(?:bool|str|int|float|path|list\[[^\]]*\]|[a-z_]+\[[^\]]*\])>")


@pytest.mark.e2e
def test_every_help_uses_plain_words_and_fits_80_columns() -> None:
    """Point 8: every command's help, as typer renders it (the same code path as ``msctl X
    --help``), in one subprocess."""
    result = subprocess.run(
        [sys.executable, "-c", _HELP_OF_EVERY_COMMAND],
        env={**os.environ, "COLUMNS": "80", "TERM": "dumb", "PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    helps = dict(part.split("\n", 1) for part in result.stdout.split("@@@ ")[1:] if "\n" in part)
    assert {"msctl ", "msctl topic pub", "msctl assemble", "msctl logs"} <= set(helps)
    for name, text in helps.items():
        assert "Usage:" in text, name
        assert not _PYTHON_METAVAR.findall(text), (name, _PYTHON_METAVAR.findall(text), text)
        assert all(len(line) <= 80 for line in text.splitlines()), (name, text)
    # The examples of `msctl assemble --help`: each command whole on its line, its
    # description on the next (they wrapped mid-command).
    assemble = helps["msctl assemble"]
    for example in (
        "msctl assemble dragon --use limb1=hlv1-limb-04",
        "msctl assemble urdf -o /tmp/dragon.urdf",
    ):
        assert f"\n {example} " in assemble, assemble
