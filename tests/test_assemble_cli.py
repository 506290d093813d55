"""``msctl assemble`` end to end: the real command in a subprocess, a private MSCTL_HOME."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from components.assembly import load_assembly

pytestmark = pytest.mark.e2e


@pytest.fixture
def env(tmp_path: Path) -> dict[str, str]:
    environment = os.environ.copy()
    environment["MSCTL_HOME"] = str(tmp_path / "home")
    environment.pop("MSCTL_ASSEMBLIES_DIR", None)
    environment.pop("MSCTL_CALIBRATION_DIR", None)
    return environment


def msctl(env: dict[str, str], *args: str) -> subprocess.CompletedProcess[str]:
    result = subprocess.run(
        [sys.executable, "-m", "msctl", "assemble", *args],
        capture_output=True,
        text=True,
        env=env,
        timeout=60,
    )
    assert result.returncode == 0, result.stderr
    return result


def test_resolve_swap_and_show(env: dict[str, str]) -> None:
    first = json.loads(msctl(env, "dragon", "--json").stdout)
    home = Path(env["MSCTL_HOME"]) / "assembly"
    assert first["units"] == {
        "limb1": "hlv1-limb-01",
        "limb2": "hlv1-limb-02",
        "wheel1": "hlv1-wheel-01",
        "wheel2": "hlv1-wheel-02",
    }
    assert json.loads((home / "assembly.lock.json").read_text()) == first

    swapped = msctl(env, "dragon", "--use", "wheel2=hlv2-wheel-03", "--json")
    second = json.loads(swapped.stdout)  # exactly one JSON document on stdout
    assert "changed: wheel2" in swapped.stderr
    assert second["units"] == {**first["units"], "wheel2": "hlv2-wheel-03"}
    for before, after in zip(first["modules"], second["modules"], strict=True):
        assert (before == after) == (before["slot"] != "wheel2")

    # Resolving again keeps the swap, and says it is not the default; show reads it back.
    again = msctl(env, "dragon")
    assert "not the defaults: wheel2=hlv2-wheel-03 (default hlv1-wheel-02)" in again.stderr
    assert "--defaults" in again.stderr
    shown = json.loads(msctl(env, "show", "--json").stdout)
    assert shown["units"]["wheel2"] == "hlv2-wheel-03"

    table = msctl(env, "show").stdout
    assert "hlv2-wheel-03" in table and "per-host plan" in table

    assembly = load_assembly(home)
    assert assembly.module("wheel2").module_type == "hl_wheel_v2"
    assert assembly.urdf_path.read_text() == msctl(env, "urdf").stdout

    # --defaults puts every slot back on the template's default.
    reset = msctl(env, "dragon", "--defaults", "--json")
    assert json.loads(reset.stdout)["units"] == first["units"]
    assert "changed: wheel2" in reset.stderr and "not the defaults" not in reset.stderr


def test_models_to_stdout_or_file(env: dict[str, str], tmp_path: Path) -> None:
    msctl(env, "minimal")
    urdf = msctl(env, "urdf").stdout
    assert urdf.startswith("<?xml") and "<robot" in urdf
    target = tmp_path / "out" / "model.xml"
    # A missing directory is named, not made: a typo in -o must not scatter files.
    refused = subprocess.run(
        [sys.executable, "-m", "msctl", "assemble", "mjcf", "-o", str(target)],
        capture_output=True,
        text=True,
        env=env,
        timeout=60,
    )
    assert refused.returncode == 2 and f"no directory {target.parent}" in refused.stderr
    assert not target.parent.exists()
    target.parent.mkdir()
    result = msctl(env, "mjcf", "-o", str(target))
    assert result.stdout == "" and target.read_text().startswith("<mujoco")
    # Written atomically, yet with the mode a plain write gives (not the temp file's 0600).
    umask = os.umask(0)
    os.umask(umask)
    assert target.stat().st_mode & 0o777 == 0o666 & ~umask


def test_list(env: dict[str, str]) -> None:
    listing = json.loads(msctl(env, "--list", "--json").stdout)
    assert set(listing["templates"]) == {
        "minimal",
        "dragon",
        "dragon_x4",
        "tricycle",
        "two_dragons",
    }
    assert set(listing["module_types"]) == {
        "hl_limb_v1",
        "hl_limb_v2",
        "hl_wheel_v1",
        "hl_wheel_v2",
        "gl_limb",
    }
    assert "dragon.limb1" in listing["units"]["gl-limb-01"]["fits"]
    assert "tricycle.limb1" not in listing["units"]["hlv2-limb-01"]["fits"]
    assert "hlv1-limb-04" in msctl(env, "--list").stdout


def test_show_before_any_resolution_says_what_to_run(env: dict[str, str]) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "msctl", "assemble", "show"],
        capture_output=True,
        text=True,
        env=env,
        timeout=60,
    )
    assert result.returncode == 4
    assert "msctl assemble dragon" in result.stderr and result.stdout == ""
