"""Static data: module types, assembly templates and physical units, loaded and checked.

Every problem is raised as an :class:`~msctl.errors.InputError` or
:class:`~msctl.errors.NotFoundError` naming the file, the field and the fix. Parsed files are
cached by modification time, so resolving again in the same process only stats them.

Where the data lives: the ``assemblies`` and ``calibration`` packages shipped with msctl, or the
directories named by ``MSCTL_ASSEMBLIES_DIR`` and ``MSCTL_CALIBRATION_DIR`` (a field team may
keep its calibration in its own repository).
"""

from __future__ import annotations

import math
import os
import re
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from components import kinds
from components.assembly import BusPlan
from msctl.assembler import recording as robot_recording
from msctl.assembler import transforms as tf
from msctl.assembler.urdf import MOVABLE, ModuleUrdf, parse_module_urdf
from msctl.errors import InputError, NotFoundError, did_you_mean
from msctl.net import radio

T = TypeVar("T")

#: Slot, station and module type names become ROS name components and file names.
NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")
#: Unit serials are file names: no path separators, no leading dot.
SERIAL_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
CONTROL_MODES = ("position", "velocity")
#: A host name as RFC 1123 allows it: it reaches ssh, systemd units and argument lists.
HOST_RE = re.compile(
    r"^(?=.{1,253}$)[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?"
    r"(?:\.[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*$"
)
#: Widest position limits a joint type allows (a revolute joint turning further is
#: continuous; a module's linear joint travels at most this far).
TYPE_TRAVEL = {"revolute": 2 * math.pi, "prismatic": 10.0}
#: Largest plausible max_velocity (rad/s or m/s) and max_effort (N·m or N) of a module's
#: joint: beyond these a number is a typo, and a limit that large limits nothing.
MAX_VELOCITY = 100.0
MAX_EFFORT = 10_000.0


def _package_dir(package: str) -> Path:
    import importlib.util

    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        raise NotFoundError(f"the {package!r} data package is not installed", hint="pip install .")
    return Path(next(iter(spec.submodule_search_locations)))


def assemblies_dir() -> Path:
    """Templates live here, module types in ``modules/`` below (``MSCTL_ASSEMBLIES_DIR``)."""
    env = os.environ.get("MSCTL_ASSEMBLIES_DIR")
    return Path(env) if env else _package_dir("assemblies")


def modules_dir() -> Path:
    """Module type files (``<type>.toml``) and their URDFs (``urdf/``)."""
    return assemblies_dir() / "modules"


def calibration_dir() -> Path:
    """One ``<serial>.toml`` per physical unit (``MSCTL_CALIBRATION_DIR``)."""
    env = os.environ.get("MSCTL_CALIBRATION_DIR")
    return Path(env) if env else _package_dir("calibration")


# ---------------------------------------------------------------------------------- caching

_cache: dict[tuple[str, Path], tuple[tuple[int, int], Any]] = {}


def _cached(kind: str, path: Path, parse: Callable[[Path], T]) -> T:
    """``parse(path)``, reused while the file's mtime and size are unchanged."""
    try:
        st = path.stat()
    except FileNotFoundError:
        raise
    stamp = (st.st_mtime_ns, st.st_size)
    hit = _cache.get((kind, path))
    if hit is not None and hit[0] == stamp:
        return hit[1]
    value = parse(path)
    _cache[(kind, path)] = (stamp, value)
    return value


def clear_cache() -> None:
    """Forget every parsed file (tests that edit files within one mtime tick use this)."""
    _cache.clear()


def read_toml(path: Path) -> dict[str, Any]:
    """Parse a TOML file.

    Raises:
        InputError: If it is malformed, naming the line.
    """
    try:
        with path.open("rb") as fh:
            document = tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        text = str(exc)
        match = re.search(r"line (\d+)", text)
        where = f"{path}:{match.group(1)}" if match else str(path)
        raise InputError(f"{where}: malformed TOML: {text}", hint="fix the syntax there") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: not UTF-8 text", hint="save it as UTF-8") from None
    _check_finite(path, document, "")
    return document


def _check_finite(path: Path, value: Any, where: str) -> None:
    """Every number in a data file is finite: nan and inf are never a limit, an offset or
    a gain, and downstream (MuJoCo, JSON, the motors) cannot take them."""
    if isinstance(value, float) and not math.isfinite(value):
        raise InputError(
            f"{path}: field {where or '(root)'} is {value}: every number must be finite",
            hint="write a finite number (an unbounded joint is type continuous)",
        )
    if isinstance(value, dict):
        for key, item in value.items():
            _check_finite(path, item, f"{where}.{key}" if where else str(key))
    elif isinstance(value, list):
        for i, item in enumerate(value):
            _check_finite(path, item, f"{where}[{i}]")


# ---------------------------------------------------------------------------- field checking


#: A template's ``claims`` values (see :class:`Template`).
CLAIM_POLICIES = ("open", "required")

#: Seconds a module may go without a visible operator before it holds itself, where the
#: template has ground stations and its ``[safety] operator_timeout`` says nothing: a
#: router drops a cut link's tokens after its lease (about 1 s), so 3 s rides out a
#: reconnecting link's flap and still stops a robot nobody can reach within seconds.
OPERATOR_TIMEOUT = 3.0
#: What a template's ``[safety]`` table may say.
TEMPLATE_SAFETY_KEYS = ("operator_timeout",)

#: What a template's ``[network]`` table may say (link classes: :mod:`msctl.net.radio`).
NETWORK_KEYS = ("secure", *radio.CLASSES, "links")


