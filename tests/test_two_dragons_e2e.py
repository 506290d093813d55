"""The paper's two-Dragon deployment in simulation: ``msctl up two_dragons --sim`` brings all
60 planned components up, the 8 motor interfaces as the one simulator, every other kind as
its own code (3 human operators, 6 autonomous operators, 5 data monitors, 2 data archivers
beside the robots' 44), each healthy."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import wait_until
from running import Up

from components import kinds
from components.assembly import load_assembly

pytestmark = [pytest.mark.e2e, pytest.mark.timeout(1200)]


def test_up_two_dragons_sim_reaches_60_of_60_components_healthy(tmp_path) -> None:
    up = Up(tmp_path / "home", "two_dragons", "--sim", "--timeout", "300", up_wait=360.0)
    try:
        assembly = load_assembly(tmp_path / "home" / "assembly")
        planned = {c.name: c.kind for c in assembly.components}
        assert len(planned) == 60

        def components() -> dict[str, dict]:
            result = up.msctl("ps", "--json")
            assert result.returncode == 0, result.stderr
            return {c["name"]: c for c in json.loads(result.stdout)["components"]}

        def healthy() -> dict[str, str] | None:
            running = components()
            simulated = running.get("sim/simulator", {}).get("state") == "running"
            states = {}
            for name, kind in planned.items():
                if kinds.replaced_in_simulation(kind):
                    states[name] = "running" if simulated else "simulator down"
                else:
                    states[name] = running.get(name, {}).get("state", "absent")
            return states if all(s == "running" for s in states.values()) else None

        try:
            states = wait_until(healthy, 300.0, "every component of two_dragons running")
        except AssertionError:
            raise AssertionError(
                {n: c["state"] for n, c in components().items() if c["state"] != "running"}
            ) from None
        assert len(states) == 60
        # Every kind is real code: nothing is reported as not built, nothing stood in for
        # but the motor interfaces.
        state = json.loads((tmp_path / "home" / "run" / "state.json").read_text())
        assert state["not_built"] == [] and state["template"] == "two_dragons"
        running = components()
        by_kind: dict[str, int] = {}
        for name in running:
            by_kind[running[name]["kind"]] = by_kind.get(running[name]["kind"], 0) + 1
        # The plan's kinds, the simulator standing in for every motor interface.
        expected: dict[str, int] = {"simulator": 1}
        for kind in planned.values():
            if not kinds.replaced_in_simulation(kind):
                expected[kind] = expected.get(kind, 0) + 1
        assert by_kind == expected
        assert all(c["restarts"] == 0 for c in running.values()), {
            n: c["last_error"] for n, c in running.items() if c["restarts"]
        }
        # Sharing one computer, each process yields the CPU as its kinds say, every one of
        # its threads: recording and aggregating below the robot's safety path.
        kinds_of: dict[int, list[str]] = {}
        for component in running.values():
            kinds_of.setdefault(component["pid"], []).append(component["kind"])
        niceness = {pid: _niceness(pid) for pid in kinds_of}
        assert niceness == {pid: {kinds.process_niceness(k)} for pid, k in kinds_of.items()}
        assert {
            n for pid, k in kinds_of.items() if "data_archiver" in k for n in niceness[pid]
        } == {10}
        assert {
            n for pid, k in kinds_of.items() if "joint_manager" in k for n in niceness[pid]
        } == {0}
    finally:
        up.down()


def _niceness(pid: int) -> set[int]:
    """The nice values of every thread of a process (field 19 of /proc/<pid>/task/*/stat)."""
    values = set()
    for stat in Path(f"/proc/{pid}/task").glob("*/stat"):
        try:
            text = stat.read_text()
        except OSError:
            continue  # a thread that just ended
        values.add(int(text.rsplit(")", 1)[1].split()[16]))
    return values
