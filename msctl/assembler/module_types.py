"""Module types (``assemblies/modules/<key>.toml`` and their URDFs), loaded and checked."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from components import kinds
from msctl.assembler import checks, files
from msctl.assembler import transforms as tf
from msctl.assembler.models import (
    NAME_RE,
    ChainEntry,
    ComponentEntry,
    JointEntry,
    ModuleTypeFile,
)
from msctl.assembler.schema import decode, missing
from msctl.assembler.urdf import MOVABLE, ModuleUrdf, parse_module_urdf
from msctl.errors import InputError, NotFoundError, did_you_mean

CONTROL_MODES = ("position", "velocity")
#: Widest position limits a joint type allows (a revolute joint turning further is
#: continuous; a module's linear joint travels at most this far).
TYPE_TRAVEL = {"revolute": 2 * math.pi, "prismatic": 10.0}
#: Largest plausible max_velocity (rad/s or m/s) and max_effort (N·m or N) of a module's
#: joint: beyond these a number is a typo, and a limit that large limits nothing.
MAX_VELOCITY = 100.0
MAX_EFFORT = 10_000.0


@dataclass(frozen=True)
class JointDef:
    """A movable joint of a module type (limits in calibrated space, SI units)."""

    name: str
    type: str
    lower: float
    upper: float
    max_velocity: float
    max_effort: float
    motor: str | None
    motor_id: int | None
    control: str
    actuated: bool
    armature: float
    motor_params: dict[str, Any]


@dataclass(frozen=True)
class ComponentDef:
    """A component a module runs: kind, optional name, link or chain it is about, params."""

    kind: str
    name: str
    link: str | None
    chain: str | None
    params: dict[str, Any]


@dataclass(frozen=True)
class ModuleType:
    """A module type file (``assemblies/modules/<key>.toml``) and its parsed URDF."""

    key: str
    path: Path
    description: str
    family: str
    kind: str
    revision: int
    urdf: ModuleUrdf
    shares_computer: bool
    bus: dict[str, Any]
    health: dict[str, Any]
    connectors: dict[str, tuple[str, tf.Vec, tf.Vec]]
    chains: dict[str, tuple[str, str, tuple[str, ...]]]
    joints: dict[str, JointDef]
    components: tuple[ComponentDef, ...]
    interesting_links: tuple[str, ...]
    injections: tuple[dict[str, Any], ...]
    overrides: tuple[dict[str, Any], ...]
    #: The ``[safety]`` table (:mod:`components.safety`): limits beyond which it is halted.
    safety: dict[str, Any] = field(default_factory=dict)

    def has_link(self, link: str) -> bool:
        """Whether ``link`` names a URDF link or a connector link (``connector_<name>``)."""
        return link in self.urdf.links or (
            link.startswith("connector_") and link[len("connector_") :] in self.connectors
        )


def module_type_names() -> list[str]:
    """Every module type key, sorted."""
    return sorted(p.stem for p in files.modules_dir().glob("*.toml"))


def load_module_type(key: str, *, referrer: str = "") -> ModuleType:
    """Load and check module type ``key``.

    Args:
        key: Module type key (file stem).
        referrer: Where the name came from (``"<file>: field slots[0].fits"``), for the error.

    Raises:
        NotFoundError: If no such module type file exists.
        InputError: If it or its URDF is malformed or inconsistent.
    """
    path = files.modules_dir() / f"{key}.toml"
    if not NAME_RE.match(key) or not path.is_file():
        known = ", ".join(module_type_names()) or "none"
        near = did_you_mean(key, module_type_names())
        raise NotFoundError(
            f"{referrer + ': ' if referrer else ''}unknown module type {key!r}",
            hint=f"{near + ' ' if near else ''}known module types: {known} "
            f"(files in {files.modules_dir()})",
        )
    module = files.cached("module", path, parse_module_type)
    # The URDF has its own mtime: re-check it even when the TOML is unchanged.
    urdf = files.cached("urdf", module.urdf.path, parse_module_urdf)
    if urdf is not module.urdf:
        files.forget("module", path)
        module = files.cached("module", path, parse_module_type)
    return module


def parse_module_type(path: Path) -> ModuleType:
    """Read and check one module type file (see :class:`~msctl.assembler.models.ModuleTypeFile`).

    Raises:
        InputError: Naming the file, the field and the fix.
    """
    raw = files.read_toml(path)
    f = decode(path, raw, ModuleTypeFile)
    urdf = _urdf(path, f.urdf)
    backend = checks.backend(f.bus.kind, f"{path}: field bus.kind")
    checks.check_bus_options(backend, raw["bus"], f"{path}: field bus.options")
    joints = _joints(path, f.joints, urdf, backend)
    connectors = _connectors(path, f, urdf)
    chains = _chains(path, f.chains, urdf)
    module = ModuleType(
        key=path.stem,
        path=path,
        description=f.description,
        family=f.family,
        kind=f.kind,
        revision=f.revision,
        urdf=urdf,
        shares_computer=f.shares_computer,
        bus=dict(raw["bus"]),
        health=dict(f.health),
        safety=dict(f.safety),
        connectors=connectors,
        chains=chains,
        joints=joints,
        components=(),
        interesting_links=tuple(f.interesting_links),
        injections=tuple(checks.check_entries(path, "injections", f.injections, "injection")),
        overrides=tuple(checks.check_entries(path, "overrides", f.overrides, "override")),
    )
    for i, link in enumerate(module.interesting_links):
        if not isinstance(link, str) or not module.has_link(link):
            raise InputError(f"{path}: field interesting_links[{i}]: {link!r} is not a link")
    module = replace(module, components=_components(path, f.components, module))
    checks.check_health(module, module.health, f"{path}: field health")
    checks.check_safety(module.safety, f"{path}: field safety")
    checks.check_extensions(module, module.injections, module.overrides, str(path))
    return module


def _urdf(path: Path, relative: str) -> ModuleUrdf:
    """The module's URDF: inside its folder, present, its meshes inside too, parsed."""
    where = f"{path}: field urdf"
    urdf_path = checks.confined(path.parent, relative, where)
    if not urdf_path.is_file():
        raise InputError(
            f"{where}: {urdf_path} does not exist", hint="fix the path or add the URDF"
        )
    checks.check_meshes(urdf_path, path.parent, where)
    return files.cached("urdf", urdf_path, parse_module_urdf)


