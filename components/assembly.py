"""The resolved assembly, as everything downstream reads it.

``msctl assemble`` writes one resolved assembly into :func:`assembly_dir`::

    $MSCTL_HOME/assembly/            MSCTL_HOME defaults to $XDG_STATE_HOME/msctl
        assembly.lock.json           or ~/.local/state/msctl
        assembly.urdf
        assembly.mjcf.xml

The lock file is the single source of truth: which unit sits in which slot, every module's bus,
joints (limits, calibration, motor), kinematic chains, and every component with the host it runs
on. The launcher, simulator, kinematics, TUI and teleop read it through :func:`load_assembly` and
nothing else. This module is pure data (standard library plus two small project dataclasses) so
it loads in a few milliseconds anywhere.

Joint and link names are assembly-unique: ``<slot>_<name>`` (``limb1_joint3``); each module's
ROS namespace is ``/<slot>``.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from components.joints import JointCalibration, JointSpec
from components.motors.base import MotorSpec

#: Lock file format version; bumped on incompatible changes.
SCHEMA_VERSION = 1
LOCK_NAME = "assembly.lock.json"
URDF_NAME = "assembly.urdf"
MJCF_NAME = "assembly.mjcf.xml"

#: The component kinds the assembler plans (later issues implement them).
COMPONENT_KINDS = (
    "motor_interface",
    "joint_manager",
    "health_monitor",
    "location_publisher",
    "kinematics_manager",
    "human_operator",
    "autonomous_operator",
    "data_monitor",
    "data_archiver",
)


class AssemblyError(Exception):
    """No resolved assembly, or one that cannot be read; the message says what to run."""


def state_dir() -> Path:
    """msctl's state directory: ``$MSCTL_HOME``, else ``$XDG_STATE_HOME/msctl``,
    else ``~/.local/state/msctl``."""
    home = os.environ.get("MSCTL_HOME")
    if home:
        return Path(home).expanduser()
    xdg = os.environ.get("XDG_STATE_HOME")
    if xdg:
        return Path(xdg).expanduser() / "msctl"
    return Path.home() / ".local" / "state" / "msctl"


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
        kind: ``"canopen"`` or ``"dynamixel"`` (a motor backend name).
        channel: CAN interface (``can0``) or serial port (``/dev/ttyUSB0``).
        bitrate: CAN bitrate in bit/s (CANopen only).
        baudrate: Serial baud rate (Dynamixel only).
        options: Backend options from module data (protocol, sync period...).
    """

    kind: str
    channel: str
    bitrate: int | None = None
    baudrate: int | None = None
    options: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class JointPlan:
    """One joint of a module: static spec, this unit's calibration, and its motor.

    Attributes:
        spec: Limits in calibrated (URDF) space; ``spec.name`` is the assembly name.
        calibration: This unit's zero offset and direction.
        raw_name: The joint's name inside its module (``joint3``), as motor backends know it.
        motor_id: CANopen node id or Dynamixel id.
        motor_model: Motor model key (``cia402``, ``XM430-W350``).
        motor_params: Extra per-motor constants (gear ratio, counts per revolution...).
        actuated: Whether a motor drives the joint.
        control: ``"position"`` or ``"velocity"`` (wheels).
        armature: Reflected rotor inertia, for simulation (kg·m² or kg).
    """

    spec: JointSpec
    calibration: JointCalibration
    raw_name: str
    motor_id: int | None = None
    motor_model: str | None = None
    motor_params: Mapping[str, Any] = field(default_factory=dict)
    actuated: bool = True
    control: str = "position"
    armature: float = 0.0

    @property
    def name(self) -> str:
        """Assembly-unique joint name (``limb1_joint3``)."""
        return self.spec.name


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
        injections: ``{"name": ..., **params}`` for the joint manager (module, then unit data).
        overrides: ``{"name": ..., **params}`` for the joint manager (module, then unit data).
        health: Health monitor thresholds.
        root_link: The module's root link (assembly name).
        connectors: Connector name -> connector link (assembly name).
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
    injections: tuple[Mapping[str, Any], ...] = ()
    overrides: tuple[Mapping[str, Any], ...] = ()
    health: Mapping[str, Any] = field(default_factory=dict)
    root_link: str = ""
    connectors: Mapping[str, str] = field(default_factory=dict)

    def joint(self, name: str) -> JointPlan:
        """A joint by assembly name (``limb1_joint3``) or module name (``joint3``).

        Raises:
            KeyError: If the module has no such joint.
        """
        for plan in self.joints:
            if name in (plan.spec.name, plan.raw_name):
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
        kind: One of :data:`COMPONENT_KINDS`.
        host: Hostname it runs on.
        module: Slot of the module it belongs to, or ``None`` for ground-station components.
        namespace: ROS namespace (``/limb1``, ``/gc1``).
        params: Kind-specific parameters (joints, links, chain, injections, overrides...).
    """

    name: str
    kind: str
    host: str
    module: str | None
    namespace: str
    params: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class ResolvedAssembly:
    """A template resolved with physical units: the one thing downstream tools read.

    Attributes:
        template: Template name (``dragon``).
        units: Slot -> unit serial, in template order.
        modules: One plan per slot, in template order.
        components: Every component, robot side then ground stations.
        hosts: Every hostname with something to run, in first-use order.
        urdf_path: The composed URDF.
        mjcf_path: The MuJoCo model.
        mobile: Whether the assembly moves (floating base in simulation).
        root_links: Root link of each robot (one per connected group of modules).
        connections: How modules are joined (``{"parent", "child", "joint", "angle"}``).
        lock_path: The lock file this was read from.
        document: The raw lock document.
    """

    template: str
    units: Mapping[str, str]
    modules: tuple[ModulePlan, ...]
    components: tuple[ComponentPlan, ...]
    hosts: tuple[str, ...]
    urdf_path: Path
    mjcf_path: Path
    mobile: bool
    root_links: tuple[str, ...] = ()
    connections: tuple[Mapping[str, Any], ...] = ()
    lock_path: Path | None = None
    document: Mapping[str, Any] = field(default_factory=dict, repr=False, compare=False)

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
                if plan.spec.name == name:
                    return plan
        raise KeyError(f"no joint {name!r} in {self.template}")


def load_assembly(path: Path | None = None) -> ResolvedAssembly:
    """Read the resolved assembly.

    Args:
        path: The lock file, or the directory holding it; defaults to :func:`lock_path`.

    Raises:
        AssemblyError: If nothing was resolved yet, or the lock file is unreadable or from an
            incompatible version (the message says what to run).
    """
    if path is None:
        path = lock_path()
    path = Path(path)
    if path.is_dir():
        path = path / LOCK_NAME
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise AssemblyError(
            f"no resolved assembly at {path}: run `msctl assemble dragon` (or another "
            "template, see `msctl assemble --list`) first"
        ) from None
    except OSError as exc:
        raise AssemblyError(f"cannot read {path}: {exc}") from exc
    try:
        document = json.loads(text)
    except json.JSONDecodeError as exc:
        raise AssemblyError(
            f"{path} is not valid JSON (line {exc.lineno}): run `msctl assemble <template>` again"
        ) from exc
    return from_document(document, path)


def from_document(document: Mapping[str, Any], path: Path | None = None) -> ResolvedAssembly:
    """Build a :class:`ResolvedAssembly` from a lock document (as written by the assembler).

    Raises:
        AssemblyError: If the document is from another schema version or lacks a field.
    """
    where = str(path) if path else "lock document"
    schema = document.get("schema")
    if schema != SCHEMA_VERSION:
        raise AssemblyError(
            f"{where} has schema {schema!r}, this msctl reads {SCHEMA_VERSION}: run "
            "`msctl assemble <template>` again"
        )
    base = path.parent if path else Path(".")
    try:
        modules = tuple(_module(m) for m in document["modules"])
        components = tuple(
            ComponentPlan(
                name=c["name"],
                kind=c["kind"],
                host=c["host"],
                module=c.get("module"),
                namespace=c["namespace"],
                params=c.get("params", {}),
            )
            for c in document["components"]
        )
        artifacts = document["artifacts"]
        return ResolvedAssembly(
            template=document["template"],
            units=dict(document["units"]),
            modules=modules,
            components=components,
            hosts=tuple(document["hosts"]),
            urdf_path=base / artifacts["urdf"],
            mjcf_path=base / artifacts["mjcf"],
            mobile=bool(document["mobile"]),
            root_links=tuple(document.get("root_links", ())),
            connections=tuple(document.get("connections", ())),
            lock_path=path,
            document=document,
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise AssemblyError(
            f"{where} is incomplete ({type(exc).__name__}: {exc}): run "
            "`msctl assemble <template>` again"
        ) from exc


def _limit(value: float | None, default: float) -> float:
    # JSON has no infinity: the lock writes unbounded limits as null.
    return default if value is None else float(value)


def _module(m: Mapping[str, Any]) -> ModulePlan:
    bus = m["bus"]
    joints = tuple(
        JointPlan(
            spec=JointSpec(
                name=j["name"],
                type=j["type"],
                lower=_limit(j.get("lower"), -math.inf),
                upper=_limit(j.get("upper"), math.inf),
                max_velocity=float(j["max_velocity"]),
                max_effort=float(j["max_effort"]),
            ),
            calibration=JointCalibration(
                zero_offset=float(j.get("zero_offset", 0.0)),
                direction=int(j.get("direction", 1)),
            ),
            raw_name=j["raw_name"],
            motor_id=j.get("motor_id"),
            motor_model=j.get("motor_model"),
            motor_params=j.get("motor_params", {}),
            actuated=bool(j.get("actuated", True)),
            control=j.get("control", "position"),
            armature=float(j.get("armature", 0.0)),
        )
        for j in m["joints"]
    )
    chains = tuple(
        ChainPlan(
            name=c["name"],
            base_link=c["base_link"],
            tip_link=c["tip_link"],
            joints=tuple(c.get("joints", ())),
        )
        for c in m.get("chains", ())
    )
    return ModulePlan(
        slot=m["slot"],
        namespace=m["namespace"],
        module_type=m["module_type"],
        family=m["family"],
        kind=m["kind"],
        revision=int(m["revision"]),
        unit=m["unit"],
        host=m["host"],
        bus=BusPlan(
            kind=bus["kind"],
            channel=bus["channel"],
            bitrate=bus.get("bitrate"),
            baudrate=bus.get("baudrate"),
            options=bus.get("options", {}),
        ),
        joints=joints,
        chains=chains,
        interesting_links=tuple(m.get("interesting_links", ())),
        injections=tuple(m.get("injections", ())),
        overrides=tuple(m.get("overrides", ())),
        health=m.get("health", {}),
        root_link=m.get("root_link", ""),
        connectors=m.get("connectors", {}),
    )
