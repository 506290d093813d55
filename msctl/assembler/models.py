"""The assembler's input files as typed models: a module type, a template, a unit.

Each model is the file's shape, field for field, as msgspec decodes it (types, presence,
defaults, name and host patterns); :func:`msctl.assembler.schema.decode` words a refusal for
the operator from each field's ``Meta``: its ``description`` says what the field must be, an
``extra`` ``hint`` what to do when a value of the right type breaks the field's rule.
Unknown keys are ignored, as they always were. What needs more than one field (a slot's
module type exists, limits are ordered, ids are unique) is checked after decoding, by the
named functions of :mod:`msctl.assembler.checks` and the parsers beside the models.
"""

from __future__ import annotations

import re
from typing import Annotated, Any

import msgspec
from msgspec import Meta

#: Slot, station and module type names become ROS name components and file names.
NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")
#: A host name as RFC 1123 allows it: it reaches ssh, systemd units and argument lists.
HOST_RE = re.compile(
    r"^(?=.{1,253}$)[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?"
    r"(?:\.[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*$"
)

Name = Annotated[
    str,
    Meta(
        pattern=NAME_RE.pattern,
        description="a name of letters, digits and _",
        extra={"hint": "use letters, digits and _, starting with a letter (it becomes a ROS name)"},
    ),
]
Host = Annotated[
    str,
    Meta(
        pattern=HOST_RE.pattern,
        description="a hostname",
        extra={
            "problem": "not a valid host name",
            "hint": "use letters, digits, - and . (e.g. hl-limb-03), as `hostname` prints it",
        },
    ),
]
Text = Annotated[str, Meta(description="a string")]
Number = Annotated[float, Meta(description="a number")]
Integer = Annotated[int, Meta(description="an integer")]
Flag = Annotated[bool, Meta(description="true or false")]
Table = Annotated[dict[str, Any], Meta(description="a table")]
Vec3 = Annotated[
    tuple[float, float, float],
    Meta(description="a list of 3 numbers", extra={"hint": "it must be 3 numbers"}),
]
MotorId = Annotated[int, Meta(description="a motor id")]

ORIGIN: tuple[float, float, float] = (0.0, 0.0, 0.0)


class Place(msgspec.Struct, frozen=True):
    """Where something sits: a translation and roll-pitch-yaw."""

    xyz: Vec3 = ORIGIN
    rpy: Vec3 = ORIGIN


# ------------------------------------------------------------------------------ module types


class JointEntry(msgspec.Struct, frozen=True):
    """One ``[[joints]]`` table of a module type."""

    name: Name
    max_velocity: Number
    max_effort: Number
    type: Text | None = None
    lower: Number | None = None
    upper: Number | None = None
    armature: Number = 0.0
    control: Text = "position"
    actuated: Flag = True
    motor: Text | None = None
    motor_id: MotorId | None = None
    motor_params: Table = {}


class ConnectorEntry(msgspec.Struct, frozen=True):
    """One ``[connectors.<name>]`` table: a link and a pose on it."""

    link: Text
    xyz: Vec3 = ORIGIN
    rpy: Vec3 = ORIGIN


class ChainEntry(msgspec.Struct, frozen=True):
    """One ``[[chains]]`` table: a kinematic chain from ``base`` to ``tip``."""

    name: Name
    base: Text
    tip: Text


class ComponentEntry(msgspec.Struct, frozen=True):
    """One ``[[components]]`` table of a module type."""

    kind: Text
    name: Name | None = None
    link: Text | None = None
    chain: Text | None = None
    params: Table = {}


class ModuleBus(msgspec.Struct, frozen=True):
    """The ``[bus]`` of a module type (the whole table is kept as written, too)."""

    kind: Text


