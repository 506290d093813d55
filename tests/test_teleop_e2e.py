"""``msctl teleop`` for real: the command in a tmux terminal against a simulated Dragon
(``msctl up dragon --detach`` in its own MSCTL_HOME, behind its own router).

Keys go in through tmux; an observer on its own session watches the wire (``joint_set`` and
``cmd_vel``) and the simulated joint's ``joint_read``. ``msctl down`` at the end.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import threading
from collections.abc import Iterator
from typing import Any

import pytest
from conftest import wait_until
from running import Up

from components.comm.node import Node
from components.comm.session import open_session
from components.messages import JOINT_STATE, joint_samples
from msctl.teleop.wire import TWIST

# Real msctl processes and a simulator: on a loaded two-core machine each step takes long.
pytestmark = [
    pytest.mark.e2e,
    pytest.mark.timeout(900),
    pytest.mark.skipif(shutil.which("tmux") is None, reason="tmux is not installed"),
]


@pytest.fixture(scope="module")
def dragon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Up]:
    up = Up(tmp_path_factory.mktemp("teleop_dragon"), "dragon")
    try:
        yield up
    finally:
        up.down()


class Observer:
    """The wire, from its own session: commands and the joint's readings."""

    def __init__(self, up: Up) -> None:
        self.session = open_session(up.settings())
        self.node = Node(self.session, "teleop_observer")
        self.lock = threading.Lock()
        self.joint_set: list[Any] = []
        self.cmd_vel: list[Any] = []
        self.position: float | None = None
        self.node.subscription("/limb1/joint_set", JOINT_STATE, self._on_set)
        self.node.subscription("/cmd_vel", TWIST, self._on_twist)
        self.node.subscription("/limb1/joint_read", JOINT_STATE, self._on_read)

    def _on_set(self, message: Any) -> None:
        with self.lock:
            self.joint_set.extend(joint_samples(message))

    def _on_twist(self, message: Any) -> None:
        with self.lock:
            self.cmd_vel.append(message)

    def _on_read(self, message: Any) -> None:
        for sample in joint_samples(message):
            if sample.name == "limb1_joint1" and sample.position is not None:
                with self.lock:
                    self.position = sample.position

    def close(self) -> None:
        self.node.close()
        self.session.close()


def _tmux(*args: str) -> str:
    result = subprocess.run(
        ["tmux", *args], capture_output=True, text=True, timeout=30.0, check=True
    )
    return result.stdout


