"""Robot-side recording and ``msctl bag pull`` across a rehearsal of ``dragon`` (five computers,
secure, ``wifi`` links), with the template's ``[recording] robots = true``.

Each robot computer records its own modules into its own ``MSCTL_HOME/bags`` (one file a
second here); the ground station pulls hl-limb-01's bag over the fleet: once as fast as the
link goes (the figure is printed), once paced and cut by a 3 s outage of hl-limb-01's link
with a patience shorter than the outage (it fails, naming the host and what is not
verified), then again, resuming (nothing fetched twice) and verifying; once more, paced and
cut, with the pull's own patience riding through the outage. The pulled bag opens with
rosbags and holds limb1's joint_states. One rehearsal for the whole module.

Needs root (CI runs as root); skipped, saying so, without it.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import wait_until
from rehearse_rigs import GROUND, ROOT_REHEARSAL, Stage, rehearsed
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from msctl.assembler.data import assemblies_dir

pytestmark = [pytest.mark.e2e, pytest.mark.timeout(1200), ROOT_REHEARSAL]

ROBOT = "hl-limb-01"
ARCHIVER = "limb1/data_archiver"
#: Files the robot records before its recorder is stopped (one a second).
FILES = 8


@pytest.fixture(scope="module")
def stage(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Stage]:
    """A dragon rehearsal whose template records on every robot computer, a file a second."""
    root = tmp_path_factory.mktemp("pull")
    templates = root / "assemblies"
    shutil.copytree(assemblies_dir(), templates, ignore=shutil.ignore_patterns("__pycache__"))
    dragon = templates / "dragon.toml"
    dragon.write_text(
        dragon.read_text()
        + '\n[recording]\nrobots = true\nmax_file_duration = 1.0\ncompression = "none"\n'
    )
    stage = Stage(root / "home", env={"MSCTL_ASSEMBLIES_DIR": str(templates)})
    stage.home.mkdir()
    with rehearsed(stage):
        yield stage


def robot_bag(stage: Stage) -> Path | None:
    bags = [p for p in (stage.computer_home(ROBOT) / "bags").glob("limb1_data_archiver_*")]
    return bags[0] if len(bags) == 1 else None


@pytest.fixture(scope="module")
def recorded(stage: Stage) -> dict[str, Any]:
    """hl-limb-01's bag once FILES files are written and its recorder stopped: the ground's
    dry-run listing of it (every file finished)."""
    wait_until(
        lambda: (bag := robot_bag(stage)) and len(list(bag.glob("*.mcap"))) > FILES,
        timeout=180,
        what=f"{FILES} files recorded on {ROBOT}",
    )
    stopped = stage.on(GROUND, "stop", ARCHIVER, timeout=120)
    assert stopped.returncode == 0, stopped.stderr

    last: list[Any] = []

    def finished() -> dict[str, Any] | None:
        done = stage.on(GROUND, "bag", "pull", ROBOT, "--dry-run", "--json", timeout=120)
        last[:] = [done.returncode, done.stdout[-2000:], done.stderr[-2000:]]
        if done.returncode != 0:
            return None
        listing = json.loads(done.stdout)
        actions = [f["action"] for f in listing["files"]]
        return listing if actions and all(a == "fetch" for a in actions) else None

    try:
        # Each try is an msctl start on the ground station: seconds apiece at load 40.
        return wait_until(finished, timeout=300, what=f"{ROBOT}'s bag finished", interval=1.0)
    except AssertionError as exc:
        shelf = stage.computer_home(ROBOT) / "bags"
        on_disk = sorted(f"{p.relative_to(shelf)} {p.stat().st_size}" for p in shelf.rglob("*"))
        raise AssertionError(f"{exc}; last dry run: {last}; on {ROBOT}: {on_disk}") from None


def pull(stage: Stage, *args: str) -> tuple[int, dict[str, Any], str]:
    done = stage.on(GROUND, "bag", "pull", ROBOT, "--json", *args, timeout=300)
    return done.returncode, json.loads(done.stdout) if done.stdout.strip() else {}, done.stderr


def verified_files(into: Path) -> list[Path]:
    """Files verified and renamed (not a ``.part``, nor the pull's ``.pull.lock``)."""
    return [
        p
        for p in into.rglob("*")
        if p.is_file() and not p.name.endswith(".part") and p.name[0] != "."
    ]


def cut_while_pulling(stage: Stage, into: Path, *args: str) -> tuple[int, dict[str, Any], str]:
    """A paced pull into ``into`` whose robot link goes down for 3 s once a file is here."""
    process = stage.start(
        GROUND, "msctl", "bag", "pull", ROBOT, "--json", "--into", str(into), *args
    )
    try:
        wait_until(lambda: verified_files(into), timeout=120, what="a first file pulled")
        cut = stage.msctl("rehearse", "link", ROBOT, "--down", "3")
        assert cut.returncode == 0, cut.stderr
        out, err = process.communicate(timeout=300)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    return process.returncode, json.loads(out) if out.strip() else {}, err


def pace(recorded: dict[str, Any]) -> str:
    """``--limit`` (kB/s) that makes pulling the bag take about 30 s: long enough for the
    outage to fall inside it, an msctl start away on a machine at load 40."""
    total = sum(f["size"] for f in recorded["files"])
    return f"{max(total / 1000 / 30, 1.0):.1f}"


def same_as_robot(stage: Stage, into: Path, recorded: dict[str, Any]) -> None:
    robot = stage.computer_home(ROBOT) / "bags"
    for entry in recorded["files"]:
        here = into / entry["path"]
        assert here.read_bytes() == (robot / entry["path"]).read_bytes(), entry["path"]


def test_the_robot_recorded_its_own_module_in_many_files(recorded: dict[str, Any]) -> None:
    paths = [f["path"] for f in recorded["files"]]
    assert sum(p.endswith(".mcap") for p in paths) > FILES
    assert paths[-1].endswith("/metadata.yaml")  # last: a bag is whole once it is here
    assert {p.split("/")[0] for p in paths} == {paths[0].split("/")[0]}  # one bag


def test_a_pull_as_fast_as_the_wifi_link_goes(stage: Stage, recorded: dict[str, Any]) -> None:
    into = stage.home / "fast"
    code, report, stderr = pull(stage, "--into", str(into))
    assert code == 0, stderr
    assert len(report["pulled"]) == len(recorded["files"]) and not report["failed"]
    same_as_robot(stage, into, recorded)
    print(
        f"\nbag pull over wifi: {report['fetched_bytes']:,} bytes in {report['seconds']:.2f} s, "
        f"{report['kB_per_s']} kB/s"
    )


def test_a_pull_cut_by_an_outage_fails_naming_the_host_and_the_next_resumes(
    stage: Stage, recorded: dict[str, Any]
) -> None:
    into = stage.computer_home(GROUND) / "pulled" / ROBOT  # the default
    total = sum(f["size"] for f in recorded["files"])
    code, first, stderr = cut_while_pulling(
        stage, into, "--limit", pace(recorded), "--patience", "1"
    )
    assert code == 3, stderr
    assert f"{ROBOT} gave no answer for 1 s" in first["silent"]
    assert first["pulled"] and first["failed"], first
    assert f"{ROBOT} gave no answer" in stderr and "not verified:" in stderr
    failed = [f["path"] for f in first["failed"]]
    assert all(f"{path}" in stderr for path in failed)

    # Link back (the pull's own patience rides through the routers' reconnect): it resumes.
    code, second, stderr = pull(stage)
    assert code == 0, stderr
    assert {f["path"] for f in second["skipped"]} == {f["path"] for f in first["pulled"]}
    assert {f["path"] for f in second["pulled"]} == set(failed)
    # Nothing fetched twice: what the first left in a .part, the second did not ask again.
    assert first["fetched_bytes"] + second["fetched_bytes"] == total
    assert not list(into.rglob("*.part"))
    same_as_robot(stage, into, recorded)


def test_a_pull_rides_through_an_outage_by_itself(stage: Stage, recorded: dict[str, Any]) -> None:
    into = stage.home / "patient"
    code, report, stderr = cut_while_pulling(stage, into, "--limit", pace(recorded))
    assert code == 0, stderr
    assert len(report["pulled"]) == len(recorded["files"]) and not report["silent"]
    same_as_robot(stage, into, recorded)


def test_the_pulled_bag_opens_with_rosbags_and_holds_limb1_joint_states(
    stage: Stage, recorded: dict[str, Any]
) -> None:
    into = stage.home / "fast"
    bag = into / recorded["files"][0]["path"].split("/")[0]
    if not (bag / "metadata.yaml").is_file():
        code, _report, stderr = pull(stage, "--into", str(into))
        assert code == 0, stderr
    if any(f.get("abandoned") for f in recorded["files"]) or list(bag.glob(".*.cut")):
        # The recorder was stopped too hard to finish its last file (at load 40 its 3 s
        # between SIGINT and SIGKILL can run out): the copy is completed here, as a field
        # team would.
        done = stage.msctl("bag", "recover", str(bag))
        assert done.returncode == 0, done.stderr
    store = get_typestore(Stores.ROS2_JAZZY)
    with Reader(bag) as reader:
        (states,) = [c for c in reader.connections if c.topic == "/limb1/joint_states"]
        assert states.msgtype == "sensor_msgs/msg/JointState" and states.msgcount > 100
        _, _, raw = next(reader.messages(connections=[states]))
        message = store.deserialize_cdr(raw, states.msgtype)
        assert message.name and all(name.startswith("limb1_") for name in message.name)
        others = {c.topic for c in reader.connections if not c.topic.startswith("/limb1/")}
        assert not others, others  # its own module only: nothing drawn over the radio
