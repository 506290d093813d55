"""The launcher's health judgement on Zenoh (msctl.launcher.watch): a component is healthy once
its node is on the graph and its first output arrived; a node token the live graph never
delivered is asked for directly, so a running component never stays "starting"."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest
from conftest import wait_until

from components.comm.node import Node
from components.comm.session import SessionSettings, open_session
from components.messages import DIAGNOSTIC_ARRAY, diagnostic_array
from msctl.launcher import watch as watch_module
from msctl.launcher.plan import ComponentRun
from msctl.launcher.watch import RECHECK_AFTER, HealthWatch


def rear_operator(name: str) -> ComponentRun:
    """An autonomous operator of the rear station (they share its diagnostics output)."""
    return ComponentRun(
        name=f"gc_rear/{name}",
        kind="autonomous_operator",
        namespace="/gc_rear",
        node_fqn=f"/gc_rear/{name}",
        first_output="/gc_rear/diagnostics",
    )


GUARDIAN = rear_operator("d2_guardian")


class Clock:
    """Fake monotonic time."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


class BlindGraph:
    """A live graph that missed every token (what the watch must not be stuck on)."""

    def node_names(self) -> set[str]:
        return set()

    def close(self) -> None:
        pass


@pytest.fixture
def watched(open_sessions: Callable[[], Any]) -> Any:
    clock = Clock()
    # A peer, as the launcher's: its recheck asks through a client of the router.
    watch = HealthWatch(open_sessions(), [GUARDIAN], clock=clock)
    component = Node(open_sessions(), "d2_guardian", "/gc_rear")
    component.output = component.publisher("/gc_rear/diagnostics", DIAGNOSTIC_ARRAY)
    try:
        yield watch, component, clock
    finally:
        watch.close()
        component.close()


def publish_output(component: Node) -> None:
    component.output.publish(diagnostic_array([]))


def test_a_component_is_healthy_once_its_node_and_its_output_are_seen(watched: Any) -> None:
    watch, component, _clock = watched

    def published() -> bool:
        publish_output(component)
        return watch.status()[GUARDIAN.name][1]

    wait_until(lambda: watch.status()[GUARDIAN.name][0], 30.0, "the node on the live graph")
    assert not watch.healthy(GUARDIAN.name)  # its node alone is not enough
    wait_until(published, 30.0, "its first output", interval=0.1)
    assert watch.healthy(GUARDIAN.name)
    watch.forget([GUARDIAN.name])  # its process restarted: it must show itself again
    assert watch.status()[GUARDIAN.name] == (True, False)


def test_a_component_that_starts_after_the_watch_is_seen_by_its_first_output(
    open_sessions: Callable[[], Any], router_endpoint: str
) -> None:
    """Outputs taken through a client of the router: a new peer sends its samples there from
    the start, where a peer session (the launcher's) gets them only once directly linked
    (measured: the first sample of 3 new peers in 20)."""
    client = open_session(SessionSettings(mode="client", connect=(router_endpoint,), listen=()))
    watch = HealthWatch(open_sessions(), [GUARDIAN], outputs_session=client)
    try:
        for _ in range(3):  # each a component process starting: one output, at once
            component = Node(open_sessions(), "d2_guardian", "/gc_rear")
            output = component.publisher("/gc_rear/diagnostics", DIAGNOSTIC_ARRAY)
            output.publish(diagnostic_array([]))
            wait_until(lambda: watch.status()[GUARDIAN.name][1], 30.0, "its one output")
            watch.forget([GUARDIAN.name])
            component.close()
    finally:
        watch.close()
        client.close()