class _Fields:
    """Typed access to one TOML table, with errors naming the file and the field."""

    def __init__(self, path: Path, table: Any, prefix: str = ""):
        self.path = path
        self.prefix = prefix
        if not isinstance(table, dict):
            raise InputError(f"{path}: field {prefix.rstrip('.') or '(root)'} must be a table")
        self.table = table

    def where(self, key: str) -> str:
        return f"{self.path}: field {self.prefix}{key}"

    def get(self, key: str, kind: type | tuple[type, ...], default: Any = ..., what: str = ""):
        if key not in self.table:
            if default is ...:
                raise InputError(
                    f"{self.where(key)} is missing", hint=f"add {key} = <{what or _name(kind)}>"
                )
            return default
        value = self.table[key]
        # bool is an int in Python; a TOML `true` where a number is expected is a mistake.
        ok = isinstance(value, kind) and not (isinstance(value, bool) and bool not in _tuple(kind))
        if not ok:
            raise InputError(
                f"{self.where(key)} is {value!r}", hint=f"it must be {what or _name(kind)}"
            )
        return value

    def number(self, key: str, default: Any = ...) -> float:
        value = self.get(key, (int, float), default, "a number")
        return value if value is None else float(value)

    def name(self, key: str, default: Any = ...) -> str:
        value = self.get(key, str, default, "a name of letters, digits and _")
        if value is not None and not NAME_RE.match(value):
            raise InputError(
                f"{self.where(key)} is {value!r}",
                hint="use letters, digits and _, starting with a letter (it becomes a ROS name)",
            )
        return value

    def vec3(self, key: str, default: Any = ...) -> tf.Vec:
        value = self.get(key, list, default, "a list of 3 numbers")
        if len(value) != 3 or not all(
            isinstance(v, int | float) and not isinstance(v, bool) for v in value
        ):
            raise InputError(f"{self.where(key)} is {value!r}", hint="it must be 3 numbers")
        return (float(value[0]), float(value[1]), float(value[2]))

    def sub(self, key: str, default: Any = ...) -> _Fields:
        return _Fields(self.path, self.get(key, dict, default, "a table"), f"{self.prefix}{key}.")

    def entries(self, key: str, what: str) -> list[dict[str, Any]]:
        """A list of tables, each a dict with string keys (``{"name": ..., **params}``)."""
        value = self.get(key, list, [], f"a list of {what}")
        for i, item in enumerate(value):
            if not isinstance(item, dict) or not isinstance(item.get("name"), str):
                raise InputError(
                    f"{self.where(key)}[{i}] is {item!r}",
                    hint=f'each {what} is a table with a name, e.g. {{ name = "..." }}',
                )
        return [dict(item) for item in value]


def _tuple(kind: type | tuple[type, ...]) -> tuple[type, ...]:
    return kind if isinstance(kind, tuple) else (kind,)


def _name(kind: type | tuple[type, ...]) -> str:
    names = {
        str: "a string",
        int: "an integer",
        float: "a number",
        bool: "true or false",
        list: "a list",
        dict: "a table",
    }
    return " or ".join(names.get(k, k.__name__) for k in _tuple(kind))


# ------------------------------------------------------------------------------ module types


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
    return sorted(p.stem for p in modules_dir().glob("*.toml"))


def load_module_type(key: str, *, referrer: str = "") -> ModuleType:
    """Load and check module type ``key``.

    Args:
        key: Module type key (file stem).
        referrer: Where the name came from (``"<file>: field slots[0].fits"``), for the error.

    Raises:
        NotFoundError: If no such module type file exists.
        InputError: If it or its URDF is malformed or inconsistent.
    """
    path = modules_dir() / f"{key}.toml"
    if not NAME_RE.match(key) or not path.is_file():
        known = ", ".join(module_type_names()) or "none"
        near = did_you_mean(key, module_type_names())
        raise NotFoundError(
            f"{referrer + ': ' if referrer else ''}unknown module type {key!r}",
            hint=f"{near + ' ' if near else ''}known module types: {known} "
            f"(files in {modules_dir()})",
        )
    module = _cached("module", path, _parse_module_type)
    # The URDF has its own mtime: re-check it even when the TOML is unchanged.
    urdf = _cached("urdf", module.urdf.path, parse_module_urdf)
    if urdf is not module.urdf:
        _cache.pop(("module", path), None)
        module = _cached("module", path, _parse_module_type)
    return module


