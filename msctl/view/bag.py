"""The picture of a recorded bag: the same :class:`~msctl.view.scene.Scene` as the live view,
fed from the bag's messages at their recorded times, so rerun's timeline scrubs through it.

What it reads, per module of the assembly: ``joint_read`` (forward kinematics at the
viewer), ``tip_pose`` and ``ik_target`` (markers), ``health`` (its worst status is the
module's level; a module whose health stops for :data:`STALE_AFTER` seconds of the bag's
time turns STALE), ``/cmd_vel`` (an arrow) and each wheel module's ``joint_set`` (its
commanded twist, an arrow at the module). The assembly is the resolved one of this
computer: bags do not carry the lock, so the view says which recorded modules it does not know.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from msctl.view.scene import Scene

#: Seconds of bag time without a module's health before it shows STALE (the health board's).
STALE_AFTER = 2.5
#: Seconds of bag time between two drawings (the timeline's resolution).
DRAW_PERIOD = 0.05

_LEVELS = ("OK", "WARN", "ERROR", "STALE")


@dataclass
class BagViewReport:
    """What a bag view drew.

    Attributes:
        messages: Messages read.
        drawings: Times the scene was drawn.
        start: First log time (s).
        end: Last log time (s).
        unknown_modules: Recorded module namespaces the assembly has no slot for.
    """

    messages: int = 0
    drawings: int = 0
    start: float = 0.0
    end: float = 0.0
    unknown_modules: list[str] = field(default_factory=list)


def wanted_topics(assembly: Any) -> dict[str, tuple[str, str]]:
    """Topic -> ``(what, module or marker)`` of every topic the view reads from a bag."""
    topics: dict[str, tuple[str, str]] = {}
    for module in assembly.modules:
        slot = module.slot
        topics[f"/{slot}/health"] = ("health", slot)
        if module.joints:
            topics[f"/{slot}/joint_read"] = ("joints", slot)
        if module.chains:
            topics[f"/{slot}/tip_pose"] = ("marker", f"{slot}/tip")
            topics[f"/{slot}/ik_target"] = ("marker", f"{slot}/ik_target")
        if any(j.control == "velocity" for j in module.joints):
            topics[f"/{slot}/joint_set"] = ("wheels", slot)
    if assembly.mobile:
        topics["/cmd_vel"] = ("twist", "")
    return topics


def worst_status(message: Any) -> tuple[str, str]:
    """A DiagnosticArray's worst level name and that status's ``name: message``."""
    worst, text = 0, ""
    for status in message.status:
        level = status.level if isinstance(status.level, int) else int.from_bytes(status.level)
        if level > worst or not text:
            worst, text = max(worst, level), f"{status.name}: {status.message}"
    return _LEVELS[min(worst, 3)], text if worst else ""


def draw_bag(
    bag: Path,
    assembly: Any,
    scene: Scene,
    sink: Any,
    progress: Callable[[float], None] | None = None,
) -> BagViewReport:
    """Read a bag into ``sink`` at its recorded times.

    Args:
        bag: The bag directory.
        assembly: The resolved assembly it was recorded from.
        scene: Its scene.
        sink: Where to draw (:class:`~msctl.view.rerun_sink.RerunSink`).
        progress: Called with the fraction of the bag's time done.

    Raises:
        BagError: If the bag cannot be read.
    """
    from components.comm.types import registry
    from components.messages import joint_samples
    from msctl.recorder.bag import inspect, read_messages

    info = inspect(bag)
    topics = wanted_topics(assembly)
    report = BagViewReport(unknown_modules=_unknown_modules(info.metadata.topics, assembly))
    types = registry()
    decoders: dict[str, Any] = {}
    last_health: dict[str, float] = {}
    start_ns, end_ns = info.metadata.starting_time, info.end_time
    span = max(end_ns - start_ns, 1)
    next_draw = 0.0
    first = True
    last_ns = start_ns
    for message in read_messages(info, topics=topics):
        what, key = topics[message.topic]
        if message.type not in decoders:
            decoders[message.type] = types.deserializer(message.type)
        decoded = decoders[message.type](message.data)
        now = message.log_time / 1e9
        if first:
            report.start, first = now, False
            sink.at_ns(message.log_time)
            sink.draw_shapes(scene)
            sink.draw(scene, scene.everything())
        report.messages += 1
        report.end, last_ns = now, message.log_time
        if what == "joints":
            scene.set_joints(key, {s.name: s.position for s in joint_samples(decoded)})
        elif what == "marker":
            p, o = decoded.pose.position, decoded.pose.orientation
            pose = ((p.x, p.y, p.z), (o.x, o.y, o.z, o.w))
            scene.set_marker(key, decoded.header.frame_id, pose)
        elif what == "health":
            level, text = worst_status(decoded)
            before = scene.modules[key].level
            scene.set_health(key, level, text, present=True)
            last_health[key] = now
            if level != before:
                sink.at_ns(message.log_time)
                sink.say(f"{key}: {before} -> {level} {text}".rstrip(), level)
        elif what == "wheels":
            velocities = {s.name: s.velocity for s in joint_samples(decoded)}
            scene.set_wheel_command(key, velocities, now)
        elif what == "twist":
            sink.at_ns(message.log_time)
            root = scene.link_pose(assembly.root_links[0])
            origin = root[0] if root else (0.0, 0.0, 0.0)
            sink.arrow(origin, (decoded.linear.x, decoded.linear.y, decoded.linear.z))
        if now >= next_draw:
            next_draw = now + DRAW_PERIOD
            scene.expire_wheel_commands(now)
            for slot, seen in last_health.items():
                state = scene.modules[slot]
                if now - seen > STALE_AFTER and state.level != "STALE":
                    scene.set_health(slot, "STALE", f"no health for {now - seen:.1f} s", True)
                    sink.at_ns(message.log_time)
                    sink.say(f"{slot}: STALE (no health for {now - seen:.1f} s)", "STALE")
            changes = scene.changes()
            if changes:
                sink.at_ns(message.log_time)
                sink.draw(scene, changes)
                report.drawings += 1
            if progress is not None:
                progress((message.log_time - start_ns) / span)
    changes = scene.changes()
    if changes:
        sink.at_ns(last_ns)
        sink.draw(scene, changes)
        report.drawings += 1
    return report


def _unknown_modules(recorded: Iterable[Any], assembly: Any) -> list[str]:
    slots = {m.slot for m in assembly.modules}
    out = set()
    for topic in recorded:
        parts = topic.name.strip("/").split("/")
        if len(parts) == 2 and parts[1] in ("joint_read", "health") and parts[0] not in slots:
            out.add(parts[0])
    return sorted(out)
