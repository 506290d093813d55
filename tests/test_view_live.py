"""The live view follows the graph (:class:`~msctl.view.live.LiveView` on a real Zenoh router):
limb1 played by nodes of the test, as the fleet emulator plays a module (its components' nodes
on the graph, its health), and drawn into an ``.rrd``. It turns OK when its health arrives, its
joints move the picture, a claim shows, and once its nodes leave the view says so (faded links,
"left the graph"). The time from the nodes closing to the view saying so is printed, not
asserted (it depends on the machine's load)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import quick_peer_settings, quick_router, resolved_assembly, wait_until

from components.comm import Node
from components.comm.session import SessionSettings
from components.messages import DIAGNOSTIC_ARRAY, JOINT_STATE, msg

pytest.importorskip("rerun", reason="the view extra is not installed: pip install '.[view]'")


@pytest.fixture
def router_endpoint() -> Iterator[str]:
    yield from quick_router()


@pytest.fixture
def session_settings(router_endpoint: str) -> SessionSettings:
    return quick_peer_settings(router_endpoint)


class Recorder:
    """A sink that keeps what it was told to say (and draws into an .rrd as well)."""

    def __init__(self, path: Path) -> None:
        from msctl.view.rerun_sink import RerunSink

        self.inner = RerunSink(save=path)
        self.said: list[str] = []

    def say(self, text: str, level: str = "INFO") -> None:
        self.said.append(text)
        self.inner.say(text, level)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)


def test_the_view_follows_a_module_onto_and_off_the_graph(
    open_sessions: Callable[[], Any], tmp_path: Path
) -> None:
    from assemblies.fleet import health_array
    from components.claims import Claims
    from components.data_monitor.plan import watched
    from msctl.view.live import LiveView
    from msctl.view.scene import scene_of

    dragon = resolved_assembly(tmp_path, "dragon")
    spec = next(s for s in watched(dragon) if s.name == "limb1")
    module_session = open_sessions()
    nodes = {
        e.label: Node(module_session, e.node.rpartition("/")[2], e.node.rpartition("/")[0])
        for e in spec.expected
    }
    health = nodes["health_monitor"].publisher("health", DIAGNOSTIC_ARRAY)
    joints = nodes["joint_manager"].publisher("joint_read", JOINT_STATE)
    labels = [e.label for e in spec.expected if e.label != "health_monitor"]
    stop, quiet = threading.Event(), threading.Event()

    def play() -> None:
        started = time.monotonic()
        while not quiet.wait(0.1):
            now = time.monotonic() - started
            health.publish(health_array(dragon.module("limb1"), labels, now, time.time()))
            joints.publish(msg(JOINT_STATE, name=["limb1_joint2"], position=np.array([0.8])))

    player = threading.Thread(target=play, daemon=True)
    scene = scene_of(dragon)
    sink = Recorder(tmp_path / "live.rrd")
    view = LiveView(Node(open_sessions(), "view", "/"), dragon, scene, sink)
    operator_session = open_sessions()
    operator = Node(operator_session, "teleop", "/ground1")
    claims = Claims(operator_session, 0)
    try:
        with view:
            runner = threading.Thread(target=view.run, args=(stop.is_set,), daemon=True)
            runner.start()
            player.start()
            limb1 = scene.modules["limb1"]
            wait_until(lambda: limb1.present and limb1.level == "OK", 30, "limb1 OK in the view")
            wait_until(lambda: scene.link_pose("limb1_palm_link")[0][2] < -0.3, 30, "joint2 moved")
            assert scene.modules["limb2"].level != "OK", "limb2 never spoke"
            claim = claims.claim("limb1", "ana@ground1", operator)
            wait_until(lambda: limb1.holder == "ana@ground1", 30, "the claim in the view")
            claim.release()
            wait_until(lambda: limb1.holder == "", 30, "the claim released in the view")
            quiet.set()
            player.join(timeout=5)
            left = time.monotonic()
            for node in nodes.values():
                node.close()
            wait_until(lambda: not limb1.present, 30, "limb1 gone from the view")
            print(
                f"\nlimb1's nodes closed -> the view said it left: {time.monotonic() - left:.2f} s"
            )
            assert limb1.look == "GONE"
            wait_until(lambda: "limb1: left the graph" in sink.said, 10, "the alarm log")
            assert "limb1: claimed by ana@ground1" in sink.said
            stop.set()
            runner.join(timeout=10)
    finally:
        stop.set()
        quiet.set()
        claims.close()
        operator.close()
        sink.close()
        view.node.close()
        for node in nodes.values():
            node.close()
