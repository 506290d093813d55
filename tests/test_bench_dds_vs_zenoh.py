"""bench/dds_vs_zenoh.py end to end: two robots in network namespaces, each stack, short bounds.

The benchmark is run as a user runs it (``--json``), with two robots (the smallest fleet with
a link to cut) and short windows, and its document is checked for Table IV's four rows and for
figures that can only come from a run that did what it says: a whole graph, bytes on the
bridge, robot 2's joint_states reaching robot 1 across it (about 0.4 Mb/s at 100 Hz) and again
after the cut link came back. No figure is held to a speed. Afterwards no namespace of the run
is left. Skipped without root or ``ip netns``; the DDS run also without rclpy.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from ros_rigs import needs_rclpy

pytestmark = pytest.mark.e2e

BENCH = Path(__file__).resolve().parent.parent / "bench" / "dds_vs_zenoh.py"
ROWS = ("component_startup", "startup_bandwidth", "recovery", "max_stable_robots")
#: Each step's bound (s): far beyond what two robots need, short enough for a test.
BOUND = 40


def _netns_unusable() -> str | None:
    if not hasattr(os, "geteuid") or os.geteuid() != 0:
        return "needs root (network namespaces)"
    if shutil.which("ip") is None:
        return "needs the ip command (iproute2)"
    probe = f"msb-test-{os.getpid()}"
    done = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
    if done.returncode != 0:
        return f"ip netns add fails here: {done.stderr.strip()}"
    subprocess.run(["ip", "netns", "delete", probe], capture_output=True)
    return None


NETNS_UNUSABLE = _netns_unusable()
needs_netns = pytest.mark.skipif(NETNS_UNUSABLE is not None, reason=NETNS_UNUSABLE or "")


def _namespaces() -> list[str]:
    listing = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    return [line.split()[0] for line in listing.splitlines() if line.strip()]


@needs_netns
@pytest.mark.parametrize("stack", ["zenoh", pytest.param("dds", marks=needs_rclpy)])
def test_two_robots_give_every_row_of_table_iv(stack: str) -> None:
    """Every row for the stack, figures a real run gives, and nothing of the run left over."""
    # A 3 s cut: Zenoh (1 s lease) notices it, DDS (20 s lease) does not; both recover.
    command = [
        sys.executable, str(BENCH), "--robots", "2", "--stacks", stack, "--bound", str(BOUND),
        "--steady", "1", "--cut-max", "3", "--json",
    ]  # fmt: skip
    bench = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    out, err = bench.communicate(timeout=240)
    assert bench.returncode == 0, err[-3000:]
    document = json.loads(out)

    table = document["table"]
    assert tuple(table) == ROWS
    for row in ROWS:
        assert table[row]["paper_dds"] and table[row]["paper_zenoh"]
        assert table[row]["robots"] == 2
        assert table[row][stack]["text"], row

    (run,) = document["runs"]
    assert (run["stack"], run["robots"], run["converged"], run["stable"]) == (stack, 2, True, True)
    assert run["problems"] == [], err[-3000:]
    assert 0 < run["startup_s"] < BOUND
    assert 0 <= run["discovery_s"] <= run["startup_s"]
    assert table["component_startup"][stack]["s"] == run["startup_s"]
    # Discovery crossed the bridge; at rest, each stack's upkeep is small next to a data stream.
    assert run["startup"]["bytes"] > 0
    assert table["startup_bandwidth"][stack]["mbps"] == run["startup"]["mbps"] > 0
    assert 0 <= run["steady"]["mbps"] < run["steady_data"]["mbps"]
    # robot 2's 100 Hz joint_states (~500 B a sample) to robot 1: tenths of a Mb/s, not bytes.
    assert 0.05 < run["steady_data"]["mbps"] < 10
    assert run["first_data_s"] is not None
    # The link was cut and restored, and the data came back within the bound.
    assert 0 < run["cut_s"] <= 3 + 1
    assert 0 <= run["recovery_data_s"] < BOUND
    assert table["recovery"][stack]["data_s"] == run["recovery_data_s"]
    if stack == "zenoh":  # a 1 s lease: the cut was noticed, and the graph healed
        assert run["loss_noticed_s"] is not None and run["loss_noticed_s"] < 3 + 1
        assert run["recovery_nodes_s"] is not None and run["recovery_topics_s"] is not None
        assert run["routers_s"] is not None
    assert table["max_stable_robots"][stack]["robots"] == 2
    assert run["cpu_percent"]["robot"] > 0

    leftovers = [n for n in _namespaces() if n.startswith(f"msb-{bench.pid}-")]
    assert leftovers == []
