"""Template + units -> one resolved assembly: the lock document and the composed URDF.

Which unit fills a slot, in order of precedence:

1. ``--use SLOT=UNIT``;
2. the previous resolution's unit for that slot (so a swap keeps every other choice), if it is
   still free and still fits;
3. the template's ``default`` unit for the slot, if free;
4. the only free unit whose module type fits;
5. several fit: ask ``choose`` (the CLI's picker on a terminal), else fail listing them.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Any

from components import kinds
from components.assembly import (
    SCHEMA_VERSION,
    Artifacts,
    ChainPlan,
    ComponentPlan,
    Connection,
    HostRole,
    JointPlan,
    LockDocument,
    ModulePlan,
    RobotPlacement,
    Sources,
    to_builtins,
)
from msctl.assembler import data
from msctl.assembler import transforms as tf
from msctl.assembler.data import ModuleType, Template, Unit
from msctl.assembler.recording import robot_archivers
from msctl.assembler.urdf import ModulePart, Mount, compose, connector_link
from msctl.errors import InputError, NotFoundError, did_you_mean
from msctl.net import radio

#: ``choose(slot, candidate serials) -> serial``, or None when no one can be asked.
Chooser = Callable[[str, list[str]], str]


@dataclass
class Resolution:
    """A resolved assembly in memory: nothing is written until :func:`msctl.assembler.store`.

    Attributes:
        template: The checked template.
        units: Slot -> the unit in it.
        lock: The lock document.
        urdf: The composed URDF.
    """

    template: Template
    units: dict[str, Unit]
    lock: LockDocument
    urdf: str

    @cached_property
    def document(self) -> dict[str, Any]:
        """The lock as plain JSON-ready data."""
        return to_builtins(self.lock)

    def mjcf(self) -> str:
        """The MuJoCo model (imports mujoco: ~0.1 s the first time)."""
        from msctl.assembler.mjcf import build_mjcf

        return build_mjcf(self.document, self.urdf)


def parse_uses(uses: Sequence[str]) -> dict[str, str]:
    """``["limb1=hlv1-limb-02", ...]`` -> ``{"limb1": "hlv1-limb-02"}``.

    Raises:
        InputError: On a malformed item or a slot named twice.
    """
    chosen: dict[str, str] = {}
    for item in uses:
        slot, eq, serial = item.partition("=")
        slot, serial = slot.strip(), serial.strip()
        if not eq or not slot or not serial:
            raise InputError(
                f"--use {item!r}: expected SLOT=UNIT", hint="e.g. --use limb1=hlv1-limb-02"
            )
        if slot in chosen and chosen[slot] != serial:
            raise InputError(
                f"--use: slot {slot!r} is given twice ({chosen[slot]}, {serial})",
                hint="give each slot one unit",
            )
        chosen[slot] = serial
    return chosen


def off_defaults(template_name: str, units: Mapping[str, str]) -> list[tuple[str, str, str]]:
    """``(slot, unit, default)`` for each slot whose unit is not the template's default.

    Empty when the template can no longer be read (the caller has a lock to go by).
    """
    try:
        template = data.load_template(template_name)
    except (InputError, NotFoundError):
        return []
    return [
        (slot.name, units[slot.name], slot.default)
        for slot in template.slots
        if slot.default is not None and units.get(slot.name, slot.default) != slot.default
    ]


def fitting_units(template: Template, slot: str) -> list[str]:
    """Serials of every unit whose module type the slot accepts (all unit files are read)."""
    fits = template.slot(slot).fits
    return [s for s in data.unit_serials() if data.load_unit(s).module_type in fits]


def choose_units(
    template: Template,
    uses: Mapping[str, str],
    previous: Mapping[str, str] | None = None,
    choose: Chooser | None = None,
) -> dict[str, str]:
    """Pick a unit for every slot (see the module docstring for the precedence).

    Raises:
        InputError: Unknown slot, a unit that does not fit its slot, a unit in two slots, or
            several fitting units and no one to ask.
        NotFoundError: A unit with no calibration file.
    """
    slots = [s.name for s in template.slots]
    chosen: dict[str, str] = {}
    owner: dict[str, str] = {}
    for slot, serial in uses.items():
        if slot not in slots:
            raise InputError(
                f"--use {slot}={serial}: template {template.name} ({template.path}) has no slot "
                f"{slot!r}",
                hint=" ".join(
                    filter(None, (did_you_mean(slot, slots), f"slots: {', '.join(slots)}"))
                ),
            )
        if serial in owner:
            raise InputError(
                f"--use: unit {serial!r} is named for both slot {owner[serial]} and slot {slot}",
                hint="a physical unit can fill one slot only; pick another unit for one of them",
            )
        if not data.unit_exists(serial):
            fitting = fitting_units(template, slot)
            raise NotFoundError(
                f"--use {slot}={serial}: unknown unit {serial!r} (no "
                f"{data.calibration_dir() / (serial + '.toml')})",
                hint=(
                    f"{did_you_mean(serial, fitting)} units that fit {slot}: "
                    f"{', '.join(fitting) or 'none'}; {data.units_searched()}"
                ).lstrip(),
            )
        _check_fits(template, slot, data.load_unit(serial), f"--use {slot}={serial}")
        chosen[slot] = serial
        owner[serial] = slot

    def free_fit(slot: str, serial: str | None) -> bool:
        if not serial or serial in owner or not data.unit_exists(serial):
            return False
        return data.load_unit(serial).module_type in template.slot(slot).fits

    for slot in slots:  # previous resolution, so a swap keeps every other choice
        serial = (previous or {}).get(slot)
        if slot not in chosen and free_fit(slot, serial):
            chosen[slot], owner[serial] = serial, slot  # type: ignore[index]
    for slot_def in template.slots:  # template defaults
        slot, serial = slot_def.name, slot_def.default
        if slot not in chosen and free_fit(slot, serial):
            chosen[slot], owner[serial] = serial, slot  # type: ignore[index]
    for slot in slots:
        if slot in chosen:
            continue
        candidates = [s for s in fitting_units(template, slot) if s not in owner]
        fits = ", ".join(template.slot(slot).fits)
        if not candidates:
            taken = [f"{s} (in {owner[s]})" for s in fitting_units(template, slot) if s in owner]
            raise InputError(
                f"{template.path}: slot {slot}: no free unit of type {fits}"
                + (f"; taken: {', '.join(taken)}" if taken else ""),
                hint=f"add a calibration file for a {fits} unit in {data.calibration_dir()}",
            )
        if len(candidates) == 1:
            serial = candidates[0]
        elif choose is not None:
            serial = choose(slot, candidates)
            if serial not in candidates:
                raise InputError(f"slot {slot}: {serial!r} is not one of {', '.join(candidates)}")
        else:
            raise InputError(
                f"{template.path}: slot {slot}: {len(candidates)} units fit "
                f"({', '.join(candidates)})",
                hint=f"choose one with --use {slot}=<unit>",
            )
        chosen[slot], owner[serial] = serial, slot
    return {slot: chosen[slot] for slot in slots}


def _check_fits(template: Template, slot: str, unit: Unit, where: str) -> None:
    fits = template.slot(slot).fits
    if unit.module_type not in fits:
        raise InputError(
            f"{where}: unit {unit.serial} is a {unit.module_type} ({unit.path}), but slot {slot} "
            f"of {template.name} takes {', '.join(fits)}",
            hint=f"use a {' or '.join(fits)} unit for {slot} (see `msctl assemble --list`)",
        )


def resolve(
    template_name: str,
    uses: Mapping[str, str] | None = None,
    previous: Mapping[str, str] | None = None,
    choose: Chooser | None = None,
) -> Resolution:
    """Resolve a template into a lock document and URDF, in memory.

    Args:
        template_name: Template file stem (``dragon``).
        uses: Explicit slot -> unit choices.
        previous: The previous resolution's slot -> unit, kept where still valid.
        choose: Asked when several units fit a slot; None to fail instead.

    Raises:
        InputError, NotFoundError: For any bad input, naming the file, field or slot and the fix.
    """
    template = data.load_template(template_name)
    serials = choose_units(template, uses or {}, previous, choose)
    units: dict[str, Unit] = {}
    for slot, serial in serials.items():
        unit = data.load_unit(serial)
        _check_fits(template, slot, unit, f"{template.path}: slot {slot}")
        module = data.load_module_type(unit.module_type, referrer=f"{unit.path}: field module_type")
        data.check_unit(unit, module)
        units[slot] = unit
    _check_hosts(template, units)
    return _plan(template, units)


def _check_hosts(template: Template, units: Mapping[str, Unit]) -> None:
    by_host: dict[str, list[str]] = {}
    for slot, unit in units.items():
        by_host.setdefault(unit.host, []).append(slot)
    for host, slots in by_host.items():
        if len(slots) < 2:
            continue
        for slot in slots:
            module = template.module_types[units[slot].module_type]
            if not module.shares_computer:
                others = [s for s in slots if s != slot]
                a, b = units[slot], units[others[0]]
                raise InputError(
                    f"{a.path}: field host: unit {a.serial} (slot {slot}) and unit {b.serial} "
                    f"(slot {others[0]}, {b.path}) both say host {host!r}, and a {module.key} "
                    "needs its onboard computer to itself",
                    hint="fix the hostname in one calibration file, or use another unit",
                )
        channels: dict[str, str] = {}
        for slot in slots:
            channel = units[slot].bus["channel"]
            if channel in channels:
                raise InputError(
                    f"{units[slot].path}: field bus.channel: {channel!r} on host {host!r} is "
                    f"already used by slot {channels[channel]} ({units[channels[channel]].serial})",
                    hint="modules sharing a computer need one bus each",
                )
            channels[channel] = slot


def _check_secure_hosts(template: Template, hosts: Mapping[str, Any]) -> None:
    """A secure network gives each computer a certificate whose CN carries its host name:
    one too long for a CN is refused here, not at `msctl net init`."""
    from msctl.net import pki

    for host in hosts:
        try:
            pki.check_name(host, "host")
        except pki.PkiError as exc:
            raise InputError(f"{template.path}: field network.secure: {exc}") from None


def _limit(value: float) -> float | None:
    return value if math.isfinite(value) else None


def _prefix_params(entry: Mapping[str, Any], p: str) -> dict[str, Any]:
    """Module-scoped joint and link names in injection/override/component params -> assembly."""
    out = dict(entry)
    for key in ("joint", "link"):
        if isinstance(out.get(key), str):
            out[key] = p + out[key]
    for key in ("joints", "links"):
        if isinstance(out.get(key), list):
            out[key] = [p + v for v in out[key]]
    return out


def split_targets(entries: Sequence[Mapping[str, Any]]) -> dict[str, list[dict[str, Any]]]:
    """Group ``{"name", "component"?, ...}`` entries by the component kind they apply to
    (the joint manager when ``component`` is absent)."""
    grouped: dict[str, list[dict[str, Any]]] = {}
    for entry in entries:
        target = kinds.extension_target(entry)
        body = {k: v for k, v in entry.items() if k != "component"}
        grouped.setdefault(target, []).append(body)
    return grouped


def _joint_plan(p: str, jd: data.JointDef, cal: data.JointCalibrationDef | None) -> JointPlan:
    lower = jd.lower if cal is None or cal.lower is None else cal.lower
    upper = jd.upper if cal is None or cal.upper is None else cal.upper
    return JointPlan(
        name=p + jd.name,
        raw_name=jd.name,
        type=jd.type,  # type: ignore[arg-type]
        lower=_limit(lower),
        upper=_limit(upper),
        max_velocity=jd.max_velocity,
        max_effort=jd.max_effort,
        zero_offset=cal.zero_offset if cal else 0.0,
        direction=cal.direction if cal else 1,  # type: ignore[arg-type]
        motor_id=cal.motor_id if cal and cal.motor_id is not None else jd.motor_id,
        motor_model=jd.motor,
        motor_params=dict(jd.motor_params),
        actuated=jd.actuated,
        control=jd.control,  # type: ignore[arg-type]
        armature=jd.armature,
    )


def _plan(template: Template, units: Mapping[str, Unit]) -> Resolution:
    """The lock document and composed URDF of a template with a checked unit per slot."""
    types = {s.name: template.module_types[units[s.name].module_type] for s in template.slots}
    modules: list[ModulePlan] = []
    components: list[ComponentPlan] = []
    parts: list[ModulePart] = []
    for slot_def in template.slots:
        slot = slot_def.name
        module_plan, module_components, part = _place_module(slot, types[slot], units[slot])
        modules.append(module_plan)
        components += module_components
        parts.append(part)
    # [recording] robots: each robot computer records its own modules' topics locally.
    hosts = [(m.slot, m.host) for m in modules]
    components += robot_archivers(template.robot_recording, hosts, components)
    components += _station_components(template)
    mounts, connections = _mounts(template, types)
    robots = _robots(template, types, mounts)
    host_plans = _host_plans(components)
    # A link class named for a computer of no module or station is a typo: say so here.
    radio.check_hosts(radio.Network.from_dict(template.network), host_plans, template.path)
    if template.secure:
        _check_secure_hosts(template, host_plans)
    counts: dict[str, int] = {}
    for comp in components:
        counts[comp.kind] = counts.get(comp.kind, 0) + 1

    lock = LockDocument(
        schema=SCHEMA_VERSION,
        template=template.name,
        description=template.description,
        mobile=template.mobile,
        claims=template.claims,
        operator_timeout=template.operator_timeout,
        secure=template.secure,
        network=template.network,
        units={slot: units[slot].serial for slot in units},
        modules=tuple(modules),
        components=tuple(components),
        hosts=tuple(host_plans),
        host_plans=host_plans,
        component_counts=counts,
        root_links=tuple(r.root_link for r in robots),
        robots=tuple(robots),
        connections=tuple(connections),
        artifacts=Artifacts(),
        sources=Sources(
            template=str(template.path),
            module_types={k: str(m.path) for k, m in template.module_types.items()},
            units={u.serial: str(u.path) for u in units.values()},
        ),
    )
    urdf = compose(template.name, parts, mounts)
    return Resolution(template=template, units=dict(units), lock=lock, urdf=urdf)


def _place_module(
    slot: str, module: ModuleType, unit: Unit
) -> tuple[ModulePlan, list[ComponentPlan], ModulePart]:
    """One slot's module plan, its components, and its part of the URDF."""
    p = slot + "_"
    joints = tuple(_joint_plan(p, jd, unit.joints.get(jd.name)) for jd in module.joints.values())
    limits = {
        j.raw_name: (j.spec.lower, j.spec.upper, j.max_effort, j.max_velocity) for j in joints
    }
    bus = data.merged_bus(module, unit)
    health = {**module.health, **unit.health}
    plan = ModulePlan(
        slot=slot,
        namespace=f"/{slot}",
        module_type=module.key,
        family=module.family,
        kind=module.kind,
        revision=module.revision,
        unit=unit.serial,
        host=unit.host,
        bus=bus,
        joints=joints,
        chains=tuple(
            ChainPlan(name, p + base, p + tip, tuple(p + j for j in js))
            for name, (base, tip, js) in module.chains.items()
        ),
        interesting_links=tuple(p + link for link in module.interesting_links),
        health=health,
        safety={**module.safety, **unit.safety},
        root_link=p + module.urdf.root_link,
        connectors={c: connector_link(slot, c) for c in module.connectors},
        calibration_file=str(unit.path),
    )
    facts: dict[str, Any] = {
        "joints": [j.name for j in joints if j.actuated],
        "bus": bus.kind,
        "channel": bus.channel,
        "thresholds": health,
    }
    extensions = {
        "injections": split_targets([*module.injections, *unit.injections]),
        "overrides": split_targets([*module.overrides, *unit.overrides]),
    }
    components = [
        _module_component(slot, module, c, facts, extensions, unit.host) for c in module.components
    ]
    return plan, components, ModulePart(slot, module.urdf, limits, dict(module.connectors))


