"""The radio budget on a rehearsal of ``dragon`` (five computers, secure, one rehearsal for
the module): the routers' generated configs downsample each robot's high-rate telemetry on
its radio link only, keep the link within 250 kbit/s per robot each way even with a recorder
of every topic on the ground, and keep the e-stop and health working on a 256 kbit/s link
losing 20 % of its packets; a link as slow as the Moon's, its two ends named ``deep-space``
in the template, is not dropped by its lease.

Every command runs as a user would type it, on the computer it names (``msctl rehearse exec
HOST -- ...``). Byte counts are the link emulator's (``msctl rehearse status --json``).
Needs root (CI runs as root); skipped, saying so, without it.
"""

from __future__ import annotations

import json
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from typing import Any

import pytest
from conftest import wait_until
from rehearse_rigs import GROUND, ROBOTS, ROOT_REHEARSAL, Stage, rehearsed

from msctl.assembler.data import assemblies_dir

pytestmark = [pytest.mark.e2e, pytest.mark.timeout(1200), ROOT_REHEARSAL]

#: The issue's target: at most this much per robot link, each way, kbit/s.
BUDGET_KBIT = 250.0
#: The template's default rate of joint_states across a radio link (msctl.net.radio).
GROUND_HZ = 10.0

#: Counts a topic's samples on the computer it runs on, through that computer's own
#: session (a TLS client with the operator's identity on the ground station, a loopback
#: client on a robot computer): how many arrived between the first and the last.
COUNT = textwrap.dedent(
    """
    import json, sys, threading, time
    from components.comm.session import SessionSettings, open_session
    topic, seconds = sys.argv[1], float(sys.argv[2])
    arrivals = []
    lock = threading.Lock()
    def arrived(_sample):
        with lock:
            arrivals.append(time.monotonic())
    session = open_session(SessionSettings.joining())
    try:
        subscriber = session.declare_subscriber(f"0/{topic.strip('/')}/**", arrived)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            with lock:
                if arrivals and arrivals[-1] - arrivals[0] >= seconds:
                    break
            time.sleep(0.05)
        subscriber.undeclare()
    finally:
        session.close()
    with lock:
        span = arrivals[-1] - arrivals[0] if len(arrivals) > 1 else 0.0
        print(json.dumps({"count": len(arrivals), "span_s": span}))
    """
)


#: The computers at the two ends of the link switched to the Moon's (deep-space class).
MOON_ENDS = (ROBOTS["wheel2"], GROUND)


@pytest.fixture(scope="module")
def stage(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stage]:
    """A dragon rehearsal whose template names the two ends of the link the Moon test slows
    down as ``deep-space`` (as a user would for that link); the rest is radio."""
    root = tmp_path_factory.mktemp("budget")
    templates = root / "assemblies"
    shutil.copytree(assemblies_dir(), templates, ignore=shutil.ignore_patterns("__pycache__"))
    dragon = templates / "dragon.toml"
    ends = "".join(f'{host} = "deep-space"\n' for host in MOON_ENDS)
    dragon.write_text(dragon.read_text() + f"\n[network.links]\n{ends}")
    stage = Stage(root / "home", env={"MSCTL_ASSEMBLIES_DIR": str(templates)})
    stage.home.mkdir()
    with rehearsed(stage, timeout=900) as stage:
        wait_until(lambda: health_shows_every_module(stage), 300, "every module OK at the ground")
        yield stage


def health(stage: Stage) -> dict[str, Any] | None:
    done = stage.on(GROUND, "health", "--once", "--json", "--timeout", "20")
    try:
        return json.loads(done.stdout)
    except ValueError:
        return None


def health_shows_every_module(stage: Stage) -> bool:
    """Every module's own health reached the ground and says OK (a topic's rate may WARN, and
    the computers' CPU and memory are left aside: the five share two loaded cores)."""
    document = health(stage)
    if document is None or {row["name"] for row in document["modules"]} != set(ROBOTS):
        return False
    return all(
        row["items"]
        and all(
            item["level"] == "OK" or (item["level"] == "WARN" and "/topics/" in item["name"])
            for item in row["items"]
            if "/host/" not in item["name"]
        )
        for row in document["modules"]
    )


def link_bytes(stage: Stage) -> tuple[float, dict[str, dict[str, int]]]:
    """When (the middle of the call) and each computer's link counters, bytes each way."""
    before = time.monotonic()
    document = stage.status()
    when = (before + time.monotonic()) / 2
    return when, {
        c["name"]: {side: c["link"][side]["bytes"] for side in ("up", "down")}
        for c in document["computers"]
    }


def robot_rates(stage: Stage, seconds: float) -> dict[str, dict[str, float]]:
    """Each robot link's kbit/s each way over about ``seconds``."""
    start, first = link_bytes(stage)
    time.sleep(seconds)  # the window a rate is measured over, not a wait for an event
    end, last = link_bytes(stage)
    return {
        host: {
            side: (last[host][side] - first[host][side]) * 8 / 1000 / (end - start)
            for side in ("up", "down")
        }
        for host in ROBOTS.values()
    }


def count(stage: Stage, host: str, topic: str, seconds: float) -> subprocess.Popen[str]:
    return stage.start(host, sys.executable, "-c", COUNT, topic, str(seconds))


def counted(process: subprocess.Popen[str]) -> dict[str, float]:
    out, err = process.communicate(timeout=120)
    assert process.returncode == 0, err[-2000:]
    return json.loads(out.strip().splitlines()[-1])


