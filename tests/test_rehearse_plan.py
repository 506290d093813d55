"""``msctl rehearse``'s plan, state and environments, with plain calls (no namespace made).

What a rehearsal makes from a resolved assembly: one computer per host (robots, then ground
stations), each with its own namespace, address, home and link profile; the environment its
commands and its agent run with; and the state file ``down`` reads back, even after a crash.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from components.assembly import from_document
from msctl.assembler import resolve
from msctl.rehearse import computers as rc
from msctl.rehearse import rehearsal as rh


@pytest.fixture(scope="module")
def dragon() -> object:
    return from_document(resolve("dragon", {}).document)


def test_one_computer_per_host_robots_first_then_stations(dragon: object, tmp_path: Path) -> None:
    computers = rh.plan_computers(dragon, tmp_path, "wifi", {"ground1": "cellular"})
    assert [(c.name, c.role) for c in computers] == [
        ("hl-limb-01", "robot"),
        ("hl-limb-02", "robot"),
        ("hl-wheel-01", "robot"),
        ("hl-wheel-02", "robot"),
        ("ground1", "station"),
    ]
    assert len({c.address for c in computers}) == 5
    assert all(c.address.startswith("10.77.0.") for c in computers)
    assert {c.name: c.profile for c in computers}["ground1"] == "cellular"
    assert {c.profile for c in computers if c.role == "robot"} == {"wifi"}
    # Every home and namespace is the rehearsal's own: two MSCTL_HOMEs never share one.
    assert all(c.home.is_relative_to(tmp_path) for c in computers)
    prefix = rh.namespace_prefix(tmp_path)
    assert all(c.netns.startswith(prefix) for c in computers)
    assert rh.namespace_prefix(tmp_path / "other") != prefix


def test_a_link_for_a_host_not_in_the_plan_is_refused(dragon: object, tmp_path: Path) -> None:
    with pytest.raises(rc.RehearseError, match=r"--link names ground2.*its computers: hl-limb-01"):
        rh.plan_computers(dragon, tmp_path, "lan", {"ground2": "wifi"})


@pytest.mark.parametrize(
    ("links", "expected"),
    [
        ([], (None, {})),
        (["wifi"], ("wifi", {})),
        (["wifi", "ground1=cellular"], ("wifi", {"ground1": "cellular"})),
        (["hl-limb-01=earth-moon"], (None, {"hl-limb-01": "earth-moon"})),
    ],
)
def test_link_options(links: list[str], expected: tuple) -> None:
    assert rh.parse_links(links) == expected


@pytest.mark.parametrize(
    ("links", "message"),
    [
        (["wifi", "lan"], "both set every link"),
        (["=wifi"], "write PROFILE or HOST=PROFILE"),
        (["ground1="], "write PROFILE or HOST=PROFILE"),
    ],
)
def test_bad_link_options(links: list[str], message: str) -> None:
    with pytest.raises(rc.RehearseError, match=message):
        rh.parse_links(links)


def test_every_computer_knows_every_other_by_name(dragon: object, tmp_path: Path) -> None:
    computers = rh.plan_computers(dragon, tmp_path, "lan", {})
    lines = rc.hosts_text(computers).splitlines()
    assert "127.0.0.1\tlocalhost" in lines
    for computer in computers:
        assert f"{computer.address}\t{computer.name}" in lines


def _rehearsal(dragon: object, root: Path, secure: bool) -> rh.Rehearsal:
    return rh.Rehearsal(
        root=root,
        template="dragon",
        uses={},
        secure=secure,
        computers=rh.plan_computers(dragon, root, "lan", {}),
        operator="alice@ground1",
    )


def test_commands_run_as_the_computer_with_its_name_home_and_operator(
    dragon: object, tmp_path: Path
) -> None:
    rehearsal = _rehearsal(dragon, tmp_path, secure=True)
    base = {
        "PATH": "/usr/bin",
        "MSCTL_ZENOH_CONNECT": "tcp/elsewhere:7447",
        "MSCTL_IDENTITY": "bob@laptop",
        "MSCTL_SECURE": "0",
        "TERM": "xterm",
    }
    ground = rehearsal.env(rehearsal.computer("ground1"), base)
    assert ground["MSCTL_HOST"] == "ground1"
    assert ground["MSCTL_HOME"] == str(rehearsal.computer("ground1").home)
    assert ground["MSCTL_IDENTITY"] == "alice@ground1"  # the station's operator
    assert "MSCTL_ZENOH_CONNECT" not in ground and "MSCTL_SECURE" not in ground
    assert ground["TERM"] == "xterm"  # the terminal is the caller's
    robot = rehearsal.env(rehearsal.computer("hl-limb-01"), base)
    assert "MSCTL_IDENTITY" not in robot  # a robot computer has no operator at its keyboard
    plain = _rehearsal(dragon, tmp_path, secure=False)
    assert "MSCTL_IDENTITY" not in plain.env(plain.computer("ground1"), base)


def test_agents_run_secure_with_emulated_hardware_on_robots(dragon: object, tmp_path: Path) -> None:
    rehearsal = _rehearsal(dragon, tmp_path, secure=True)
    robot = rehearsal.agent_env(rehearsal.computer("hl-wheel-02"))
    ground = rehearsal.agent_env(rehearsal.computer("ground1"))
    assert robot["MSCTL_SECURE"] == ground["MSCTL_SECURE"] == "1"
    assert robot["MSCTL_EMULATE_HARDWARE"] == "1"
    assert "MSCTL_EMULATE_HARDWARE" not in ground
    assert robot["MSCTL_ZENOH_CONNECT"] == "tcp/localhost:7447"
    assert not any(k.startswith("MSCTL_ROUTER_") for k in robot)


def test_plain_links_go_from_every_robot_to_every_station(dragon: object, tmp_path: Path) -> None:
    rehearsal = _rehearsal(dragon, tmp_path, secure=False)
    robot = rehearsal.agent_env(rehearsal.computer("hl-limb-02"))
    ground = rehearsal.agent_env(rehearsal.computer("ground1"))
    assert robot["MSCTL_ROUTER_CONNECT"] == "tcp/ground1:7448"
    assert "MSCTL_SECURE" not in robot
    assert ground["MSCTL_ROUTER_LISTEN"] == "tcp/0.0.0.0:7448"
    assert "MSCTL_ROUTER_CONNECT" not in ground


def test_a_station_less_assembly_links_robots_to_the_first(tmp_path: Path) -> None:
    minimal = from_document(resolve("minimal", {}).document)
    rehearsal = rh.Rehearsal(
        root=tmp_path,
        template="minimal",
        uses={},
        secure=False,
        computers=rh.plan_computers(minimal, tmp_path, "lan", {}),
    )
    first = rehearsal.computers[0]
    assert rehearsal.ground is first  # operators work from the first robot computer
    assert rh.plain_links(rehearsal, first) == {"MSCTL_ROUTER_LISTEN": "tcp/0.0.0.0:7448"}


def test_a_station_less_assembly_is_operated_from_its_first_robot(tmp_path: Path) -> None:
    minimal = from_document(resolve("minimal", {}).document)
    rehearsal = rh.Rehearsal(
        root=tmp_path,
        template="minimal",
        uses={},
        secure=True,
        computers=rh.plan_computers(minimal, tmp_path, "lan", {}),
        operator="alice@hl-limb-01",
    )
    # `msctl net init` made the operator there; without it, `msctl up --all` is refused.
    assert rehearsal.env(rehearsal.ground, {})["MSCTL_IDENTITY"] == "alice@hl-limb-01"


def test_commands_enter_the_namespace_and_take_the_host_name(
    dragon: object, tmp_path: Path
) -> None:
    computer = rh.plan_computers(dragon, tmp_path, "lan", {})[0]
    argv = rc.exec_argv(computer, ["msctl", "ps"])
    assert argv[:4] == ["ip", "netns", "exec", computer.netns]
    assert argv[4:6] == ["unshare", "--uts"]
    assert argv[-3:] == [computer.name, "msctl", "ps"]


def test_the_state_file_round_trips(dragon: object, tmp_path: Path) -> None:
    rehearsal = _rehearsal(dragon, tmp_path, secure=True)
    rehearsal.emulator_pid = 1234
    rehearsal.save()
    again = rh.Rehearsal.load(tmp_path)
    assert again.computers == rehearsal.computers
    assert (again.secure, again.operator, again.emulator_pid) == (True, "alice@ground1", 1234)


def test_no_rehearsal_and_a_broken_state_say_what_to_do(tmp_path: Path) -> None:
    with pytest.raises(rc.RehearseError, match="no rehearsal in") as missing:
        rh.Rehearsal.load(tmp_path)
    assert "msctl rehearse up" in str(missing.value.hint)
    (tmp_path / rh.STATE_FILE).write_text(json.dumps({"template": "dragon"}))
    with pytest.raises(rc.RehearseError, match="is not a rehearsal's state") as broken:
        rh.Rehearsal.load(tmp_path)
    assert "msctl rehearse down" in str(broken.value.hint)


def test_an_unknown_computer_is_named_with_the_known_ones(dragon: object, tmp_path: Path) -> None:
    rehearsal = _rehearsal(dragon, tmp_path, secure=True)
    with pytest.raises(rc.RehearseError, match="no computer 'hl-limb-1'") as wrong:
        rehearsal.computer("hl-limb-1")
    assert "ground1" in str(wrong.value)
    assert "hl-limb-01" in str(wrong.value.hint)


def test_every_step_of_rehearse_up_takes_from_one_budget() -> None:
    import time

    from msctl.errors import OperationTimeout
    from msctl.rehearse.start import left

    deadline = time.monotonic() + 60.0
    assert 0 < left(deadline, "msctl assemble dragon", 60.0) <= 60.0
    # Spent by the earlier steps: the next one is not started, and the error names it.
    with pytest.raises(OperationTimeout) as spent:
        left(time.monotonic() - 1.0, "msctl up --all", 60.0)
    said = str(spent.value)
    assert "`msctl up --all` did not finish within 60 s" in said and "one budget" in said
    assert spent.value.exit_code == 5


def test_a_step_killed_by_a_signal_is_named_a_crash_with_its_last_output(
    dragon: object, tmp_path: Path
) -> None:
    import subprocess

    from msctl.rehearse.privileges import RehearseError
    from msctl.rehearse.start import _check

    ground = rh.plan_computers(dragon, tmp_path, "wifi", {})[-1]
    traceback = "Fatal Python error: Segmentation fault\n\nThread 0x1 (most recent call first):\n"
    crashed = subprocess.CompletedProcess(["msctl"], -11, "", "asking...\n" + traceback)
    with pytest.raises(RehearseError) as caught:
        _check(crashed, ground, "msctl up --all")
    said = str(caught.value)
    assert "`msctl up --all` crashed on ground1 (SIGSEGV)" in said
    assert "Fatal Python error: Segmentation fault" in said and "most recent call first" in said
    said_last = "one\nno agent answered for hl-limb-01\n"
    failed = subprocess.CompletedProcess(["msctl"], 3, "", said_last)
    with pytest.raises(RehearseError) as caught:
        _check(failed, ground, "msctl up --all")
    assert str(caught.value).endswith("failed on ground1 (3): no agent answered for hl-limb-01")
