"""The picture of an assembly, composed at the operator's end: the Core of ``msctl view``.

Everything here is pure: the lock's composed URDF gives every link's shapes and the kinematic
tree; joint positions (each module's own ``joint_read``) go in by plain calls, and forward
kinematics gives every link's pose in the world, as robot_state_publisher would, but at the
viewer, so nothing global is put on the radio. Health, presence, halts and claims go in as
plain values too; :meth:`Scene.changes` says what to draw again. No Zenoh, no clock, no
viewer: the live view (:mod:`msctl.view.live`) and the bag view (:mod:`msctl.view.bag`) feed
it, and a sink (:mod:`msctl.view.rerun_sink`) draws what it says.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from msctl.view.wheels import WheelCommands, WheelTwist, twist_of, wheel_joints

if TYPE_CHECKING:
    from components.assembly import ResolvedAssembly

#: Below this a joint's move (rad or m) does not redraw its links.
MOVE_TOLERANCE = 1e-4

#: Link colours (RGBA) by health level: the module's links are tinted by its level.
LEVEL_COLOURS: dict[str, tuple[int, int, int, int]] = {
    "OK": (150, 170, 190, 255),
    "WARN": (240, 190, 40, 255),
    "ERROR": (220, 50, 40, 255),
    "STALE": (110, 110, 110, 140),
    "UNSEEN": (90, 90, 100, 120),
    "GONE": (60, 60, 60, 80),
}

Pose = tuple[tuple[float, float, float], tuple[float, float, float, float]]
"""A translation (m) and a unit quaternion ``(x, y, z, w)``."""


class SceneError(ValueError):
    """The assembly cannot be drawn; the message names the link, joint or file at fault."""


@dataclass(frozen=True)
class Shape:
    """One visual of a link, in the link's frame.

    Attributes:
        kind: ``box``, ``cylinder``, ``sphere`` or ``mesh``.
        size: Box edge lengths; cylinder ``(radius, length)``; sphere ``(radius,)``; a mesh's
            scale.
        origin: Where the shape sits in its link's frame.
        mesh: The mesh file (``mesh`` only): a path, or ``package://`` URI as the URDF has it.
    """

    kind: str
    size: tuple[float, ...]
    origin: Pose = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    mesh: str = ""


@dataclass(frozen=True)
class LinkLook:
    """A link that has something to draw (visuals), and the module it belongs to.

    Attributes:
        link: Its name in the composed URDF.
        module: The slot of its module (``""`` for a link of no module, e.g. ``world``).
        shapes: Its visuals.
    """

    link: str
    module: str
    shapes: tuple[Shape, ...]


@dataclass
class ModuleState:
    """What the view knows of one module.

    Attributes:
        slot: The module's slot (``limb1``).
        kind: ``limb``, ``wheel`` ...
        level: Its health level name (``OK``, ``WARN``, ``ERROR``, ``STALE``), ``UNSEEN``
            until its health arrives.
        message: The worst item and its message.
        present: Whether its nodes are on the graph.
        halted: Whether it says it is halted.
        holder: Who holds its claim (``user@host``), ``""`` when nobody.
        joints_seen: Whether its joint positions have arrived.
    """

    slot: str
    kind: str
    level: str = "UNSEEN"
    message: str = ""
    present: bool = False
    halted: bool = False
    holder: str = ""
    joints_seen: bool = False

    @property
    def look(self) -> str:
        """The colour key of its links: its level, or ``GONE`` once its nodes left."""
        if not self.present and self.level != "UNSEEN":
            return "GONE"
        return self.level

    def line(self) -> str:
        """One line for the status panel."""
        parts = [f"{self.slot} ({self.kind}): {self.level}"]
        if self.message and self.level not in ("OK", "UNSEEN"):
            parts.append(self.message)
        if not self.present:
            parts.append("not on the graph")
        if self.halted:
            parts.append("HALTED")
        parts.append(f"claimed by {self.holder}" if self.holder else "unclaimed")
        return " · ".join(parts)


@dataclass
class Changes:
    """What to draw again since the last :meth:`Scene.changes`.

    Attributes:
        poses: Link -> its pose in the world.
        looks: Module -> its colour key (:data:`LEVEL_COLOURS`).
        status: Module -> its status line.
        markers: Marker name (``limb1/tip``) -> its pose in the world.
        twists: Wheel module -> its commanded twist (:mod:`msctl.view.wheels`).
    """

    poses: dict[str, Pose] = field(default_factory=dict)
    looks: dict[str, str] = field(default_factory=dict)
    status: dict[str, str] = field(default_factory=dict)
    markers: dict[str, Pose] = field(default_factory=dict)
    twists: dict[str, WheelTwist] = field(default_factory=dict)

    def __bool__(self) -> bool:
        return bool(self.poses or self.looks or self.status or self.markers or self.twists)


def _floats(text: str | None, count: int, default: float = 0.0) -> tuple[float, ...]:
    if not text:
        return (default,) * count
    values = tuple(float(v) for v in text.split())
    if len(values) != count:
        raise SceneError(f"expected {count} numbers, not {text!r}")
    return values


def quaternion_from_matrix(rotation: np.ndarray) -> tuple[float, float, float, float]:
    """A rotation matrix as a unit quaternion ``(x, y, z, w)``."""
    import pinocchio as pin

    q = pin.Quaternion(np.asarray(rotation, dtype=float))
    q.normalize()
    return (float(q.x), float(q.y), float(q.z), float(q.w))


def _origin(element: ET.Element | None) -> Pose:
    import pinocchio as pin

    if element is None:
        return ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    xyz = _floats(element.get("xyz"), 3)
    rpy = _floats(element.get("rpy"), 3)
    rotation = pin.rpy.rpyToMatrix(*rpy)
    return ((xyz[0], xyz[1], xyz[2]), quaternion_from_matrix(rotation))


def _shapes(link: ET.Element) -> tuple[Shape, ...]:
    out = []
    for visual in link.findall("visual"):
        geometry = visual.find("geometry")
        if geometry is None or not len(geometry):
            continue
        shape = geometry[0]
        origin = _origin(visual.find("origin"))
        name = link.get("name")
        try:
            if shape.tag == "box":
                out.append(Shape("box", _floats(shape.get("size"), 3), origin))
            elif shape.tag == "cylinder":
                radius, length = float(shape.get("radius", 0)), float(shape.get("length", 0))
                out.append(Shape("cylinder", (radius, length), origin))
            elif shape.tag == "sphere":
                out.append(Shape("sphere", (float(shape.get("radius", 0)),), origin))
            elif shape.tag == "mesh":
                scale = _floats(shape.get("scale"), 3, 1.0)
                out.append(Shape("mesh", scale, origin, shape.get("filename", "")))
        except (SceneError, ValueError) as exc:
            raise SceneError(
                f"URDF link {name!r}: its <{shape.tag}> cannot be read: {exc}"
            ) from None
    return tuple(out)


def module_of_link(link: str, slots: Iterable[str]) -> str:
    """The slot whose prefix a link's name carries (``limb1_link3`` -> ``limb1``), or ``""``."""
    best = ""
    for slot in slots:
        if link.startswith(f"{slot}_") and len(slot) > len(best):
            best = slot
    return best


