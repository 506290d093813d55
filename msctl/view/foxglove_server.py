"""``msctl view --foxglove``: a foxglove-sdk WebSocket server for Foxglove (or Lichtblick).

Foxglove's 3D panel animates a URDF from ``/tf`` and ``/tf_static``; msctl puts no global
``/tf`` on the network, so this server composes them here, from the lock's URDF and each
module's own ``joint_read`` (:class:`~msctl.view.scene.Scene`'s forward kinematics), for its
own clients only. Channels:

* ``/robot_description`` (std_msgs/String): the composed URDF, sent again to each subscriber
  (a late one gets it too, as a latched topic would give it);
* ``/tf_static`` and ``/tf`` (tf2_msgs/TFMessage): ``world`` -> every drawn link, the static
  ones once (and again to each subscriber), the moving ones as they move;
* ``/view/wheel_twist`` (visualization_msgs/MarkerArray): each wheel module's commanded twist
  (from its ``joint_set``) as an arrow at the module, which Foxglove's 3D panel draws (namespace
  ``wheel_twist/<slot>``; deleted while the module is commanded still);
* each module's own topics it shows (``joint_read``, ``health``, ``tip_pose``, ``ik_target``,
  a wheel module's ``joint_set``),
  as the raw CDR they arrived in, with ``ros2msg`` schemas written as rosbag2 writes them.

Assets: ``package://msctl/<path>`` URIs are files of msctl's installed packages (module URDFs
and their meshes); anything else is not found.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Self

from msctl.view.scene import Pose, Scene
from msctl.view.wheels import TWIST_TOLERANCE, WheelTwist

STRING = "std_msgs/msg/String"
TF = "tf2_msgs/msg/TFMessage"
MARKERS = "visualization_msgs/msg/MarkerArray"
#: The wheel modules' commanded twists, as arrow markers.
WHEEL_TWIST = "/view/wheel_twist"
#: Arrow colour (RGBA, 0-1): the rerun view's.
TWIST_RGBA = (60 / 255, 200 / 255, 230 / 255, 1.0)
#: The frame every link is placed in.
WORLD = "world"
#: What ``package://msctl/`` resolves to: the directory above msctl's packages.
PACKAGE_ROOT = Path(__file__).resolve().parents[2]


def asset(uri: str) -> bytes | None:
    """The bytes of a ``package://msctl/...`` file of msctl's own data, or ``None``."""
    prefix = "package://msctl/"
    if not uri.startswith(prefix):
        return None
    path = (PACKAGE_ROOT / uri[len(prefix) :]).resolve()
    allowed = [PACKAGE_ROOT / name for name in ("assemblies", "components", "msctl")]
    if not any(path.is_relative_to(root) for root in allowed) or not path.is_file():
        return None
    return path.read_bytes()


def tf_message(encode: Callable[[Any], bytes], poses: dict[str, Pose], stamp: int) -> bytes:
    """A ``tf2_msgs/TFMessage`` (CDR) placing each link of ``poses`` in :data:`WORLD`.

    Args:
        encode: The TFMessage serializer.
        poses: Link -> its pose in the world.
        stamp: The transforms' time (ns since the epoch).
    """
    from components.messages import msg

    transforms = []
    for link, (xyz, quaternion) in poses.items():
        stamped = msg("geometry_msgs/msg/TransformStamped", child_frame_id=link)
        stamped.header.frame_id = WORLD
        stamped.header.stamp.sec, stamped.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
        t, r = stamped.transform.translation, stamped.transform.rotation
        t.x, t.y, t.z = xyz
        r.x, r.y, r.z, r.w = quaternion
        transforms.append(stamped)
    return encode(msg(TF, transforms=transforms))