def _parse_module_type(path: Path) -> ModuleType:
    f = _Fields(path, read_toml(path))
    urdf_rel = f.get("urdf", str, what="a path relative to the module file")
    urdf_path = _confined(path.parent, urdf_rel, f.where("urdf"))
    if not urdf_path.is_file():
        raise InputError(
            f"{f.where('urdf')}: {urdf_path} does not exist", hint="fix the path or add the URDF"
        )
    _check_meshes(urdf_path, path.parent, f.where("urdf"))
    urdf = _cached("urdf", urdf_path, parse_module_urdf)
    kind = f.name("kind")
    bus = f.sub("bus")
    bus_kind = bus.get("kind", str)
    backend = _backend(bus_kind, bus.where("kind"))
    _check_bus_options(backend, bus.table, bus.where("options"))

    joints: dict[str, JointDef] = {}
    for i, raw in enumerate(f.get("joints", list, [], "a list of joints tables")):
        j = _Fields(path, raw, f"joints[{i}].")
        name = j.name("name")
        if name in joints:
            raise InputError(f"{j.where('name')}: joint {name!r} is listed twice")
        if name not in urdf.joints or urdf.joint_type(name) not in MOVABLE:
            raise InputError(
                f"{j.where('name')}: {name!r} is not a movable joint of {urdf.path}",
                hint=f"movable joints there: {', '.join(_movable(urdf))}",
            )
        jtype = j.get("type", str, urdf.joint_type(name))
        if jtype != urdf.joint_type(name):
            raise InputError(
                f"{j.where('type')} is {jtype!r} but {urdf.path} says {urdf.joint_type(name)!r}",
                hint="make them agree",
            )
        bounded = jtype != "continuous"
        lower = j.number("lower") if bounded else -math.inf
        upper = j.number("upper") if bounded else math.inf
        if lower >= upper:
            raise InputError(f"{j.where('lower')} ({lower}) is not below upper ({upper})")
        travel = TYPE_TRAVEL.get(jtype, math.inf)
        for key, value in (("lower", lower), ("upper", upper)):
            if bounded and abs(value) > travel:
                raise InputError(
                    f"{j.where(key)} is {value}: outside what a {jtype} joint allows (±{travel:g})",
                    hint="give the joint's real travel (a joint turning further is continuous)",
                )
        max_velocity = j.number("max_velocity")
        max_effort = j.number("max_effort")
        for key, value, largest in (
            ("max_velocity", max_velocity, MAX_VELOCITY),
            ("max_effort", max_effort, MAX_EFFORT),
        ):
            if not 0 < value <= largest:
                raise InputError(
                    f"{j.where(key)} is {value}: it must be > 0 and at most {largest:g}",
                    hint="give the joint's rated limit (a command's magnitude is clamped to it)",
                )
        armature = j.number("armature", 0.0)
        if armature < 0:
            raise InputError(f"{j.where('armature')} is {armature}", hint="it must be >= 0")
        control = j.get("control", str, "position")
        if control not in CONTROL_MODES:
            raise InputError(
                f"{j.where('control')} is {control!r}", hint="use position or velocity"
            )
        actuated = j.get("actuated", bool, True)
        motor = j.get("motor", str, None)
        if actuated and motor is None:
            raise InputError(
                f"{j.where('motor')} is missing", hint='name the motor model, e.g. "cia402"'
            )
        joints[name] = JointDef(
            name=name,
            type=jtype,
            lower=lower,
            upper=upper,
            max_velocity=max_velocity,
            max_effort=max_effort,
            motor=motor,
            motor_id=_motor_id(backend, j, "motor_id"),
            control=control,
            actuated=actuated,
            armature=armature,
            motor_params=dict(j.get("motor_params", dict, {})),
        )
    _check_unique_ids(
        {n: jd.motor_id for n, jd in joints.items() if jd.actuated}, f"{path}: field joints"
    )
    missing = [n for n in _movable(urdf) if n not in joints]
    if missing:
        raise InputError(
            f"{path}: field joints: {urdf.path} has movable joints with no joints entry: "
            f"{', '.join(missing)}",
            hint="describe every movable joint (limits, motor) in the module file",
        )

    connectors: dict[str, tuple[str, tf.Vec, tf.Vec]] = {}
    table = f.sub("connectors", {})
    for cname in table.table:
        c = table.sub(cname)
        if not NAME_RE.match(cname):
            raise InputError(f"{path}: connector name {cname!r} is not a valid name")
        link = c.get("link", str)
        if link not in urdf.links:
            raise InputError(
                f"{c.where('link')}: {link!r} is not a link of {urdf.path}",
                hint=f"links there: {', '.join(urdf.links)}",
            )
        connectors[cname] = (link, c.vec3("xyz", (0.0, 0.0, 0.0)), c.vec3("rpy", (0.0, 0.0, 0.0)))

    chains: dict[str, tuple[str, str, tuple[str, ...]]] = {}
    for i, raw in enumerate(f.get("chains", list, [], "a list of chains tables")):
        c = _Fields(path, raw, f"chains[{i}].")
        name = c.name("name")
        base, tip = c.get("base", str), c.get("tip", str)
        for key, link in (("base", base), ("tip", tip)):
            if link not in urdf.links:
                raise InputError(f"{c.where(key)}: {link!r} is not a link of {urdf.path}")
        chain = urdf.chain(base, tip)
        if chain is None:
            raise InputError(f"{c.where('base')}: {base!r} is not above {tip!r} in {urdf.path}")
        chains[name] = (base, tip, tuple(chain))

    module = ModuleType(
        key=path.stem,
        path=path,
        description=f.get("description", str, ""),
        family=f.get("family", str),
        kind=kind,
        revision=f.get("revision", int, 1),
        urdf=urdf,
        shares_computer=f.get("shares_computer", bool, False),
        bus={k: v for k, v in bus.table.items()},
        health=dict(f.get("health", dict, {})),
        safety=dict(f.get("safety", dict, {})),
        connectors=connectors,
        chains=chains,
        joints=joints,
        components=(),
        interesting_links=tuple(f.get("interesting_links", list, [])),
        injections=tuple(f.entries("injections", "injection")),
        overrides=tuple(f.entries("overrides", "override")),
    )
    for i, link in enumerate(module.interesting_links):
        if not isinstance(link, str) or not module.has_link(link):
            raise InputError(f"{path}: field interesting_links[{i}]: {link!r} is not a link")

    components = []
    for i, raw in enumerate(f.get("components", list, [], "a list of components tables")):
        c = _Fields(path, raw, f"components[{i}].")
        ckind = c.get("kind", str)
        module_kinds = [k.name for k in kinds.placed(kinds.Placement.MODULE)]
        if ckind not in module_kinds:
            raise InputError(
                f"{c.where('kind')} is {ckind!r}",
                hint=f"a module runs one of {', '.join(module_kinds)}",
            )
        params = dict(c.get("params", dict, {}))
        _check_kind_params(ckind, params, c.where("params"))
        link = c.get("link", str, None)
        if link is not None and not module.has_link(link):
            raise InputError(
                f"{c.where('link')}: {link!r} is not a link or connector of this module"
            )
        chain = c.get("chain", str, None)
        if chain is not None and chain not in chains:
            raise InputError(
                f"{c.where('chain')}: no chain {chain!r}",
                hint=f"chains: {', '.join(chains) or 'none'}",
            )
        components.append(ComponentDef(ckind, c.name("name", ckind), link, chain, params))
    names = [c.name for c in components]
    for name in names:
        if names.count(name) > 1:
            raise InputError(
                f"{path}: field components: two components are named {name!r}",
                hint="give each a distinct name",
            )
    module = _replace(module, components=tuple(components))
    _check_health(module, module.health, f"{path}: field health")
    _check_safety(module.safety, f"{path}: field safety")
    _check_extensions(module, module.injections, module.overrides, str(path))
    return module


