"""The live picture: a :class:`~msctl.view.scene.Scene` fed from the data plane.

What it subscribes to is exactly what it shows, per module, nothing global:

* ``/<slot>/joint_read`` of every module with joints: the joint manager's calibrated
  positions, the joint space of the URDF (forward kinematics at the viewer, as the location
  publishers and the kinematics manager do it; ``joint_states`` is the motors' raw feedback);
* ``/<slot>/tip_pose`` and ``/<slot>/ik_target`` of every module with a kinematic chain;
* ``/cmd_vel`` when the assembly is mobile (the commanded twist, as an arrow);
* ``/<slot>/joint_set`` of every wheel module: the wheel velocities it is commanded, drawn as
  its commanded twist (an arrow at the module; stopped after the joint manager's watchdog
  time without a command, as the wheels are);
* each module's ``/<slot>/health`` and the graph, through :class:`~msctl.health.live.LiveHealth`
  (levels, STALE, a module leaving the graph, the alarms), without asking the supervisors;
* the claims' liveliness tokens (:class:`~components.claims.Claims`).

Zenoh calls in on its own threads; callbacks only keep the latest sample under a lock. One
loop (:meth:`LiveView.run`) applies them at a bounded rate, evaluates health four times a
second (so a module going STALE or leaving shows within a second) and draws what changed.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from msctl.view.scene import Scene

#: Seconds between two health evaluations.
HEALTH_PERIOD = 0.25
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
TWIST = "geometry_msgs/msg/Twist"


def _pose_of(message: Any) -> tuple[str, Any]:
    p, o = message.pose.position, message.pose.orientation
    return message.header.frame_id, ((p.x, p.y, p.z), (o.x, o.y, o.z, o.w))


class LiveView:
    """Follows a running assembly and draws it.

    Args:
        node: An open node (``msctl.plane.connected``); its owner closes it.
        assembly: The resolved assembly.
        scene: Its scene.
        sink: Where to draw (:class:`~msctl.view.rerun_sink.RerunSink`).
        period: Seconds between two drawings (10 Hz: what a ground station's radio budget
            lets through of a module's joint_read by default; drawing faster shows nothing new).
        clock: Wall-clock seconds (the timeline's time).
    """

    def __init__(
        self,
        node: Any,
        assembly: Any,
        scene: Scene,
        sink: Any,
        period: float = 0.1,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.node = node
        self.assembly = assembly
        self.scene = scene
        self.sink = sink
        self.period = period
        self.clock = clock
        self._lock = threading.Lock()
        self._joints: dict[str, Any] = {}
        self._markers: dict[str, Any] = {}
        self._twist: Any = None
        self._wheel_sets: dict[str, list[bytes]] = {}
        self._holders: dict[str, str] = {}
        self._holders_changed = False
        self._subscriptions: list[Any] = []
        self.health: Any = None
        self.claims: Any = None
        self._next_health = 0.0
        self.topics: list[str] = []
        self.drawn = 0
        self._decode: Any = None

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> LiveView:
        """Subscribe to what the picture shows and draw the assembly's shapes."""
        from components.claims import Claims
        from components.messages import JOINT_STATE
        from msctl.health.live import LiveHealth

        now = self.clock()
        self.sink.at(now)
        self.sink.draw_shapes(self.scene)
        self.sink.draw(self.scene, self.scene.everything())
        for module in self.assembly.modules:
            slot = module.slot
            if module.joints:
                # Raw: only the latest sample of each step is decoded, not every one.
                self._subscribe(f"/{slot}/joint_read", JOINT_STATE, self._on_joints, slot, raw=True)
            if module.chains:
                for name in ("tip_pose", "ik_target"):
                    marker = f"{slot}/{'tip' if name == 'tip_pose' else 'ik_target'}"
                    self._subscribe(f"/{slot}/{name}", POSE_STAMPED, self._on_marker, marker)
        if self.assembly.mobile:
            self._subscribe("/cmd_vel", TWIST, self._on_twist, "")
        for slot in self.scene.wheel_commands.wheels:
            self._subscribe(f"/{slot}/joint_set", JOINT_STATE, self._on_wheel_set, slot, raw=True)
        self.health = LiveHealth(self.node, self.assembly, supervisors=False).start()
        self.claims = Claims(self.node.session, self.node.domain)
        self.claims.on_change(self._on_claim)
        for module, holder in self.claims.holders().items():
            self._on_claim(module, holder)
        return self

    def _subscribe(
        self, topic: str, type_name: str, callback: Any, key: str, raw: bool = False
    ) -> None:
        self.topics.append(topic)
        self._subscriptions.append(
            self.node.subscription(topic, type_name, lambda m, k=key: callback(k, m), raw=raw)
        )

    def close(self) -> None:
        """Stop every subscription (idempotent); the node stays open."""
        for subscription in self._subscriptions:
            subscription.close()
        self._subscriptions.clear()
        if self.health is not None:
            self.health.close()
            self.health = None
        if self.claims is not None:
            self.claims.close()
            self.claims = None

    def __enter__(self) -> LiveView:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ inputs (Zenoh threads)
    def _on_joints(self, slot: str, message: Any) -> None:
        with self._lock:
            self._joints[slot] = message

    def _on_marker(self, name: str, message: Any) -> None:
        with self._lock:
            self._markers[name] = message

    def _on_wheel_set(self, slot: str, payload: Any) -> None:
        with self._lock:
            # A few per step (commands come at ~40 Hz): each may name some wheels only.
            self._wheel_sets.setdefault(slot, []).append(bytes(payload))
            del self._wheel_sets[slot][:-8]

    def _on_twist(self, _key: str, message: Any) -> None:
        with self._lock:
            self._twist = message

    def _on_claim(self, module: str, holder: Any) -> None:
        with self._lock:
            self._holders[module] = holder.holder if holder is not None else ""
            self._holders_changed = True

    # ------------------------------------------------------------------ the loop
    def step(self) -> None:
        """Apply what arrived, evaluate health when due, draw what changed."""
        from components.messages import joint_samples

        if self._decode is None:
            from components.comm.types import registry
            from components.messages import JOINT_STATE

            self._decode = registry().deserializer(JOINT_STATE)
        with self._lock:
            joints, self._joints = self._joints, {}
            markers, self._markers = self._markers, {}
            twist, self._twist = self._twist, None
            wheel_sets, self._wheel_sets = self._wheel_sets, {}
            holders = dict(self._holders) if self._holders_changed else {}
            self._holders_changed = False
        now = self.clock()
        self.sink.at(now)
        for slot, payload in joints.items():
            samples = joint_samples(self._decode(bytes(payload)))
            self.scene.set_joints(slot, {s.name: s.position for s in samples})
        self._take_wheel_sets(wheel_sets, now)
        for name, message in markers.items():
            frame, pose = _pose_of(message)
            self.scene.set_marker(name, frame, pose)
        for slot, holder in holders.items():
            before = self.scene.modules.get(slot)
            if before is not None and before.holder != holder:
                self.sink.say(
                    f"{slot}: claimed by {holder}" if holder else f"{slot}: claim released"
                )
            self.scene.set_holder(slot, holder)
        if time.monotonic() >= self._next_health and self.health is not None:
            self._next_health = time.monotonic() + HEALTH_PERIOD
            self._take_health()
        if twist is not None:
            origin = self.scene.link_pose(self.assembly.root_links[0])
            start = origin[0] if origin else (0.0, 0.0, 0.0)
            self.sink.arrow(start, (twist.linear.x, twist.linear.y, twist.linear.z))
        changes = self.scene.changes()
        if changes:
            self.sink.draw(self.scene, changes)
            self.drawn += 1

    def _take_wheel_sets(self, wheel_sets: dict[str, list[bytes]], now: float) -> None:
        from components.messages import joint_samples

        for slot, payloads in wheel_sets.items():
            for payload in payloads:
                samples = joint_samples(self._decode(payload))
                self.scene.set_wheel_command(slot, {s.name: s.velocity for s in samples}, now)
        self.scene.expire_wheel_commands(now)

    def _take_health(self) -> None:
        snapshot = self.health.evaluate()
        for row in snapshot.modules:
            # On the graph: any of its components' nodes live (what the graph says now, not
            # what its last health said); a module with none planned counts by its health.
            if row.components:
                present = any(c.live > 0 for c in row.components)
            else:
                present = row.health_age is not None
            before = self.scene.modules.get(row.name)
            was_present = before.present if before else False
            was_seen = before is not None and before.level != "UNSEEN"
            self.scene.set_health(row.name, row.level.name, row.message, present)
            if was_seen and was_present != present:
                self.sink.say(
                    f"{row.name}: {'back on' if present else 'left'} the graph",
                    "INFO" if present else "ERROR",
                )
        for alarm in self.health.take_alarms():
            self.sink.say(alarm.line(), alarm.after.name)

    def run(self, until: Callable[[], bool]) -> None:
        """Step every :attr:`period` seconds until ``until()`` says stop."""
        while not until():
            started = time.monotonic()
            self.step()
            time.sleep(max(0.0, self.period - (time.monotonic() - started)))
