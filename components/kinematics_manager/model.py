"""Pinocchio models of one module, or of one limb chain, cut out of the composed URDF.

The composed URDF holds the whole assembly, modules bolted together by fixed ``mount`` joints.
A module's kinematics must not depend on what it is bolted to (a limb is the same limb in
``minimal`` and in ``dragon``), so the models here are rooted at a link of the module itself:

* :func:`module_model` keeps every link of the module reachable from its root link, stopping
  at the joints that mount another module (location publisher);
* :func:`chain_model` keeps the path from a chain's base link to its tip link (kinematics
  manager), so no joint off that path (a gripper finger) takes part in IK.

Continuous joints are rewritten as revolute joints with unbounded limits before Pinocchio
reads the URDF: Pinocchio would give them two configuration entries (cos, sin), and keeping
one angle per joint lets callers use joint angles directly as ``q``.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pinocchio as pin

#: Limit written for continuous joints (Pinocchio needs finite numbers); any |limit| at or above
#: :data:`UNBOUNDED` means "no limit".
_CONTINUOUS_LIMIT = 1e9
UNBOUNDED = 1e8

_MOVABLE = ("revolute", "continuous", "prismatic")


class ModelError(ValueError):
    """A model cannot be cut out of the URDF; the message names the link or joint at fault."""


@dataclass(frozen=True)
class _Urdf:
    links: dict[str, ET.Element]
    joints: dict[str, ET.Element]
    children: dict[str, list[ET.Element]]
    parent_joint: dict[str, ET.Element]


def _parse(urdf_text: str) -> _Urdf:
    try:
        robot = ET.fromstring(urdf_text)
    except ET.ParseError as exc:
        raise ModelError(f"the composed URDF is not valid XML: {exc}") from exc
    links = {link.get("name", ""): link for link in robot.findall("link")}
    joints: dict[str, ET.Element] = {}
    children: dict[str, list[ET.Element]] = {}
    parent_joint: dict[str, ET.Element] = {}
    for joint in robot.findall("joint"):
        joints[joint.get("name", "")] = joint
        parent = _link_of(joint, "parent")
        children.setdefault(parent, []).append(joint)
        parent_joint[_link_of(joint, "child")] = joint
    return _Urdf(links, joints, children, parent_joint)


def _link_of(joint: ET.Element, tag: str) -> str:
    element = joint.find(tag)
    if element is None or not element.get("link"):
        raise ModelError(f"URDF joint {joint.get('name')!r} has no <{tag} link=...>")
    return element.get("link", "")


def _robot(urdf: _Urdf, links: Iterable[str], joints: Iterable[ET.Element]) -> str:
    """A URDF of the given links and joints, continuous joints made unbounded revolute."""
    robot = ET.Element("robot", {"name": "cut"})
    for name in links:
        robot.append(urdf.links.get(name, ET.Element("link", {"name": name})))
    for joint in joints:
        if joint.get("type") == "continuous":
            joint = _as_unbounded_revolute(joint)
        robot.append(joint)
    return ET.tostring(robot, encoding="unicode")


def _as_unbounded_revolute(joint: ET.Element) -> ET.Element:
    copy = ET.fromstring(ET.tostring(joint))
    copy.set("type", "revolute")
    limit = copy.find("limit")
    if limit is None:
        limit = ET.SubElement(copy, "limit", {"effort": "0", "velocity": "0"})
    limit.set("lower", str(-_CONTINUOUS_LIMIT))
    limit.set("upper", str(_CONTINUOUS_LIMIT))
    return copy


def origin_of(joint: ET.Element) -> pin.SE3:
    """The placement a URDF joint's ``<origin>`` gives its child link in its parent link."""
    origin = joint.find("origin")
    xyz = [0.0, 0.0, 0.0]
    rpy = [0.0, 0.0, 0.0]
    if origin is not None:
        xyz = [float(v) for v in origin.get("xyz", "0 0 0").split()]
        rpy = [float(v) for v in origin.get("rpy", "0 0 0").split()]
    return pin.SE3(pin.rpy.rpyToMatrix(*rpy), np.array(xyz))


