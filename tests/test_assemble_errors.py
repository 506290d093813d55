"""Bad input to ``msctl assemble``: one red line naming the file, field or slot and the fix, a
non-zero exit, and nothing written (the previous resolution stays intact).

Each case runs the real ``msctl`` on a private copy of the shipped data, broken on purpose.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from components.assembly import LOCK_NAME, MJCF_NAME, URDF_NAME, encode_lock
from msctl.assembler import resolve
from msctl.assembler.store import write_assembly
from msctl.errors import InputError, NotFoundError

REPO = Path(__file__).resolve().parents[1]


def _copy(src: Path, dst: Path) -> None:
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))


@pytest.fixture
def world(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> dict[str, Path]:
    """A private copy of the data, a private MSCTL_HOME, and a good dragon resolution in it."""
    assemblies, calibration, home = (
        tmp_path / "assemblies",
        tmp_path / "calibration",
        tmp_path / "home",
    )
    _copy(REPO / "assemblies", assemblies)
    _copy(REPO / "calibration", calibration)
    monkeypatch.setenv("MSCTL_ASSEMBLIES_DIR", str(assemblies))
    monkeypatch.setenv("MSCTL_CALIBRATION_DIR", str(calibration))
    monkeypatch.setenv("MSCTL_HOME", str(home))
    good = resolve("dragon")
    write_assembly(
        home / "assembly",
        {URDF_NAME: good.urdf, MJCF_NAME: "<mujoco/>", LOCK_NAME: encode_lock(good.lock)},
    )
    return {"assemblies": assemblies, "calibration": calibration, "home": home}


def edit(relative: str, old: str, new: str, count: int = 1) -> Callable[[dict[str, Path]], None]:
    """A mutation of one data file: replace ``old`` by ``new``."""

    def apply(world: dict[str, Path]) -> None:
        root, _, rest = relative.partition("/")
        path = world[root] / rest
        text = path.read_text()
        assert old in text, (path, old)
        path.write_text(text.replace(old, new, count))

    return apply


def append(relative: str, extra: str) -> Callable[[dict[str, Path]], None]:
    def apply(world: dict[str, Path]) -> None:
        root, _, rest = relative.partition("/")
        path = world[root] / rest
        path.write_text(path.read_text() + extra)

    return apply


def nothing(world: dict[str, Path]) -> None:
    pass


def forget_previous(world: dict[str, Path]) -> None:
    """No previous resolution to take units from."""
    shutil.rmtree(world["home"])


def both(*mutations: Callable[[dict[str, Path]], None]) -> Callable[[dict[str, Path]], None]:
    def apply(world: dict[str, Path]) -> None:
        for mutate in mutations:
            mutate(world)

    return apply


def line_of(world: dict[str, Path], relative: str, needle: str) -> int:
    root, _, rest = relative.partition("/")
    lines = (world[root] / rest).read_text().splitlines()
    return next(i for i, line in enumerate(lines, 1) if needle in line)


CASES = {
    "unknown template": (nothing, ["nope"], 4, ["unknown template 'nope'", "dragon", "--list"]),
    "unknown module type in a template": (
        edit("assemblies/dragon.toml", '"hl_limb_v1"', '"hl_limb_v9"'),
        ["dragon"],
        4,
        [
            "dragon.toml",
            "slots[0].fits[0]",
            "slot limb1",
            "unknown module type 'hl_limb_v9'",
            "known module types: gl_limb, hl_limb_v1",
        ],
    ),
    "unknown module type in a unit": (
        edit(
            "calibration/hlv1-limb-01.toml",
            'module_type = "hl_limb_v1"',
            'module_type = "hl_limb_v7"',
        ),
        ["dragon"],
        4,
        ["hlv1-limb-01.toml", "field module_type", "'hl_limb_v7'", "known module types"],
    ),
    "unknown unit": (
        nothing,
        ["dragon", "--use", "limb1=hlv9-limb-99"],
        4,
        [
            "unknown unit 'hlv9-limb-99'",
            "--use limb1=",
            "units that fit limb1:",
            "hlv1-limb-04",
            "units are read from {calibration}",
            "MSCTL_CALIBRATION_DIR",
        ],
    ),
    "unit of the wrong type": (
        nothing,
        ["dragon", "--use", "wheel1=hlv1-limb-04"],
        2,
        [
            "hlv1-limb-04 is a hl_limb_v1",
            "slot wheel1",
            "hl_wheel_v1, hl_wheel_v2",
            "hlv1-limb-04.toml",
        ],
    ),
    "same unit in two slots": (
        nothing,
        ["dragon", "--use", "limb1=hlv1-limb-04", "--use", "limb2=hlv1-limb-04"],
        2,
        ["unit 'hlv1-limb-04'", "slot limb1", "slot limb2", "one slot only"],
    ),
    "two units on one computer": (
        edit("calibration/hlv1-limb-02.toml", 'host = "hl-limb-02"', 'host = "hl-limb-01"'),
        ["dragon"],
        2,
        [
            "hlv1-limb-01.toml: field host",
            "hlv1-limb-02.toml",
            "'hl-limb-01'",
            "computer to itself",
            "fix the hostname",
        ],
    ),
    "shared computer, same bus": (
        edit("calibration/gl-limb-02.toml", "/dev/ttyUSB1", "/dev/ttyUSB0"),
        ["dragon", "--use", "limb1=gl-limb-01", "--use", "limb2=gl-limb-02"],
        2,
        ["gl-limb-02.toml: field bus.channel", "'/dev/ttyUSB0'", "gl-pi-01", "one bus each"],
    ),
    "connector that does not exist": (
        edit("assemblies/dragon.toml", 'parent = "limb1.tip"', 'parent = "limb1.elbow"'),
        ["dragon"],
        2,
        [
            "dragon.toml: field connections[1].parent",
            "no connector 'elbow'",
            "its connectors: base, side_left, side_right, tip",
        ],
    ),
    "calibration for a joint the module lacks": (
        append("calibration/hlv1-limb-01.toml", "\n[joints.joint9]\nmotor_id = 10\n"),
        ["dragon"],
        2,
        [
            "hlv1-limb-01.toml: field joints.joint9",
            "hl_limb_v1 has no joint 'joint9'",
            "joint1, joint2",
            "rename or remove",
        ],
    ),
    "override for a joint the module lacks": (
        edit("calibration/hlv1-limb-03.toml", 'joint = "joint5"', 'joint = "joint12"'),
        ["dragon", "--use", "limb1=hlv1-limb-03"],
        2,
        ["hlv1-limb-03.toml: field overrides[0] (locked_joint)", "no joint 'joint12'"],
    ),
    "NaN in a module (was an internal error naming no file)": (
        edit("assemblies/modules/hl_limb_v1.toml", "lower = -3.05", "lower = nan"),
        ["dragon"],
        2,
        ["hl_limb_v1.toml: field joints[0].lower is nan", "finite"],
    ),
    "the README tour's unit with its override misspelt": (
        edit("calibration/hlv1-limb-03.toml", 'name = "locked_joint"', 'name = "lock_joint"'),
        ["dragon", "--use", "limb1=hlv1-limb-03"],
        2,
        [
            "hlv1-limb-03.toml: field overrides[0].name",
            "no override named 'lock_joint' for joint_manager; known: locked_joint",
        ],
    ),
    "a station asking for 100,000,000 components": (
        edit("assemblies/dragon.toml", "human_operator = 1", "human_operator = 100000000"),
        ["dragon"],
        2,
        ["dragon.toml: field stations[0].components.human_operator is 100000000", "0 to 64"],
    ),
    "malformed template TOML": (
        edit("assemblies/dragon.toml", "mobile = true", "mobile = yes"),
        ["dragon"],
        2,
        [
            "dragon.toml:{line:assemblies/dragon.toml:mobile = yes}: malformed TOML",
            "fix the syntax",
        ],
    ),
    "malformed calibration TOML": (
        edit("calibration/hlv1-wheel-02.toml", "[bus]", "[bus"),
        ["dragon"],
        2,
        ["hlv1-wheel-02.toml:{line:calibration/hlv1-wheel-02.toml:[bus}: malformed TOML"],
    ),
    "URDF that does not parse": (
        edit("assemblies/modules/urdf/hl_wheel_v1.urdf", "</robot>", "</robt>"),
        ["dragon"],
        2,
        [
            "hl_wheel_v1.urdf:{line:assemblies/modules/urdf/hl_wheel_v1.urdf:</robt>}: "
            "URDF does not parse",
            "fix the XML at line",
        ],
    ),
    "URDF joint to a missing link": (
        edit(
            "assemblies/modules/urdf/hl_wheel_v1.urdf",
            '<child link="wheel_left_link"/>',
            '<child link="wheel_lft_link"/>',
        ),
        ["dragon"],
        2,
        ["hl_wheel_v1.urdf: joint 'wheel_left' child link 'wheel_lft_link' is not a <link>"],
    ),
    "unknown slot": (
        nothing,
        ["dragon", "--use", "limb9=hlv1-limb-04"],
        2,
        ["--use limb9=hlv1-limb-04", "no slot 'limb9'", "slots: limb1, limb2, wheel1, wheel2"],
    ),
    "several units fit and no terminal": (
        both(edit("assemblies/dragon.toml", 'default = "hlv1-limb-01"\n', ""), forget_previous),
        ["dragon"],
        2,
        ["dragon.toml: slot limb1:", "units fit (gl-limb-01", "hlv1-limb-03", "--use limb1=<unit>"],
    ),
}


def _expand(text: str, world: dict[str, Path]) -> str:
    text = text.replace("{calibration}", str(world["calibration"]))
    return re.sub(
        r"\{line:([^:]+):([^}]+)\}", lambda m: str(line_of(world, m.group(1), m.group(2))), text
    )


def _snapshot(home: Path) -> dict[str, bytes]:
    if not home.exists():
        return {}
    return {
        str(p.relative_to(home)): (p.read_bytes() if p.is_file() else b"")
        for p in sorted(home.rglob("*"))
    }


@pytest.mark.e2e
@pytest.mark.parametrize("case", list(CASES))
def test_bad_input_is_one_clear_line_and_writes_nothing(case: str, world: dict[str, Path]) -> None:
    mutate, args, code, expected = CASES[case]
    mutate(world)
    before = _snapshot(world["home"])
    result = subprocess.run(
        [sys.executable, "-m", "msctl", "assemble", *args],
        capture_output=True,
        text=True,
        env=os.environ.copy(),
        timeout=60,
    )
    lines = result.stderr.strip().splitlines()
    assert result.returncode == code, result.stderr
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    for piece in expected:
        assert _expand(piece, world) in lines[0], lines[0]
    assert result.stdout == ""
    assert _snapshot(world["home"]) == before  # the previous resolution is untouched


def test_errors_are_project_errors_in_process(world: dict[str, Path]) -> None:
    with pytest.raises(NotFoundError):
        resolve("nope")
    with pytest.raises(InputError, match="one slot only"):
        resolve("dragon", {"limb1": "hlv1-limb-04", "limb2": "hlv1-limb-04"})


def test_a_failure_while_writing_keeps_the_previous_resolution(
    world: dict[str, Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    from msctl.assembler import store

    home = world["home"]
    before = _snapshot(home)

    def broken(path: Path, text: str) -> None:
        if path.name == LOCK_NAME:
            raise OSError(28, "No space left on device")
        path.write_text(text)

    monkeypatch.setattr(store, "_write", broken)
    with pytest.raises(OSError):
        write_assembly(home / "assembly", {URDF_NAME: "<robot/>", LOCK_NAME: "{}"})
    assert _snapshot(home) == before
