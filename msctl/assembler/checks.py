"""Checks of the assembler's inputs that need more than one field's type.

Types, presence and name patterns are the models' (:mod:`msctl.assembler.models`); what is
here reads a value against another file, a registry or a rule of the robot's world (a motor
id in its bus's range, component parameters against their kind's entry, an injection aimed
at a component the module runs). Each raises an :class:`~msctl.errors.InputError` naming the
file, the field and the fix.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING, Any

from components import kinds
from msctl.errors import InputError

if TYPE_CHECKING:
    from msctl.assembler.module_types import ModuleType


def check_entries(path: Path, key: str, value: list[Any], what: str) -> list[dict[str, Any]]:
    """Injections or overrides: each a table with a string ``name`` (and its parameters)."""
    for i, item in enumerate(value):
        if not isinstance(item, dict) or not isinstance(item.get("name"), str):
            raise InputError(
                f"{path}: field {key}[{i}] is {item!r}",
                hint=f'each {what} is a table with a name, e.g. {{ name = "..." }}',
            )
    return [dict(item) for item in value]


def confined(folder: Path, relative: str, where: str) -> Path:
    """``folder / relative``, refused unless it stays inside ``folder`` (no ``../../etc``)."""
    resolved = (folder / relative).resolve()
    if not resolved.is_relative_to(folder.resolve()):
        raise InputError(
            f"{where} is {relative!r}: it leaves {folder}",
            hint="keep a module's files in its folder (a path relative to it, without ..)",
        )
    return resolved


def check_meshes(urdf_path: Path, folder: Path, where: str) -> None:
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


def backend(name: str, where: str) -> Any:
    """The motor backend ``name`` (its options, id range and channel check)."""
    from components.motors.options import MotorOptionsError, backend_info, backend_names

    try:
        return backend_info(name)
    except MotorOptionsError:
        raise InputError(
            f"{where} is {name!r}: no such motor backend",
            hint=f"use one of {', '.join(backend_names())}",
        ) from None


def check_bus_options(backend: Any, bus: dict[str, Any], where: str) -> None:
    """The bus's options (and bitrate/baudrate) against the backend's typed options."""
    from components.motors.options import MotorOptionsError

    options = bus.get("options", {})
    if not isinstance(options, dict):
        raise InputError(f"{where} is {options!r}", hint="it must be a table")
    try:
        backend.parse_options(options, bitrate=bus.get("bitrate"), baudrate=bus.get("baudrate"))
    except MotorOptionsError as exc:
        raise InputError(f"{where}: {exc}", hint="fix or remove that option") from None


def check_motor_id(backend: Any, motor_id: int | None, where: str) -> None:
    """An optional motor id, inside the bus kind's id range."""
    if motor_id is not None and motor_id not in backend.motor_ids:
        ids = backend.motor_ids
        raise InputError(
            f"{where} is {motor_id}: a {backend.name} motor id is {ids.start}..{ids.stop - 1}",
            hint="use the id the motor is configured with",
        )


def check_unique_ids(ids: dict[str, int | None], where: str) -> None:
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


def check_kind_params(
    kind: str, params: dict[str, Any], where: str, robots: list[str] | None = None
) -> None:
    """A component's parameters against its kind's entry (names, types, ranges; with the
    template's ``robots``, the kind's own check of them as a whole)."""
    try:
        kinds.check_params(kinds.get(kind), params, robots)
    except kinds.KindError as exc:
        raise InputError(f"{where}: {exc}", hint="fix or remove that parameter") from None


def check_health(module: ModuleType, health: dict[str, Any], where: str) -> None:
    """The ``[health]`` table, as each kind the module runs that reads it checks it."""
    for kind in {c.kind for c in module.components}:
        if "thresholds" in kinds.get(kind).module_facts:
            check_kind_params(kind, {"thresholds": health}, where)


def check_safety(safety: dict[str, Any], where: str) -> None:
    """The ``[safety]`` table (:class:`components.safety.SafetyLimits`)."""
    from components.safety import SafetyLimits

    try:
        SafetyLimits.from_mapping(safety, "[safety]")
    except ValueError as exc:
        raise InputError(f"{where}: {exc}", hint="see components/safety.py") from None


def check_extensions(module: ModuleType, injections: Any, overrides: Any, source: str) -> None:
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
        check_joint_params(module, entries, f"{source}: field {field_name}")


def check_joint_params(module: ModuleType, entries: Any, where: str) -> None:
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