def test_a_node_token_the_live_graph_missed_is_found_by_asking(
    watched: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    watch, component, clock = watched
    watch._graph.close()
    watch._graph = BlindGraph()
    asked: list[set[str]] = []
    real_snapshot = watch_module.snapshot

    def counted_snapshot(*args: Any) -> Any:
        found = real_snapshot(*args)
        asked.append(found.node_names())
        return found

    monkeypatch.setattr(watch_module, "snapshot", counted_snapshot)

    def published() -> bool:
        publish_output(component)
        return watch.status()[GUARDIAN.name][1]

    wait_until(published, 30.0, "its first output", interval=0.1)
    # Not asked before RECHECK_AFTER: the live graph usually catches up by itself.
    assert watch.status()[GUARDIAN.name] == (False, True) and asked == []
    clock.now += RECHECK_AFTER

    def found() -> bool:
        status = watch.status()[GUARDIAN.name]
        if not status[0]:
            clock.now += RECHECK_AFTER  # a query that ran before the token reached the router
        return status[0]

    wait_until(found, 30.0, "the node found by a direct query", interval=0.1)
    assert watch.healthy(GUARDIAN.name)
    assert all(names <= {"/gc_rear/d2_guardian"} for names in asked) and asked
    # A restart forgets what the query found: the component must show itself again.
    watch.forget([GUARDIAN.name])
    assert watch.status()[GUARDIAN.name] == (False, False)


def test_nothing_is_asked_while_the_live_graph_has_every_node(watched: Any, monkeypatch) -> None:
    watch, component, clock = watched
    monkeypatch.setattr(
        watch_module, "snapshot", lambda *a: pytest.fail("asked while the graph had the node")
    )

    def published() -> bool:
        publish_output(component)
        return watch.healthy(GUARDIAN.name)

    wait_until(published, 30.0, "node and output", interval=0.1)
    clock.now += 10 * RECHECK_AFTER
    assert watch.healthy(GUARDIAN.name)


def test_the_shared_judgement_is_node_and_first_output_with_fake_time() -> None:
    """ComponentWatch, the part both transports share: outputs shared by a namespace's
    components, the age of the first output, a restart forgotten."""
    from components.health_monitor.startup_watch import ComponentWatch

    posture = rear_operator("d2_posture")

    class Fixed(ComponentWatch):
        nodes: set[str] = set()

        def node_names(self) -> set[str]:
            return set(self.nodes)

    clock = Clock()
    watch = Fixed([GUARDIAN, posture], clock)
    assert watch.outputs() == {"/gc_rear/diagnostics": [GUARDIAN.name, posture.name]}
    assert watch.status() == {GUARDIAN.name: (False, False), posture.name: (False, False)}
    watch.saw([GUARDIAN.name, posture.name])
    clock.now += 1.5
    watch.saw([GUARDIAN.name])  # a later sample does not make the first one younger
    assert watch.output_age(GUARDIAN.name) == 1.5
    Fixed.nodes = {GUARDIAN.node_fqn}
    assert watch.healthy(GUARDIAN.name) and not watch.healthy(posture.name)
    watch.forget([GUARDIAN.name])
    assert watch.output_age(GUARDIAN.name) is None and not watch.healthy(GUARDIAN.name)


def test_the_launcher_takes_outputs_on_its_peer_session_when_no_client_opens(
    open_sessions: Callable[[], Any], session_settings: SessionSettings, monkeypatch
) -> None:
    """The router answered a moment ago and no longer does: the launch goes on, its watch
    taking the outputs on the peer session, and says so."""
    from types import SimpleNamespace

    from components.comm.session import SessionOpenError
    from msctl.launcher import run

    def refuse(settings: SessionSettings) -> Any:
        raise SessionOpenError(f"no router at {settings.connect[0]}")

    monkeypatch.setattr(run, "open_session", refuse)
    peer = open_sessions()
    launch = SimpleNamespace(
        settings=session_settings,
        session=peer,
        plan=SimpleNamespace(components=[GUARDIAN]),
        events=[],
        watch=None,
        _watch_session=None,
    )
    run.Launch._watch(launch)  # type: ignore[arg-type]
    try:
        assert launch._watch_session is None
        endpoint = session_settings.connect[0]
        assert launch.events == [
            f"health watch: outputs on the peer session (no router at {endpoint})"
        ]
        component = Node(open_sessions(), "d2_guardian", "/gc_rear")
        component.output = component.publisher("/gc_rear/diagnostics", DIAGNOSTIC_ARRAY)

        def published() -> bool:
            publish_output(component)
            return launch.watch.status()[GUARDIAN.name][1]

        wait_until(published, 30.0, "its output on the peer session", interval=0.1)
        component.close()
    finally:
        launch.watch.close()
