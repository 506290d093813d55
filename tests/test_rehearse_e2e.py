"""The operator commands across computers, on a rehearsal of ``dragon`` (five computers, secure).

``msctl rehearse up dragon --link wifi --detach`` stands up hl-limb-01/02 and hl-wheel-01/02
(robot computers: their real CANopen backends against emulated drives) and ground1 (the
ground station), one network namespace each, linked through the userspace link emulator,
secured as the README says (``msctl net init`` on the ground station, its ``net/`` copied to
every computer, mutual TLS and access control); the ground station then runs ``msctl up
--all``. Every command below runs as a user would type it, through ``msctl rehearse exec
HOST -- ...``, on the computer it names. The rehearsal is the suite's shared one
(``conftest.DRAGON_REHEARSAL``): the presence and rejoin modules run on it next, and the last of
them takes it down, checking that no namespace, process or file is left.

Needs root (CI runs as root); skipped, saying so, without it.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from conftest import wait_until
from rehearse_rigs import GROUND, ROBOTS, ROOT_REHEARSAL, Stage

pytestmark = [
    pytest.mark.e2e,
    pytest.mark.timeout(900),
    ROOT_REHEARSAL,
]


@pytest.fixture(scope="module")
def stage(dragon: Stage) -> Stage:
    """The suite's shared rehearsal of dragon (conftest.DRAGON_REHEARSAL)."""
    return dragon


def health(stage: Stage, host: str = GROUND) -> tuple[int, dict[str, Any]]:
    done = stage.on(host, "health", "--once", "--json", "--timeout", "15")
    assert done.returncode in (0, 1), done.stderr
    return done.returncode, json.loads(done.stdout)


def all_ok(document: dict[str, Any]) -> bool:
    """Every item of every module OK (a rate may WARN on a loaded machine), but the computers'
    own CPU and memory: the five share this machine's two cores with the rest of the suite,
    so its load is not theirs."""
    return all(
        item["level"] == "OK" or (item["level"] == "WARN" and "/topics/" in item["name"])
        for row in document["modules"]
        for item in row["items"]
        if "/host/" not in item["name"]
    )


def test_up_made_five_computers_each_with_its_own_link(stage: Stage) -> None:
    document = stage.status()
    assert document["secure"] is True and document["emulator"] == "running"
    names = {c["name"]: c for c in document["computers"]}
    assert set(names) == {*ROBOTS.values(), GROUND}
    assert len({c["address"] for c in names.values()}) == 5
    for computer in names.values():
        assert computer["link"]["profile"] == "wifi"
        assert computer["link"]["up"]["packets"] > 0, computer  # the radio carried its traffic
        # An agent and a router at least, inside the computer's own namespace.
        commands = " ".join(p["command"] for p in computer["processes"])
        assert "msctl agent" in commands and "router" in commands, commands


def test_every_computer_has_its_own_host_name_and_home(stage: Stage) -> None:
    done = stage.msctl(
        "rehearse", "exec", "hl-limb-02", "--", "sh", "-c", 'hostname; echo "$MSCTL_HOME"'
    )
    assert done.returncode == 0, done.stderr
    name, home = done.stdout.split()
    assert name == "hl-limb-02"
    assert Path(home).name == "hl-limb-02" and Path(home).is_relative_to(stage.home)


def test_health_shows_every_module_ok_from_its_own_computer(stage: Stage) -> None:
    _code, document = wait_until(
        lambda: (r := health(stage)) and all_ok(r[1]) and r, timeout=120, what="every module OK"
    )
    assert document["assembly"] == "dragon"
    assert {row["name"]: row["host"] for row in document["modules"]} == ROBOTS
    assert [s["name"] for s in document["stations"]] == ["gc1"]