def _module_component(
    slot: str,
    module: ModuleType,
    c: data.ComponentDef,
    facts: Mapping[str, Any],
    extensions: Mapping[str, dict[str, list[dict[str, Any]]]],
    host: str,
) -> ComponentPlan:
    """A module's component: the module facts its kind reads, the link or chain it is
    about, its params and the injections and overrides aimed at it, in assembly names."""
    p = slot + "_"
    params: dict[str, Any] = {fact: facts[fact] for fact in kinds.get(c.kind).module_facts}
    if c.link is not None:
        params["link"] = p + c.link
    if c.chain is not None:
        base, tip, js = module.chains[c.chain]
        params.update(
            chain=c.chain, base_link=p + base, tip_link=p + tip, joints=[p + j for j in js]
        )
    params.update(_prefix_params(c.params, p))
    for key, entries in extensions.items():
        if c.kind in entries:
            params[key] = [_prefix_params(e, p) for e in entries[c.kind]]
    return ComponentPlan(
        name=f"{slot}/{c.name}",
        kind=c.kind,
        host=host,
        module=slot,
        namespace=f"/{slot}",
        params=params,
    )


def _station_components(template: Template) -> list[ComponentPlan]:
    """Every ground station's components, on the station's host."""
    return [
        ComponentPlan(
            name=f"{station.name}/{component}",
            kind=kind_name,
            host=station.host,
            module=None,
            namespace=f"/{station.name}",
            params=dict(params),
        )
        for station in template.stations
        for kind_name, component, params in station.components
    ]


