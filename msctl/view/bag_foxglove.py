"""``msctl bag view --foxglove``: a recorded bag played to Foxglove, with its playback bar.

The same picture as the live ``msctl view --foxglove``
(:class:`~msctl.view.foxglove_server.FoxgloveView`): ``/robot_description`` (again to each
subscriber), ``/tf_static`` and ``/tf`` composed from the bag's ``joint_read`` by the
:class:`~msctl.view.scene.Scene`, meshes through the asset handler; and every topic of the
bag as the raw CDR it was recorded in, with its ``ros2msg`` schema as recorded (a schema in
the old ``MSG: pkg/msg/Type`` form, which Foxglove cannot parse, is sent in rosbag2's form,
and the view says which topics).

foxglove-sdk's server advertises the bag's time range (``playbackControl``): Foxglove shows
its playback bar over that range, and its play, pause, speed and seek come back as playback
control requests. A :class:`~msctl.view.playback.Playhead` (pure) says where the picture is;
the loop (:meth:`BagFoxglove.run`) sends each message when the playhead passes its recorded
time, stamped with it, and announces the playhead's time. A seek sends the picture at the
new time at once: every topic's latest message up to it, and the links where its joints were.

The bag is read into memory once (as rerun's bag view reads it whole into its recording), so
seeking is a bisection, not a re-read.
"""

from __future__ import annotations

import bisect
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from msctl.view.foxglove_server import MARKERS, STRING, TF, WHEEL_TWIST, ServedPicture
from msctl.view.playback import ENDED, PLAYING, Playhead
from msctl.view.scene import Scene

#: What the view composes itself (topic -> type): a bag's own topics of these names are not
#: forwarded.
COMPOSED = {"/robot_description": STRING, "/tf_static": TF, "/tf": TF, WHEEL_TWIST: MARKERS}
#: Nanoseconds per second.
SECOND = 1_000_000_000


@dataclass
class RecordedBag:
    """A bag read into memory, in log-time order.

    Attributes:
        path: The bag.
        messages: Every message (:class:`~msctl.recorder.bag.BagMessage`), by log time.
        definitions: Topic -> its :class:`~msctl.recorder.bag.TopicDefinition` as recorded.
        fixed: Topics whose schema was recorded in the old form and is sent fixed.
        left_out: The bag's own topics of :data:`COMPOSED` names (not forwarded).
    """

    path: Path
    messages: list[Any] = field(default_factory=list)
    definitions: dict[str, Any] = field(default_factory=dict)
    fixed: list[str] = field(default_factory=list)
    left_out: list[str] = field(default_factory=list)
    _times: list[int] = field(default_factory=list)
    _by_topic: dict[str, tuple[list[int], list[int]]] = field(default_factory=dict)

    @property
    def start(self) -> int:
        """The first log time (ns)."""
        return self._times[0]

    @property
    def end(self) -> int:
        """The last log time (ns)."""
        return self._times[-1]

    def index(self) -> None:
        """Sort by log time and index each topic's messages (after :attr:`messages` is set)."""
        self.messages.sort(key=lambda m: m.log_time)
        self._times = [m.log_time for m in self.messages]
        self._by_topic = {}
        for i, message in enumerate(self.messages):
            times, indexes = self._by_topic.setdefault(message.topic, ([], []))
            times.append(message.log_time)
            indexes.append(i)

    def after(self, at: int) -> int:
        """The index of the first message recorded after ``at`` (ns)."""
        return bisect.bisect_right(self._times, at)

    def latest(self, topic: str, at: int) -> Any | None:
        """A topic's last message recorded at or before ``at`` (ns), or ``None``."""
        times, indexes = self._by_topic.get(topic, ([], []))
        found = bisect.bisect_right(times, at)
        return self.messages[indexes[found - 1]] if found else None