def test_ps_all_lists_every_computer_of_the_plan(stage: Stage) -> None:
    # A generous answer time: the five computers share two loaded cores.
    done = stage.on(GROUND, "ps", "--all", "--json", "--timeout", "30")
    assert done.returncode == 0, done.stderr
    document = json.loads(done.stdout)
    hosts = {c["host"] for c in document["components"]}
    assert hosts == {*ROBOTS.values(), GROUND}
    motors = {c["name"]: c for c in document["components"] if c["kind"] == "motor_interface"}
    assert {m["host"] for m in motors.values()} == set(ROBOTS.values())  # each on its robot
    assert all(m["state"] == "running" for m in motors.values()), motors


def test_estop_and_recover_reach_every_module_from_the_ground(stage: Stage) -> None:
    done = stage.on(GROUND, "estop")
    assert done.returncode == 0, done.stderr
    for module in ROBOTS:
        assert re.search(rf"^{module}\s+halted", done.stdout + done.stderr, re.M), done
    done = stage.on(GROUND, "recover")
    assert done.returncode == 0, done.stderr
    for module in ROBOTS:
        assert re.search(rf"^{module}\s+recovered", done.stdout + done.stderr, re.M), done


def test_logs_of_a_component_on_another_computer(stage: Stage) -> None:
    done = stage.on(GROUND, "logs", "limb2/motor_interface")
    assert done.returncode == 0, done.stderr
    # The real CANopen backend, on its robot, against emulated drives.
    assert "canopen" in done.stdout, done.stdout[-2000:]


def test_restart_of_a_component_on_another_computer(stage: Stage) -> None:
    def pid() -> int:
        listed = stage.on(GROUND, "ps", "--json", "--timeout", "30")
        assert listed.returncode in (0, 1), listed.stderr
        rows = {c["name"]: c for c in json.loads(listed.stdout)["components"]}
        return rows["wheel1/joint_manager"]["pid"]

    before = pid()
    done = stage.on(GROUND, "restart", "wheel1/joint_manager")
    assert done.returncode == 0, done.stderr
    assert "hl-wheel-01" in done.stderr
    wait_until(lambda: pid() not in (before, None), timeout=120, what="a new process")
    wait_until(lambda: all_ok(health(stage)[1]), timeout=120, what="healthy again")


def test_record_on_the_ground_station(stage: Stage) -> None:
    bag = stage.home / "ground-bag"
    recorder = stage.spawn(
        GROUND, "record", "/limb1/joint_states", "/wheel2/health", "-o", str(bag)
    )
    try:
        # limb1's joint_states alone (the radio sends it at 10 Hz; wheel2's health beside it
        # made a total over 50 with 49 of them).
        wait_until(
            lambda: (
                (bag / "metadata.yaml").exists()
                and _bag_messages(stage, bag, "/limb1/joint_states") > 50
            ),
            timeout=120,
            what="limb1's joint_states in the bag",
        )
    finally:
        recorder.send_signal(signal.SIGINT)
        _out, err = recorder.communicate(timeout=60)
    assert recorder.returncode == 0, err
    info = json.loads(stage.msctl("bag", "info", str(bag), "--json").stdout)
    topics = {t["name"]: t["count"] for t in info["topics"]}
    assert topics.get("/limb1/joint_states", 0) > 50, topics


def _bag_messages(stage: Stage, bag: Path, topic: str | None = None) -> int:
    """Messages in the bag so far (of ``topic`` alone, when given)."""
    done = stage.msctl("bag", "info", str(bag), "--json")
    if done.returncode != 0:
        return 0
    info = json.loads(done.stdout)
    if topic is None:
        return int(info.get("message_count", 0))
    return next((int(t["count"]) for t in info["topics"] if t["name"] == topic), 0)


