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
from typing import Any

from components.assembly import MJCF_NAME, SCHEMA_VERSION, URDF_NAME
from msctl.assembler import data
from msctl.assembler import transforms as tf
from msctl.assembler.data import ModuleType, Template, Unit
from msctl.assembler.urdf import ModulePart, Mount, compose, connector_link
from msctl.errors import InputError, NotFoundError

#: ``choose(slot, candidate serials) -> serial``, or None when no one can be asked.
Chooser = Callable[[str, list[str]], str]


@dataclass
class Resolution:
    """A resolved assembly in memory: nothing is written until :func:`msctl.assembler.store`.

    Attributes:
        template: The checked template.
        units: Slot -> the unit in it.
        document: The lock document (JSON-ready).
        urdf: The composed URDF.
    """

    template: Template
    units: dict[str, Unit]
    document: dict[str, Any]
    urdf: str

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
                hint=f"slots: {', '.join(slots)}",
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
                hint=f"units that fit {slot}: {', '.join(fitting) or 'none'}",
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


def _split_targets(entries: Sequence[Mapping[str, Any]], p: str) -> dict[str, list[dict]]:
    """Group ``{"name", "component"?, ...}`` entries by the component kind they apply to."""
    grouped: dict[str, list[dict]] = {}
    for entry in entries:
        target = entry.get("component", "joint_manager")
        body = {k: v for k, v in entry.items() if k != "component"}
        grouped.setdefault(target, []).append(_prefix_params(body, p))
    return grouped