def read_bag(bag: Path, progress: Callable[[float], None] | None = None) -> RecordedBag:
    """A bag's messages and schemas, read whole.

    Raises:
        BagError: If the bag cannot be read or holds no message.
    """
    from components.recording.definitions import fixed_definition, needs_fixing
    from components.recording.errors import BagError
    from msctl.recorder.bag import inspect, read_messages

    info = inspect(bag)
    recorded = RecordedBag(bag)
    span = max(info.end_time - info.metadata.starting_time, 1)

    def described(definition: Any) -> None:
        if needs_fixing(definition.definition):
            definition.definition = fixed_definition(definition.definition)
            recorded.fixed.append(definition.name)
        recorded.definitions[definition.name] = definition

    for count, message in enumerate(read_messages(info, on_definition=described)):
        if message.topic in COMPOSED:
            if message.topic not in recorded.left_out:
                recorded.left_out.append(message.topic)
            continue
        recorded.messages.append(message)
        if progress is not None and count % 1000 == 0:
            progress((message.log_time - info.metadata.starting_time) / span)
    if not recorded.messages:
        raise BagError(f"{bag}: no message to play")
    recorded.index()
    return recorded


class BagFoxglove(ServedPicture):
    """Plays a recorded bag to Foxglove clients, as the live view serves a running assembly.

    Args:
        recorded: The bag (:func:`read_bag`).
        assembly: The resolved assembly it was recorded from.
        scene: Its scene.
        port: The WebSocket port on ``host`` (0: any free one).
        host: Where to listen.
        period: Seconds between two steps of the loop.
        clock: Wall-clock seconds (monotonic) that move the playhead.
    """

    def __init__(
        self,
        recorded: RecordedBag,
        assembly: Any,
        scene: Scene,
        port: int = 8765,
        host: str = "127.0.0.1",
        period: float = 0.05,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.recorded = recorded
        self.assembly = assembly
        self.scene = scene
        self.port = port
        self.host = host
        self.period = period
        self.clock = clock
        self.playhead = Playhead(recorded.start, recorded.end)
        self.server: Any = None
        self.channels: dict[str, Any] = {}
        self.sent = 0
        self._lock = threading.Lock()
        self._jump_to: int | None = recorded.start  # the picture at the start, first
        self._resend: set[str] = set()
        self._cursor = 0  # the next message to send
        self._ended = False
        self._joint_topics = {f"/{m.slot}/joint_read": m.slot for m in assembly.modules}
        self._wheel_topics = {f"/{slot}/joint_set": slot for slot in scene.wheel_commands.wheels}
        self._decoders: dict[str, Any] = {}

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> BagFoxglove:
        """Open the server over the bag's time range and advertise every channel."""
        from foxglove.websocket import Capability

        self._open()
        for topic, type_name in COMPOSED.items():
            self._channel(topic, type_name)
        for topic, definition in self.recorded.definitions.items():
            if topic not in COMPOSED:
                encoding = definition.encoding or "ros2msg"
                self._channel(topic, definition.type, definition.definition, encoding)
        self._serve(
            f"msctl bag view {self.recorded.path.name}",
            _Listener(self),
            capabilities=[Capability.Time],
            playback_time_range=(self.recorded.start, self.recorded.end),
        )
        self.step()
        return self

    # ------------------------------------------------------------------ requests (server thread)
    def control(self, request: Any) -> Any:
        """Apply the Foxglove app's play, pause, speed or seek; the state it then shows."""
        from foxglove.websocket import PlaybackCommand

        now = self.clock()
        with self._lock:
            head = self.playhead
            if request.playback_speed and request.playback_speed != head.speed:
                head.set_speed(request.playback_speed, now)
            jumped = request.seek_time is not None
            if jumped:
                self._jump_to = head.seek(request.seek_time, now)
            if request.playback_command == PlaybackCommand.Play:
                if head.play(now):
                    self._jump_to, jumped = head.start, True
            else:
                head.pause(now)
            self._ended = False
            return self._state(now, jumped, request.request_id)

    def _state(self, now: float, did_seek: bool, request_id: str | None) -> Any:
        from foxglove.websocket import PlaybackState, PlaybackStatus

        status = {PLAYING: PlaybackStatus.Playing, ENDED: PlaybackStatus.Ended}.get(
            self.playhead.status(now), PlaybackStatus.Paused
        )
        return PlaybackState(
            status, self.playhead.time(now), self.playhead.speed, did_seek, request_id
        )

    def resend(self, topic: str) -> None:
        """Send a topic's present message again at the next step (a new subscriber's)."""
        with self._lock:
            self._resend.add(topic)

    # ------------------------------------------------------------------ the loop
    def step(self) -> None:
        """Jump if asked, send what the playhead passed, announce its time."""
        now = self.clock()
        with self._lock:
            jump, self._jump_to = self._jump_to, None
            resend, self._resend = self._resend, set()
            at = self.playhead.time(now)
            status = self.playhead.status(now)
        if jump is not None:
            self._jump(jump)
            at = max(at, jump)
        for topic in resend:
            self._send_present(topic, at)
        upto = self.recorded.after(at)
        for message in self.recorded.messages[self._cursor : upto]:
            self.channels[message.topic].log(message.data, log_time=message.log_time)
            self._take(message)
        self.sent += max(0, upto - self._cursor)
        self._cursor = max(self._cursor, upto)
        self.scene.expire_wheel_commands(at / SECOND)
        changes = self.scene.changes()
        self._send_tf(changes.poses, at)
        self._send_twists(changes.twists, at)
        if self.server is not None:
            self.server.broadcast_time(at)
            if status == ENDED and not self._ended:
                self._ended = True
                self.server.broadcast_playback_state(self._state(now, False, None))

    def _take(self, message: Any) -> None:
        """Feed the scene what moves the picture: joints, wheel commands."""
        slot = self._joint_topics.get(message.topic)
        wheels = self._wheel_topics.get(message.topic)
        if slot is None and wheels is None:
            return
        from components.messages import joint_samples

        decode = self._decoders.get(message.type)
        if decode is None:
            from components.comm.types import registry

            decode = self._decoders[message.type] = registry().deserializer(message.type)
        samples = joint_samples(decode(message.data))
        if wheels is not None:
            velocities = {s.name: s.velocity for s in samples}
            self.scene.set_wheel_command(wheels, velocities, message.log_time / SECOND)
        else:
            self.scene.set_joints(slot, {s.name: s.position for s in samples})

    def _jump(self, at: int) -> None:
        """The picture at bag time ``at``: every topic's latest message, the links placed,
        the wheel modules' commands as they stood then."""
        self.scene.reset_wheel_commands()
        for topic in self.recorded.definitions:
            if topic not in COMPOSED:
                latest = self.recorded.latest(topic, at)
                if latest is not None:
                    self.channels[topic].log(latest.data, log_time=latest.log_time)
                    self._take(latest)
        self._cursor = self.recorded.after(at)
        self.scene.expire_wheel_commands(at / SECOND)
        self.scene.changes()
        self._send_description(at)
        everything = self.scene.everything()
        self._send_tf(everything.poses, at)
        self._send_twists(everything.twists, at)

    def _send_present(self, topic: str, at: int) -> None:
        if topic in ("/robot_description", "/tf_static"):
            self._send_description(at)
        elif topic == "/tf":
            self._send_tf(self.scene.everything().poses, at)
        elif topic == WHEEL_TWIST:
            self._send_twists(self.scene.everything().twists, at)
        elif topic in self.channels:
            latest = self.recorded.latest(topic, at)
            if latest is not None:
                self.channels[topic].log(latest.data, log_time=latest.log_time)


class _Listener:
    """Foxglove's playback requests to the player; each new subscriber gets the present."""

    def __init__(self, player: BagFoxglove) -> None:
        self.player = player

    def on_subscribe(self, _client: Any, channel: Any) -> None:
        self.player.resend(channel.topic)

    def on_playback_control_request(self, request: Any) -> Any:
        return self.player.control(request)


__all__ = ["COMPOSED", "BagFoxglove", "RecordedBag", "read_bag"]
