"""What the teleop reads from the assembly's data (modules, robots, cmd_vel, which modes fit)
and the command's errors: each names what is wrong and what to do, before any network."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import free_port

from components.assembly import ResolvedAssembly, from_document
from components.comm.node import Node
from components.comm.session import SessionSettings, open_session
from msctl.assembler import resolve
from msctl.errors import NetworkError, NotFoundError
from msctl.teleop.keys import DRIVE, IK
from msctl.teleop.link import (
    Link,
    check_modules,
    cmd_vel_topic,
    robots_of,
    root_link,
    unavailable_modes,
)

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def two_dragons() -> ResolvedAssembly:
    return from_document(resolve("two_dragons").document)


@pytest.fixture(scope="module")
def dragon() -> ResolvedAssembly:
    return from_document(resolve("dragon").document)


def test_modules_joined_by_connections_are_one_robot_named_by_its_root(two_dragons) -> None:
    robots = robots_of(two_dragons)
    assert {robots[f"d1_{m}"] for m in ("limb1", "limb2", "wheel1", "wheel2")} == {"d1_limb1"}
    assert {robots[f"d2_{m}"] for m in ("limb1", "limb2", "wheel1", "wheel2")} == {"d2_limb1"}
    assert root_link(two_dragons, "d2_limb1") == "d2_limb1_base_link"


def test_cmd_vel_is_the_robots_own(dragon, two_dragons) -> None:
    assert cmd_vel_topic(dragon, ["limb1"]) == "/cmd_vel"
    assert cmd_vel_topic(two_dragons, ["d2_wheel1", "d2_limb2"]) == "/d2_limb1/cmd_vel"
    assert cmd_vel_topic(two_dragons, ["d1_wheel1", "d2_wheel1"]) is None
    minimal = from_document(resolve("minimal").document)
    assert cmd_vel_topic(minimal, ["limb1"]) is None


def test_modes_the_data_rules_out_say_why(dragon, two_dragons) -> None:
    assert IK in unavailable_modes(dragon, ["wheel1"])
    assert "kinematic chain" in unavailable_modes(dragon, ["wheel1"])[IK]
    both = unavailable_modes(two_dragons, ["d1_wheel1", "d2_wheel1"])
    assert "several robots" in both[DRIVE] and "--cmd-vel" in both[DRIVE]
    assert DRIVE not in unavailable_modes(two_dragons, ["d1_wheel1", "d2_wheel1"], "/cmd_vel")


def test_an_unknown_module_is_refused_naming_the_modules_there_are(dragon) -> None:
    assert check_modules(dragon, []) == ["limb1", "limb2", "wheel1", "wheel2"]
    assert check_modules(dragon, ["wheel2", "limb1"]) == ["limb1", "wheel2"]
    with pytest.raises(NotFoundError) as caught:
        check_modules(dragon, ["limb3"])
    text = str(caught.value)
    assert "dragon has no module 'limb3'" in text
    assert "did you mean" in text and "limb1, limb2, wheel1, wheel2" in text


def test_a_module_whose_joint_manager_does_not_answer_is_named(dragon) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(SessionSettings(mode="router", connect=(), listen=(endpoint,)))
    session = open_session(
        SessionSettings(connect=(endpoint,), listen=("tcp/127.0.0.1:0",), multicast=False)
    )
    node = Node(session, "teleop_alone")
    try:
        with pytest.raises(NetworkError) as caught:
            Link.open(node, dragon, ["limb2"], health=False, timeout=0.5)
        assert "no answer from the joint manager of limb2 (/limb2/joints)" in str(caught.value)
        assert "msctl ps" in str(caught.value)
    finally:
        node.close()
        session.close()
        router.close()


def _teleop(home: Path, *args: str) -> subprocess.CompletedProcess:
    env = {
        **os.environ,
        "MSCTL_HOME": str(home),
        # Nothing listens there: the errors below must come before any network.
        "MSCTL_ZENOH_CONNECT": f"tcp/127.0.0.1:{free_port()}",
        "MSCTL_ZENOH_MULTICAST": "0",
        "PYTHONPATH": str(ROOT),
    }
    return subprocess.run(
        [sys.executable, "-m", "msctl", "teleop", *args],
        env=env,
        capture_output=True,
        text=True,
        timeout=120.0,
        cwd=ROOT,
        check=False,
    )


def test_the_command_names_its_mistakes_before_the_network(tmp_path: Path) -> None:
    from msctl.assembler.store import write_resolution

    result = _teleop(tmp_path, "--mode", "fly")
    assert result.returncode == 2
    assert "--mode must be one of joint, ik, drive, not 'fly'" in result.stderr
    result = _teleop(tmp_path)  # no lock file in this MSCTL_HOME
    assert result.returncode == 4, result.stderr
    write_resolution(tmp_path / "assembly", resolve("dragon"))
    result = _teleop(tmp_path, "--module", "limb9")
    assert result.returncode == 4
    assert "dragon has no module 'limb9'" in result.stderr
    result = _teleop(tmp_path, "--module", "wheel1", "--mode", "ik")
    assert result.returncode == 2
    assert "--mode ik: no commanded module is a limb with a kinematic chain" in result.stderr
    result = _teleop(tmp_path, "--repeat-timeout", "0")
    assert result.returncode == 2 and "--repeat-timeout" in result.stderr