def test_teleop_drives_joints_and_wheels_from_the_ground(stage: Stage) -> None:
    if shutil.which("tmux") is None:
        pytest.skip("tmux is not installed")
    session = f"rehearse-teleop-{os.getpid()}"
    command = (
        f"env -u COLUMNS -u LINES MSCTL_HOME={stage.home} {sys.executable} -m msctl rehearse "
        f"exec {GROUND} -- msctl teleop; echo EXITED $?; sleep 600"
    )
    # Each command must cross the radio and the robot router's access control to be seen
    # on the robot computer it commands.
    joint_set = stage.spawn(
        "hl-limb-01", "topic", "echo", "/limb1/joint_set", "--once", "--timeout", "240"
    )
    cmd_vel = stage.spawn("hl-wheel-01", "topic", "echo", "/cmd_vel", "--once", "--timeout", "240")
    subprocess.run(
        ["tmux", "new-session", "-d", "-s", session, "-x", "160", "-y", "40", command], check=True
    )

    def screen() -> str:
        return subprocess.run(
            ["tmux", "capture-pane", "-p", "-t", session], capture_output=True, text=True
        ).stdout

    def hold(key: str, watcher: subprocess.Popen[str]) -> str:
        """Press ``key`` as a held key repeats it, until ``watcher`` saw its message."""
        deadline = time.monotonic() + 90
        while watcher.poll() is None and time.monotonic() < deadline:
            subprocess.run(["tmux", "send-keys", "-t", session, key], check=True)
            time.sleep(0.05)
        out, err = watcher.communicate(timeout=60)
        assert watcher.returncode == 0, (err, screen())
        return out

    try:
        wait_until(lambda: "limb1" in screen(), timeout=120, what="the teleop screen")
        claims = wait_until(
            lambda: (
                (c := stage.on("hl-limb-01", "claims", "--json")).returncode == 0
                and json.loads(c.stdout)["claims"]
            ),
            timeout=60,
            what="the teleop's claims, seen on a robot computer",
        )
        assert "limb1" in {c["module"] for c in claims}
        assert all(c["holder"].endswith(f"@{GROUND}") for c in claims), claims
        assert "position" in hold("w", joint_set)  # joint mode: jog limb1's joint
        subprocess.run(["tmux", "send-keys", "-t", session, "3"], check=True)  # drive mode
        assert "linear" in hold("i", cmd_vel)
        subprocess.run(["tmux", "send-keys", "-t", session, "Escape"], check=True)
        wait_until(lambda: "EXITED" in screen(), timeout=60, what="teleop quits")
        assert "EXITED 0" in screen(), screen()
    finally:
        for watcher in (joint_set, cmd_vel):
            if watcher.poll() is None:
                watcher.kill()
        subprocess.run(["tmux", "kill-session", "-t", session], capture_output=True, check=False)


def _processes(stage: Stage) -> dict[str, tuple[int, str]]:
    """Component -> (pid, its process's last error), of every computer (``ps --all``)."""
    done = stage.on(GROUND, "ps", "--all", "--json", "--timeout", "30")
    assert done.returncode == 0, done.stderr
    return {
        c["name"]: (c["pid"], c.get("last_error") or "")
        for c in json.loads(done.stdout)["components"]
    }


def _link_back(stage: Stage, host: str) -> bool:
    link = next(c["link"] for c in stage.status()["computers"] if c["name"] == host)
    return not (link["up"]["outage"] or link["down"]["outage"])


#: Outages of the ground station's link in a row (the issue saw the second one do lasting
#: damage the first did not).
GROUND_OUTAGES = 2


