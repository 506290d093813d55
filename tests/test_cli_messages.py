"""What an operator reads when something is named wrong, mistyped, or interrupted.

In-process: the nearest-name suggestions and the assembler's errors. Subprocesses (e2e): the
help's metavars, Ctrl-C at any moment, and ``msctl run`` failing fast with nothing up.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from conftest import free_port

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