def _check_health(module: ModuleType, health: dict[str, Any], where: str) -> None:
    """The ``[health]`` table, as each kind the module runs that reads it checks it."""
    for kind in {c.kind for c in module.components}:
        if "thresholds" in kinds.get(kind).module_facts:
            _check_kind_params(kind, {"thresholds": health}, where)


def _check_safety(safety: dict[str, Any], where: str) -> None:
    """The ``[safety]`` table (:class:`components.safety.SafetyLimits`)."""
    from components.safety import SafetyLimits

    try:
        SafetyLimits.from_mapping(safety, "[safety]")
    except ValueError as exc:
        raise InputError(f"{where}: {exc}", hint="see components/safety.py") from None


def _confined(folder: Path, relative: str, where: str) -> Path:
    """``folder / relative``, refused unless it stays inside ``folder`` (no ``../../etc``)."""
    resolved = (folder / relative).resolve()
    if not resolved.is_relative_to(folder.resolve()):
        raise InputError(
            f"{where} is {relative!r}: it leaves {folder}",
            hint="keep a module's files in its folder (a path relative to it, without ..)",
        )
    return resolved


def _check_meshes(urdf_path: Path, folder: Path, where: str) -> None:
    """Every mesh a module URDF names stays inside the module's folder."""
    text = urdf_path.read_text(encoding="utf-8", errors="replace")
    inside = folder.resolve()
    for filename in re.findall(r"<mesh\b[^>]*\bfilename\s*=\s*[\"']([^\"']*)[\"']", text):
        name = filename.removeprefix("file://")
        remote = "://" in name or name.startswith("/")
        if remote or not (urdf_path.parent / name).resolve().is_relative_to(inside):
            raise InputError(
                f"{where}: {urdf_path} names mesh {filename!r}, which leaves {folder}",
                hint="give meshes as paths relative to the URDF, inside the module's folder",
            )


def _backend(name: str, where: str) -> Any:
    from components.motors.options import MotorOptionsError, backend_info, backend_names

    try:
        return backend_info(name)
    except MotorOptionsError:
        raise InputError(
            f"{where} is {name!r}: no such motor backend",
            hint=f"use one of {', '.join(backend_names())}",
        ) from None


def _check_bus_options(backend: Any, bus: dict[str, Any], where: str) -> None:
    """The bus's options (and bitrate/baudrate) against the backend's typed options."""
    from components.motors.options import MotorOptionsError

    options = bus.get("options", {})
    if not isinstance(options, dict):
        raise InputError(f"{where} is {options!r}", hint="it must be a table")
    try:
        backend.parse_options(options, bitrate=bus.get("bitrate"), baudrate=bus.get("baudrate"))
    except MotorOptionsError as exc:
        raise InputError(f"{where}: {exc}", hint="fix or remove that option") from None


def _motor_id(backend: Any, fields: _Fields, key: str) -> int | None:
    """An optional motor id, inside the bus kind's id range."""
    value = fields.get(key, int, None, "a motor id")
    if value is not None and value not in backend.motor_ids:
        ids = backend.motor_ids
        raise InputError(
            f"{fields.where(key)} is {value}: a {backend.name} motor id is "
            f"{ids.start}..{ids.stop - 1}",
            hint="use the id the motor is configured with",
        )
    return value


def _check_unique_ids(ids: dict[str, int | None], where: str) -> None:
    """No two motors of one bus share an id (they would both answer, or fight)."""
    seen: dict[int, str] = {}
    for joint, motor_id in ids.items():
        if motor_id is None:
            continue
        if motor_id in seen:
            raise InputError(
                f"{where}: joints {seen[motor_id]} and {joint} both use motor id {motor_id}",
                hint="give each motor on a bus its own id",
            )
        seen[motor_id] = joint


def _check_kind_params(
    kind: str, params: dict[str, Any], where: str, robots: list[str] | None = None
) -> None:
    """A component's parameters against its kind's entry (names, types, ranges; with the
    template's ``robots``, the kind's own check of them as a whole)."""
    try:
        kinds.check_params(kinds.get(kind), params, robots)
    except kinds.KindError as exc:
        raise InputError(f"{where}: {exc}", hint="fix or remove that parameter") from None


def _named_components(
    counts: _Fields, kind: str, defaults: dict[str, Any], robots: list[str]
) -> list[tuple[str, str, dict[str, Any]]]:
    """A station's components of ``kind`` given as a list of tables, each with a ``name``
    and its parameters (over the station's ``params.<kind>``), each checked."""
    items = counts.entries(kind, f"{kind} table")
    if len(items) > kinds.MAX_PER_STATION:
        raise InputError(
            f"{counts.where(kind)} lists {len(items)} components",
            hint=f"a station runs 0 to {kinds.MAX_PER_STATION} components of one kind",
        )
    out = []
    for i, item in enumerate(items):
        entry = _Fields(counts.path, item, f"{counts.prefix}{kind}[{i}].")
        component = entry.name("name")
        own = {**defaults, **{k: v for k, v in item.items() if k != "name"}}
        where = f"{counts.path}: field {counts.prefix}{kind}[{i}] ({component})"
        try:
            kinds.check_params(kinds.get(kind), own, robots)
        except kinds.KindError as exc:
            raise InputError(f"{where}: {exc}", hint="fix or remove that parameter") from None
        out.append((kind, component, own))
    return out


