"""Module URDFs in, one assembly URDF out.

Module URDFs are parsed once with ElementTree (cached by file modification time) and checked to
be a tree; composing copies their elements with every link, joint and material name prefixed by
the slot (``limb1_joint3``), adds one fixed link per connector (``limb1_connector_tip``) and one
fixed joint per connection (``wheel1_mount``). No URDF library on this path: composing a Dragon
takes about a millisecond.
"""

from __future__ import annotations

import copy
import math
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from msctl.assembler import transforms as tf
from msctl.errors import InputError

MOVABLE = ("revolute", "continuous", "prismatic")
JOINT_TYPES = (*MOVABLE, "fixed", "floating", "planar")


@dataclass
class ModuleUrdf:
    """A parsed, checked module URDF.

    Attributes:
        path: The file.
        links: Link name -> element, in file order.
        joints: Joint name -> element, in file order.
        materials: Top-level material elements.
        parent: Child link -> (joint name, parent link).
        root_link: The one link with no parent.
    """

    path: Path
    links: dict[str, ET.Element]
    joints: dict[str, ET.Element]
    materials: list[ET.Element]
    parent: dict[str, tuple[str, str]]
    root_link: str

    def joint_type(self, name: str) -> str:
        """The type attribute of joint ``name``."""
        return self.joints[name].get("type", "")

    def chain(self, base: str, tip: str) -> list[str] | None:
        """Movable joints from ``base`` to ``tip``, or None if ``base`` is not above ``tip``."""
        joints: list[str] = []
        link = tip
        while link != base:
            if link not in self.parent:
                return None
            joint, link = self.parent[link]
            if self.joint_type(joint) in MOVABLE:
                joints.append(joint)
        joints.reverse()
        return joints

    def fixed_transform(self, link: str) -> tf.Transform | None:
        """Pose of ``link`` in the root link's frame if only fixed joints separate them."""
        pose: tf.Transform = (tf.IDENTITY, (0.0, 0.0, 0.0))
        while link != self.root_link:
            joint, link = self.parent[link]
            element = self.joints[joint]
            if element.get("type") != "fixed":
                return None
            pose = tf.compose(_origin(element), pose)
        return pose


def parse_module_urdf(path: Path) -> ModuleUrdf:
    """Parse and check a module URDF.

    Raises:
        InputError: If it does not parse (with its line), is not a ``<robot>``, or is not a
            tree of uniquely named links and joints.
    """
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        line, column = exc.position
        raise InputError(
            f"{path}:{line}: URDF does not parse ({exc.msg if hasattr(exc, 'msg') else exc})",
            hint=f"fix the XML at line {line}, column {column}",
        ) from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read URDF ({exc.strerror})") from None
    if root.tag != "robot":
        raise InputError(f"{path}: URDF root element is <{root.tag}>, expected <robot>")
    links: dict[str, ET.Element] = {}
    joints: dict[str, ET.Element] = {}
    for element in root.findall("link"):
        name = element.get("name")
        if not name or name in links:
            raise InputError(f"{path}: <link name={name!r}> is unnamed or named twice")
        links[name] = element
    parent: dict[str, tuple[str, str]] = {}
    for element in root.findall("joint"):
        name = element.get("name")
        if not name or name in joints:
            raise InputError(f"{path}: <joint name={name!r}> is unnamed or named twice")
        kind = element.get("type")
        if kind not in JOINT_TYPES:
            raise InputError(
                f"{path}: joint {name!r} has type {kind!r}",
                hint=f"use one of {', '.join(JOINT_TYPES)}",
            )
        parent_el, child_el = element.find("parent"), element.find("child")
        p = parent_el.get("link") if parent_el is not None else None
        c = child_el.get("link") if child_el is not None else None
        for role, link in (("parent", p), ("child", c)):
            if link not in links:
                raise InputError(
                    f"{path}: joint {name!r} {role} link {link!r} is not a <link> of this URDF"
                )
        if c in parent:
            raise InputError(
                f"{path}: link {c!r} is the child of two joints ({parent[c][0]!r}, {name!r})",
                hint="a URDF must be a tree",
            )
        parent[c] = (name, p)  # type: ignore[index]
        joints[name] = element
    roots = [name for name in links if name not in parent]
    if len(roots) != 1:
        raise InputError(
            f"{path}: URDF has {len(roots)} root links ({', '.join(roots) or 'a cycle'})",
            hint="a URDF must be a tree with exactly one root link",
        )
    for link in links:  # catch cycles hanging off the tree
        seen = set()
        while link in parent:
            if link in seen:
                raise InputError(f"{path}: joints form a cycle through link {link!r}")
            seen.add(link)
            link = parent[link][1]
    return ModuleUrdf(
        path=path,
        links=links,
        joints=joints,
        materials=root.findall("material"),
        parent=parent,
        root_link=roots[0],
    )