def estop_acked_by_every_module(stage: Stage, within_s: float = 2.0) -> None:
    done = stage.on(GROUND, "estop", "--timeout", f"{within_s:g}", timeout=120)
    said = done.stdout + done.stderr
    assert done.returncode == 0, said
    for module in ROBOTS:
        assert re.search(rf"^{module}\s+halted", said, re.M), said
    # Recover is asked again until every module took it: the next test needs them running
    # (a recover whose route lapsed on this link is another part's concern, not the budget's).
    wait_until(
        lambda: stage.on(GROUND, "recover", timeout=120).returncode == 0, 120, "every recover"
    )


def test_joint_states_cross_at_the_templates_rate_and_stay_whole_on_the_robot(
    stage: Stage,
) -> None:
    on_robot = count(stage, ROBOTS["limb1"], "/limb1/joint_states", 10)
    on_ground = count(stage, GROUND, "/limb1/joint_states", 10)
    robot, ground = counted(on_robot), counted(on_ground)
    # At most 10 a second reached the ground (one more at each end of its window) ...
    assert 1 < ground["count"] <= GROUND_HZ * ground["span_s"] + 2, ground
    # ... while the robot's own components see the motor loop's rate: several times that.
    robot_hz = (robot["count"] - 1) / robot["span_s"]
    ground_hz = (ground["count"] - 1) / ground["span_s"]
    assert robot_hz > 3 * ground_hz, (robot, ground)


def test_each_robot_link_stays_within_its_budget_with_every_topic_recorded_on_the_ground(
    stage: Stage,
) -> None:
    at_rest = robot_rates(stage, 10)
    recorder = stage.spawn(GROUND, "record", "--all", "-o", str(stage.home / "everything"))
    try:
        # Recording: the recorder subscribes to every topic, so each robot's telemetry
        # crosses its link (before the budget, 100 Hz joint_states of every module did).
        wait_until(
            lambda: (stage.home / "everything").exists() or recorder.poll() is not None,
            60,
            "the recorder's bag",
        )
        assert recorder.poll() is None, recorder.communicate()[1][-2000:]
        recording = robot_rates(stage, 15)
    finally:
        recorder.send_signal(signal.SIGINT)
        try:
            recorder.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            recorder.kill()
            recorder.communicate()
    for rates in (at_rest, recording):
        for host, rate in rates.items():
            assert rate["up"] < BUDGET_KBIT and rate["down"] < BUDGET_KBIT, (host, rates)


def test_estop_and_health_get_through_256_kbits_losing_a_fifth_of_the_packets(
    stage: Stage,
) -> None:
    changed = stage.msctl("rehearse", "link", GROUND, "--profile", "degraded")
    assert changed.returncode == 0, changed.stderr
    try:
        # Every module acknowledges, within 5 s: a TCP stream losing a fifth of its packets
        # backs its retransmissions off (0.2, 0.4, 0.8 s ...), and one halt in a dozen took
        # over the 2 s default on a loaded CI run (the p99 < 1 s is bench/rehearse.py's
        # to measure, not a pass/fail bound for a shared machine).
        for _ in range(3):
            estop_acked_by_every_module(stage, within_s=5.0)
        # Each module's health keeps reaching the ground (at its 1 Hz, late at times: the
        # ground's view calls a module STALE after 2.5 s without it, which a TCP stream
        # losing a fifth of its packets exceeds now and then).
        counting = {m: count(stage, GROUND, f"/{m}/health", 5) for m in ROBOTS}
        for module, process in counting.items():
            arrived = counted(process)
            assert arrived["count"] >= 3 and arrived["span_s"] >= 5, (module, arrived)
    finally:
        changed = stage.msctl("rehearse", "link", GROUND, "--profile", "wifi")
        assert changed.returncode == 0, changed.stderr


def established_links(stage: Stage, port: int = 7448) -> set[str]:
    """The TCP connections of ground1's router's TLS port, as ``peer:port`` (one per robot
    router linked: a new one means the link was dropped and opened again)."""
    done = stage.run(GROUND, "ss", "-Htn", "state", "established", f"( sport = :{port} )")
    assert done.returncode == 0, done.stderr
    return {line.split()[-1] for line in done.stdout.splitlines() if line.strip()}


def test_a_link_as_slow_as_the_moons_is_not_dropped_by_its_lease(stage: Stage) -> None:
    # With radio's 5 s lease this link was closed and opened again every 20-60 s: TCP's
    # retransmissions over a 2.56 s round trip hold the stream back longer than that. Both
    # ends are deep-space in this template (a 30 s lease).
    robot = ROBOTS["wheel2"]
    address = next(
        c["address"].split("/")[0] for c in stage.status()["computers"] if c["name"] == robot
    )

    def link() -> set[str]:
        return {peer for peer in established_links(stage) if peer.startswith(f"{address}:")}

    changed = stage.msctl("rehearse", "link", robot, "--profile", "earth-moon")
    assert changed.returncode == 0, changed.stderr
    try:
        # The switch itself is no field condition (a link does not jump from 5 ms to 1.28 s):
        # the link is measured once it runs at the Moon's delay, one connection for 15 s.
        readings: list[set[str]] = []

        def settled() -> bool:
            readings.append(link())
            time.sleep(15)  # the span one connection must last to count as settled
            readings.append(link())
            return len(readings[-1]) == 1 and readings[-1] == readings[-2]

        wait_until(settled, 300, "the link at the Moon's delay")
        before = readings[-1]
        time.sleep(45)  # the window over which the link must hold, not a wait for an event
        after = link()
    finally:
        changed = stage.msctl("rehearse", "link", robot, "--profile", "wifi")
        assert changed.returncode == 0, changed.stderr
    assert after == before, (before, after, readings)
