"""The data_monitor component kind: registered, planned on the ground stations, and run for
real in-process on Zenoh (in-process publishers stand in for the modules)."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from typing import Any

import pytest
from conftest import quick_peer_settings, quick_router, wait_until
from test_health_board import health
from test_health_live import FakeModule

from components import kinds
from components.assembly import ResolvedAssembly, from_document
from components.build import build_component
from components.comm.node import Node
from components.comm.session import SessionSettings, open_session
from components.data_monitor.core import DIAGNOSTIC_STATUS
from components.executor.runner import run_built
from components.messages import DIAGNOSTIC_ARRAY
from msctl.assembler import resolve
from msctl.health.live import LiveHealth
from msctl.launcher.plan import plan_host


@pytest.fixture(scope="module")
def dragon() -> ResolvedAssembly:
    return from_document(resolve("dragon").document)


@pytest.fixture
def router_endpoint() -> Iterator[str]:
    yield from quick_router()


@pytest.fixture
def session_settings(router_endpoint: str) -> SessionSettings:
    return quick_peer_settings(router_endpoint)


def test_the_kind_is_a_runnable_station_kind_with_checked_parameters() -> None:
    entry = kinds.get("data_monitor")
    assert entry.placement is kinds.Placement.STATION and entry.runnable
    assert entry.healthy_output == "/diagnostics_toplevel_state"
    kinds.check_params(entry, {"publish_period": 2.0, "max_items": 10})
    with pytest.raises(kinds.KindError, match="publish_period must be > 0"):
        kinds.check_params(entry, {"publish_period": 0.0})
    with pytest.raises(kinds.KindError, match="no parameter 'period'"):
        kinds.check_params(entry, {"period": 1.0})


def test_two_dragons_starts_its_five_data_monitors_one_process_per_station() -> None:
    two = from_document(resolve("two_dragons").document)
    plan = plan_host(two, "a-laptop")
    monitors = [c for c in plan.components if c.kind == "data_monitor"]
    assert sorted(c.name for c in monitors) == [
        "gc_front/data_monitor_1",
        "gc_front/data_monitor_2",
        "gc_rear/data_monitor_1",
        "gc_rear/data_monitor_2",
        "gc_remote/data_monitor",
    ]
    processes = {
        p.name for p in plan.processes if any(c.kind == "data_monitor" for c in p.components)
    }
    assert processes == {
        "gc_front_data_monitor",
        "gc_rear_data_monitor",
        "gc_remote_data_monitor",
    }
    assert {c.node_fqn for c in monitors} >= {"/gc_front/data_monitor_1", "/gc_remote/data_monitor"}
    assert "data_monitor" not in {k for _, k in plan.not_built}


def test_the_data_monitor_publishes_the_aggregate_and_serves_its_alarms(
    dragon: ResolvedAssembly, session_settings: SessionSettings
) -> None:
    built = build_component(dragon.component("gc1/data_monitor"), dragon, {})
    ready = threading.Event()
    executors: list[Any] = []

    def on_ready(executor: Any) -> None:
        executors.append(executor)
        ready.set()

    runner = threading.Thread(
        target=run_built, args=([built], session_settings), kwargs={"on_ready": on_ready}
    )
    runner.start()
    modules = open_session(session_settings)
    viewer = open_session(session_settings)
    node = Node(viewer, "agg_reader")
    received: list[Any] = []
    top: list[Any] = []
    limb = None
    live = None
    try:
        assert ready.wait(30.0)
        node.subscription("/diagnostics_agg", DIAGNOSTIC_ARRAY, received.append)
        node.subscription("/diagnostics_toplevel_state", DIAGNOSTIC_STATUS, top.append)
        limb = FakeModule(modules, dragon, "limb1")

        def limb_ok() -> bool:
            for array in received[-3:]:
                levels = {s.name: s.level for s in array.status}
                if levels.get("/dragon/limb1") == 0:
                    return True
            return False

        wait_until(limb_ok, timeout=30.0, what="/dragon/limb1 OK in /diagnostics_agg")
        names = {s.name for s in received[-1].status}
        assert {"/dragon", "/dragon/limb1/components", "/dragon/gc1"} <= names
        assert "/dragon/limb1/components/joint_manager" in names
        wait_until(lambda: top, timeout=30.0, what="/diagnostics_toplevel_state")
        assert top[-1].name == "toplevel_state"
        limb.message = health("limb1", ("motors/j1", 2, "too hot", {}))
        wait_until(
            lambda: any(
                s.name == "/dragon/limb1/motors/j1" and s.level == 2 for s in received[-1].status
            ),
            timeout=30.0,
            what="the hot motor in /diagnostics_agg",
        )
        # A screen opened now gets what the data monitor saw before it.
        live = LiveHealth(node, dragon, supervisors=False).start()
        wait_until(live.data_monitors, timeout=30.0, what="the alarm service on the graph")
        assert live.data_monitors() == ["/gc1/data_monitor/alarms"]
        assert live.fetch_history() > 0
        assert live.history_source == "gc1/data_monitor"
        assert any(a.item == "limb1/motors/j1" and a.after.name == "ERROR" for a in live.alarms())
    finally:
        if live is not None:
            live.close()
        if limb is not None:
            limb.close()
        if executors:
            executors[0].stop()
        runner.join(timeout=30.0)
        node.close()
        viewer.close()
        modules.close()
    assert not runner.is_alive()
