"""Each wheel module's commanded twist, drawn at the module: from its ``joint_set`` (the wheel
velocities the steering sends it), in the Core with plain calls; live in rerun and Foxglove
(a real Zenoh router, a test node sending the commands at 40 Hz as the steering does); and
from a bag, in rerun (the ``.rrd`` read back) and played to Foxglove (seeks).

The dragon lies flat along x with wheel1 at limb1's tip (+x) and wheel2 at limb2's (-x),
turned half a turn: the same spin (+2 rad/s on both wheels, radius 0.16 m) drives wheel1
along +x at 0.32 m/s and wheel2 along -x. Opposite spins on a module turn it on the spot.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import quick_peer_settings, quick_router, resolved_assembly, wait_until
from test_view_bag import SECOND, column, home, rows_of, spec  # noqa: F401 (home: a fixture)
from test_view_foxglove import Client
from typer.testing import CliRunner

from components.comm import Node
from components.comm.session import SessionSettings
from components.comm.types import registry
from components.messages import JOINT_STATE, msg
from components.recording.writer import BagWriter
from msctl.app import app
from msctl.view.scene import Scene, scene_of
from msctl.view.wheels import COMMAND_TIMEOUT

pytest.importorskip("rerun", reason="the view extra is not installed: pip install '.[view]'")
pytest.importorskip("foxglove", reason="the view extra is not installed: pip install '.[view]'")

MARKERS = "visualization_msgs/msg/MarkerArray"


def command(slot: str, left: float, right: float) -> Any:
    """A wheel module's ``joint_set``: velocities only, as the wheel drive sends them."""
    names = [f"{slot}_wheel_left", f"{slot}_wheel_right"]
    return msg(JOINT_STATE, name=names, velocity=np.array([left, right]))


def velocities(slot: str, left: float, right: float) -> dict[str, float]:
    return {f"{slot}_wheel_left": left, f"{slot}_wheel_right": right}


# ---------------------------------------------------------------------- the Core
@pytest.fixture(scope="module")
def dragon(tmp_path_factory: pytest.TempPathFactory) -> Any:
    return resolved_assembly(tmp_path_factory.mktemp("wheels"), "dragon")


def test_each_wheel_module_gets_its_own_twist_from_its_wheels(dragon: Any) -> None:
    scene: Scene = scene_of(dragon)
    assert set(scene.wheel_commands.wheels) == {"wheel1", "wheel2"}, "limbs have no wheels"
    scene.changes()
    assert not scene.changes().twists, "nothing commanded, nothing drawn"
    scene.set_wheel_command("wheel1", velocities("wheel1", 2.0, 2.0), at=10.0)
    scene.set_wheel_command("wheel2", velocities("wheel2", 2.0, -2.0), at=10.0)
    scene.set_wheel_command("limb1", {"limb1_joint1": 1.0}, at=10.0)
    twists = scene.changes().twists
    assert set(twists) == {"wheel1", "wheel2"}
    ahead, spin = twists["wheel1"], twists["wheel2"]
    assert ahead.linear == pytest.approx((0.32, 0.0, 0.0), abs=1e-9)
    assert ahead.yaw_rate == pytest.approx(0.0, abs=1e-9)
    body = scene.link_pose("wheel1_body_link")[0]
    assert ahead.origin[0] == pytest.approx(body[0], abs=0.05), "drawn at wheel1, +x"
    assert spin.origin[0] < -1.0 and spin.speed == pytest.approx(0.0, abs=1e-9)
    assert abs(spin.yaw_rate) > 1.0, "opposite spins turn wheel2 on the spot"
    assert ahead.label("wheel1") == "wheel1: 0.32 m/s, +0.00 rad/s"
    # A repeat draws nothing; a change draws that module only; one wheel may change alone.
    scene.set_wheel_command("wheel1", velocities("wheel1", 2.0, 2.0), at=10.1)
    assert not scene.changes().twists
    scene.set_wheel_command("wheel1", {"wheel1_wheel_right": 0.0}, at=10.2)
    changed = scene.changes().twists
    assert set(changed) == {"wheel1"}
    assert changed["wheel1"].linear[0] == pytest.approx(0.16) and changed["wheel1"].yaw_rate < 0
    # Commands stop: the joint managers' watchdogs stop the wheels, and so does the picture.
    assert scene.expire_wheel_commands(10.2 + COMMAND_TIMEOUT / 2) == []
    assert scene.expire_wheel_commands(10.2 + COMMAND_TIMEOUT * 2) == ["wheel1", "wheel2"]
    stopped = scene.changes().twists
    assert stopped["wheel1"].speed == 0.0 and stopped["wheel2"].yaw_rate == 0.0
    # The limbs moving carries the arrow with the wheel: limb1's joint2 lifts wheel1.
    scene.set_joints("limb1", {"limb1_joint2": 0.8})
    scene.set_wheel_command("wheel1", velocities("wheel1", 1.0, 1.0), at=20.0)
    lifted = scene.changes().twists["wheel1"]
    assert abs(lifted.origin[2] - ahead.origin[2]) > 0.3