@dataclass(frozen=True)
class Placement:
    """Where one robot of the assembly stands: its root link and its pose in the world."""

    root_link: str
    xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)


class Scene:
    """The assembly's picture: link shapes, link poses from joint positions, module looks.

    Args:
        urdf_text: The lock's composed URDF.
        modules: ``(slot, kind)`` of every module.
        robots: Where each robot stands (its root link and pose in the world).
        wheels: Wheel module -> its velocity-controlled joints (those whose link has a
            radius are its wheels; their commanded twist is drawn).

    Raises:
        SceneError: If the URDF cannot be read or a root link is missing.
    """

    def __init__(
        self,
        urdf_text: str,
        modules: Sequence[tuple[str, str]],
        robots: Sequence[Placement],
        wheels: Mapping[str, Sequence[str]] | None = None,
    ) -> None:
        import pinocchio as pin

        from components.kinematics_manager.model import ModelError, module_model

        try:
            robot = ET.fromstring(urdf_text)
        except ET.ParseError as exc:
            raise SceneError(f"the composed URDF is not valid XML: {exc}") from None
        self.modules: dict[str, ModuleState] = {s: ModuleState(s, k) for s, k in modules}
        self.links: list[LinkLook] = []
        for link in robot.findall("link"):
            shapes = _shapes(link)
            if shapes:
                name = link.get("name", "")
                self.links.append(LinkLook(name, module_of_link(name, self.modules), shapes))
        self._models = []
        for placement in robots:
            try:
                model = module_model(urdf_text, placement.root_link, prefix="")
            except ModelError as exc:
                raise SceneError(str(exc)) from None
            base = pin.SE3(pin.rpy.rpyToMatrix(*placement.rpy), np.array(placement.xyz))
            drawn = [
                look.link for look in self.links if model.model.existFrame(look.link, pin.BODY)
            ]
            self._models.append((model, base, drawn, np.zeros(model.nq)))
        self._joint_model = {
            name: i for i, (model, *_) in enumerate(self._models) for name in model.joint_names
        }
        self._drawn_poses: dict[str, Pose] = {}
        self._dirty_models: set[int] = set(range(len(self._models)))
        self._drawn_looks: dict[str, str] = {}
        self._drawn_status: dict[str, str] = {}
        self._markers: dict[str, tuple[str, Pose]] = {}
        self._world: dict[str, pin.SE3] = {}
        self.wheel_commands = WheelCommands(
            {slot: wheel_joints(robot, joints) for slot, joints in (wheels or {}).items()}
        )
        self._drawn_twists: dict[str, WheelTwist] = {}

    # ------------------------------------------------------------------ inputs
    def set_joints(self, slot: str, positions: Mapping[str, float]) -> bool:
        """Take a module's joint positions (by joint name, as its ``joint_read`` says).

        Joints of no robot and non-finite values are skipped. Returns whether any joint moved
        by more than :data:`MOVE_TOLERANCE`.
        """
        moved = False
        for name, value in positions.items():
            i = self._joint_model.get(name)
            if i is None or value is None or not math.isfinite(value):
                continue
            model, _, _, q = self._models[i]
            k = model.index(name)
            if abs(q[k] - value) > MOVE_TOLERANCE:
                q[k] = value
                self._dirty_models.add(i)
                moved = True
        state = self.modules.get(slot)
        if state is not None:
            state.joints_seen = True
        return moved

    def set_health(self, slot: str, level: str, message: str = "", present: bool = True) -> None:
        """Take a module's health level (``OK`` ... ``STALE``) and whether it is on the graph."""
        state = self.modules.get(slot)
        if state is None:
            return
        state.level, state.message, state.present = level, message, present
        state.halted = "halted" in message.lower()

    def set_holder(self, slot: str, holder: str) -> None:
        """Take who holds a module's claim (``""``: nobody)."""
        state = self.modules.get(slot)
        if state is not None:
            state.holder = holder

    def set_wheel_command(
        self, slot: str, velocities: Mapping[str, float | None], at: float
    ) -> None:
        """Take a wheel module's commanded wheel velocities (its ``joint_set``, rad/s) at
        ``at`` (s, wall or bag time); other modules and joints are skipped."""
        self.wheel_commands.command(slot, velocities, at)

    def expire_wheel_commands(self, now: float) -> list[str]:
        """Stop the wheels of modules commanded nothing lately, as their joint managers'
        watchdogs do (:meth:`~msctl.view.wheels.WheelCommands.expire`); returns them."""
        return self.wheel_commands.expire(now)

    def reset_wheel_commands(self) -> None:
        """Forget every wheel command and drawn twist (a bag's picture jumping in time)."""
        self.wheel_commands.reset()
        self._drawn_twists.clear()

    def set_marker(self, name: str, frame: str, pose: Pose) -> None:
        """Place a marker (a limb's tip, its IK target) given in a link's frame."""
        self._markers[name] = (frame, pose)

    # ------------------------------------------------------------------ outputs
    def eye(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """A camera position and target that keep the whole assembly in sight: from the side
        (-y) and above, so a limb lifting shows. Call after a first :meth:`changes`."""
        points = np.array([p[0] for p in self._drawn_poses.values()] or [(0.0, 0.0, 0.0)])
        low, high = points.min(axis=0), points.max(axis=0)
        centre = (low + high) / 2
        reach = max(float(np.max(high - low)), 0.5)
        eye = centre + np.array([0.35, -1.1, 0.6]) * reach
        return (
            (float(eye[0]), float(eye[1]), float(eye[2])),
            (float(centre[0]), float(centre[1]), float(centre[2])),
        )

    def link_pose(self, link: str) -> Pose | None:
        """A link's last computed pose in the world (after :meth:`changes`)."""
        return self._drawn_poses.get(link)

    def everything(self) -> Changes:
        """Every link pose, look and status line as last computed: a new sink's first picture."""
        self.changes()
        return Changes(
            poses=dict(self._drawn_poses),
            looks=dict(self._drawn_looks),
            status=dict(self._drawn_status),
            twists=dict(self._drawn_twists),
        )

    def changes(self) -> Changes:
        """What changed since the last call: link poses, module looks and status, markers."""
        import pinocchio as pin

        out = Changes()
        for i in sorted(self._dirty_models):
            model, base, drawn, q = self._models[i]
            for link, placement in zip(drawn, model.placements(q, drawn), strict=True):
                world = base * placement
                self._world[link] = world
                pose = _pose(world)
                if _moved(self._drawn_poses.get(link), pose):
                    self._drawn_poses[link] = out.poses[link] = pose
        self._dirty_models.clear()
        for slot, state in self.modules.items():
            if self._drawn_looks.get(slot) != state.look:
                self._drawn_looks[slot] = out.looks[slot] = state.look
            line = state.line()
            if self._drawn_status.get(slot) != line:
                self._drawn_status[slot] = out.status[slot] = line
        for name, (frame, pose) in self._markers.items():
            parent = self._world.get(frame, pin.SE3.Identity())
            local = pin.SE3(
                pin.Quaternion(pose[1][3], pose[1][0], pose[1][1], pose[1][2]).matrix(),
                np.array(pose[0]),
            )
            out.markers[name] = _pose(parent * local)
        self._markers.clear()
        commands = self.wheel_commands
        for slot in commands.commanded():
            twist = twist_of(commands.wheels[slot], commands.velocities(slot), self._world)
            if twist is not None and twist.differs(self._drawn_twists.get(slot)):
                self._drawn_twists[slot] = out.twists[slot] = twist
        return out


def _pose(placement: Any) -> Pose:
    """A Pinocchio placement (``SE3``) as a :data:`Pose`."""
    translation = placement.translation
    return (
        (float(translation[0]), float(translation[1]), float(translation[2])),
        quaternion_from_matrix(placement.rotation),
    )


def _moved(before: Pose | None, after: Pose) -> bool:
    if before is None:
        return True
    return any(
        abs(a - b) > MOVE_TOLERANCE
        for a, b in zip(before[0] + before[1], after[0] + after[1], strict=True)
    )


def scene_of(assembly: ResolvedAssembly) -> Scene:
    """The scene of a resolved assembly (its lock and composed URDF).

    Raises:
        SceneError: If the composed URDF is missing or unreadable (naming the file).
    """
    urdf_path = Path(assembly.urdf_path)
    try:
        text = urdf_path.read_text()
    except OSError as exc:
        raise SceneError(
            f"cannot read the composed URDF {urdf_path}: {exc.strerror}; run `msctl assemble`"
        ) from None
    lock = assembly.lock
    robots = [Placement(r.root_link, tuple(r.xyz), tuple(r.rpy)) for r in lock.robots] or [
        Placement(root) for root in lock.root_links
    ]
    modules = [(m.slot, m.kind) for m in lock.modules]
    wheels = {
        m.slot: [j.name for j in m.joints if j.control == "velocity"] for m in assembly.modules
    }
    try:
        return Scene(text, modules, robots, {slot: j for slot, j in wheels.items() if j})
    except SceneError as exc:
        raise SceneError(f"{urdf_path}: {exc}") from None
