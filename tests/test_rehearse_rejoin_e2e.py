"""A robot computer that reboots rejoins by itself, on a rehearsal of ``dragon`` (issue 31, item 5).

``msctl rehearse up dragon --link wifi --detach`` stands up hl-limb-01/02, hl-wheel-01/02 and
ground1 (secure, as the field runs) and runs ``msctl up --all`` on ground1. Every agent then
keeps what it was asked on disk. ``msctl rehearse reboot hl-wheel-02`` kills every process of
that computer at once (a power cut) and starts its agent again, as systemd does at boot; with
no other command, the ground must see wheel2 healthy again, ``ps --all`` list its part running,
and the alarms say that hl-wheel-02 came back and rejoined. The time from the agent's start to
wheel2 healthy at the ground is printed (the target is 10 s). After ``down --all``, a reboot
brings nothing back; a desired state cut short is refused and shown at the ground, not acted on.

Needs root (CI runs as root); skipped, saying so, without it.
"""

from __future__ import annotations

import json
import sys
import threading
from pathlib import Path
from typing import Any

import psutil
import pytest
from conftest import wait_until
from rehearse_rigs import GROUND, ROBOTS, ROOT_REHEARSAL, Stage

from msctl.launcher import desired
from msctl.rehearse.computers import namespaces
from msctl.rehearse.rehearsal import namespace_prefix

pytestmark = [pytest.mark.e2e, pytest.mark.timeout(900), ROOT_REHEARSAL]

#: The computer rebooted, and its module.
REBOOTED, MODULE = "hl-wheel-02", "wheel2"
PROBE = str(Path(__file__).with_name("rejoin_probe.py"))


@pytest.fixture(scope="module")
def stage(dragon: Stage) -> Stage:
    """The suite's shared rehearsal of dragon (conftest.DRAGON_REHEARSAL)."""
    return dragon


class Probe:
    """``rejoin_probe.py watch MODULE`` on the ground station, its lines read as they come."""

    def __init__(self, stage: Stage, module: str) -> None:
        self.process = stage.start(GROUND, sys.executable, PROBE, "watch", module)
        self.lines: list[dict[str, Any]] = []
        self._lock = threading.Lock()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            try:
                record = json.loads(line)
            except ValueError:
                continue
            with self._lock:
                self.lines.append(record)

    def seen(self) -> list[dict[str, Any]]:
        """Every line so far."""
        with self._lock:
            return list(self.lines)

    def levels(self) -> list[dict[str, Any]]:
        """The row's healthy/not transitions so far."""
        return [line for line in self.seen() if "healthy" in line]

    def alarms(self) -> list[dict[str, Any]]:
        """The board's alarms so far."""
        return [line["alarm"] for line in self.seen() if "alarm" in line]

    def close(self) -> str:
        """Stop it; its error output (for messages)."""
        self.process.kill()
        _, err = self.process.communicate(timeout=30)
        return err[-3000:]


class Watch(Probe):
    """``msctl health --watch --json`` on the ground station, its alarm lines read as they come."""

    def __init__(self, stage: Stage) -> None:
        self.process = stage.spawn(GROUND, "health", "--watch", "--json")
        self.lines = []
        self._lock = threading.Lock()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def alarms(self) -> list[dict[str, Any]]:
        """The alarms it printed so far (one JSON object a line)."""
        return [line for line in self.seen() if "item" in line]


#: The last `health --once` document, for the message of a wait that ran out.
LAST_HEALTH: list[dict[str, Any]] = [{}]


def health(stage: Stage) -> tuple[int, dict[str, Any]]:
    done = stage.on(GROUND, "health", "--once", "--json", "--timeout", "15")
    assert done.returncode in (0, 1), done.stderr
    LAST_HEALTH[0] = json.loads(done.stdout)
    return done.returncode, LAST_HEALTH[0]


def not_ok() -> list[str]:
    """What kept the last `health --once` from every module OK (for failure messages)."""
    return [
        f"{item['name']}: {item['level']} {item['message']}"
        for row in LAST_HEALTH[0].get("modules", [])
        for item in row["items"]
        if item["level"] != "OK" and "/host/" not in item["name"]
    ]


def module_ok(document: dict[str, Any], module: str) -> bool:
    """Every item of ``module`` OK (a rate may WARN on a loaded machine), but its computer's
    own CPU and memory, whose load is the whole test machine's."""
    row = next(r for r in document["modules"] if r["name"] == module)
    return all(
        item["level"] == "OK" or (item["level"] == "WARN" and "/topics/" in item["name"])
        for item in row["items"]
        if "/host/" not in item["name"]
    )


