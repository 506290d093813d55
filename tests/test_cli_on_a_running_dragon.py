"""What the topic, service, logs, run and assemble commands say on a live graph: a mistyped
type, topic, service, component, template or unit; a service with no server; an example run;
a process log (issue 18, points 1-3, 7, 13, 14, 16, 19).

End to end: real ``msctl`` subprocesses against one running simulated Dragon shared by the
module (``msctl up dragon --detach``, its own router on a free loopback port), so the graph
the commands read is the real one: the liveliness tokens of its components. Each test names
the point it keeps fixed.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import free_port, wait_until
from running import ROOT, Up

from components.comm import Node
from components.comm.graph import snapshot
from components.comm.liveliness import EntityKind
from components.comm.session import open_session

# The first test also waits for the Dragon to come up (50 s measured at load 25).
pytestmark = [pytest.mark.e2e, pytest.mark.timeout(600)]

JOINTS = "sensor_msgs/msg/JointState"
STRING = "std_msgs/msg/String"
TRIGGER = "std_srvs/srv/Trigger"


@pytest.fixture(scope="module")
def dragon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Up]:
    """One simulated Dragon for the whole module (starting one costs 10-50 s)."""
    running = Up(tmp_path_factory.mktemp("newcomer") / "home", "dragon")
    try:
        yield running
    finally:
        running.down()


@pytest.fixture
def probe(dragon: Up) -> Iterator[Node]:
    """A node of this process, ``/newcomer/probe``, on the Dragon's router."""
    session = open_session(dragon.settings())
    node = Node(session, "probe", "/newcomer")
    try:
        yield node
    finally:
        node.close()
        session.close()


def error_line(stderr: str) -> str:
    """The one line an error prints (failing the test if it printed more)."""
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1, stderr
    assert lines[0].startswith("error: "), stderr
    return lines[0]


def no_router_env(tmp_path: Path) -> dict[str, str]:
    """An environment whose endpoint no router listens on."""
    return {
        **os.environ,
        "MSCTL_HOME": str(tmp_path / "home"),
        "MSCTL_ZENOH_CONNECT": f"tcp/127.0.0.1:{free_port()}",
        "MSCTL_ZENOH_LISTEN": "tcp/127.0.0.1:0",
        "MSCTL_ZENOH_MULTICAST": "0",
        "PYTHONPATH": str(ROOT),
    }


def msctl(*args: str, env: dict[str, str], timeout: float = 120.0) -> subprocess.CompletedProcess:
    """One ``msctl`` command in a subprocess."""
    return subprocess.run(
        [sys.executable, "-m", "msctl", *args],
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=ROOT,
        check=False,
    )


# --------------------------------------------------------------------------- 1, 2, 3: types
def test_a_mistyped_type_is_called_a_typo_next_to_the_type_the_topic_carries(
    dragon: Up,
) -> None:
    """Point 1: not "a type msctl does not know — register its .msg definition"."""
    result = dragon.msctl("topic", "echo", "/limb1/joint_read", "std_msgs/msg/Strin", "--once")
    assert result.returncode == 4, result.stderr
    line = error_line(result.stderr)
    assert f"topic /limb1/joint_read carries {JOINTS} (/limb1/joint_manager)" in line
    assert "did you mean 'std_msgs/msg/String'?" in line
    assert "register its .msg definition" not in line


def test_echo_of_another_type_names_the_type_its_publisher_carries(dragon: Up) -> None:
    """Point 2: one line naming the publisher's type, no dropped-sample line, no timeout."""
    result = dragon.msctl("topic", "echo", "/limb1/joint_read", STRING, "--timeout", "3")
    assert result.returncode == 2, result.stderr
    line = error_line(result.stderr)
    assert f"carries {JOINTS} (/limb1/joint_manager), not {STRING}" in line
    assert "no message on" not in line


