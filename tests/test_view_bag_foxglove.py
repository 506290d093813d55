"""``msctl bag view --foxglove`` at protocol level: a bag written with msctl's own writer (the
four seconds of a dragon of tests/test_view_bag.py: limb1's joint2 from 0 to 1 rad) played by
:class:`~msctl.view.bag_foxglove.BagFoxglove` to a WebSocket client offering
``foxglove.sdk.v1``. The server advertises the bag's time range (playback control), the
composed ``/robot_description``, ``/tf_static``, ``/tf`` and the bag's own topics with their
schemas as recorded; a seek sends the picture at that time (joint_read recorded there, the
palm raised on ``/tf``); playing sends the messages after it, stamped with their recorded
times, until the end. The playhead itself (a pure Core) is tested with fake time.
"""

from __future__ import annotations

import contextlib
import json
import struct
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import resolved_assembly, wait_until
from test_view_bag import SECOND, write_bag

from components.comm.types import registry
from msctl.view.playback import ENDED, MAX_SPEED, PAUSED, PLAYING, Playhead

JOINT_STATE = "sensor_msgs/msg/JointState"
ROOT = Path(__file__).resolve().parents[1]


# ---------------------------------------------------------------------- the playhead (Core)
def test_the_playhead_plays_pauses_seeks_and_stops_at_the_end() -> None:
    head = Playhead(1000 * SECOND, 1004 * SECOND)
    assert (head.time(0.0), head.status(0.0)) == (1000 * SECOND, PAUSED)
    assert head.play(10.0) is False
    assert head.time(11.5) == 1001_500_000_000 and head.status(11.5) == PLAYING
    head.set_speed(2.0, 11.5)
    assert head.time(12.0) == 1002_500_000_000, "twice as fast from the change on"
    head.pause(12.0)
    assert head.time(50.0) == 1002_500_000_000 and head.status(50.0) == PAUSED
    assert head.seek(999 * SECOND, 50.0) == 1000 * SECOND, "clamped to the bag"
    assert head.seek(1003 * SECOND, 50.0) == 1003 * SECOND
    head.play(50.0)
    assert head.time(60.0) == 1004 * SECOND and head.status(60.0) == ENDED
    assert head.play(61.0) is True, "play at the end starts again"
    assert head.time(61.0) == 1000 * SECOND
    head.set_speed(float("inf"), 61.0)
    assert head.speed == MAX_SPEED
    with pytest.raises(ValueError, match="cannot come before"):
        Playhead(2, 1)


# ---------------------------------------------------------------------- the protocol
class Client:
    """A Foxglove WebSocket client: serverInfo, advertise, message data with log times,
    time, playback state and fetchAsset responses, collected as they come."""

    def __init__(self, port: int) -> None:
        from websockets.sync.client import connect

        self._stack = contextlib.ExitStack()
        self.socket = self._stack.enter_context(
            connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"])
        )
        self.info: dict[str, Any] = {}
        self.channels: dict[str, dict[str, Any]] = {}
        self.messages: dict[int, list[tuple[int, bytes]]] = {}
        self.times: list[int] = []
        self.states: list[tuple[int, int, float, bool, str]] = []
        self.assets: dict[int, tuple[int, str, bytes]] = {}
        self.lock = threading.Lock()
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        with contextlib.suppress(Exception):
            for frame in self.socket:
                with self.lock:
                    if isinstance(frame, str):
                        self._json(json.loads(frame))
                    else:
                        self._binary(frame)

    def _json(self, document: dict[str, Any]) -> None:
        if document.get("op") == "serverInfo":
            self.info = document
        elif document.get("op") == "advertise":
            for channel in document["channels"]:
                self.channels[channel["topic"]] = channel

    def _binary(self, frame: bytes) -> None:
        if frame[0] == 0x01:  # message data: subscription, log time, payload
            subscription, log_time = struct.unpack_from("<IQ", frame, 1)
            self.messages.setdefault(subscription, []).append((log_time, frame[13:]))
        elif frame[0] == 0x02:  # time
            self.times.append(struct.unpack_from("<Q", frame, 1)[0])
        elif frame[0] == 0x04:  # fetch asset response
            request, status, length = struct.unpack_from("<IBI", frame, 1)
            error = frame[10 : 10 + length].decode()
            self.assets[request] = (status, error, frame[10 + length :])
        elif frame[0] == 0x05:  # playback state
            status, current, speed, seeked, length = struct.unpack_from("<BQfBI", frame, 1)
            request = frame[19 : 19 + length].decode()
            self.states.append((status, current, speed, bool(seeked), request))

    def send(self, **document: Any) -> None:
        self.socket.send(json.dumps(document))

    def subscribe(self, topic: str, subscription: int) -> None:
        channel = self.channels[topic]["id"]
        self.send(op="subscribe", subscriptions=[{"id": subscription, "channelId": channel}])

    def control(self, play: bool, speed: float, seek: int | None, request: str) -> None:
        """A playback control request (binary opcode 3), as Foxglove's playback bar sends."""
        rid = request.encode()
        self.socket.send(
            bytes([0x03, 0 if play else 1])
            + struct.pack("<fBQI", speed, seek is not None, seek or 0, len(rid))
            + rid
        )

    def received(self, subscription: int) -> list[tuple[int, bytes]]:
        with self.lock:
            return list(self.messages.get(subscription, []))

    def state(self, request: str) -> tuple[int, int, float, bool, str] | None:
        with self.lock:
            return next((s for s in self.states if s[4] == request), None)

    def close(self) -> None:
        self._stack.close()
        self.thread.join(timeout=10)