def rejoined_and_heard(document: dict[str, Any]) -> bool:
    """The rebooted module all OK, and every other module's health arriving at the ground.

    Not every other module OK: at load 45 on two cores (other tests' rehearsals beside this
    one) the emulated CANopen drives of the limbs, starved, missed their heartbeats and
    latched faults that only `msctl recover` clears, with no reboot anywhere near them.
    """
    return module_ok(document, MODULE) and all(
        item["level"] == "OK"
        for row in document["modules"]
        for item in row["items"]
        if item["name"] == f"{row['name']}/health"
    )


def until_health(predicate: Any, what: str) -> Any:
    """``wait_until`` on `health --once` answers, saying what was not OK if it runs out (a
    generous bound: five computers, and other tests' rehearsals, share two cores)."""
    try:
        return wait_until(predicate, timeout=300, what=what)
    except AssertionError as exc:
        raise AssertionError(f"{exc}; not OK at the end: {not_ok()}") from None


def agent_started(stage: Stage, host: str) -> float:
    """When the agent now running on ``host`` started (Unix seconds), seen from outside it."""
    computer = next(c for c in stage.status()["computers"] if c["name"] == host)
    pids = [p["pid"] for p in computer["processes"] if "msctl agent" in p["command"]]
    assert len(pids) == 1, computer["processes"]
    return psutil.Process(pids[0]).create_time()


def desired_path(stage: Stage, host: str) -> Path:
    return stage.computer_home(host) / "agent" / desired.FILE_NAME


def agent_document(stage: Stage, host: str) -> dict[str, Any]:
    """``host``'s agent's own ``ps`` document, asked from the ground station (``{}``: no
    answer yet)."""
    done = stage.run(GROUND, sys.executable, PROBE, "agent", host, timeout=120)
    return json.loads(done.stdout) if done.returncode == 0 else {}


def test_up_all_left_each_computer_its_desired_state(stage: Stage) -> None:
    for host in [*ROBOTS.values(), GROUND]:
        kept = desired.read(desired_path(stage, host), host)
        assert kept is not None, host
        assert kept.template == "dragon" and kept.assembly["template"] == "dragon"


def test_a_rebooted_computer_rejoins_and_the_ground_says_so(stage: Stage) -> None:
    until_health(
        lambda: rejoined_and_heard(health(stage)[1]), f"{MODULE} OK at first, every module heard"
    )
    probe = Probe(stage, MODULE)
    try:
        wait_until(
            lambda: any(line["healthy"] for line in probe.levels()),
            timeout=120,
            what=f"the probe on {GROUND} seeing {MODULE} healthy",
        )
        done = stage.msctl("rehearse", "reboot", REBOOTED)
        assert done.returncode == 0, done.stderr
        started = agent_started(stage, REBOOTED)
        # Nothing else is done: the ground must see it go, then come back healthy.
        back = wait_until(
            lambda: next(
                (
                    line
                    for line in probe.levels()
                    if line["healthy"]
                    and line["at"] > started
                    and any(not o["healthy"] for o in probe.levels() if o["at"] < line["at"])
                ),
                None,
            ),
            timeout=180,
            what=f"{MODULE} healthy again at {GROUND} after the reboot",
        )
        lost = [o for o in probe.levels() if not o["healthy"]]
        rejoined = wait_until(
            lambda: [a for a in probe.alarms() if a["item"] == f"{MODULE}/agent"],
            timeout=60,
            what="the rejoin alarm at the ground",
        )
    finally:
        errors = probe.close()
    report = agent_document(stage, REBOOTED)["rejoin"]
    print(
        f"\n{REBOOTED} rebooted: its agent started its part {report['at'] - started:.1f} s after "
        f"its own start; {MODULE} healthy again at {GROUND} {back['at'] - started:.1f} s after "
        f"it (target 10 s); the ground saw it go: {lost[-1]['bad'][:2]}"
    )
    assert report["outcome"] == "rejoined", report
    assert rejoined[0]["to"] == "OK", (rejoined, errors)
    assert f"{REBOOTED} rebooted or lost power and rejoined" in rejoined[0]["message"]
    assert rejoined[0]["at"] == round(report["at"], 3)  # timed by the agent, not the board

    # An operator who opens `msctl health` after it sees the same alarm, and it is kept in
    # the alarm file (`msctl health --alarms`).
    watch = Watch(stage)
    try:
        seen = wait_until(
            lambda: [a for a in watch.alarms() if a["item"] == f"{MODULE}/agent"],
            timeout=120,
            what="the rejoin alarm in `msctl health --watch`",
        )
    finally:
        watch.close()
    assert seen[0]["at"] == rejoined[0]["at"] and seen[0]["to"] == "OK", seen
    done = stage.on(GROUND, "health", "--alarms", "--json")
    assert done.returncode == 0, done.stderr
    kept = json.loads(done.stdout)["alarms"]
    assert any(a["item"] == f"{MODULE}/agent" and "rejoined" in a["message"] for a in kept), kept

    # ps --all from the ground: the part runs again, on its own computer.
    listed = wait_until(
        lambda: (
            (r := stage.on(GROUND, "ps", "--all", "--json", "--timeout", "30")).returncode == 0
            and r
        ),
        timeout=120,
        what="ps --all answered by every computer",
    )
    rows = [c for c in json.loads(listed.stdout)["components"] if c["host"] == REBOOTED]
    assert rows and all(c["state"] == "running" for c in rows), rows

    # wheel2 OK at the ground and every module heard, with no other command. (The rejoin's
    # item is not asked of `--once`: its snapshot has the supervisors' answers of one round,
    # which on a loaded machine often misses a computer; `--watch` above had it.)
    until_health(
        lambda: rejoined_and_heard(health(stage)[1]), f"{MODULE} OK and every module heard"
    )
    print(f"not OK at the ground at the end (other than host metrics): {not_ok()}")