def _floats(text: str | None, count: int = 3) -> tuple[float, ...]:
    if not text:
        return (0.0,) * count
    return tuple(float(v) for v in text.split())


def _origin(element: ET.Element) -> tf.Transform:
    origin = element.find("origin")
    if origin is None:
        return tf.IDENTITY, (0.0, 0.0, 0.0)
    return tf.from_xyz_rpy(_floats(origin.get("xyz")), _floats(origin.get("rpy")))  # type: ignore[arg-type]


def _fmt(value: float) -> str:
    text = repr(float(value))
    return text[:-2] if text.endswith(".0") else text


def _vec(values: Iterable[float]) -> str:
    return " ".join(_fmt(v) for v in values)


@dataclass
class ModulePart:
    """One module as it goes into the assembly URDF.

    Attributes:
        slot: Prefix for every name.
        urdf: The parsed module URDF.
        limits: Raw joint name -> (lower, upper, max_effort, max_velocity); infinite bounds
            are omitted from ``<limit>``.
        connectors: Connector name -> (link, xyz, rpy).
    """

    slot: str
    urdf: ModuleUrdf
    limits: dict[str, tuple[float, float, float, float]]
    connectors: dict[str, tuple[str, tf.Vec, tf.Vec]] = field(default_factory=dict)


@dataclass
class Mount:
    """A fixed joint joining two modules: ``joint`` from ``parent_link`` to ``child_link``."""

    joint: str
    parent_link: str
    child_link: str
    xyz: tf.Vec
    rpy: tf.Vec


def connector_link(slot: str, connector: str) -> str:
    """Assembly name of a connector's link (``limb1_connector_tip``)."""
    return f"{slot}_connector_{connector}"


def compose(name: str, parts: Sequence[ModulePart], mounts: Sequence[Mount]) -> str:
    """The assembly URDF as a string.

    Args:
        name: ``<robot name>``.
        parts: Modules in template order.
        mounts: Fixed joints joining modules (and placing robots under ``world`` when an
            assembly holds several robots).
    """
    robot = ET.Element("robot", {"name": name})
    robot.text = "\n  "
    body: list[ET.Element] = []
    if any(m.parent_link == "world" for m in mounts):
        body.append(ET.Element("link", {"name": "world"}))
    for part in parts:
        p = part.slot + "_"
        for material in part.urdf.materials:
            new = copy.deepcopy(material)
            new.set("name", p + material.get("name", ""))
            body.append(new)
        for link_name, link in part.urdf.links.items():
            new = copy.deepcopy(link)
            new.set("name", p + link_name)
            for material in new.iter("material"):
                if material.get("name"):
                    material.set("name", p + material.get("name", ""))
            body.append(new)
        for joint_name, joint in part.urdf.joints.items():
            new = copy.deepcopy(joint)
            new.set("name", p + joint_name)
            for tag in ("parent", "child"):
                sub = new.find(tag)
                sub.set("link", p + sub.get("link", ""))  # type: ignore[union-attr]
            mimic = new.find("mimic")
            if mimic is not None:
                mimic.set("joint", p + mimic.get("joint", ""))
            if joint_name in part.limits:
                _set_limit(new, *part.limits[joint_name])
            body.append(new)
        for connector, (link, xyz, rpy) in part.connectors.items():
            cl = connector_link(part.slot, connector)
            body.append(ET.Element("link", {"name": cl}))
            body.append(_fixed(f"{cl}_fixed", p + link, cl, xyz, rpy))
    for mount in mounts:
        body.append(_fixed(mount.joint, mount.parent_link, mount.child_link, mount.xyz, mount.rpy))
    for element in body:
        element.tail = "\n  "
    if body:
        body[-1].tail = "\n"
    robot.extend(body)
    return '<?xml version="1.0"?>\n' + ET.tostring(robot, encoding="unicode") + "\n"


def _set_limit(joint: ET.Element, lower: float, upper: float, effort: float, velocity: float):
    limit = joint.find("limit")
    if limit is None:
        limit = ET.SubElement(joint, "limit")
    limit.attrib.clear()
    if math.isfinite(lower) and math.isfinite(upper):
        limit.set("lower", _fmt(lower))
        limit.set("upper", _fmt(upper))
    limit.set("effort", _fmt(effort))
    limit.set("velocity", _fmt(velocity))


def _fixed(name: str, parent: str, child: str, xyz: tf.Vec, rpy: tf.Vec) -> ET.Element:
    joint = ET.Element("joint", {"name": name, "type": "fixed"})
    ET.SubElement(joint, "parent", {"link": parent})
    ET.SubElement(joint, "child", {"link": child})
    ET.SubElement(joint, "origin", {"xyz": _vec(xyz), "rpy": _vec(rpy)})
    return joint
