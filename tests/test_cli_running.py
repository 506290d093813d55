"""What the CLI says about a running assembly when a name is wrong or an action would
change it under its feet (a real detached ``msctl up minimal``)."""

from __future__ import annotations

import re
from collections.abc import Iterator

import pytest
from running import Up

pytestmark = pytest.mark.e2e


@pytest.fixture(scope="module")
def minimal(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Up]:
    up = Up(tmp_path_factory.mktemp("cli_running"), "minimal")
    try:
        yield up
    finally:
        up.down()


def _line(result) -> str:
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, result.stderr
    return lines[0]


def test_a_mistyped_component_gets_the_nearest_name_in_logs_and_logs_f(minimal: Up) -> None:
    plain = minimal.msctl("logs", "limb1/joint_managr")
    follow = minimal.msctl("logs", "limb1/joint_managr", "-f")
    assert plain.returncode == follow.returncode == 4, plain.stderr + follow.stderr
    assert _line(plain) == _line(follow)  # one wording, followed or not
    assert "did you mean 'limb1/joint_manager'?" in _line(plain)


def test_a_mistyped_component_gets_the_nearest_name_in_restart(minimal: Up) -> None:
    result = minimal.msctl("restart", "limb1/joint_managr")
    assert result.returncode == 4, result.stderr
    assert "did you mean 'limb1/joint_manager'?" in _line(result)


def test_assembling_while_it_runs_is_refused_and_the_lock_file_kept(minimal: Up) -> None:
    lock = minimal.home / "assembly" / "assembly.lock.json"
    before = lock.read_bytes()
    result = minimal.msctl("assemble", "dragon")
    assert result.returncode == 2, result.stderr
    line = _line(result)
    assert "assembly minimal is running" in line and "msctl down" in line
    assert lock.read_bytes() == before
    assert minimal.msctl("ps", "--json").returncode == 0


def test_logs_mark_the_run_and_stamp_every_line(minimal: Up) -> None:
    result = minimal.msctl("logs", "limb1/joint_manager", "-n", "500")
    assert result.returncode == 0, result.stderr
    lines = [line for line in result.stdout.splitlines() if line.strip()]
    assert any("===== msctl up minimal on test-laptop started" in line for line in lines), lines
    stamped = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d[.,]\d{3} ")
    assert all(stamped.match(line) for line in lines), lines