def test_reboot_brings_the_agent_back_alone(stage: Stage) -> None:
    done = stage.msctl("rehearse", "reboot", "hl-limb-02")
    assert done.returncode == 0, done.stderr
    assert "processes killed" in done.stderr
    wait_until(
        lambda: "/msctl/hl_limb_02/request" in stage.on(GROUND, "service", "list").stdout,
        timeout=120,
        what="hl-limb-02's agent back on the fleet",
    )


def test_after_down_all_a_reboot_brings_nothing_back(stage: Stage) -> None:
    done = stage.on(GROUND, "down", "--all", timeout=180)
    assert done.returncode == 0, done.stderr
    for host in [*ROBOTS.values(), GROUND]:
        assert not desired_path(stage, host).exists(), host
    done = stage.msctl("rehearse", "reboot", REBOOTED)
    assert done.returncode == 0, done.stderr
    document = wait_until(
        lambda: (
            (d := agent_document(stage, REBOOTED)).get("supervisor_pid")
            == agent_pid(stage, REBOOTED)
            and d
        ),
        timeout=120,
        what=f"the new agent of {REBOOTED} answering",
    )
    assert document["state"] == "idle" and document["components"] == [], document
    assert "rejoin" not in document, document


def agent_pid(stage: Stage, host: str) -> int | None:
    computer = next(c for c in stage.status()["computers"] if c["name"] == host)
    pids = [p["pid"] for p in computer["processes"] if "msctl agent" in p["command"]]
    return pids[0] if len(pids) == 1 else None


def test_a_desired_state_cut_short_is_refused_and_shown_at_the_ground(stage: Stage) -> None:
    # A desired state as a power cut in the middle of a plain write would leave it.
    host, module = "hl-limb-02", "limb2"
    path = desired_path(stage, host)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text('{"format": "msctl-desired-state", "version": 1, "host": "hl-li')
    done = stage.msctl("rehearse", "reboot", host)
    assert done.returncode == 0, done.stderr
    document = wait_until(
        lambda: (
            (d := agent_document(stage, host)).get("supervisor_pid") == agent_pid(stage, host)
            and "rejoin" in d
            and d
        ),
        timeout=120,
        what=f"the new agent of {host} reporting what it found",
    )
    assert document["state"] == "idle" and document["components"] == [], document
    report = document["rejoin"]
    assert report["outcome"] == "refused" and str(path) in report["message"], report
    wait_until(
        lambda: (
            (r := health(stage))
            and any(
                i["name"] == f"{module}/agent" and i["level"] == "ERROR"
                for row in r[1]["modules"]
                for i in row["items"]
            )
            and r
        ),
        timeout=60,
        what=f"the refusal shown at {GROUND}",
    )
    assert path.exists()  # left for the operator to look at, not acted on
    done = stage.on(GROUND, "down", "--all", timeout=180)
    assert done.returncode == 0, done.stderr
    assert not path.exists()  # a down clears it


def test_down_all_then_rehearse_down_leaves_nothing(stage: Stage) -> None:
    """The last test on the shared rehearsal (conftest.DRAGON_REHEARSAL): it ends it."""
    done = stage.on(GROUND, "down", "--all", timeout=180)
    assert done.returncode == 0, done.stderr
    root = stage.home / "rehearse"
    prefix = namespace_prefix(root)
    done = stage.msctl("rehearse", "down")
    assert done.returncode == 0, done.stderr
    assert not [n for n in namespaces() if n.startswith(prefix)]
    assert not root.exists()
    assert not list(Path("/etc/netns").glob(prefix + "*"))
