"""``msctl view --foxglove`` at protocol level: a WebSocket client offering ``foxglove.sdk.v1``
against :class:`~msctl.view.foxglove_server.FoxgloveView` on a real Zenoh router, a dragon's
``joint_read`` published by a node of the test. Advertise, subscribe, CDR decoded (the URDF on
``/robot_description``, limb1's links on ``/tf``, the module's own ``joint_read`` as it was
sent), ``fetchAsset`` of a module's URDF, and an unknown asset refused."""

from __future__ import annotations

import contextlib
import json
import struct
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import quick_peer_settings, quick_router, resolved_assembly, wait_until

from components.comm import Node
from components.comm.session import SessionSettings
from components.comm.types import registry
from components.messages import JOINT_STATE, msg

pytest.importorskip("foxglove", reason="the view extra is not installed: pip install '.[view]'")

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def router_endpoint() -> Iterator[str]:
    yield from quick_router()


@pytest.fixture
def session_settings(router_endpoint: str) -> SessionSettings:
    return quick_peer_settings(router_endpoint)


class Client:
    """A Foxglove WebSocket client: JSON ops in, binary frames collected by opcode."""

    def __init__(self, port: int) -> None:
        from websockets.sync.client import connect

        self._stack = contextlib.ExitStack()
        self.socket = self._stack.enter_context(
            connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"])
        )
        self.channels: dict[str, dict[str, Any]] = {}
        self.messages: dict[int, list[bytes]] = {}
        self.assets: dict[int, tuple[int, str, bytes]] = {}
        self.lock = threading.Lock()
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        try:
            for frame in self.socket:
                with self.lock:
                    if isinstance(frame, str):
                        document = json.loads(frame)
                        if document.get("op") == "advertise":
                            for channel in document["channels"]:
                                self.channels[channel["topic"]] = channel
                    elif frame[0] == 0x01:  # message data
                        (subscription,) = struct.unpack_from("<I", frame, 1)
                        self.messages.setdefault(subscription, []).append(frame[13:])
                    elif frame[0] == 0x04:  # fetch asset response
                        request, status, length = struct.unpack_from("<IBI", frame, 1)
                        error = frame[10 : 10 + length].decode()
                        self.assets[request] = (status, error, frame[10 + length :])
        except Exception:
            return

    def send(self, **document: Any) -> None:
        self.socket.send(json.dumps(document))

    def subscribe(self, topic: str, subscription: int) -> None:
        channel = self.channels[topic]["id"]
        self.send(op="subscribe", subscriptions=[{"id": subscription, "channelId": channel}])

    def received(self, subscription: int) -> list[bytes]:
        with self.lock:
            return list(self.messages.get(subscription, []))

    def close(self) -> None:
        self._stack.close()
        self.thread.join(timeout=10)


def test_foxglove_clients_get_the_robot_its_tf_and_the_modules_topics(
    open_sessions: Callable[[], Any], tmp_path: Path
) -> None:
    from msctl.view.foxglove_server import FoxgloveView
    from msctl.view.scene import scene_of

    dragon = resolved_assembly(tmp_path, "dragon")
    types = registry()
    talker = Node(open_sessions(), "joint_manager", "/limb1")
    publisher = talker.publisher("/limb1/joint_read", JOINT_STATE)
    view = FoxgloveView(Node(open_sessions(), "view", "/"), dragon, scene_of(dragon), port=0)
    stop = threading.Event()
    with view:
        runner = threading.Thread(target=view.run, args=(stop.is_set,), daemon=True)
        runner.start()
        client = Client(view.port)
        try:
            wanted = ["/robot_description", "/tf_static", "/tf", "/limb1/joint_read"]
            wait_until(lambda: all(t in client.channels for t in wanted), 30, "advertise")
            joints = client.channels["/limb1/joint_read"]
            assert (joints["encoding"], joints["schemaEncoding"]) == ("cdr", "ros2msg")
            assert joints["schemaName"] == JOINT_STATE
            assert "MSG: std_msgs/Header" in joints["schema"]
            for number, topic in enumerate(wanted, start=1):
                client.subscribe(topic, number)
            # A subscriber that comes late still gets the description, as from a latched topic.
            wait_until(lambda: client.received(1), 30, "/robot_description")
            urdf = types.deserializer("std_msgs/msg/String")(client.received(1)[0]).data
            assert urdf == Path(dragon.urdf_path).read_text()
            wait_until(lambda: client.received(2), 30, "/tf_static")
            static = types.deserializer("tf2_msgs/msg/TFMessage")(client.received(2)[-1])
            assert {t.header.frame_id for t in static.transforms} == {"world"}
            assert "limb1_palm_link" in {t.child_frame_id for t in static.transforms}

            def sent_and_seen() -> bool:
                state = msg(JOINT_STATE, name=["limb1_joint2"], position=np.array([0.8]))
                publisher.publish(state)
                return bool(client.received(3)) and bool(client.received(4))

            wait_until(sent_and_seen, 30, "/tf and /limb1/joint_read at the client")
            tf = types.deserializer("tf2_msgs/msg/TFMessage")(client.received(3)[-1])
            moved = {t.child_frame_id: t.transform.translation for t in tf.transforms}
            assert "limb1_palm_link" in moved and "limb2_palm_link" not in moved
            assert abs(moved["limb1_palm_link"].z) > 0.3, "the palm lifted with joint2"
            echoed = types.deserializer(JOINT_STATE)(client.received(4)[-1])
            assert list(echoed.name) == ["limb1_joint2"] and echoed.position[0] == 0.8

            client.send(
                op="fetchAsset",
                uri="package://msctl/assemblies/modules/urdf/hl_limb_v1.urdf",
                requestId=7,
            )
            client.send(op="fetchAsset", uri="package://msctl/../../etc/passwd", requestId=8)
            wait_until(lambda: 7 in client.assets and 8 in client.assets, 30, "assets")
            status, error, data = client.assets[7]
            assert (status, error) == (0, "")
            assert data == (ROOT / "assemblies/modules/urdf/hl_limb_v1.urdf").read_bytes()
            assert client.assets[8][0] == 1, "outside msctl's packages: not served"
        finally:
            client.close()
            stop.set()
            runner.join(timeout=10)
            talker.close()
            view.node.close()