def test_outages_of_the_ground_link_heal_by_themselves(stage: Stage) -> None:
    """The ground station's link down 5 s, twice (every robot unreachable at once): with no
    process restarted, an e-stop sent as the link returns reaches every module, commands
    reach the robots and their data the ground again, health is OK at the ground, and the
    recorder that ran through it all resumed by itself and accounts for each gap."""
    before = _processes(stage)
    bag = stage.home / "outage-bag"
    recorder = stage.spawn(
        GROUND, "record", "/limb1/joint_states", "/wheel2/joint_states", "-o", str(bag), "--json"
    )
    healed: list[float] = []
    try:
        wait_until(lambda: _bag_messages(stage, bag) > 100, timeout=120, what="messages in the bag")
        for _ in range(GROUND_OUTAGES):
            done = stage.msctl("rehearse", "link", GROUND, "--down", "5")
            assert done.returncode == 0, done.stderr
            wait_until(lambda: _link_back(stage, GROUND), timeout=60, what="the link back")
            back = time.monotonic()
            # At once: a halt that finds no route yet is sent again until its deadline.
            done = stage.on(GROUND, "estop", "--json", "--timeout", "10")
            assert done.returncode == 0, (done.stdout, done.stderr)
            acked = {m["module"] for m in json.loads(done.stdout)["modules"] if m["ok"]}
            assert acked == set(ROBOTS), done.stdout
            done = stage.on(GROUND, "recover", "--timeout", "10")
            assert done.returncode == 0, done.stderr
            # Ground -> robot: a command crosses the radio and the robot router's ACL.
            seen = stage.spawn(
                "hl-limb-01", "topic", "echo", "/limb1/joint_set", "--once", "--timeout", "120"
            )

            def published(seen: subprocess.Popen[str] = seen) -> bool:
                """Publish one command; whether the robot's echo has seen one (and exited)."""
                stage.on(
                    GROUND, "topic", "pub", "/limb1/joint_set", "sensor_msgs/msg/JointState",
                    "{name: [limb1_joint2], position: [0.0]}", "--once", "--fire-and-forget",
                )  # fmt: skip
                return seen.poll() is not None

            wait_until(published, timeout=120, what="a command from the ground seen on the robot")
            out, err = seen.communicate(timeout=150)
            assert seen.returncode == 0 and "limb1_joint2" in out, err
            # Robot -> ground: every module's health, from its own computer, OK again.
            wait_until(lambda: all_ok(health(stage)[1]), timeout=120, what="healthy again")
            healed.append(time.monotonic() - back)
    finally:
        recorder.send_signal(signal.SIGINT)
        out, err = recorder.communicate(timeout=60)
    print(
        f"\nhealthy at the ground again {', '.join(f'{s:.1f}' for s in healed)} s after "
        "each outage's end (commands of the test included)"
    )
    assert recorder.returncode == 0, err  # receiving again at the end
    summary = json.loads(out)
    gaps, thinned = summary["gaps"], summary["thinned"]
    for topic in ("/limb1/joint_states", "/wheel2/joint_states"):
        mine = [g for g in gaps if g["topic"] == topic]
        # One gap per outage at least (a flapping return may split one), each accounted for.
        assert len(mine) >= GROUND_OUTAGES, gaps
        assert all(g["end_ns"] and g["seconds"] >= 1.0 for g in mine), mine
        # Sampled at 10 Hz on the (secure) radio: its sequence numbers jump by design, so
        # what an outage swallowed cannot be told, and is not made up.
        assert thinned[topic] == 10.0, thinned
        assert all(g["lost"] is None for g in mine), mine
    assert "back: /limb1/joint_states" in err
    after = _processes(stage)
    # Nothing was restarted, by hand or otherwise (the last error says why, if it was).
    restarted = {n: after[n] for n in before if after.get(n, (0, ""))[0] != before[n][0]}
    assert not restarted and after.keys() == before.keys(), restarted


def test_an_outage_makes_ps_all_name_the_computer_and_exit_1(stage: Stage) -> None:
    done = stage.msctl("rehearse", "link", "hl-wheel-02", "--down", "0")
    assert done.returncode == 0, done.stderr
    try:
        listed = wait_until(
            lambda: (
                (r := stage.on(GROUND, "ps", "--all", "--json", "--timeout", "3"))
                and r.returncode == 1
                and r
            ),
            timeout=60,
            what="ps --all noticing the outage",
        )
        assert "hl-wheel-02" in listed.stderr
        status = stage.status()
        link = next(c["link"] for c in status["computers"] if c["name"] == "hl-wheel-02")
        assert link["up"]["outage"] or link["down"]["outage"], link
    finally:
        stage.msctl("rehearse", "link", "hl-wheel-02", "--up")
    wait_until(
        lambda: stage.on(GROUND, "ps", "--all", "--json", "--timeout", "30").returncode == 0,
        timeout=120,
        what="every computer answering again",
    )