def _mounts(
    template: Template, types: Mapping[str, ModuleType]
) -> tuple[list[Mount], list[Connection]]:
    """Each connection as a fixed URDF joint (the child's root hung from the parent's
    connector, mated and turned by its angle) and as the lock records it."""
    mounts: list[Mount] = []
    connections: list[Connection] = []
    for c in template.connections:
        child = types[c.child]
        link, xyz, rpy = child.connectors[c.child_connector]
        in_root = tf.compose(child.urdf.fixed_transform(link), tf.from_xyz_rpy(xyz, rpy))  # type: ignore[arg-type]
        pose = tf.compose(tf.mating(c.angle), tf.inverse(in_root))
        mxyz, mrpy = tf.to_xyz_rpy(pose)
        joint = f"{c.child}_mount"
        mounts.append(
            Mount(
                joint,
                connector_link(c.parent, c.parent_connector),
                f"{c.child}_{child.urdf.root_link}",
                mxyz,
                mrpy,
            )
        )
        connections.append(
            Connection(
                parent=f"{c.parent}.{c.parent_connector}",
                child=f"{c.child}.{c.child_connector}",
                joint=joint,
                angle=c.angle,
            )
        )
    return mounts, connections


def _robots(
    template: Template, types: Mapping[str, ModuleType], mounts: list[Mount]
) -> list[RobotPlacement]:
    """Each robot by its root slot and place; with several, each hangs from a world link
    at its place (added to ``mounts``)."""
    roots = template.roots
    robots = []
    for root in roots:
        slot_def = template.slot(root)
        root_link = f"{root}_{types[root].urdf.root_link}"
        robots.append(RobotPlacement(root, root_link, *slot_def.place))
        if len(roots) > 1:
            mounts.append(Mount(f"{root}_place", "world", root_link, *slot_def.place))
    return robots


def _host_plans(components: Sequence[ComponentPlan]) -> dict[str, HostRole]:
    """What each host does: a robot computer if it runs a module's components, else ground."""
    host_plans: dict[str, HostRole] = {}
    for comp in components:
        plan = host_plans.setdefault(comp.host, HostRole("ground"))
        plan.components.append(comp.name)
        if comp.module and comp.module not in plan.modules:
            plan.modules.append(comp.module)
    return {
        host: HostRole("robot" if plan.modules else "ground", plan.modules, plan.components)
        for host, plan in host_plans.items()
    }