def _check_extensions(module: ModuleType, injections: Any, overrides: Any, source: str) -> None:
    """Each injection and override targets a component the module runs, exists for that
    kind, and its parameters type-check; joint parameters name the module's joints."""
    from components.executor import registry

    run = {c.kind for c in module.components}
    for field_name, what, entries in (
        ("injections", "injection", injections),
        ("overrides", "override", overrides),
    ):
        for i, entry in enumerate(entries):
            where = f"{source}: field {field_name}[{i}]"
            target = kinds.extension_target(entry)
            if target not in run:
                raise InputError(
                    f"{where}: {what} {entry.get('name')!r} targets {target!r}, which module "
                    f"type {module.key} does not run",
                    hint=f"its components: {', '.join(sorted(run)) or 'none'}",
                )
            spec = {k: v for k, v in entry.items() if k != "component"}
            try:
                registry.check(what, target, spec)
            except registry.RegistryError as exc:
                raise InputError(f"{where}.name: {exc}", hint=f"see the {what}s known") from None
        _check_joint_params(module, entries, f"{source}: field {field_name}")


def merged_bus(module: ModuleType, unit: Unit) -> BusPlan:
    """A unit's bus: the module type's, with the unit's values (channel...) over it."""
    bus = {k: v for k, v in module.bus.items() if k != "options"}
    bus.update({k: v for k, v in unit.bus.items() if k != "options"})
    options = {**module.bus.get("options", {}), **unit.bus.get("options", {})}
    return BusPlan(
        kind=bus["kind"],
        channel=bus["channel"],
        bitrate=bus.get("bitrate"),
        baudrate=bus.get("baudrate"),
        options=options,
    )


def _replace(module: ModuleType, **changes: Any) -> ModuleType:
    from dataclasses import replace

    return replace(module, **changes)


def _movable(urdf: ModuleUrdf) -> list[str]:
    return [n for n in urdf.joints if urdf.joint_type(n) in MOVABLE]


def _check_joint_params(module: ModuleType, entries: Any, where: str) -> None:
    """Injection/override params named ``joint`` or ``joints`` must name joints of the module."""
    for i, entry in enumerate(entries):
        named = entry.get("joints", [])
        named = [named] if isinstance(named, str) else list(named)
        if "joint" in entry:
            named.append(entry["joint"])
        for joint in named:
            if joint not in module.joints:
                raise InputError(
                    f"{where}[{i}] ({entry.get('name')}): module type {module.key} has no joint "
                    f"{joint!r}",
                    hint=f"its joints: {', '.join(module.joints)}",
                )


# ---------------------------------------------------------------------------------- templates


@dataclass(frozen=True)
class SlotDef:
    """A place in a template for one module."""

    name: str
    fits: tuple[str, ...]
    default: str | None
    place: tuple[tf.Vec, tf.Vec]
    index: int


@dataclass(frozen=True)
class ConnectionDef:
    """``parent`` slot's connector carries ``child`` slot's connector."""

    parent: str
    parent_connector: str
    child: str
    child_connector: str
    angle: float
    index: int


@dataclass(frozen=True)
class StationDef:
    """A ground-control station: its host and the components it runs.

    Attributes:
        name: The station's name (its namespace).
        host: Its computer.
        components: ``(kind, name, params)`` of each component, in data order; a kind
            given as a count ``n`` has components ``kind`` (n = 1) or ``kind_1`` ...
            ``kind_n``, a kind given as a list has the names the list gives.
    """

    name: str
    host: str
    components: tuple[tuple[str, str, dict[str, Any]], ...]


@dataclass(frozen=True)
class Template:
    """An assembly template (``assemblies/<name>.toml``)."""

    name: str
    path: Path
    description: str
    mobile: bool
    slots: tuple[SlotDef, ...]
    connections: tuple[ConnectionDef, ...]
    stations: tuple[StationDef, ...]
    module_types: dict[str, ModuleType] = field(default_factory=dict)
    #: ``[safety] operator_timeout``: seconds without a visible ground station or claim
    #: holder before a module holds itself (:mod:`components.joint_manager.presence`);
    #: ``None``: never (no station and nothing said, or ``operator_timeout = false``).
    operator_timeout: float | None = None
    #: ``"open"``: an unclaimed module takes commands from anyone; ``"required"``: only from
    #: the holder of its claim (see :mod:`components.claims`).
    claims: str = "open"
    #: ``[network] secure = true``: every computer's router runs the config ``msctl net
    #: config`` generates (mutual TLS, access control), as ``--secure`` does.
    secure: bool = False
    #: ``[network]``'s link classes and which computer's link is which, as the lock keeps
    #: them (:meth:`msctl.net.radio.Network.as_dict`).
    network: dict[str, Any] = field(default_factory=dict)
    #: ``[recording] robots = true``: the parameters of the data archiver each robot computer
    #: runs to record its own modules locally (:mod:`msctl.assembler.recording`); ``None``: off.
    robot_recording: dict[str, Any] | None = None

    def slot(self, name: str) -> SlotDef:
        """The slot called ``name`` (KeyError if none)."""
        for slot in self.slots:
            if slot.name == name:
                return slot
        raise KeyError(name)

    @property
    def roots(self) -> list[str]:
        """Slots no connection carries: one per robot."""
        children = {c.child for c in self.connections}
        return [s.name for s in self.slots if s.name not in children]


def template_names() -> list[str]:
    """Every template name, sorted."""
    return sorted(p.stem for p in assemblies_dir().glob("*.toml"))


