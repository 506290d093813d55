"""What the CLI says about a running assembly when a name is wrong or an action would
change it under its feet (a real detached ``msctl up minimal``)."""

from __future__ import annotations

import json
import re
from collections.abc import Iterator

import pytest
from conftest import wait_until
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


def _ps(up: Up) -> dict[str, dict]:
    result = up.msctl("ps", "--json")
    assert result.returncode == 0, result.stderr
    return {row["name"]: row for row in json.loads(result.stdout)["components"]}


def _all_running(up: Up) -> dict[str, dict] | None:
    rows = _ps(up)
    return rows if all(r["state"] == "running" for r in rows.values()) else None


def _joint_read(up: Up) -> dict:
    result = up.msctl("topic", "echo", "/limb1/joint_read", "--once", "--json", "--timeout", "10")
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout.strip().splitlines()[-1])


def test_restart_names_what_it_takes_and_only_rebuilds_one_component(minimal: Up) -> None:
    before = wait_until(lambda: _all_running(minimal), 60.0, interval=0.5)
    siblings = sorted(
        n for n, r in before.items() if r["process"] == "limb1" and "joint_m" not in n
    )
    assert len(siblings) >= 2, before

    # A plain restart says which components go with the process, and how to spare them.
    result = minimal.msctl("restart", "limb1/joint_manager")
    assert result.returncode == 0, result.stderr
    said = " ".join(result.stderr.split())
    assert all(name in said for name in siblings), said
    assert "share the process" in said and "msctl restart --only limb1/joint_manager" in said
    restarted = wait_until(
        lambda: (
            (rows := _all_running(minimal))
            and rows["limb1/joint_manager"]["pid"] != before["limb1/joint_manager"]["pid"]
            and rows
        ),
        60.0,
        interval=0.5,
    )

    # --only: the same pid, the siblings untouched, the rebuilt one commanding the limb.
    result = minimal.msctl("restart", "--only", "limb1/joint_manager", timeout=90.0)
    assert result.returncode == 0, result.stderr
    said = " ".join(result.stderr.split())
    assert "rebuilt alone in process limb1" in said and "ran on untouched" in said, said
    after = _ps(minimal)
    pid = restarted["limb1/joint_manager"]["pid"]
    assert {after[n]["pid"] for n in [*siblings, "limb1/joint_manager"]} == {pid}
    assert all(after[n]["state"] == "running" for n in siblings)
    log = minimal.msctl("logs", "limb1/joint_manager", "-n", "500").stdout
    assert log.count("rebuilt limb1/joint_manager") == 1
    assert log.count("built limb1/health_monitor") == 2  # start, then the plain restart only

    name = _joint_read(minimal)["name"][0]
    pub = minimal.msctl(
        "topic", "pub", "/limb1/joint_set", "sensor_msgs/msg/JointState",
        f"{{name: [{name}], position: [0.3]}}", "-r", "10", "-t", "30",
    )  # fmt: skip
    assert pub.returncode == 0, pub.stderr
    wait_until(lambda: abs(_joint_read(minimal)["position"][0] - 0.3) < 0.05, 60.0, interval=0.5)


def test_restart_only_says_when_it_cannot(minimal: Up) -> None:
    result = minimal.msctl("restart", "--only", "limb1")
    assert result.returncode == 1, result.stderr
    assert "--only restarts one component, and limb1 is a process" in result.stderr
    result = minimal.msctl("restart", "--only", "sim/simulator")
    # Alone in its process, it is restarted as it is: --only changes nothing there.
    assert result.returncode == 0, result.stderr
