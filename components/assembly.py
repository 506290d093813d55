"""The resolved assembly, as everything downstream reads it.

``msctl assemble`` writes one resolved assembly into :func:`assembly_dir`::

    $MSCTL_HOME/assembly/            MSCTL_HOME defaults to $XDG_STATE_HOME/msctl
        assembly.lock.json           or ~/.local/state/msctl
        assembly.urdf
        assembly.mjcf.xml

The lock file is the single source of truth: which unit sits in which slot, every module's bus,
joints (limits, calibration, motor), kinematic chains, and every component with the host it runs
on. The launcher, simulator, kinematics, TUI and teleop read it through :func:`load_assembly` and
nothing else. The dataclasses below are the lock file's schema: msgspec encodes and decodes
them (no hand-written reading or writing), checks every type and range, and names the path of
a bad value (``$.modules[2].joints[0].max_velocity``).

Joint and link names are assembly-unique: ``<slot>_<name>`` (``limb1_joint3``); each module's
ROS namespace is ``/<slot>``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Annotated, Any, Literal

import msgspec
from msgspec import Meta

from components.errors import ComponentError
from components.joints import JointCalibration, JointSpec
from components.motors.base import MotorSpec
from components.paths import state_dir

#: Lock file format version; bumped on incompatible changes.
SCHEMA_VERSION = 2
LOCK_NAME = "assembly.lock.json"
URDF_NAME = "assembly.urdf"
MJCF_NAME = "assembly.mjcf.xml"

#: Constraints the lock's numbers obey (the assembler checks its inputs more closely).
Positive = Annotated[float, Meta(gt=0)]
NonNegative = Annotated[float, Meta(ge=0)]
Direction = Literal[1, -1]


class AssemblyError(ComponentError):
    """No resolved assembly, or one that cannot be read; the message says what to run."""


def assembly_dir() -> Path:
    """Directory of the resolved assembly (lock file and generated artifacts)."""
    return state_dir() / "assembly"


def lock_path() -> Path:
    """Path of the lock file of the resolved assembly."""
    return assembly_dir() / LOCK_NAME


@dataclass(frozen=True)
class BusPlan:
    """The bus a module's motors hang on.

    Attributes:
        kind: A motor backend name (``canopen``, ``dynamixel``).
        channel: CAN interface (``can0``) or serial port (``/dev/ttyUSB0``).
        bitrate: CAN bitrate in bit/s (CANopen only).
        baudrate: Serial baud rate (Dynamixel only).
        options: Backend options from module data (checked against the backend's options).
    """

    kind: str
    channel: str
    bitrate: int | None = None
    baudrate: int | None = None
    options: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class JointPlan:
    """One joint of a module: limits, this unit's calibration, and its motor.

    Attributes:
        name: Assembly-unique joint name (``limb1_joint3``).
        raw_name: The joint's name inside its module (``joint3``), as motor backends know it.
        type: ``revolute``, ``continuous`` or ``prismatic``.
        lower: Lower limit in calibrated (URDF) space; ``None`` when unbounded.
        upper: Upper limit in calibrated space; ``None`` when unbounded.
        max_velocity: Largest commanded speed (rad/s or m/s).
        max_effort: Largest commanded effort (N·m or N).
        zero_offset: This unit's raw position of calibrated zero.
        direction: This unit's sign between raw and calibrated.
        motor_id: CANopen node id or Dynamixel id.
        motor_model: Motor model key (``cia402``, ``XM430-W350``).
        motor_params: Extra per-motor constants (gear ratio, counts per revolution...).
        actuated: Whether a motor drives the joint.
        control: ``"position"`` or ``"velocity"`` (wheels).
        armature: Reflected rotor inertia, for simulation (kg·m² or kg).
    """

    name: str
    raw_name: str
    type: Literal["revolute", "continuous", "prismatic"]
    max_velocity: Positive
    max_effort: Positive
    lower: float | None = None
    upper: float | None = None
    zero_offset: float = 0.0
    direction: Direction = 1
    motor_id: int | None = None
    motor_model: str | None = None
    motor_params: dict[str, Any] = field(default_factory=dict)
    actuated: bool = True
    control: Literal["position", "velocity"] = "position"
    armature: NonNegative = 0.0

    @cached_property
    def spec(self) -> JointSpec:
        """Limits in calibrated (URDF) space, unbounded ends as infinities."""
        return JointSpec(
            name=self.name,
            type=self.type,
            lower=-math.inf if self.lower is None else self.lower,
            upper=math.inf if self.upper is None else self.upper,
            max_velocity=self.max_velocity,
            max_effort=self.max_effort,
        )

    @cached_property
    def calibration(self) -> JointCalibration:
        """This unit's zero offset and direction."""
        return JointCalibration(zero_offset=self.zero_offset, direction=self.direction)


@dataclass(frozen=True)
class ChainPlan:
    """A kinematic chain of a limb, in assembly link and joint names.

    Attributes:
        name: Chain name inside its module (``arm``).
        base_link: First link of the chain (``limb1_base_link``).
        tip_link: Last link of the chain (``limb1_tip_link``).
        joints: Movable joints from base to tip.
    """

    name: str
    base_link: str
    tip_link: str
    joints: tuple[str, ...] = ()


@dataclass(frozen=True)
class ModulePlan:
    """One module of the assembly: which unit fills the slot and everything about it.

    Attributes:
        slot: Slot name in the template (``limb1``).
        namespace: ROS namespace of the module's components (``/limb1``).
        module_type: Module type key (``hl_limb_v1``).
        family: ``H-line`` or ``G-line``.
        kind: ``limb`` or ``wheel``.
        revision: Module type revision.
        unit: Serial of the physical unit in the slot.
        host: Hostname of the unit's onboard computer.
        bus: The motor bus.
        joints: Movable joints (actuated or not), in module order.
        chains: Kinematic chains (limbs).
        interesting_links: Links location publishers and UIs care about (assembly names).
        health: Health monitor thresholds (module data, then unit data).
        safety: Safety limits (module data, then unit data; see :mod:`components.safety`).
        root_link: The module's root link (assembly name).
        connectors: Connector name -> connector link (assembly name).
        calibration_file: The unit's calibration file (where a runtime re-zero saves).
    """

    slot: str
    namespace: str
    module_type: str
    family: str
    kind: str
    revision: int
    unit: str
    host: str
    bus: BusPlan
    joints: tuple[JointPlan, ...] = ()
    chains: tuple[ChainPlan, ...] = ()
    interesting_links: tuple[str, ...] = ()
    health: dict[str, Any] = field(default_factory=dict)
    safety: dict[str, Any] = field(default_factory=dict)
    root_link: str = ""
    connectors: dict[str, str] = field(default_factory=dict)
    calibration_file: str = ""

    def joint(self, name: str) -> JointPlan:
        """A joint by assembly name (``limb1_joint3``) or module name (``joint3``).

        Raises:
            KeyError: If the module has no such joint.
        """
        for plan in self.joints:
            if name in (plan.name, plan.raw_name):
                return plan
        raise KeyError(f"module {self.slot} has no joint {name!r}")

    @property
    def actuated_joints(self) -> tuple[JointPlan, ...]:
        """The joints a motor drives."""
        return tuple(j for j in self.joints if j.actuated)

    def motor_specs(self) -> list[MotorSpec]:
        """The motors on this module's bus, as a motor backend takes them (raw joint names)."""
        return [
            MotorSpec(
                joint=j.raw_name,
                motor_id=j.motor_id if j.motor_id is not None else 0,
                model=j.motor_model or "",
                params=dict(j.motor_params),
            )
            for j in self.joints
            if j.actuated
        ]


@dataclass(frozen=True)
class ComponentPlan:
    """One component to run.

    Attributes:
        name: Assembly-unique name (``limb1/joint_manager``, ``gc1/human_operator``).
        kind: A kind of :mod:`components.kinds`.
        host: Hostname it runs on.
        module: Slot of the module it belongs to, or ``None`` for ground-station components.
        namespace: ROS namespace (``/limb1``, ``/gc1``).
        params: Kind-specific parameters (joints, links, chain, injections, overrides...),
            checked against the kind at ``msctl assemble``.
    """

    name: str
    kind: str
    host: str
    module: str | None
    namespace: str
    params: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class HostRole:
    """What one computer does for the assembly (for listings)."""

    role: Literal["robot", "ground"]
    modules: list[str] = field(default_factory=list)
    components: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class RobotPlacement:
    """One robot (a connected group of modules): its root and where it stands."""

    root: str
    root_link: str
    xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Connection:
    """``parent`` slot's connector carries ``child`` slot's connector through ``joint``."""

    parent: str
    child: str
    joint: str
    angle: float = 0.0


@dataclass(frozen=True)
class Sources:
    """The files an assembly was resolved from."""

    template: str
    module_types: dict[str, str] = field(default_factory=dict)
    units: dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class Artifacts:
    """Generated files, relative to the lock file."""

    urdf: str = URDF_NAME
    mjcf: str = MJCF_NAME


@dataclass(frozen=True)
class LockDocument:
    """The lock file, field for field: written and read only through msgspec.

    Attributes:
        schema: :data:`SCHEMA_VERSION` of the writer.
        template: Template name (``dragon``).
        description: The template's description.
        mobile: Whether the assembly moves (floating base in simulation).
        claims: ``"open"``: an unclaimed module takes commands from anyone; ``"required"``:
            only from the holder of its claim (:mod:`components.claims`).
        operator_timeout: Seconds a module goes without a visible ground station or claim
            holder before it holds itself (the template's ``[safety] operator_timeout``;
            ``None``: never).
        secure: Whether every router runs the fleet's generated config (mutual TLS, access
            control; the template's ``[network] secure``).
        network: The links between computers: each class's budget and which computer's
            link is which (:meth:`msctl.net.radio.Network.as_dict`; empty: the defaults).
        units: Slot -> unit serial, in template order.
        modules: One plan per slot, in template order.
        components: Every component, robot side then ground stations.
        hosts: Every hostname with something to run, in first-use order.
        host_plans: What each host does.
        component_counts: Kind -> how many components.
        root_links: Root link of each robot.
        robots: Each robot's root and place.
        connections: How modules are joined.
        artifacts: Generated files.
        sources: The input files.
    """

    schema: int
    template: str
    mobile: bool
    units: dict[str, str]
    modules: tuple[ModulePlan, ...]
    components: tuple[ComponentPlan, ...]
    hosts: tuple[str, ...]
    description: str = ""
    host_plans: dict[str, HostRole] = field(default_factory=dict)
    component_counts: dict[str, int] = field(default_factory=dict)
    root_links: tuple[str, ...] = ()
    robots: tuple[RobotPlacement, ...] = ()
    connections: tuple[Connection, ...] = ()
    artifacts: Artifacts = field(default_factory=Artifacts)
    sources: Sources | None = None
    claims: Literal["open", "required"] = "open"
    operator_timeout: float | None = None
    secure: bool = False
    network: dict[str, Any] = field(default_factory=dict)


def encode_lock(lock: LockDocument) -> str:
    """The lock file's text: indented JSON in field order, so two resolutions diff cleanly."""
    return msgspec.json.format(msgspec.json.encode(lock), indent=2).decode() + "\n"


def to_builtins(lock: LockDocument) -> dict[str, Any]:
    """The lock as plain JSON-ready data (for ``--json`` listings and the MJCF writer)."""
    return msgspec.to_builtins(lock)


@dataclass(frozen=True)
class ResolvedAssembly:
    """A template resolved with physical units: the one thing downstream tools read.

    Attributes:
        lock: The lock document.
        urdf_path: The composed URDF.
        mjcf_path: The MuJoCo model.
        lock_path: The lock file this was read from.
    """

    lock: LockDocument
    urdf_path: Path
    mjcf_path: Path
    lock_path: Path | None = None

    @property
    def template(self) -> str:
        """Template name."""
        return self.lock.template

    @property
    def units(self) -> dict[str, str]:
        """Slot -> unit serial."""
        return self.lock.units

    @property
    def modules(self) -> tuple[ModulePlan, ...]:
        """One plan per slot, in template order."""
        return self.lock.modules

    @property
    def components(self) -> tuple[ComponentPlan, ...]:
        """Every component, robot side then ground stations."""
        return self.lock.components

    @property
    def hosts(self) -> tuple[str, ...]:
        """Every hostname with something to run."""
        return self.lock.hosts

    @property
    def mobile(self) -> bool:
        """Whether the assembly moves."""
        return self.lock.mobile

    @property
    def claims(self) -> str:
        """``"open"`` or ``"required"``: whether a module takes commands only from the holder
        of its claim even while nobody holds it."""
        return self.lock.claims

    @property
    def operator_timeout(self) -> float | None:
        """Seconds a module goes without a visible operator before it holds itself
        (:mod:`components.joint_manager.presence`); ``None``: never."""
        return self.lock.operator_timeout

    @property
    def secure(self) -> bool:
        """Whether the assembly's routers run the fleet's generated config (mutual TLS)."""
        return self.lock.secure

    @property
    def root_links(self) -> tuple[str, ...]:
        """Root link of each robot."""
        return self.lock.root_links

    @property
    def connections(self) -> tuple[Connection, ...]:
        """How modules are joined."""
        return self.lock.connections

    @cached_property
    def document(self) -> dict[str, Any]:
        """The lock as plain data (listings)."""
        return to_builtins(self.lock)

    def module(self, slot: str) -> ModulePlan:
        """The module in ``slot``.

        Raises:
            KeyError: If the assembly has no such slot (the message lists the slots).
        """
        for plan in self.modules:
            if plan.slot == slot:
                return plan
        raise KeyError(f"no slot {slot!r} in {self.template}; slots: {', '.join(self.units)}")

    def components_on(self, host: str) -> list[ComponentPlan]:
        """The components that run on ``host``."""
        return [c for c in self.components if c.host == host]

    def component(self, name: str) -> ComponentPlan:
        """A component by name (``limb1/joint_manager``).

        Raises:
            KeyError: If no component has that name.
        """
        for plan in self.components:
            if plan.name == name:
                return plan
        raise KeyError(f"no component {name!r} in {self.template}")

    @property
    def joints(self) -> list[JointPlan]:
        """Every movable joint of every module, in module order."""
        return [j for m in self.modules for j in m.joints]

    def joint(self, name: str) -> JointPlan:
        """A joint by assembly name (``limb1_joint3``).

        Raises:
            KeyError: If no module has that joint.
        """
        for module in self.modules:
            for plan in module.joints:
                if plan.name == name:
                    return plan
        raise KeyError(f"no joint {name!r} in {self.template}")


def load_assembly(path: Path | None = None) -> ResolvedAssembly:
    """Read the resolved assembly.

    Args:
        path: The lock file, or the directory holding it; defaults to :func:`lock_path`.

    Raises:
        AssemblyError: If nothing was resolved yet, or the lock file is unreadable, invalid
            or from an incompatible version (the message names the field and what to run).
    """
    if path is None:
        path = lock_path()
    path = Path(path)
    if path.is_dir():
        path = path / LOCK_NAME
    try:
        text = path.read_bytes()
    except FileNotFoundError:
        raise AssemblyError(
            f"no resolved assembly at {path}: run `msctl assemble dragon` (or another "
            "template, see `msctl assemble --list`) first"
        ) from None
    except OSError as exc:
        raise AssemblyError(f"cannot read {path}: {exc}") from exc
    return decode_lock(text, path)


class _Schema(msgspec.Struct):
    schema: Any = None


def decode_lock(text: bytes | str, path: Path | None = None) -> ResolvedAssembly:
    """A :class:`ResolvedAssembly` from lock file text, checked against the schema.

    Raises:
        AssemblyError: If the text is not JSON, is from another schema version, or a field
            is missing or invalid (naming its path, e.g. ``$.modules[0].joints[2].lower``).
    """
    where = str(path) if path else "lock document"
    again = "run `msctl assemble <template>` again"
    try:
        schema = msgspec.json.decode(text, type=_Schema).schema
    except (msgspec.DecodeError, msgspec.ValidationError) as exc:
        raise AssemblyError(f"{where} is not a lock file ({exc}): {again}") from None
    if schema != SCHEMA_VERSION:
        raise AssemblyError(
            f"{where} has schema {schema!r}, this msctl reads {SCHEMA_VERSION}: {again}"
        )
    try:
        lock = msgspec.json.decode(text, type=LockDocument)
    except (msgspec.DecodeError, msgspec.ValidationError) as exc:
        raise AssemblyError(f"{where} is invalid: {exc}: {again}") from None
    return _bound(lock, path)


def from_document(document: Any, path: Path | None = None) -> ResolvedAssembly:
    """A :class:`ResolvedAssembly` from a lock document already parsed (an agent's request).

    Raises:
        AssemblyError: As :func:`decode_lock`.
    """
    where = str(path) if path else "lock document"
    if not isinstance(document, dict) or document.get("schema") != SCHEMA_VERSION:
        schema = document.get("schema") if isinstance(document, dict) else None
        raise AssemblyError(
            f"{where} has schema {schema!r}, this msctl reads {SCHEMA_VERSION}: run "
            "`msctl assemble <template>` again"
        )
    try:
        lock = msgspec.convert(document, type=LockDocument)
    except msgspec.ValidationError as exc:
        raise AssemblyError(f"{where} is invalid: {exc}") from None
    return _bound(lock, path)


def _bound(lock: LockDocument, path: Path | None) -> ResolvedAssembly:
    base = path.parent if path else Path(".")
    return ResolvedAssembly(
        lock=lock,
        urdf_path=base / lock.artifacts.urdf,
        mjcf_path=base / lock.artifacts.mjcf,
        lock_path=path,
    )
