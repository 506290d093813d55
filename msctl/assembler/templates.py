"""Assembly templates (``assemblies/<name>.toml``): slots, how they connect, stations."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from msctl.assembler import files
from msctl.assembler import recording as robot_recording
from msctl.assembler import transforms as tf
from msctl.assembler.models import NAME_RE, ConnectionEntry, SlotEntry, TemplateFile
from msctl.assembler.module_types import ModuleType, load_module_type
from msctl.assembler.schema import decode
from msctl.assembler.stations import StationDef, parse_stations
from msctl.errors import InputError, NotFoundError, did_you_mean
from msctl.net import radio

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
    return sorted(p.stem for p in files.assemblies_dir().glob("*.toml"))


def load_template(name: str) -> Template:
    """Load and check template ``name`` and the module types its slots accept.

    Raises:
        NotFoundError: If there is no such template or a slot names an unknown module type.
        InputError: If the template is malformed: bad fields, unknown slots or connectors,
            a slot carried twice, a cycle.
    """
    path = files.assemblies_dir() / f"{name}.toml"
    if not NAME_RE.match(name) or not path.is_file():
        near = did_you_mean(name, template_names())
        raise NotFoundError(
            f"unknown template {name!r}",
            hint=f"{near + ' ' if near else ''}templates: {', '.join(template_names()) or 'none'} "
            f"(files in {files.assemblies_dir()}); see `msctl assemble --list`",
        )
    template = files.cached("template", path, parse_template)
    # Module types are checked on every call (their files may have changed, cheap when cached).
    types: dict[str, ModuleType] = {}
    for slot in template.slots:
        for i, key in enumerate(slot.fits):
            if key not in types:
                types[key] = load_module_type(
                    key, referrer=f"{path}: field slots[{slot.index}].fits[{i}] (slot {slot.name})"
                )
    _check_connections(template, types)
    return replace(template, module_types=types)


def parse_template(path: Path) -> Template:
    """Read and check one template file (see :class:`~msctl.assembler.models.TemplateFile`).

    Raises:
        InputError: Naming the file, the field and the fix.
    """
    raw = files.read_toml(path)
    f = decode(path, raw, TemplateFile)
    slots = _slots(path, f.slots)
    slot_names = {s.name for s in slots}
    connections = _connections(path, f.connections, slot_names)
    _check_tree(path, connections, slot_names)
    # Robots by their root slot: what a station component may be given as its robot.
    robots = [s.name for s in slots if s.name not in {c.child for c in connections}]
    stations = parse_stations(path, f.stations, slot_names, robots)
    if f.claims not in CLAIM_POLICIES:
        raise InputError(
            f"{path}: field claims is {f.claims!r}",
            hint='write claims = "required" (only a claim\'s holder commands a module) or '
            'claims = "open" (an unclaimed module takes anyone\'s commands; the default)',
        )
    operator_timeout = _operator_timeout(path, f.safety, bool(stations))
    network = raw.get("network", {})
    for key in network:
        if key not in NETWORK_KEYS:
            raise InputError(
                f"{path}: field network.{key} is not a network setting",
                hint=f"the [network] table takes {', '.join(NETWORK_KEYS)}",
            )
    return Template(
        name=path.stem,
        path=path,
        description=f.description,
        mobile=f.mobile,
        slots=slots,
        connections=connections,
        stations=stations,
        claims=f.claims,
        operator_timeout=operator_timeout,
        secure=f.network.secure,
        robot_recording=robot_recording.parse(f.recording, path),
        network=radio.parse(network, path).as_dict(),
    )


def _slots(path: Path, entries: list[SlotEntry]) -> tuple[SlotDef, ...]:
    """Every slot, named once; a template has at least one."""
    slots: list[SlotDef] = []
    for i, entry in enumerate(entries):
        if any(other.name == entry.name for other in slots):
            raise InputError(f"{path}: field slots[{i}].name: slot {entry.name!r} is defined twice")
        place = (entry.place.xyz, entry.place.rpy)
        slots.append(SlotDef(entry.name, tuple(entry.fits), entry.default, place, i))
    if not slots:
        raise InputError(
            f"{path}: field slots is empty", hint="add at least one slot (a slots table)"
        )
    return tuple(slots)


def _connections(
    path: Path, entries: list[ConnectionEntry], slot_names: set[str]
) -> tuple[ConnectionDef, ...]:
    """Every connection between two slots' connectors; a slot hangs from one parent at most."""
    connections: list[ConnectionDef] = []
    carried: dict[str, int] = {}
    for i, entry in enumerate(entries):
        where = f"{path}: field connections[{i}]."
        (parent, pc), (child, cc) = (
            _end(f"{where}{key}", value, slot_names)
            for key, value in (("parent", entry.parent), ("child", entry.child))
        )
        if child in carried:
            raise InputError(
                f"{where}child: slot {child!r} is already carried by connections[{carried[child]}]",
                hint="a module hangs from exactly one parent (the assembly is a tree)",
            )
        carried[child] = i
        connections.append(ConnectionDef(parent, pc, child, cc, entry.angle, i))
    return tuple(connections)