class KinematicModel:
    """A Pinocchio model with one angle (or length) per movable joint, addressed by name.

    Attributes:
        model: The Pinocchio model (``nq == nv``: one entry per movable joint).
        data: Its work data (not thread-safe: one model per core).
        root_link: The link every placement is expressed in.
        joint_names: Movable joints in configuration order.
        lower: Lower position limits in configuration order (``-inf`` when unbounded).
        upper: Upper position limits in configuration order (``+inf`` when unbounded).
        revolute: Which joints are angles (unwrapping applies) rather than lengths.
    """

    def __init__(self, urdf_text: str, root_link: str) -> None:
        try:
            self.model = pin.buildModelFromXML(urdf_text)
        except (RuntimeError, ValueError) as exc:
            raise ModelError(
                f"Pinocchio cannot read the model rooted at {root_link}: {exc}"
            ) from exc
        if self.model.nq != self.model.nv:
            raise ModelError(
                f"the model rooted at {root_link} has joints with more than one coordinate "
                "(floating or planar); only revolute, continuous and prismatic joints are supported"
            )
        self.data = self.model.createData()
        self.root_link = root_link
        names = list(self.model.names)[1:]
        self.joint_names: tuple[str, ...] = tuple(names)
        self._index = {name: self.model.joints[self.model.getJointId(name)].idx_q for name in names}
        lower = np.array(self.model.lowerPositionLimit, dtype=float)
        upper = np.array(self.model.upperPositionLimit, dtype=float)
        self.lower = np.where(lower <= -UNBOUNDED, -np.inf, lower)
        self.upper = np.where(upper >= UNBOUNDED, np.inf, upper)
        self.revolute = np.array(
            [
                self.model.joints[self.model.getJointId(n)].shortname().startswith("JointModelR")
                for n in names
            ],
            dtype=bool,
        )

    @property
    def nq(self) -> int:
        """Number of movable joints."""
        return self.model.nq

    def take_positions(self, message: Any, q: np.ndarray, seen: np.ndarray) -> bool:
        """Copy the finite positions a JointState carries for this model's joints into ``q``.

        Joints of other chains or modules and non-finite values are skipped. Marks ``seen``
        for each joint taken; returns whether any was.
        """
        from components.messages import joint_samples

        index = self._index
        touched = False
        for sample in joint_samples(message):
            i = index.get(sample.name)
            if i is None or sample.position is None or not math.isfinite(sample.position):
                continue
            q[i] = sample.position
            seen[i] = True
            touched = True
        return touched

    def index(self, joint: str) -> int:
        """Configuration index of ``joint``.

        Raises:
            KeyError: If the model has no such movable joint.
        """
        try:
            return self._index[joint]
        except KeyError:
            raise KeyError(
                f"no movable joint {joint!r} under {self.root_link}; joints: {self.joint_names}"
            ) from None

    def configuration(self, positions: Mapping[str, float], default: float = 0.0) -> np.ndarray:
        """``q`` from joint positions by name (joints not given take ``default``)."""
        q = np.full(self.nq, default, dtype=float)
        for name, value in positions.items():
            i = self._index.get(name)
            if i is not None:
                q[i] = value
        return q

    def frame_id(self, link: str) -> int:
        """Pinocchio frame id of ``link``.

        Raises:
            ModelError: If the model has no such link.
        """
        if not self.model.existFrame(link, pin.BODY):
            raise ModelError(f"no link {link!r} under {self.root_link}")
        return self.model.getFrameId(link, pin.BODY)

    def supporting_joints(self, link: str) -> tuple[str, ...]:
        """Movable joints between the root and ``link`` (what its placement depends on)."""
        frame = self.model.frames[self.frame_id(link)]
        return tuple(self.model.names[j] for j in self.model.supports[frame.parentJoint][1:])

    def placements(self, q: np.ndarray, links: Sequence[str]) -> list[pin.SE3]:
        """Placements of ``links`` in the root link's frame at configuration ``q``."""
        pin.forwardKinematics(self.model, self.data, q)
        out = []
        for link in links:
            frame = self.frame_id(link)
            out.append(pin.updateFramePlacement(self.model, self.data, frame).copy())
        return out