def _plan(template: Template, units: Mapping[str, Unit]) -> Resolution:
    modules: list[dict[str, Any]] = []
    components: list[dict[str, Any]] = []
    parts: list[ModulePart] = []
    types: dict[str, ModuleType] = {}
    for slot_def in template.slots:
        slot = slot_def.name
        unit = units[slot]
        module = template.module_types[unit.module_type]
        types[slot] = module
        p = slot + "_"
        joints = []
        limits = {}
        for jd in module.joints.values():
            cal = unit.joints.get(jd.name)
            lower = jd.lower if cal is None or cal.lower is None else cal.lower
            upper = jd.upper if cal is None or cal.upper is None else cal.upper
            limits[jd.name] = (lower, upper, jd.max_effort, jd.max_velocity)
            joints.append(
                {
                    "name": p + jd.name,
                    "raw_name": jd.name,
                    "type": jd.type,
                    "lower": _limit(lower),
                    "upper": _limit(upper),
                    "max_velocity": jd.max_velocity,
                    "max_effort": jd.max_effort,
                    "zero_offset": cal.zero_offset if cal else 0.0,
                    "direction": cal.direction if cal else 1,
                    "motor_id": cal.motor_id if cal and cal.motor_id is not None else jd.motor_id,
                    "motor_model": jd.motor,
                    "motor_params": jd.motor_params,
                    "actuated": jd.actuated,
                    "control": jd.control,
                    "armature": jd.armature,
                }
            )
        bus = {k: v for k, v in module.bus.items() if k != "options"}
        bus.update({k: v for k, v in unit.bus.items() if k != "options"})
        bus["options"] = {**module.bus.get("options", {}), **unit.bus.get("options", {})}
        injections = _split_targets([*module.injections, *unit.injections], p)
        overrides = _split_targets([*module.overrides, *unit.overrides], p)
        health = {**module.health, **unit.health}
        chains = [
            {
                "name": name,
                "base_link": p + base,
                "tip_link": p + tip,
                "joints": [p + j for j in js],
            }
            for name, (base, tip, js) in module.chains.items()
        ]
        modules.append(
            {
                "slot": slot,
                "namespace": f"/{slot}",
                "module_type": module.key,
                "family": module.family,
                "kind": module.kind,
                "revision": module.revision,
                "unit": unit.serial,
                "host": unit.host,
                "bus": bus,
                "root_link": p + module.urdf.root_link,
                "joints": joints,
                "chains": chains,
                "interesting_links": [p + link for link in module.interesting_links],
                "connectors": {c: connector_link(slot, c) for c in module.connectors},
                "injections": injections.get("joint_manager", []),
                "overrides": overrides.get("joint_manager", []),
                "health": health,
            }
        )
        actuated = [p + j.name for j in module.joints.values() if j.actuated]
        for c in module.components:
            params: dict[str, Any] = {}
            if c.kind in ("motor_interface", "joint_manager", "health_monitor"):
                params["joints"] = actuated
            if c.kind == "motor_interface":
                params.update(bus=bus["kind"], channel=bus["channel"])
            if c.kind == "health_monitor":
                params["thresholds"] = health
            if c.link is not None:
                params["link"] = p + c.link
            if c.chain is not None:
                base, tip, js = module.chains[c.chain]
                params.update(
                    chain=c.chain, base_link=p + base, tip_link=p + tip, joints=[p + j for j in js]
                )
            params.update(_prefix_params(c.params, p))
            if c.kind in injections:
                params["injections"] = injections[c.kind]
            if c.kind in overrides:
                params["overrides"] = overrides[c.kind]
            components.append(
                {
                    "name": f"{slot}/{c.name}",
                    "kind": c.kind,
                    "host": unit.host,
                    "module": slot,
                    "namespace": f"/{slot}",
                    "params": params,
                }
            )
        parts.append(ModulePart(slot, module.urdf, limits, dict(module.connectors)))

    for station in template.stations:
        for kind, count, params in station.components:
            for i in range(count):
                name = f"{station.name}/{kind}" if count == 1 else f"{station.name}/{kind}_{i + 1}"
                components.append(
                    {
                        "name": name,
                        "kind": kind,
                        "host": station.host,
                        "module": None,
                        "namespace": f"/{station.name}",
                        "params": dict(params),
                    }
                )

    mounts, connections = [], []
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
            {
                "parent": f"{c.parent}.{c.parent_connector}",
                "child": f"{c.child}.{c.child_connector}",
                "joint": joint,
                "angle": c.angle,
            }
        )
    roots = template.roots
    robots = []
    for root in roots:
        slot_def = template.slot(root)
        root_link = f"{root}_{types[root].urdf.root_link}"
        robots.append(
            {
                "root": root,
                "root_link": root_link,
                "xyz": list(slot_def.place[0]),
                "rpy": list(slot_def.place[1]),
            }
        )
        if len(roots) > 1:  # several robots: hang each from a world link at its place
            mounts.append(Mount(f"{root}_place", "world", root_link, *slot_def.place))

    hosts: list[str] = []
    host_plans: dict[str, dict[str, Any]] = {}
    for comp in components:
        if comp["host"] not in host_plans:
            hosts.append(comp["host"])
            host_plans[comp["host"]] = {
                "role": "robot" if comp["module"] else "ground",
                "modules": [],
                "components": [],
            }
        plan = host_plans[comp["host"]]
        plan["components"].append(comp["name"])
        if comp["module"] and comp["module"] not in plan["modules"]:
            plan["modules"].append(comp["module"])
            plan["role"] = "robot"
    counts: dict[str, int] = {}
    for comp in components:
        counts[comp["kind"]] = counts.get(comp["kind"], 0) + 1

    document = {
        "schema": SCHEMA_VERSION,
        "template": template.name,
        "description": template.description,
        "mobile": template.mobile,
        "units": {slot: units[slot].serial for slot in units},
        "modules": modules,
        "components": components,
        "hosts": hosts,
        "host_plans": host_plans,
        "component_counts": counts,
        "root_links": [r["root_link"] for r in robots],
        "robots": robots,
        "connections": connections,
        "artifacts": {"urdf": URDF_NAME, "mjcf": MJCF_NAME},
        "sources": {
            "template": str(template.path),
            "module_types": {k: str(m.path) for k, m in template.module_types.items()},
            "units": {u.serial: str(u.path) for u in units.values()},
        },
    }
    urdf = compose(template.name, parts, mounts)
    return Resolution(template=template, units=dict(units), document=document, urdf=urdf)