def twist_markers(
    encode: Callable[[Any], bytes], twists: dict[str, WheelTwist], stamp: int
) -> bytes:
    """A ``visualization_msgs/MarkerArray`` (CDR): one arrow per wheel module's commanded
    twist, from its wheels' centre along its velocity (1 m per m/s), in :data:`WORLD`; a
    module commanded still has its arrow deleted.

    Args:
        encode: The MarkerArray serializer.
        twists: Wheel module -> its commanded twist.
        stamp: The markers' time (ns since the epoch).
    """
    from components.messages import msg

    markers = []
    for slot, twist in twists.items():
        marker = msg("visualization_msgs/msg/Marker", ns=f"wheel_twist/{slot}", id=0, type=0)
        marker.header.frame_id = WORLD
        marker.header.stamp.sec, marker.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
        marker.action = 0 if twist.speed > TWIST_TOLERANCE else 2  # ADD, or DELETE when still
        start = msg("geometry_msgs/msg/Point", x=twist.origin[0], y=twist.origin[1])
        start.z = twist.origin[2]
        end = msg("geometry_msgs/msg/Point", x=start.x + twist.linear[0])
        end.y, end.z = start.y + twist.linear[1], start.z + twist.linear[2]
        marker.points = [start, end]
        marker.pose.orientation.w = 1.0
        # For an arrow given by points: shaft diameter, head diameter, head length (m).
        marker.scale.x, marker.scale.y, marker.scale.z = 0.02, 0.05, 0.06
        marker.color.r, marker.color.g, marker.color.b, marker.color.a = TWIST_RGBA
        marker.text = twist.label(slot)
        markers.append(marker)
    return encode(msg(MARKERS, markers=markers))


class ServedPicture:
    """What the live view and a bag's player share: the foxglove-sdk context, the channels
    with ``ros2msg`` schemas, the server (assets, CDR), the composed ``/robot_description``,
    ``/tf_static``, ``/tf`` and wheel twists, and the stepping loop. Subclasses set
    :attr:`assembly`, :attr:`scene`, :attr:`host`, :attr:`port`, :attr:`period` and define
    ``start`` and ``step``.
    """

    assembly: Any
    scene: Scene
    host: str
    port: int
    period: float
    server: Any
    channels: dict[str, Any]

    def start(self) -> Self:  # pragma: no cover (each server opens its own way)
        raise NotImplementedError

    def step(self) -> None:  # pragma: no cover
        raise NotImplementedError

    def _open(self) -> None:
        """The context, and the encoders of what is composed here."""
        import foxglove

        from components.comm.types import registry

        self._context = foxglove.Context()
        types = registry()
        self._encode_string = types.serializer(STRING)
        self._encode_tf = types.serializer(TF)
        self._encode_markers = types.serializer(MARKERS)

    def _channel(
        self,
        topic: str,
        type_name: str,
        definition: str | None = None,
        encoding: str = "ros2msg",
    ) -> Any:
        """Advertise ``topic`` as CDR with its schema (msctl's own definition by default)."""
        import foxglove

        from components.recording.definitions import message_definition

        text = (message_definition(type_name) or "") if definition is None else definition
        schema = foxglove.Schema(name=type_name, encoding=encoding, data=text.encode())
        made = foxglove.Channel(topic, schema=schema, message_encoding="cdr", context=self._context)
        self.channels[topic] = made
        return made

    def _serve(self, name: str, listener: Any, **more: Any) -> None:
        """Start the WebSocket server on :attr:`host`/:attr:`port` (the port it took kept)."""
        import foxglove

        self.server = foxglove.start_server(
            name=name,
            host=self.host,
            port=self.port,
            context=self._context,
            server_listener=listener,
            asset_handler=asset,
            supported_encodings=["cdr"],
            **more,
        )
        self.port = self.server.port

    def _send_description(self, at: int) -> None:
        """``/robot_description`` and ``/tf_static``: to every subscriber, the late ones too."""
        from components.messages import msg

        urdf = Path(self.assembly.urdf_path).read_text()
        self.channels["/robot_description"].log(
            self._encode_string(msg(STRING, data=urdf)), log_time=at
        )
        poses = self.scene.everything().poses
        self.channels["/tf_static"].log(tf_message(self._encode_tf, poses, at), log_time=at)

    def _send_tf(self, poses: dict[str, Pose], at: int) -> None:
        if poses:
            self.channels["/tf"].log(tf_message(self._encode_tf, poses, at), log_time=at)

    def _send_twists(self, twists: dict[str, WheelTwist], at: int) -> None:
        if twists:
            markers = twist_markers(self._encode_markers, twists, at)
            self.channels[WHEEL_TWIST].log(markers, log_time=at)

    def close(self) -> None:
        """Stop the server (idempotent)."""
        if self.server is not None:
            self.server.stop()
            self.server = None

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def run(self, until: Callable[[], bool]) -> None:
        """Step every :attr:`period` seconds until ``until()`` says stop."""
        while not until():
            started = time.monotonic()
            self.step()
            time.sleep(max(0.0, self.period - (time.monotonic() - started)))