# ---------------------------------------------------------------------- live
@pytest.fixture
def router_endpoint() -> Iterator[str]:
    yield from quick_router()


@pytest.fixture
def session_settings(router_endpoint: str) -> SessionSettings:
    return quick_peer_settings(router_endpoint)


class Steering:
    """Sends each wheel module its command at 40 Hz, as the steering operator does."""

    def __init__(self, node: Node) -> None:
        self.publishers = {
            s: node.publisher(f"/{s}/joint_set", JOINT_STATE) for s in ("wheel1", "wheel2")
        }
        self.spins = {"wheel1": (2.0, 2.0), "wheel2": (2.0, 2.0)}
        self.quiet = threading.Event()
        self.thread = threading.Thread(target=self._send, daemon=True)

    def _send(self) -> None:
        while not self.quiet.wait(0.025):
            for slot, (left, right) in dict(self.spins).items():
                self.publishers[slot].publish(command(slot, left, right))


class Twists:
    """A real rerun sink (into an .rrd) that also keeps the twists it was told to draw."""

    def __init__(self, path: Path) -> None:
        from msctl.view.rerun_sink import RerunSink

        self.inner = RerunSink(save=path)
        self.drawn: dict[str, Any] = {}

    def draw(self, scene: Any, changes: Any) -> None:
        self.drawn.update(changes.twists)
        self.inner.draw(scene, changes)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)


def arrows(payload: bytes) -> dict[str, tuple[int, tuple[float, float, float]]]:
    """A MarkerArray's arrows: namespace -> (action, end - start)."""
    out = {}
    for marker in registry().deserializer(MARKERS)(payload).markers:
        start, end = marker.points
        out[marker.ns] = (marker.action, (end.x - start.x, end.y - start.y, end.z - start.z))
    return out


def test_live_views_draw_each_wheel_modules_command(
    open_sessions: Callable[[], Any], tmp_path: Path, dragon: Any
) -> None:
    from msctl.view.foxglove_server import WHEEL_TWIST, FoxgloveView
    from msctl.view.live import LiveView

    steering = Steering(Node(open_sessions(), "steering", "/gc1"))
    sink = Twists(tmp_path / "live.rrd")
    rerun_view = LiveView(Node(open_sessions(), "view", "/"), dragon, scene_of(dragon), sink)
    foxglove_view = FoxgloveView(
        Node(open_sessions(), "view", "/"), dragon, scene_of(dragon), port=0
    )
    stop = threading.Event()
    runners = []
    client = None
    try:
        with rerun_view, foxglove_view:
            assert (
                "/wheel1/joint_set" in rerun_view.topics
                and "/wheel2/joint_set" in rerun_view.topics
            )
            for view in (rerun_view, foxglove_view):
                runners.append(threading.Thread(target=view.run, args=(stop.is_set,), daemon=True))
                runners[-1].start()
            client = Client(foxglove_view.port)
            wait_until(lambda: WHEEL_TWIST in client.channels, 30, "the wheel twist channel")
            assert client.channels[WHEEL_TWIST]["schemaName"] == MARKERS
            client.subscribe(WHEEL_TWIST, 1)
            steering.thread.start()

            def foxglove_arrows() -> dict[str, Any]:
                got: dict[str, Any] = {}
                for payload in client.received(1):
                    got.update(arrows(payload))
                return got

            def foxglove_shows(wheel1_x: float) -> bool:
                got = foxglove_arrows()
                one, two = got.get("wheel_twist/wheel1"), got.get("wheel_twist/wheel2")
                return bool(one and two and abs(one[1][0] - wheel1_x) < 1e-6 and two[0] == 0)

            def rerun_shows(wheel1_x: float) -> bool:
                one, two = sink.drawn.get("wheel1"), sink.drawn.get("wheel2")
                return bool(one and two and abs(one.linear[0] - wheel1_x) < 1e-6)

            wait_until(lambda: rerun_shows(0.32) and foxglove_shows(0.32), 30, "forward")
            assert sink.drawn["wheel2"].linear[0] == pytest.approx(-0.32), "turned half a turn"
            steering.spins["wheel1"] = (-1.0, -1.0)
            wait_until(lambda: rerun_shows(-0.16) and foxglove_shows(-0.16), 30, "backward")
            steering.quiet.set()
            steering.thread.join(timeout=5)
            # The commands stop: the joint managers' watchdogs stop the wheels, the views too;
            # Foxglove's arrows of modules commanded still are deleted.
            wait_until(
                lambda: rerun_shows(0.0) and all(a[0] == 2 for a in foxglove_arrows().values()),
                30,
                "stopped, as the watchdog stops the wheels",
            )
    finally:
        stop.set()
        steering.quiet.set()
        for runner in runners:
            runner.join(timeout=10)
        if client is not None:
            client.close()
        sink.close()
        for view in (rerun_view, foxglove_view):
            view.node.close()
    rows = rows_of(tmp_path / "live.rrd")
    vectors = [v[0][0] for _, v in column(rows["/twist/wheel1"], "Arrows3D:vectors")]
    assert any(abs(x - 0.32) < 1e-3 for x in vectors) and any(abs(x + 0.16) < 1e-3 for x in vectors)
    assert "/twist/wheel2" in rows