def test_the_real_teleop_in_tmux_jogs_drives_estops_and_quits(dragon: Up) -> None:
    observer = Observer(dragon)
    session = f"msctl-teleop-{os.getpid()}"
    env = " ".join(
        f"{k}={v}"
        for k, v in dragon.env.items()
        if k.startswith("MSCTL_") or k in ("PYTHONPATH", "CYDR_CACHE_DIR")
    )
    command = f"env {env} {sys.executable} -m msctl teleop --module limb1 --module wheel1"
    _tmux("new-session", "-d", "-s", session, "-x", "150", "-y", "45", command)

    def screen() -> str:
        return _tmux("capture-pane", "-p", "-t", session)

    def keys(*names: str) -> None:
        _tmux("send-keys", "-t", session, *names)

    try:
        text = wait_until(
            lambda: (s := screen()) and "mode JOINT" in s and "limb1_joint1" in s and s,
            timeout=240.0,
            what="the teleop screen in tmux",
        )
        assert "modules: limb1, wheel1" in text
        wait_until(lambda: observer.position is not None, timeout=120.0, what="limb1's joint1")
        start = observer.position
        # Joint mode: w jogs limb1_joint1 up while the key repeats; tmux sends a burst.
        for _ in range(10):
            keys("w")
        wait_until(lambda: observer.joint_set, timeout=120.0, what="joint_set from the teleop")
        wait_until(lambda: "stopped (deadman)" in screen(), timeout=120.0, what="the stop")
        wait_until(
            lambda: observer.position > start + 0.005,
            timeout=120.0,
            what="the simulated joint to move",
        )
        assert {s.name for s in observer.joint_set} == {"limb1_joint1"}
        # Drive mode: a Twist on the Dragon's cmd_vel, then exactly one zero Twist.
        keys("3")
        wait_until(lambda: "mode DRIVE" in screen(), timeout=60.0, what="drive mode")
        keys("i")
        wait_until(lambda: observer.cmd_vel, timeout=120.0, what="a Twist on /cmd_vel")
        wait_until(lambda: "stopped (deadman)" in screen(), timeout=120.0, what="drive's stop")
        wait_until(
            lambda: observer.cmd_vel[-1].linear.x == 0.0, timeout=60.0, what="the zero Twist"
        )
        zeros = [m for m in observer.cmd_vel if m.linear.x == 0.0 and m.angular.z == 0.0]
        assert len(zeros) == 1 and observer.cmd_vel[0].linear.x == pytest.approx(0.2)
        # Space halts the commanded modules; ctrl+r recovers them.
        keys("Space")
        wait_until(lambda: "E-STOPPED" in screen(), timeout=60.0, what="the e-stop banner")
        wait_until(lambda: "halt: limb1 ok" in screen(), timeout=60.0, what="the halts answered")
        keys("C-r")
        wait_until(lambda: "recover: limb1 ok" in screen(), timeout=60.0, what="recovered")
        # Esc stops and quits: the tmux session ends with the process.
        keys("Escape")
        wait_until(
            lambda: (
                subprocess.run(
                    ["tmux", "has-session", "-t", session], capture_output=True, check=False
                ).returncode
                != 0
            ),
            timeout=60.0,
            what="msctl teleop to quit",
        )
    finally:
        subprocess.run(["tmux", "kill-session", "-t", session], capture_output=True, check=False)
        observer.close()


def test_a_second_teleop_is_refused_then_takes_over_and_the_first_screen_says_so(
    dragon: Up,
) -> None:
    first = f"msctl-teleop-a-{os.getpid()}"
    second = f"msctl-teleop-b-{os.getpid()}"
    env = " ".join(
        f"{k}={v}"
        for k, v in dragon.env.items()
        if k.startswith("MSCTL_") or k in ("PYTHONPATH", "CYDR_CACHE_DIR")
    )
    command = f"env {env} {sys.executable} -m msctl teleop --module limb1"

    def screen(session: str) -> str:
        return _tmux("capture-pane", "-p", "-t", session)

    _tmux("new-session", "-d", "-s", first, "-x", "150", "-y", "45", command)
    try:
        wait_until(
            lambda: "claims: limb1 (held by" in screen(first),
            timeout=240.0,
            what="the first teleop holding limb1",
        )
        # Without --take: refused before any screen, naming the holder and since when.
        refused = dragon.msctl("teleop", "--module", "limb1", timeout=240.0)
        assert refused.returncode == 1, refused.stderr
        assert "module limb1 is claimed by " in refused.stderr
        assert "(node /msctl_teleop_" in refused.stderr and " since " in refused.stderr
        assert "--take" in refused.stderr
        # With --take: the first screen says so at once.
        _tmux("new-session", "-d", "-s", second, "-x", "150", "-y", "45", command + " --take")
        wait_until(
            lambda: "claims: limb1 (held by" in screen(second),
            timeout=240.0,
            what="the second teleop holding limb1",
        )
        wait_until(
            lambda: "limb1 TAKEN by" in screen(first),
            timeout=60.0,
            what="the first screen saying limb1 was taken",
        )
        _tmux("send-keys", "-t", first, "w")
        wait_until(
            lambda: "limb1 was TAKEN OVER" in screen(first), timeout=60.0, what="keys refused"
        )
        for session in (second, first):
            _tmux("send-keys", "-t", session, "Escape")
        wait_until(
            lambda: all(
                subprocess.run(
                    ["tmux", "has-session", "-t", s], capture_output=True, check=False
                ).returncode
                != 0
                for s in (first, second)
            ),
            timeout=60.0,
            what="both teleops to quit",
        )
    finally:
        for session in (first, second):
            subprocess.run(
                ["tmux", "kill-session", "-t", session], capture_output=True, check=False
            )
