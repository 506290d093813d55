"""A rehearsed computer's own Python environment: what its builds install stays its own.

Plain calls, no namespace: the environment is a directory under the computer's home, and
real pip installs a tiny package there (no index, :mod:`workspace_rigs`).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from workspace_rigs import imports, pip_env, python_package

from msctl.rehearse.computers import Computer, environment, make_python_environment
from msctl.workspace.wheelhouse import target_python


def _computer(home: Path) -> Computer:
    return Computer("hl-limb-01", "robot", "msr-test-hl-limb-01", "10.77.0.11", home, "lan")


def test_a_computer_runs_in_its_own_environment_over_msctls(tmp_path: Path) -> None:
    computer = _computer(tmp_path / "computers" / "hl-limb-01")
    where = make_python_environment(computer)
    assert where == computer.python_env and where.is_relative_to(computer.home)
    env = environment(computer, base={"PATH": "/usr/bin", "TERM": "xterm"})
    assert env["VIRTUAL_ENV"] == str(where)
    assert env["PATH"].split(":")[0] == str(where / "bin")  # `python` is the computer's
    python = str(where / "bin" / "python")
    # msctl and what its environment holds are there, as on a computer with msctl installed.
    done = subprocess.run(
        [python, "-c", "import sys, msctl, zenoh; print(sys.prefix)"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == str(where)


def test_what_its_build_installs_stays_in_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    computer = _computer(tmp_path / "computers" / "hl-limb-01")
    where = make_python_environment(computer)
    # `msctl build` run as the computer installs with its interpreter.
    monkeypatch.setenv("VIRTUAL_ENV", environment(computer)["VIRTUAL_ENV"])
    python = target_python()
    assert python == str(where / "bin" / "python")
    package = python_package(tmp_path / "src", "limb-tools", version="1.1.0")
    subprocess.run(
        [python, "-m", "pip", "install", "--quiet", "--no-deps", str(package)],
        check=True,
        capture_output=True,
        env=pip_env(),
    )
    assert imports(python, "limb_tools") == "limb-tools 1.1.0"
    assert imports(sys.executable, "limb_tools") == ""  # msctl's own environment untouched