def _end(where: str, value: str, slot_names: set[str]) -> tuple[str, str]:
    """``"<slot>.<connector>"`` -> ``(slot, connector)``, the slot one of the template's."""
    slot, dot, connector = value.partition(".")
    if not dot or not connector:
        raise InputError(
            f"{where} is {value!r}", hint='write "<slot>.<connector>", e.g. "limb1.tip"'
        )
    if slot not in slot_names:
        raise InputError(
            f"{where}: no slot {slot!r}", hint=f"slots: {', '.join(sorted(slot_names))}"
        )
    return slot, connector


def _check_tree(path: Path, connections: tuple[ConnectionDef, ...], slot_names: set[str]) -> None:
    """With every slot carried at most once, a loop means some slots have no way up to a root."""
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


def _operator_timeout(path: Path, safety: dict[str, Any], stations: bool) -> float | None:
    """The template's ``[safety] operator_timeout``: a positive number of seconds, or
    ``false`` for never; unset, :data:`OPERATOR_TIMEOUT` if the template has stations (with
    none, nobody would ever attend its modules but a claim holder: off unless asked)."""
    for key in safety:
        if key not in TEMPLATE_SAFETY_KEYS:
            raise InputError(
                f"{path}: field safety.{key} is not a template safety setting",
                hint=f"the template's [safety] table takes {', '.join(TEMPLATE_SAFETY_KEYS)} "
                "(a module's own limits go in its module type's [safety])",
            )
    value = safety.get("operator_timeout", OPERATOR_TIMEOUT if stations else False)
    if value is False:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or value <= 0:
        raise InputError(
            f"{path}: field safety.operator_timeout is {value!r}",
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
            for key in template.slot(slot_name).fits:
                _check_connector(template, c.index, role, slot_name, types[key], connector)


def _check_connector(
    template: Template, index: int, role: str, slot: str, module: ModuleType, connector: str
) -> None:
    """One end of a connection on one module type its slot accepts: the connector exists,
    and a carried module hangs by a connector fixed to its root link."""
    where = f"{template.path}: field connections[{index}].{role}"
    if connector not in module.connectors:
        raise InputError(
            f"{where}: module type {module.key} (slot {slot}) has no connector {connector!r}",
            hint=f"its connectors: {', '.join(module.connectors) or 'none'}",
        )
    link = module.connectors[connector][0]
    if role == "child" and module.urdf.fixed_transform(link) is None:
        raise InputError(
            f"{where}: connector {connector!r} of {module.key} is on link {link!r}, which moves "
            f"relative to the module's root link {module.urdf.root_link!r}",
            hint="carry a module by a connector rigidly fixed to its root link "
            "(swap parent and child?)",
        )
