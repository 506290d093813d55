"""The checkout stays clean: what the README's commands write is ignored by git, and a test
run writes nothing in the directory it runs in (issue 18, point 20)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import CODEC_CACHE_ENV

pytestmark = pytest.mark.e2e

ROOT = Path(__file__).resolve().parents[1]
#: Where Hypothesis keeps its examples (conftest points it at a temporary directory).
HYPOTHESIS_ENV = "HYPOTHESIS_STORAGE_DIRECTORY"


def _written_by_the_readme() -> list[str]:
    """The relative paths the README's commands write (``-o``/``--output``, and the bag a
    ``msctl record`` without one names after the time)."""
    written = []
    for line in (ROOT / "README.md").read_text().splitlines():
        command = line.strip()
        if not command.startswith("msctl "):
            continue
        for match in re.finditer(r"(?:-o|--output)\s+(\S+)", command):
            written.append(match.group(1))
        if command.startswith("msctl record ") and not re.search(r"(-o|--output)\s", command):
            written.append("rosbag2_2026_01_01-00_00_00/")
    return [path for path in written if not path.startswith(("/", "~", "$"))]


def test_what_the_readme_writes_in_the_checkout_is_ignored_by_git() -> None:
    """Point 20: the tour's ``dragon.urdf``, a bag, a router config: never a change to commit."""
    written = _written_by_the_readme()
    assert "run1" in written and written, written
    for path in [*written, "dragon.urdf"]:
        ignored = subprocess.run(
            ["git", "check-ignore", "-q", "--no-index", path], cwd=ROOT, check=False
        )
        assert ignored.returncode == 0, f"{path} (written by a README command) is not ignored"


def test_a_test_run_writes_nothing_where_it_runs(tmp_path: Path) -> None:
    """Point 20: the test run's caches (Hypothesis' examples, cydr's codecs) go to temporary
    directories, not into the directory pytest runs in (the checkout, usually)."""
    where = tmp_path / "cwd"
    where.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in (HYPOTHESIS_ENV, CODEC_CACHE_ENV)}
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "-q",
            "-p",
            "no:cacheprovider",
            "-n",
            "0",
            str(
                ROOT / "tests/test_fuzz_inputs.py::test_any_attachment_decodes_or_raises_"
                "attachment_error"
            ),
            str(ROOT / "tests/test_attachment.py"),
        ],
        cwd=where,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    assert sorted(p.name for p in where.iterdir()) == []
