"""bench/cli.py end to end: a simulated dragon, a few runs of each command, then down.

The benchmark is run as a user runs it (``--json``), with 2 runs per row, and its document is
checked for every row with figures only a real run gives: a time per run, percentiles, and a
ratio to the bare session. No figure is held to a speed. Afterwards nothing of its assembly runs.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import wait_until

from msctl.launcher.state import pid_alive

pytestmark = pytest.mark.e2e

ROOT = Path(__file__).resolve().parent.parent
BENCH = ROOT / "bench" / "cli.py"
ROWS = ("bare zenoh open+close", "msctl topic list", "msctl ps")


def test_every_row_has_figures_and_the_assembly_is_brought_down() -> None:
    """Each command's row: two positive times, p50 <= p90, a finite ratio to bare."""
    done = subprocess.run(
        [sys.executable, str(BENCH), "--runs", "2", "--json"],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=ROOT,
        check=False,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    document = json.loads(done.stdout)
    assert document["template"] == "dragon"
    assert document["components"] > 0
    assert [row["command"] for row in document["rows"]] == list(ROWS)
    for row in document["rows"]:
        assert len(row["times_s"]) == 2, row
        assert all(t > 0 for t in row["times_s"]), row
        assert 0 < row["p50_s"] <= row["p90_s"], row
        assert math.isfinite(row["p50_ratio"]) and row["p50_ratio"] > 0, row
        assert math.isfinite(row["p90_ratio"]) and row["p90_ratio"] > 0, row
    bare = document["rows"][0]
    assert bare["p50_ratio"] == pytest.approx(1.0)
    state = json.loads((Path(document["home"]) / "run" / "state.json").read_text())
    # `msctl down` returns once every component is stopped; the supervisor exits just after.
    wait_until(
        lambda: not pid_alive(state["supervisor_pid"]),
        timeout=30.0,
        what="the benchmark's supervisor to exit",
    )