def _movable(urdf: ModuleUrdf) -> list[str]:
    return [n for n in urdf.joints if urdf.joint_type(n) in MOVABLE]


def _joints(
    path: Path, entries: list[JointEntry], urdf: ModuleUrdf, backend: Any
) -> dict[str, JointDef]:
    """Every movable joint of the URDF, described once, with ids unique on the bus."""
    joints: dict[str, JointDef] = {}
    for i, entry in enumerate(entries):
        where = f"{path}: field joints[{i}]."
        if entry.name in joints:
            raise InputError(f"{where}name: joint {entry.name!r} is listed twice")
        joints[entry.name] = _joint(path, i, entry, urdf)
        checks.check_motor_id(backend, entry.motor_id, f"{where}motor_id")
    checks.check_unique_ids(
        {n: jd.motor_id for n, jd in joints.items() if jd.actuated}, f"{path}: field joints"
    )
    absent = [n for n in _movable(urdf) if n not in joints]
    if absent:
        raise InputError(
            f"{path}: field joints: {urdf.path} has movable joints with no joints entry: "
            f"{', '.join(absent)}",
            hint="describe every movable joint (limits, motor) in the module file",
        )
    return joints


def _joint(path: Path, i: int, entry: JointEntry, urdf: ModuleUrdf) -> JointDef:
    """One ``[[joints]]`` entry against the URDF's joint of that name."""
    where = f"{path}: field joints[{i}]."
    name = entry.name
    if name not in urdf.joints or urdf.joint_type(name) not in MOVABLE:
        raise InputError(
            f"{where}name: {name!r} is not a movable joint of {urdf.path}",
            hint=f"movable joints there: {', '.join(_movable(urdf))}",
        )
    jtype = entry.type if entry.type is not None else urdf.joint_type(name)
    if jtype != urdf.joint_type(name):
        raise InputError(
            f"{where}type is {jtype!r} but {urdf.path} says {urdf.joint_type(name)!r}",
            hint="make them agree",
        )
    lower, upper = _limits(path, i, entry, jtype)
    _check_rated(where, entry)
    if entry.armature < 0:
        raise InputError(f"{where}armature is {entry.armature}", hint="it must be >= 0")
    if entry.control not in CONTROL_MODES:
        raise InputError(f"{where}control is {entry.control!r}", hint="use position or velocity")
    if entry.actuated and entry.motor is None:
        raise InputError(f"{where}motor is missing", hint='name the motor model, e.g. "cia402"')
    return JointDef(
        name=name,
        type=jtype,
        lower=lower,
        upper=upper,
        max_velocity=entry.max_velocity,
        max_effort=entry.max_effort,
        motor=entry.motor,
        motor_id=entry.motor_id,
        control=entry.control,
        actuated=entry.actuated,
        armature=entry.armature,
        motor_params=dict(entry.motor_params),
    )