def test_echo_waiting_when_a_publisher_of_another_type_starts_says_its_type(
    dragon: Up, probe: Node
) -> None:
    """Point 2, the other order: the echo listens first (nothing on the topic to check
    against), then a JointState publisher starts. It said a dropped sample with two type
    hashes, then 'no message within 60 s'."""
    echo = subprocess.Popen(
        [sys.executable, "-m", "msctl", "topic", "echo", "/newcomer/late", STRING],
        env=dragon.env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    try:

        def echo_listens() -> bool:
            return any(
                e.kind is EntityKind.SUBSCRIPTION
                and e.topic == "/newcomer/late"
                and e.node_name.startswith("msctl_echo_")
                for e in snapshot(probe.session, probe.domain, timeout=0.5).entities()
            )

        wait_until(
            lambda: echo.poll() is not None or echo_listens(), 120.0, "the echo's subscription"
        )
        assert echo.poll() is None, echo.communicate()
        probe.publisher("/newcomer/late", JOINTS)
        _, stderr = echo.communicate(timeout=120.0)
    finally:
        if echo.poll() is None:
            echo.kill()
            echo.communicate()
    assert echo.returncode == 2, stderr
    line = error_line(stderr)
    assert f"topic /newcomer/late carries {JOINTS} (/newcomer/probe), not {STRING}" in line
    assert "RIHS01_" not in stderr and "dropped sample" not in stderr


def test_pub_onto_a_joint_state_topic_is_refused_naming_its_publisher_unless_forced(
    dragon: Up,
) -> None:
    """Point 3: refused, naming the publishers' type (not the subscribers'); --force does."""
    args = ("topic", "pub", "/limb1/joint_read", STRING, "{data: x}", "--once")
    refused = dragon.msctl(*args)
    assert refused.returncode == 2, refused.stderr
    line = error_line(refused.stderr)
    assert f"is published as {JOINTS} (/limb1/joint_manager), not {STRING}" in line
    assert "--force" in line and "publishing" not in refused.stderr
    forced = dragon.msctl(*args, "--force")
    # Published, and honest about it: nothing subscribes to a String there.
    assert forced.returncode == 1, forced.stderr
    assert "publishing #1 on /limb1/joint_read" in forced.stderr
    assert "no subscriber matched: none delivered" in forced.stderr


# --------------------------------------------------------------------------- 7: nearest names
def test_a_mistyped_topic_or_service_gets_the_nearest_names(dragon: Up) -> None:
    """Point 7, the graph's names: a topic or service name with a typo."""
    echo = dragon.msctl("topic", "echo", "/limb1/joint_reed", "--once")
    assert echo.returncode == 4, echo.stderr
    assert "did you mean '/limb1/joint_read'?" in error_line(echo.stderr)
    typed = dragon.msctl("topic", "echo", "/limb1/joint_reed", JOINTS, "--timeout", "1")
    assert typed.returncode == 5, typed.stderr
    line = error_line(typed.stderr)
    assert "nothing publishes it" in line and "did you mean '/limb1/joint_read'?" in line
    call = dragon.msctl("service", "call", "/limb1/hatl")
    assert call.returncode == 4, call.stderr
    assert "did you mean '/limb1/halt'?" in error_line(call.stderr)
    typed_call = dragon.msctl("service", "call", "/limb1/hatl", TRIGGER)
    assert typed_call.returncode == 5, typed_call.stderr
    assert "did you mean '/limb1/halt'?" in error_line(typed_call.stderr)


def test_logs_and_logs_follow_word_a_mistyped_component_the_same(
    dragon: Up, tmp_path: Path
) -> None:
    """Point 7: ``logs`` and ``logs -f`` say the same, with a router or without one."""
    with_router = [dragon.msctl("logs", *f, "limb1/joint_managr") for f in ((), ("-f",))]
    # The same computer's last run, its router gone (after `msctl down`, say).
    alone = {**no_router_env(tmp_path), "MSCTL_HOME": str(dragon.home)}
    without = [msctl("logs", *f, "limb1/joint_managr", env=alone) for f in ((), ("-f",))]
    lines = set()
    for result in (*with_router, *without):
        assert result.returncode == 4, result.stderr
        lines.add(error_line(result.stderr))
    assert len(lines) == 1, lines
    (line,) = lines
    assert "no log for 'limb1/joint_managr' on this computer" in line
    assert "did you mean 'limb1/joint_manager'?" in line


def test_a_mistyped_template_unit_or_slot_gets_the_nearest_names(tmp_path: Path) -> None:
    """Point 7, the assembler's names, from the command line."""
    env = no_router_env(tmp_path)
    for args, near in (
        (("assemble", "dragn"), "did you mean 'dragon'?"),
        (("assemble", "dragon", "--use", "limb1=hlv1-limb-3"), "did you mean 'hlv1-limb-03'?"),
        (("assemble", "dragon", "--use", "limb=hlv1-limb-03"), "did you mean 'limb1' or 'limb2'?"),
    ):
        result = msctl(*args, env=env)
        assert result.returncode in (2, 4), result.stderr
        assert near in error_line(result.stderr), args


# --------------------------------------------------------------------------- 13, 14: services
def test_service_call_reads_its_input_before_it_looks_for_a_router(tmp_path: Path) -> None:
    """Point 13: bad VALUES is exit 2 naming the YAML, even with no router at all (it went to
    the network first: exit 3 after the router wait)."""
    result = msctl("service", "call", "/x", TRIGGER, "{x", env=no_router_env(tmp_path))
    assert result.returncode == 2, result.stderr
    line = error_line(result.stderr)
    assert "VALUES is not valid YAML" in line and "router" not in line


def test_service_call_with_no_server_says_what_happened(dragon: Up) -> None:
    """Point 14: it claimed a 3 s wait when the query had ended at once. A long --timeout
    tells the two apart (the command's own start-up is in the time measured here)."""
    started = time.monotonic()
    result = dragon.msctl("service", "call", "/nope", TRIGGER, "--timeout", "30")
    elapsed = time.monotonic() - started
    assert result.returncode == 5, result.stderr
    line = error_line(result.stderr)
    assert "/nope" in line
    if "within 30 s" in line:
        assert elapsed >= 30.0, line  # a claim of waiting 30 s must be true
    else:
        assert "no server of /nope" in line and "ended after" in line, line


# --------------------------------------------------------------------------- 16: example runs
def test_an_example_run_prints_no_resync_noise(dragon: Up) -> None:
    """Point 16: every motion's start printed 'last command and measurement differ by more
    than delta=0.1; resynchronized from the measurement' as a warning."""
    result = dragon.msctl("run", "examples/limb_wave.py", "limb1", "1", timeout=300.0)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "done waving" in result.stdout
    assert "resynchronized" not in result.stderr, result.stderr


# --------------------------------------------------------------------------- 19: logs
def test_a_process_log_marks_its_run_and_stamps_every_line(dragon: Up) -> None:
    """Point 19, end to end: the run's first line and every line after it have a time."""
    result = dragon.msctl("logs", "limb1/joint_manager", "-n", "1000")
    assert result.returncode == 0, result.stderr
    lines = [line for line in result.stdout.splitlines() if line.strip()]
    marks = [line for line in lines if "===== msctl up dragon on test-laptop started" in line]
    assert len(marks) == 1, lines
    stamped = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d[.,]\d{3} ")
    assert all(stamped.match(line) for line in lines), lines
