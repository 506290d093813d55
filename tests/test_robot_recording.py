"""Robot-side recording as a template option (``[recording] robots = true``): one data archiver
per robot computer, recording its own modules' named topics into its own ``bags``, in a
process of its own; a bad setting fails at ``msctl assemble``, naming the file and field."""

from __future__ import annotations

import json
import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest

from components.assembly import from_document
from msctl.assembler import data, resolve
from msctl.errors import InputError
from msctl.launcher.plan import plan_host

ROBOTS = {
    "limb1": "hl-limb-01",
    "limb2": "hl-limb-02",
    "wheel1": "hl-wheel-01",
    "wheel2": "hl-wheel-02",
}


@pytest.fixture
def templates(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """A copy of the shipped templates and module types, read instead of them."""
    root = tmp_path / "assemblies"
    shutil.copytree(data.assemblies_dir(), root, ignore=shutil.ignore_patterns("__pycache__"))
    monkeypatch.setenv("MSCTL_ASSEMBLIES_DIR", str(root))
    monkeypatch.setenv("MSCTL_HOME", str(tmp_path / "home"))
    data.clear_cache()
    yield root
    data.clear_cache()


def with_recording(root: Path, table: str) -> None:
    dragon = root / "dragon.toml"
    dragon.write_text(dragon.read_text() + "\n[recording]\n" + table)


def archivers(document: dict) -> dict[str, dict]:
    return {c["name"]: c for c in document["components"] if c["kind"] == "data_archiver"}


def test_each_robot_computer_records_its_own_modules_named_topics(templates: Path) -> None:
    with_recording(templates, "robots = true\nmax_file_duration = 2.5\n")
    document = resolve("dragon", {}).document
    found = archivers(document)
    assert set(found) == {f"{slot}/data_archiver" for slot in ROBOTS}
    for slot, host in ROBOTS.items():
        archiver = found[f"{slot}/data_archiver"]
        assert archiver["host"] == host and archiver["module"] == slot
        params = archiver["params"]
        assert params["directory"] == "bags" and params["max_bag_duration"] == 2.5
        topics = params["topics"].split()
        # Named, each of this module: never a wildcard drawing others' data over the radio.
        assert "*" not in topics and all(t.startswith(f"/{slot}/") for t in topics)
        assert f"/{slot}/joint_states" in topics and f"/{slot}/diagnostics" in topics
    assert document["host_plans"]["hl-limb-01"]["role"] == "robot"


def test_the_recorder_runs_apart_from_the_modules_process(templates: Path) -> None:
    with_recording(templates, "robots = true\n")
    assembly = from_document(json.loads(json.dumps(resolve("dragon", {}).document)))
    processes = {
        p.name: [c.name for c in p.components] for p in plan_host(assembly, "hl-limb-01").processes
    }
    assert processes["limb1_data_archiver"] == ["limb1/data_archiver"]
    assert "limb1/data_archiver" not in processes["limb1"]
    assert "limb1/joint_manager" in processes["limb1"]


def test_off_by_default_and_when_false(templates: Path) -> None:
    assert not archivers(resolve("dragon", {}).document)
    with_recording(templates, "robots = false\nmax_file_size = 1000\n")
    data.clear_cache()
    assert not archivers(resolve("dragon", {}).document)


@pytest.mark.parametrize(
    ("table", "says"),
    [
        ("robot = true\n", "field recording.robot is not a recording setting"),
        ('robots = "yes"\n', "field recording.robots is 'yes'"),
        ("robots = true\nmax_file_duration = -1\n", "field recording.max_file_duration"),
        ('robots = true\ncompression = "lz4"\n', "field recording.compression"),
    ],
)
def test_a_bad_setting_fails_at_assemble_naming_file_and_field(
    templates: Path, table: str, says: str
) -> None:
    with_recording(templates, table)
    with pytest.raises(InputError, match=r"dragon\.toml") as raised:
        resolve("dragon", {})
    assert says in str(raised.value)