def load_template(name: str) -> Template:
    """Load and check template ``name`` and the module types its slots accept.

    Raises:
        NotFoundError: If there is no such template or a slot names an unknown module type.
        InputError: If the template is malformed: bad fields, unknown slots or connectors,
            a slot carried twice, a cycle.
    """
    path = assemblies_dir() / f"{name}.toml"
    if not NAME_RE.match(name) or not path.is_file():
        near = did_you_mean(name, template_names())
        raise NotFoundError(
            f"unknown template {name!r}",
            hint=f"{near + ' ' if near else ''}templates: {', '.join(template_names()) or 'none'} "
            f"(files in {assemblies_dir()}); see `msctl assemble --list`",
        )
    template = _cached("template", path, _parse_template)
    # Module types are checked on every call (their files may have changed, cheap when cached).
    types: dict[str, ModuleType] = {}
    for slot in template.slots:
        for i, key in enumerate(slot.fits):
            if key not in types:
                types[key] = load_module_type(
                    key, referrer=f"{path}: field slots[{slot.index}].fits[{i}] (slot {slot.name})"
                )
    _check_connections(template, types)
    return _replace_template(template, types)


def _replace_template(template: Template, types: dict[str, ModuleType]) -> Template:
    from dataclasses import replace

    return replace(template, module_types=types)


def _parse_template(path: Path) -> Template:
    f = _Fields(path, read_toml(path))
    slots: list[SlotDef] = []
    for i, raw in enumerate(f.get("slots", list, what="a list of slots tables")):
        s = _Fields(path, raw, f"slots[{i}].")
        name = s.name("name")
        if any(other.name == name for other in slots):
            raise InputError(f"{s.where('name')}: slot {name!r} is defined twice")
        fits = s.get("fits", list, what="a list of module type names")
        if not fits or not all(isinstance(k, str) for k in fits):
            raise InputError(f"{s.where('fits')} is {fits!r}", hint="list module type names")
        place = s.sub("place", {})
        slots.append(
            SlotDef(
                name=name,
                fits=tuple(fits),
                default=s.get("default", str, None),
                place=(place.vec3("xyz", (0.0, 0.0, 0.0)), place.vec3("rpy", (0.0, 0.0, 0.0))),
                index=i,
            )
        )
    if not slots:
        raise InputError(
            f"{path}: field slots is empty", hint="add at least one slot (a slots table)"
        )
    slot_names = {s.name for s in slots}

    connections: list[ConnectionDef] = []
    carried: dict[str, int] = {}
    for i, raw in enumerate(f.get("connections", list, [], "a list of connections tables")):
        c = _Fields(path, raw, f"connections[{i}].")
        ends = []
        for key in ("parent", "child"):
            value = c.get(key, str, what='"<slot>.<connector>"')
            slot, dot, connector = value.partition(".")
            if not dot or not connector:
                raise InputError(
                    f"{c.where(key)} is {value!r}",
                    hint='write "<slot>.<connector>", e.g. "limb1.tip"',
                )
            if slot not in slot_names:
                raise InputError(
                    f"{c.where(key)}: no slot {slot!r}",
                    hint=f"slots: {', '.join(sorted(slot_names))}",
                )
            ends.append((slot, connector))
        (parent, pc), (child, cc) = ends
        if child in carried:
            raise InputError(
                f"{c.where('child')}: slot {child!r} is already carried by "
                f"connections[{carried[child]}]",
                hint="a module hangs from exactly one parent (the assembly is a tree)",
            )
        carried[child] = i
        connections.append(ConnectionDef(parent, pc, child, cc, c.number("angle", 0.0), i))
    # With every slot carried at most once, a loop means some slots have no way up to a root.
    parent_of = {c.child: c.parent for c in connections}
    for slot in slot_names:
        seen = {slot}
        while slot in parent_of:
            slot = parent_of[slot]
            if slot in seen:
                raise InputError(
                    f"{path}: field connections: slots {slot!r} ... form a loop",
                    hint="the assembly must be a tree",
                )
            seen.add(slot)

    # Robots by their root slot: what a station component may be given as its robot.
    robots = [s.name for s in slots if s.name not in {c.child for c in connections}]
    stations: list[StationDef] = []
    for i, raw in enumerate(f.get("stations", list, [], "a list of stations tables")):
        s = _Fields(path, raw, f"stations[{i}].")
        name = s.name("name")
        if name in slot_names or any(st.name == name for st in stations):
            raise InputError(f"{s.where('name')}: {name!r} is already a slot or station name")
        host = _host(s, "host")
        counts = s.sub("components", {})
        params = s.sub("params", {})
        station_kinds = [k.name for k in kinds.placed(kinds.Placement.STATION)]
        entries: list[tuple[str, str, dict[str, Any]]] = []
        for kind in counts.table:
            if kind not in station_kinds:
                raise InputError(
                    f"{counts.where(kind)}: {kind!r} is not a ground-station component kind",
                    hint=f"use one of {', '.join(station_kinds)}",
                )
            kind_params = dict(params.get(kind, dict, {}))
            if not kinds.get(kind).named:  # a named one's are checked with each component's
                _check_kind_params(kind, kind_params, params.where(kind), robots)
            if isinstance(counts.table[kind], list):
                entries += _named_components(counts, kind, kind_params, robots)
                continue
            if kinds.get(kind).named:
                raise InputError(
                    f"{counts.where(kind)} is {counts.table[kind]!r}: each {kind} is named, "
                    "with its parameters",
                    hint=f'write {kind} = [{{ name = "...", ... }}], one table per component '
                    f"(see assemblies/two_dragons.toml)",
                )
            count = counts.get(kind, int, what="a count, or a list of named components")
            if not 0 <= count <= kinds.MAX_PER_STATION:
                raise InputError(
                    f"{counts.where(kind)} is {count}",
                    hint=f"a station runs 0 to {kinds.MAX_PER_STATION} components of one kind",
                )
            for n in range(count):
                entries.append((kind, kind if count == 1 else f"{kind}_{n + 1}", kind_params))
        for kind in params.table:
            if kind not in counts.table:
                raise InputError(
                    f"{params.where(kind)}: the station runs no {kind}",
                    hint=f"add {kind} to the station's components, or remove its params",
                )
        seen: dict[str, str] = {}
        for kind, component, _ in entries:
            if component in seen:
                raise InputError(
                    f"{counts.where(kind)}: two components of station {name} are named "
                    f"{component!r} (a {seen[component]} and a {kind})",
                    hint="give each a distinct name: it is its node's name on the graph",
                )
            seen[component] = kind
        stations.append(StationDef(name, host, tuple(entries)))

    claims = f.get("claims", str, "open", '"open" or "required"')
    if claims not in CLAIM_POLICIES:
        raise InputError(
            f"{f.where('claims')} is {claims!r}",
            hint='write claims = "required" (only a claim\'s holder commands a module) or '
            'claims = "open" (an unclaimed module takes anyone\'s commands; the default)',
        )

    operator_timeout = _operator_timeout(f, bool(stations))

    network = f.sub("network", {})
    for key in network.table:
        if key not in NETWORK_KEYS:
            raise InputError(
                f"{network.where(key)} is not a network setting",
                hint=f"the [network] table takes {', '.join(NETWORK_KEYS)}",
            )

    return Template(
        name=path.stem,
        path=path,
        description=f.get("description", str, ""),
        mobile=f.get("mobile", bool, False),
        slots=tuple(slots),
        connections=tuple(connections),
        stations=tuple(stations),
        claims=claims,
        operator_timeout=operator_timeout,
        secure=network.get("secure", bool, False, "true or false"),
        robot_recording=robot_recording.parse(f.sub("recording", {}).table, path),
        network=radio.parse(network.table, path).as_dict(),
    )