def _limits(path: Path, i: int, entry: JointEntry, jtype: str) -> tuple[float, float]:
    """A joint's position limits: given and ordered, within its type's travel; a
    continuous joint has none."""
    if jtype == "continuous":
        return -math.inf, math.inf
    where = f"{path}: field joints[{i}]."
    if entry.lower is None:
        raise missing(path, f"joints[{i}].", "lower", "a number")
    if entry.upper is None:
        raise missing(path, f"joints[{i}].", "upper", "a number")
    lower, upper = entry.lower, entry.upper
    if lower >= upper:
        raise InputError(f"{where}lower ({lower}) is not below upper ({upper})")
    travel = TYPE_TRAVEL.get(jtype, math.inf)
    for key, value in (("lower", lower), ("upper", upper)):
        if abs(value) > travel:
            raise InputError(
                f"{where}{key} is {value}: outside what a {jtype} joint allows (±{travel:g})",
                hint="give the joint's real travel (a joint turning further is continuous)",
            )
    return lower, upper


def _check_rated(where: str, entry: JointEntry) -> None:
    """``max_velocity`` and ``max_effort`` are positive and plausible."""
    for key, value, largest in (
        ("max_velocity", entry.max_velocity, MAX_VELOCITY),
        ("max_effort", entry.max_effort, MAX_EFFORT),
    ):
        if not 0 < value <= largest:
            raise InputError(
                f"{where}{key} is {value}: it must be > 0 and at most {largest:g}",
                hint="give the joint's rated limit (a command's magnitude is clamped to it)",
            )


def _connectors(
    path: Path, f: ModuleTypeFile, urdf: ModuleUrdf
) -> dict[str, tuple[str, tf.Vec, tf.Vec]]:
    """Each connector: a valid name, on a link of the URDF, at a pose on it."""
    connectors: dict[str, tuple[str, tf.Vec, tf.Vec]] = {}
    for name, entry in f.connectors.items():
        if not NAME_RE.match(name):
            raise InputError(f"{path}: connector name {name!r} is not a valid name")
        if entry.link not in urdf.links:
            raise InputError(
                f"{path}: field connectors.{name}.link: {entry.link!r} is not a link of "
                f"{urdf.path}",
                hint=f"links there: {', '.join(urdf.links)}",
            )
        connectors[name] = (entry.link, entry.xyz, entry.rpy)
    return connectors


def _chains(
    path: Path, entries: list[ChainEntry], urdf: ModuleUrdf
) -> dict[str, tuple[str, str, tuple[str, ...]]]:
    """Each kinematic chain: two links of the URDF, the base above the tip."""
    chains: dict[str, tuple[str, str, tuple[str, ...]]] = {}
    for i, entry in enumerate(entries):
        where = f"{path}: field chains[{i}]."
        for key, link in (("base", entry.base), ("tip", entry.tip)):
            if link not in urdf.links:
                raise InputError(f"{where}{key}: {link!r} is not a link of {urdf.path}")
        chain = urdf.chain(entry.base, entry.tip)
        if chain is None:
            raise InputError(
                f"{where}base: {entry.base!r} is not above {entry.tip!r} in {urdf.path}"
            )
        chains[entry.name] = (entry.base, entry.tip, tuple(chain))
    return chains


def _components(
    path: Path, entries: list[ComponentEntry], module: ModuleType
) -> tuple[ComponentDef, ...]:
    """Each component: a module-side kind, its params as the kind takes them, about a link
    or chain of this module, named once."""
    module_kinds = [k.name for k in kinds.placed(kinds.Placement.MODULE)]
    components = []
    for i, entry in enumerate(entries):
        where = f"{path}: field components[{i}]."
        if entry.kind not in module_kinds:
            raise InputError(
                f"{where}kind is {entry.kind!r}",
                hint=f"a module runs one of {', '.join(module_kinds)}",
            )
        params = dict(entry.params)
        checks.check_kind_params(entry.kind, params, f"{where}params")
        if entry.link is not None and not module.has_link(entry.link):
            raise InputError(
                f"{where}link: {entry.link!r} is not a link or connector of this module"
            )
        if entry.chain is not None and entry.chain not in module.chains:
            raise InputError(
                f"{where}chain: no chain {entry.chain!r}",
                hint=f"chains: {', '.join(module.chains) or 'none'}",
            )
        name = entry.name if entry.name is not None else entry.kind
        components.append(ComponentDef(entry.kind, name, entry.link, entry.chain, params))
    names = [c.name for c in components]
    for name in names:
        if names.count(name) > 1:
            raise InputError(
                f"{path}: field components: two components are named {name!r}",
                hint="give each a distinct name",
            )
    return tuple(components)