class FoxgloveView(ServedPicture):
    """Serves a running assembly to Foxglove clients.

    Args:
        node: An open node; its owner closes it.
        assembly: The resolved assembly.
        scene: Its scene.
        port: The WebSocket port on ``host`` (0: any free one).
        host: Where to listen.
        period: Seconds between two ``/tf`` updates.
    """

    def __init__(
        self,
        node: Any,
        assembly: Any,
        scene: Scene,
        port: int = 8765,
        host: str = "127.0.0.1",
        period: float = 0.1,
    ) -> None:
        self.node = node
        self.assembly = assembly
        self.scene = scene
        self.port = port
        self.host = host
        self.period = period
        self.server: Any = None
        self.channels: dict[str, Any] = {}
        self.topics: list[str] = []
        self._subscriptions: list[Any] = []
        self._lock = threading.Lock()
        self._joints: dict[str, bytes] = {}
        self._wheel_sets: dict[str, list[bytes]] = {}
        self._decode: Any = None
        self._static: list[str] = []

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> FoxgloveView:
        """Open the server, advertise every channel, follow the modules' topics."""
        from components.comm.types import registry
        from components.messages import DIAGNOSTIC_ARRAY, JOINT_STATE

        self._open()
        self._decode = registry().deserializer(JOINT_STATE)
        channel = self._channel

        channel("/robot_description", STRING)
        channel("/tf_static", TF)
        channel("/tf", TF)
        channel(WHEEL_TWIST, MARKERS)
        wheels = self.scene.wheel_commands.wheels
        for module in self.assembly.modules:
            slot = module.slot
            shown = [(f"/{slot}/health", DIAGNOSTIC_ARRAY)]
            if module.joints:
                shown.append((f"/{slot}/joint_read", JOINT_STATE))
            if module.chains:
                shown += [
                    (f"/{slot}/{t}", "geometry_msgs/msg/PoseStamped")
                    for t in ("tip_pose", "ik_target")
                ]
            if slot in wheels:
                shown.append((f"/{slot}/joint_set", JOINT_STATE))
            for topic, type_name in shown:
                out = channel(topic, type_name)
                self._forward(topic, type_name, out, slot)
        self._serve(f"msctl view {self.assembly.template}", _Listener(self))
        self.scene.changes()
        self._send_description(time.time_ns())
        return self

    def _forward(self, topic: str, type_name: str, out: Any, slot: str) -> None:
        leaf = topic.rsplit("/", 1)[-1]

        def arrived(payload: Any) -> None:
            data = bytes(payload)
            out.log(data, log_time=time.time_ns())
            if leaf == "joint_read":
                with self._lock:
                    self._joints[slot] = data
            elif leaf == "joint_set":
                with self._lock:
                    # Each may name some wheels only: keep the few of a step, in order.
                    self._wheel_sets.setdefault(slot, []).append(data)
                    del self._wheel_sets[slot][:-8]

        self.topics.append(topic)
        self._subscriptions.append(self.node.subscription(topic, type_name, arrived, raw=True))

    def close(self) -> None:
        """Stop following and stop the server (idempotent)."""
        for subscription in self._subscriptions:
            subscription.close()
        self._subscriptions.clear()
        super().close()

    def step(self) -> None:
        """Apply the latest joint states; send the links that moved on ``/tf``."""
        from components.messages import joint_samples

        with self._lock:
            joints, self._joints = self._joints, {}
            wheel_sets, self._wheel_sets = self._wheel_sets, {}
        for slot, payload in joints.items():
            samples = joint_samples(self._decode(payload))
            self.scene.set_joints(slot, {s.name: s.position for s in samples})
        now = time.time()
        for slot, payloads in wheel_sets.items():
            for payload in payloads:
                samples = joint_samples(self._decode(payload))
                self.scene.set_wheel_command(slot, {s.name: s.velocity for s in samples}, now)
        self.scene.expire_wheel_commands(now)
        changes = self.scene.changes()
        stamp = time.time_ns()
        self._send_tf(changes.poses, stamp)
        self._send_twists(changes.twists, stamp)


class _Listener:
    """Sends ``/robot_description`` and ``/tf_static`` again to each new subscriber."""

    def __init__(self, view: FoxgloveView) -> None:
        self.view = view

    def on_subscribe(self, _client: Any, channel: Any) -> None:
        if channel.topic in ("/robot_description", "/tf_static"):
            self.view._send_description(time.time_ns())