def _operator_timeout(f: _Fields, stations: bool) -> float | None:
    """The template's ``[safety] operator_timeout``: a positive number of seconds, or
    ``false`` for never; unset, :data:`OPERATOR_TIMEOUT` if the template has stations (with
    none, nobody would ever attend its modules but a claim holder: off unless asked)."""
    safety = f.sub("safety", {})
    for key in safety.table:
        if key not in TEMPLATE_SAFETY_KEYS:
            raise InputError(
                f"{safety.where(key)} is not a template safety setting",
                hint=f"the template's [safety] table takes {', '.join(TEMPLATE_SAFETY_KEYS)} "
                "(a module's own limits go in its module type's [safety])",
            )
    value = safety.table.get("operator_timeout", OPERATOR_TIMEOUT if stations else False)
    if value is False:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or value <= 0:
        raise InputError(
            f"{safety.where('operator_timeout')} is {value!r}",
            hint="give the seconds a module may go without a visible ground station or "
            "claim holder before it holds itself (e.g. 3.0), or false for never",
        )
    return float(value)


def _check_connections(template: Template, types: dict[str, ModuleType]) -> None:
    """Every connector named must exist on every module type its slot accepts."""
    for c in template.connections:
        for role, slot_name, connector in (
            ("parent", c.parent, c.parent_connector),
            ("child", c.child, c.child_connector),
        ):
            slot = template.slot(slot_name)
            for key in slot.fits:
                module = types[key]
                if connector not in module.connectors:
                    raise InputError(
                        f"{template.path}: field connections[{c.index}].{role}: module type "
                        f"{key} (slot {slot_name}) has no connector {connector!r}",
                        hint=f"its connectors: {', '.join(module.connectors) or 'none'}",
                    )
                if role == "child":
                    link = module.connectors[connector][0]
                    if module.urdf.fixed_transform(link) is None:
                        raise InputError(
                            f"{template.path}: field connections[{c.index}].child: connector "
                            f"{connector!r} of {key} is on link {link!r}, which moves relative to "
                            f"the module's root link {module.urdf.root_link!r}",
                            hint="carry a module by a connector rigidly fixed to its root link "
                            "(swap parent and child?)",
                        )


# -------------------------------------------------------------------------------------- units


@dataclass(frozen=True)
class JointCalibrationDef:
    """A unit's entry for one joint."""

    motor_id: int | None
    zero_offset: float
    direction: int
    lower: float | None
    upper: float | None


@dataclass(frozen=True)
class Unit:
    """A physical unit (``calibration/<serial>.toml``)."""

    serial: str
    path: Path
    module_type: str
    host: str
    bus: dict[str, Any]
    joints: dict[str, JointCalibrationDef]
    injections: tuple[dict[str, Any], ...]
    overrides: tuple[dict[str, Any], ...]
    health: dict[str, Any]
    safety: dict[str, Any] = field(default_factory=dict)


def _host(fields: _Fields, key: str) -> str:
    """A host name field: letters, digits, - and dots, as RFC 1123 allows."""
    host = fields.get(key, str, what="a hostname")
    if not HOST_RE.match(host):
        raise InputError(
            f"{fields.where(key)} is {host!r}: not a valid host name",
            hint="use letters, digits, - and . (e.g. hl-limb-03), as `hostname` prints it",
        )
    return host


def units_searched() -> str:
    """Where units are looked for, and how to look elsewhere (for error hints)."""
    return (
        f"units are read from {calibration_dir()} (set MSCTL_CALIBRATION_DIR to read another "
        "folder, or `pip install -e .` in a checkout)"
    )


def unit_serials() -> list[str]:
    """Every unit serial with a calibration file, sorted."""
    return sorted(p.stem for p in calibration_dir().glob("*.toml"))


