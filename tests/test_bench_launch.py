"""bench/launch.py's component count: two_dragons starts 60 of its 60 planned components
off-robot (issue 12), its 8 motor interfaces by the simulator standing in for them."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from typing import Any

from conftest import resolved_assembly

ROOT = Path(__file__).resolve().parent.parent


def _bench() -> Any:
    spec = importlib.util.spec_from_file_location("bench_launch", ROOT / "bench" / "launch.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("bench_launch", module)
    spec.loader.exec_module(module)
    return module


def test_two_dragons_off_robot_starts_60_of_60(tmp_path: Path) -> None:
    from msctl.launcher.plan import plan_host

    assembly = resolved_assembly(tmp_path, "two_dragons")
    plan = plan_host(assembly, "bench-laptop", sim=True)
    themselves, by_simulator = _bench().started_components(assembly, plan)
    assert len(assembly.components) == 60
    assert (themselves, by_simulator) == (52, 8)
    assert not plan.not_built


def test_motor_interfaces_count_only_with_the_simulator_running(tmp_path: Path) -> None:
    from msctl.launcher.plan import plan_host

    assembly = resolved_assembly(tmp_path, "two_dragons")
    plan = plan_host(assembly, "bench-laptop", sim=True)
    plan.processes = [p for p in plan.processes if p.name != "sim"]
    themselves, by_simulator = _bench().started_components(assembly, plan)
    assert (themselves, by_simulator) == (52, 0)