@contextlib.contextmanager
def playing(bag: Path, assembly: Any, client_type: Any = None) -> Iterator[tuple[Any, Any]]:
    """``bag`` played by a BagFoxglove on a free port, stepping on a thread, and a client
    (``client_type``, this module's :class:`Client` by default) connected to it."""
    from msctl.view.bag_foxglove import BagFoxglove, read_bag
    from msctl.view.scene import scene_of

    player = BagFoxglove(read_bag(bag), assembly, scene_of(assembly), port=0)
    stop = threading.Event()
    with player:
        runner = threading.Thread(target=player.run, args=(stop.is_set,), daemon=True)
        runner.start()
        client = (client_type or Client)(player.port)
        try:
            yield client, player
        finally:
            client.close()
            stop.set()
            runner.join(timeout=10)


@pytest.fixture
def played(tmp_path: Path) -> Iterator[tuple[Client, Any, int]]:
    """The bag played by a BagFoxglove on a free port, a client connected to it."""
    dragon = resolved_assembly(tmp_path, "dragon")
    bag, start = write_bag(tmp_path / "dragon_bag")
    with playing(bag, dragon) as (client, player):
        yield client, player, start


def palm_height(tf: Any) -> float:
    moved = {t.child_frame_id: t.transform.translation for t in tf.transforms}
    return moved["limb1_palm_link"].z


def test_foxglove_plays_a_bag_over_its_range_and_seeks(played: tuple[Client, Any, int]) -> None:
    from components.recording.definitions import message_definition

    client, player, start = played
    types = registry()
    read_tf, read_joints = (
        types.deserializer("tf2_msgs/msg/TFMessage"),
        types.deserializer(JOINT_STATE),
    )
    wanted = ["/robot_description", "/tf_static", "/tf", "/limb1/joint_read", "/limb1/health"]
    wait_until(lambda: all(t in client.channels for t in wanted), 30, "advertise")
    # Foxglove's playback bar: the bag's range and the playback control capability.
    assert "playbackControl" in client.info["capabilities"]
    first, last = client.info["dataStartTime"], client.info["dataEndTime"]
    assert first["sec"] * SECOND + first["nsec"] == start
    assert last["sec"] * SECOND + last["nsec"] == start + 4 * SECOND
    # The bag's own topics as recorded (msctl's writer wrote rosbag2's schemas), and the
    # module the assembly does not know is forwarded too: it is the bag's.
    joints = client.channels["/limb1/joint_read"]
    assert (joints["encoding"], joints["schemaEncoding"]) == ("cdr", "ros2msg")
    assert (joints["schemaName"], joints["schema"]) == (
        JOINT_STATE,
        message_definition(JOINT_STATE),
    )
    assert "/limb9/joint_read" in client.channels
    for number, topic in enumerate(wanted[:4], start=1):
        client.subscribe(topic, number)
    # The picture at the start, to a subscriber that came after it was drawn.
    wait_until(
        lambda: client.received(1) and client.received(3) and client.received(4), 30, "present"
    )
    urdf = types.deserializer("std_msgs/msg/String")(client.received(1)[-1][1]).data
    assert urdf == Path(player.assembly.urdf_path).read_text()
    log_time, payload = client.received(4)[-1]
    assert log_time == start and read_joints(payload).position[0] == 0.0
    low = palm_height(read_tf(client.received(3)[-1][1]))

    client.send(
        op="fetchAsset",
        uri="package://msctl/assemblies/modules/urdf/hl_wheel_v1.urdf",
        requestId=5,
    )
    wait_until(lambda: 5 in client.assets, 30, "the asset")
    assert client.assets[5] == (
        0,
        "",
        (ROOT / "assemblies/modules/urdf/hl_wheel_v1.urdf").read_bytes(),
    )

    # Seek (paused) to 3 s: joint_read recorded there (0.75 rad) and the palm raised, at 3 s.
    seek = start + 3 * SECOND
    client.control(play=False, speed=1.0, seek=seek, request="seek-3s")
    wait_until(lambda: client.state("seek-3s"), 30, "the playback state after the seek")
    status, current, _, seeked, _ = client.state("seek-3s")
    assert (status, current, seeked) == (1, seek, True), "paused at 3 s, after a seek"

    def at_three_seconds() -> bool:
        seen = [client.received(4), client.received(3)]
        return all(any(t == seek for t, _ in got) for got in seen)

    wait_until(at_three_seconds, 30, "joint_read and /tf at 3 s")
    assert read_joints(client.received(4)[-1][1]).position[0] == pytest.approx(0.75)
    tf_time, tf = client.received(3)[-1]
    assert tf_time == seek and abs(palm_height(read_tf(tf)) - low) > 0.3, "the palm rose"
    wait_until(lambda: seek in client.times, 30, "the server's time at 3 s")
    before = len(client.received(4))

    # Play at 4x: the messages after 3 s come, in recorded order, up to the end.
    client.control(play=True, speed=4.0, seek=None, request="play")
    wait_until(lambda: client.state("play"), 30, "the playback state after play")
    assert client.state("play")[0] == 0, "playing"
    wait_until(lambda: any(s[0] == 3 for s in client.states), 60, "the end of the bag")
    after = [t for t, _ in client.received(4)[before:]]
    assert after == sorted(after) and seek < after[0] and after[-1] == start + 4 * SECOND
    assert len(after) == 20, "every joint_read recorded after 3 s, once"
    assert read_joints(client.received(4)[-1][1]).position[0] == pytest.approx(1.0)