class ChainModel(KinematicModel):
    """The path from a chain's base link to its tip link, for IK.

    Attributes:
        base_link: The chain's base (every pose is in its frame).
        tip_link: The chain's tip.
        tip_frame: Pinocchio frame id of the tip.
    """

    def __init__(self, urdf_text: str, base_link: str, tip_link: str) -> None:
        super().__init__(urdf_text, base_link)
        self.base_link = base_link
        self.tip_link = tip_link
        self.tip_frame = self.frame_id(tip_link)

    def tip(self, q: np.ndarray) -> pin.SE3:
        """The tip's placement in the base frame at ``q``."""
        pin.forwardKinematics(self.model, self.data, q)
        return pin.updateFramePlacement(self.model, self.data, self.tip_frame).copy()


def chain_model(
    urdf_text: str, base_link: str, tip_link: str, joints: Sequence[str] | None = None
) -> ChainModel:
    """Cut the path ``base_link`` -> ``tip_link`` out of a URDF.

    Args:
        urdf_text: The composed URDF.
        base_link: First link of the chain.
        tip_link: Last link of the chain.
        joints: The chain's movable joints as the assembly lists them; when given they must be
            exactly the movable joints on the path (a mismatch means the lock file and the URDF
            disagree).

    Raises:
        ModelError: If a link is missing, the tip is not below the base, or the joints differ.
    """
    urdf = _parse(urdf_text)
    for link in (base_link, tip_link):
        if link not in urdf.links:
            raise ModelError(f"the composed URDF has no link {link!r}")
    path: list[ET.Element] = []
    link = tip_link
    while link != base_link:
        joint = urdf.parent_joint.get(link)
        if joint is None:
            raise ModelError(f"{tip_link} is not below {base_link} in the composed URDF")
        path.append(joint)
        link = _link_of(joint, "parent")
    path.reverse()
    links = [base_link] + [_link_of(j, "child") for j in path]
    movable = [j.get("name", "") for j in path if j.get("type") in _MOVABLE]
    if joints is not None and list(joints) != movable:
        raise ModelError(
            f"chain {base_link} -> {tip_link}: the assembly lists joints {list(joints)}, the "
            f"URDF path has {movable}; run `msctl assemble` again"
        )
    return ChainModel(_robot(urdf, links, path), base_link, tip_link)


def module_model(
    urdf_text: str, root_link: str, prefix: str, stop_joints: Iterable[str] = ()
) -> KinematicModel:
    """Cut one module out of a URDF: every link below ``root_link`` that belongs to it.

    Args:
        urdf_text: The composed URDF.
        root_link: The module's root link.
        prefix: Its links' name prefix (``limb1_``); a child link without it is another module.
        stop_joints: Joints never crossed (the assembly's mount joints).

    Raises:
        ModelError: If the root link is missing.
    """
    urdf = _parse(urdf_text)
    if root_link not in urdf.links:
        raise ModelError(f"the composed URDF has no link {root_link!r}")
    stop = set(stop_joints)
    links, joints, stack = [], [], [root_link]
    while stack:
        link = stack.pop()
        links.append(link)
        for joint in urdf.children.get(link, ()):
            child = _link_of(joint, "child")
            if joint.get("name") in stop or not child.startswith(prefix):
                continue
            joints.append(joint)
            stack.append(child)
    return KinematicModel(_robot(urdf, links, joints), root_link)


def mount_of(urdf_text: str, link: str) -> tuple[str, pin.SE3] | None:
    """The parent link of ``link`` in the whole URDF and the joint placement, if it has one.

    A module's root link hangs from another module's connector (or ``world``) through a fixed
    mount joint: static knowledge the location publisher puts on ``tf`` so ROS tools can join
    the per-module trees.
    """
    urdf = _parse(urdf_text)
    joint = urdf.parent_joint.get(link)
    if joint is None:
        return None
    return _link_of(joint, "parent"), origin_of(joint)


def unbounded(value: float) -> bool:
    """Whether a limit means "no limit"."""
    return math.isinf(value) or abs(value) >= UNBOUNDED