def unit_exists(serial: str) -> bool:
    """Whether a calibration file exists for ``serial``."""
    return bool(SERIAL_RE.match(serial)) and (calibration_dir() / f"{serial}.toml").is_file()


def load_unit(serial: str) -> Unit:
    """Load a unit's calibration file (fields checked; joints checked by :func:`check_unit`).

    Raises:
        NotFoundError: If there is no calibration file for ``serial``.
        InputError: If the file is malformed.
    """
    if not unit_exists(serial):
        near = did_you_mean(serial, unit_serials())
        raise NotFoundError(
            f"unknown unit {serial!r}: no {calibration_dir() / (serial + '.toml')}",
            hint=f"{near + ' ' if near else ''}see `msctl assemble --list` for the units; "
            f"{units_searched()}",
        )
    unit = _cached("unit", calibration_dir() / f"{serial}.toml", _parse_unit)
    if (
        not NAME_RE.match(unit.module_type)
        or not (modules_dir() / f"{unit.module_type}.toml").is_file()
    ):
        near = did_you_mean(unit.module_type, module_type_names())
        raise NotFoundError(
            f"{unit.path}: field module_type: unknown module type {unit.module_type!r}",
            hint=f"{near + ' ' if near else ''}known module types: "
            f"{', '.join(module_type_names()) or 'none'}",
        )
    return unit


def _parse_unit(path: Path) -> Unit:
    f = _Fields(path, read_toml(path))
    bus = f.sub("bus")
    bus.get("channel", str, what='the bus channel, e.g. "can0" or "/dev/ttyUSB0"')
    joints: dict[str, JointCalibrationDef] = {}
    table = f.sub("joints", {})
    for name in table.table:
        j = table.sub(name)
        direction = j.get("direction", int, 1)
        if direction not in (1, -1):
            raise InputError(f"{j.where('direction')} is {direction}", hint="use 1 or -1")
        joints[name] = JointCalibrationDef(
            motor_id=j.get("motor_id", int, None, "a motor id"),
            zero_offset=j.number("zero_offset", 0.0),
            direction=direction,
            lower=j.number("lower", None),
            upper=j.number("upper", None),
        )
    return Unit(
        serial=path.stem,
        path=path,
        module_type=f.get("module_type", str, what="a module type name"),
        host=_host(f, "host"),
        bus=dict(bus.table),
        joints=joints,
        injections=tuple(f.entries("injections", "injection")),
        overrides=tuple(f.entries("overrides", "override")),
        health=dict(f.get("health", dict, {})),
        safety=dict(f.get("safety", dict, {})),
    )


def check_unit(unit: Unit, module: ModuleType) -> None:
    """Check a unit's calibration against its module type.

    Raises:
        InputError: For a calibration entry naming a joint the module does not have, limits
            outside the module's, a missing motor id, or overrides naming unknown joints.
    """
    for name, cal in unit.joints.items():
        where = f"{unit.path}: field joints.{name}"
        if name not in module.joints:
            raise InputError(
                f"{where}: module type {module.key} has no joint {name!r}",
                hint=f"its joints: {', '.join(module.joints)}; rename or remove the entry",
            )
        jd = module.joints[name]
        lower = jd.lower if cal.lower is None else cal.lower
        upper = jd.upper if cal.upper is None else cal.upper
        if not (jd.lower <= lower < upper <= jd.upper):
            raise InputError(
                f"{where}: limits [{lower}, {upper}] are not inside {module.key}'s "
                f"[{jd.lower}, {jd.upper}]",
                hint="a unit may only narrow a joint's range",
            )
        # A zero offset is a small correction: within two travel spans (half a turn at least
        # for a rotating joint), never the 100 rad of a typo.
        span = upper - lower if math.isfinite(upper - lower) else math.inf
        reach = min(2 * span, 2 * math.pi) if jd.type == "prismatic" else max(2 * span, math.pi)
        if jd.type == "continuous":
            reach = math.pi
        if abs(cal.zero_offset) > reach:
            raise InputError(
                f"{where}.zero_offset is {cal.zero_offset}: outside the joint's reach "
                f"(±{reach:g} for its travel [{lower:g}, {upper:g}])",
                hint="a zero offset is the raw position of calibrated zero: measure it again",
            )
    backend = _backend(module.bus["kind"], f"{module.path}: field bus.kind")
    ids: dict[str, int | None] = {}
    for name, jd in module.joints.items():
        cal = unit.joints.get(name)
        if jd.actuated and jd.motor_id is None and (cal is None or cal.motor_id is None):
            raise InputError(
                f"{unit.path}: field joints.{name}.motor_id is missing",
                hint=f"module type {module.key} has no default id for {name}: add motor_id",
            )
        motor_id = cal.motor_id if cal and cal.motor_id is not None else jd.motor_id
        if jd.actuated:
            ids[name] = motor_id
        if motor_id is not None and motor_id not in backend.motor_ids:
            r = backend.motor_ids
            raise InputError(
                f"{unit.path}: field joints.{name}.motor_id is {motor_id}: a {backend.name} "
                f"motor id is {r.start}..{r.stop - 1}",
                hint="use the id the motor is configured with",
            )
    _check_unique_ids(ids, f"{unit.path}: field joints (with {module.path}'s defaults)")
    bus = merged_bus(module, unit)
    try:
        backend.check_channel(bus.channel)
    except ValueError as exc:
        raise InputError(f"{unit.path}: field bus.channel: {exc}") from None
    merged = {**module.bus, **unit.bus, "options": bus.options}
    _check_bus_options(backend, merged, f"{unit.path}: field bus.options")
    _check_health(module, {**module.health, **unit.health}, f"{unit.path}: field health")
    _check_safety({**module.safety, **unit.safety}, f"{unit.path}: field safety")
    _check_extensions(module, unit.injections, unit.overrides, str(unit.path))
