"""Physical units (``calibration/<serial>.toml``): loaded, and checked against their type."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from components.assembly import BusPlan
from msctl.assembler import checks, files
from msctl.assembler.models import NAME_RE, UnitFile
from msctl.assembler.module_types import JointDef, ModuleType, module_type_names
from msctl.assembler.schema import decode
from msctl.errors import InputError, NotFoundError, did_you_mean

#: Unit serials are file names: no path separators, no leading dot.
SERIAL_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")


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


def units_searched() -> str:
    """Where units are looked for, and how to look elsewhere (for error hints)."""
    return (
        f"units are read from {files.calibration_dir()} (set MSCTL_CALIBRATION_DIR to read "
        "another folder, or `pip install -e .` in a checkout)"
    )


def unit_serials() -> list[str]:
    """Every unit serial with a calibration file, sorted."""
    return sorted(p.stem for p in files.calibration_dir().glob("*.toml"))


def unit_exists(serial: str) -> bool:
    """Whether a calibration file exists for ``serial``."""
    return bool(SERIAL_RE.match(serial)) and (files.calibration_dir() / f"{serial}.toml").is_file()


def load_unit(serial: str) -> Unit:
    """Load a unit's calibration file (fields checked; joints checked by :func:`check_unit`).

    Raises:
        NotFoundError: If there is no calibration file for ``serial``.
        InputError: If the file is malformed.
    """
    if not unit_exists(serial):
        near = did_you_mean(serial, unit_serials())
        raise NotFoundError(
            f"unknown unit {serial!r}: no {files.calibration_dir() / (serial + '.toml')}",
            hint=f"{near + ' ' if near else ''}see `msctl assemble --list` for the units; "
            f"{units_searched()}",
        )
    unit = files.cached("unit", files.calibration_dir() / f"{serial}.toml", parse_unit)
    if (
        not NAME_RE.match(unit.module_type)
        or not (files.modules_dir() / f"{unit.module_type}.toml").is_file()
    ):
        near = did_you_mean(unit.module_type, module_type_names())
        raise NotFoundError(
            f"{unit.path}: field module_type: unknown module type {unit.module_type!r}",
            hint=f"{near + ' ' if near else ''}known module types: "
            f"{', '.join(module_type_names()) or 'none'}",
        )
    return unit


def parse_unit(path: Path) -> Unit:
    """Read one calibration file (see :class:`~msctl.assembler.models.UnitFile`).

    Raises:
        InputError: Naming the file, the field and the fix.
    """
    raw = files.read_toml(path)
    f = decode(path, raw, UnitFile)
    joints: dict[str, JointCalibrationDef] = {}
    for name, entry in f.joints.items():
        if entry.direction not in (1, -1):
            raise InputError(
                f"{path}: field joints.{name}.direction is {entry.direction}", hint="use 1 or -1"
            )
        joints[name] = JointCalibrationDef(
            entry.motor_id, entry.zero_offset, entry.direction, entry.lower, entry.upper
        )
    return Unit(
        serial=path.stem,
        path=path,
        module_type=f.module_type,
        host=f.host,
        bus=dict(raw["bus"]),
        joints=joints,
        injections=tuple(checks.check_entries(path, "injections", f.injections, "injection")),
        overrides=tuple(checks.check_entries(path, "overrides", f.overrides, "override")),
        health=dict(f.health),
        safety=dict(f.safety),
    )


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
        _check_calibration(where, module.key, module.joints[name], cal)
    backend = checks.backend(module.bus["kind"], f"{module.path}: field bus.kind")
    _check_motor_ids(unit, module, backend)
    bus = merged_bus(module, unit)
    try:
        backend.check_channel(bus.channel)
    except ValueError as exc:
        raise InputError(f"{unit.path}: field bus.channel: {exc}") from None
    merged = {**module.bus, **unit.bus, "options": bus.options}
    checks.check_bus_options(backend, merged, f"{unit.path}: field bus.options")
    checks.check_health(module, {**module.health, **unit.health}, f"{unit.path}: field health")
    checks.check_safety({**module.safety, **unit.safety}, f"{unit.path}: field safety")
    checks.check_extensions(module, unit.injections, unit.overrides, str(unit.path))


def _check_calibration(where: str, key: str, jd: JointDef, cal: JointCalibrationDef) -> None:
    """A unit's limits only narrow its joint's range; its zero offset is a small correction."""
    lower = jd.lower if cal.lower is None else cal.lower
    upper = jd.upper if cal.upper is None else cal.upper
    if not (jd.lower <= lower < upper <= jd.upper):
        raise InputError(
            f"{where}: limits [{lower}, {upper}] are not inside {key}'s [{jd.lower}, {jd.upper}]",
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


def _check_motor_ids(unit: Unit, module: ModuleType, backend: Any) -> None:
    """Every actuated joint has an id (the unit's, else the type's), in the bus's range,
    and no two share one."""
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
        checks.check_motor_id(backend, motor_id, f"{unit.path}: field joints.{name}.motor_id")
    checks.check_unique_ids(ids, f"{unit.path}: field joints (with {module.path}'s defaults)")