# ---------------------------------------------------------------------- bags
def write_wheel_bag(directory: Path) -> tuple[Path, int]:
    """Three seconds: wheel1 +2 rad/s for 1 s, then -1 rad/s for 1 s, then no command (the
    watchdog stops it); wheel2 +2 rad/s throughout; the joints at zero."""
    types = registry()
    encode = types.serializer(JOINT_STATE)
    start = time.time_ns()
    with BagWriter(directory) as writer:
        joints = writer.add_topic(spec("/limb1/joint_read", JOINT_STATE))
        wheels = {
            s: writer.add_topic(spec(f"/{s}/joint_set", JOINT_STATE)) for s in ("wheel1", "wheel2")
        }
        for i in range(121):
            at = start + i * SECOND // 40
            state = msg(JOINT_STATE, name=["limb1_joint2"], position=np.array([0.0]))
            writer.write(joints, at, encode(state), at, i + 1)
            if i < 80:
                spin = 2.0 if i < 40 else -1.0
                writer.write(wheels["wheel1"], at, encode(command("wheel1", spin, spin)), at, i + 1)
            writer.write(wheels["wheel2"], at, encode(command("wheel2", 2.0, 2.0)), at, i + 1)
    return directory, start


def test_a_bags_wheel_commands_on_rerun_s_timeline(home: Path, tmp_path: Path) -> None:  # noqa: F811
    bag, start = write_wheel_bag(tmp_path / "wheels_bag")
    rrd = tmp_path / "wheels.rrd"
    result = CliRunner().invoke(app, ["bag", "view", str(bag), "--no-serve", "--save", str(rrd)])
    assert result.exit_code == 0, result.output
    rows = rows_of(rrd)
    drawn = [(t - start, v[0][0]) for t, v in column(rows["/twist/wheel1"], "Arrows3D:vectors")]
    assert drawn[0][1] == pytest.approx(0.32) and drawn[0][0] < SECOND // 10
    assert any(x == pytest.approx(-0.16) and SECOND <= t < 2 * SECOND for t, x in drawn)
    last_t, last_x = drawn[-1]
    assert last_x == 0.0 and last_t >= 2 * SECOND, "stopped after the commands stopped"
    wheel2 = [v[0][0] for _, v in column(rows["/twist/wheel2"], "Arrows3D:vectors")]
    assert wheel2 == [pytest.approx(-0.32)], "one command all along: drawn once"


def test_a_bags_wheel_commands_played_to_foxglove(tmp_path: Path, dragon: Any) -> None:
    from test_view_bag_foxglove import playing

    from msctl.view.foxglove_server import WHEEL_TWIST

    bag, start = write_wheel_bag(tmp_path / "wheels_bag")
    with playing(bag, dragon, Client) as (client, _player):
        wait_until(lambda: WHEEL_TWIST in client.channels, 30, "advertise")
        client.subscribe(WHEEL_TWIST, 1)
        for n, (seek, wheel1) in enumerate(
            [(0.5, (0, 0.32)), (1.5, (0, -0.16)), (2.9, (2, 0.0)), (0.2, (0, 0.32))]
        ):
            at = start + int(seek * SECOND)
            seen = len(client.received(1))
            client.socket.send(_seek(at, f"seek-{n}"))

            def shown(at: int = at, seen: int = seen) -> dict[str, Any] | None:
                later = client.received(1)[seen:]
                return arrows(later[-1]) if later else None

            got = wait_until(shown, 30, f"the wheels' arrows at {seek} s")
            action, vector = got["wheel_twist/wheel1"]
            assert (action, vector[0]) == pytest.approx(wheel1), f"wheel1 at {seek} s"
            assert got["wheel_twist/wheel2"][1][0] == pytest.approx(-0.32)


def _seek(at: int, request: str) -> bytes:
    """A paused seek (binary playback control request, opcode 3)."""
    import struct

    rid = request.encode()
    return bytes([0x03, 1]) + struct.pack("<fBQI", 1.0, 1, at, len(rid)) + rid