class ModuleTypeFile(msgspec.Struct, frozen=True):
    """``assemblies/modules/<key>.toml``."""

    urdf: Annotated[str, Meta(description="a path relative to the module file")]
    kind: Name
    family: Text
    bus: Annotated[ModuleBus, Meta(description="a table")]
    description: Text = ""
    revision: Integer = 1
    shares_computer: Flag = False
    health: Table = {}
    safety: Table = {}
    joints: Annotated[list[JointEntry], Meta(description="a list of joints tables")] = []
    connectors: Annotated[dict[str, ConnectorEntry], Meta(description="a table")] = {}
    chains: Annotated[list[ChainEntry], Meta(description="a list of chains tables")] = []
    components: Annotated[
        list[ComponentEntry], Meta(description="a list of components tables")
    ] = []
    interesting_links: Annotated[list[Any], Meta(description="a list")] = []
    injections: Annotated[list[Any], Meta(description="a list of injection")] = []
    overrides: Annotated[list[Any], Meta(description="a list of override")] = []


# ---------------------------------------------------------------------------------- templates


class SlotEntry(msgspec.Struct, frozen=True):
    """One ``[[slots]]`` table of a template."""

    name: Name
    fits: Annotated[
        list[str],
        Meta(
            min_length=1,
            description="a list of module type names",
            extra={"hint": "list module type names"},
        ),
    ]
    default: Text | None = None
    place: Annotated[Place, Meta(description="a table")] = Place()


class ConnectionEntry(msgspec.Struct, frozen=True):
    """One ``[[connections]]`` table: which slot's connector carries which."""

    parent: Annotated[str, Meta(description='"<slot>.<connector>"')]
    child: Annotated[str, Meta(description='"<slot>.<connector>"')]
    angle: Number = 0.0


class StationEntry(msgspec.Struct, frozen=True):
    """One ``[[stations]]`` table: a ground station's host and components (kind -> a count,
    or a list of named components; checked by :mod:`msctl.assembler.stations`)."""

    name: Name
    host: Host
    components: Table = {}
    params: Annotated[dict[str, Table], Meta(description="a table")] = {}


class NamedComponent(msgspec.Struct, frozen=True):
    """One table of a station kind given as a list: its name (the rest are parameters)."""

    name: Name


class TemplateNetwork(msgspec.Struct, frozen=True):
    """The ``[network]`` table's own switch (its link classes: :mod:`msctl.net.radio`)."""

    secure: Flag = False


class TemplateFile(msgspec.Struct, frozen=True):
    """``assemblies/<name>.toml``."""

    slots: Annotated[list[SlotEntry], Meta(description="a list of slots tables")]
    description: Text = ""
    mobile: Flag = False
    connections: Annotated[
        list[ConnectionEntry], Meta(description="a list of connections tables")
    ] = []
    stations: Annotated[list[StationEntry], Meta(description="a list of stations tables")] = []
    claims: Annotated[str, Meta(description='"open" or "required"')] = "open"
    safety: Table = {}
    network: Annotated[TemplateNetwork, Meta(description="a table")] = TemplateNetwork()
    recording: Table = {}


# -------------------------------------------------------------------------------------- units


class JointCalibrationEntry(msgspec.Struct, frozen=True):
    """One ``[joints.<name>]`` table of a unit."""

    motor_id: MotorId | None = None
    zero_offset: Number = 0.0
    direction: Integer = 1
    lower: Number | None = None
    upper: Number | None = None


class UnitBus(msgspec.Struct, frozen=True):
    """The ``[bus]`` of a unit (the whole table is kept as written, too)."""

    channel: Annotated[str, Meta(description='the bus channel, e.g. "can0" or "/dev/ttyUSB0"')]


class UnitFile(msgspec.Struct, frozen=True):
    """``calibration/<serial>.toml``."""

    module_type: Annotated[str, Meta(description="a module type name")]
    host: Host
    bus: Annotated[UnitBus, Meta(description="a table")]
    joints: Annotated[dict[str, JointCalibrationEntry], Meta(description="a table")] = {}
    injections: Annotated[list[Any], Meta(description="a list of injection")] = []
    overrides: Annotated[list[Any], Meta(description="a list of override")] = []
    health: Table = {}
    safety: Table = {}
