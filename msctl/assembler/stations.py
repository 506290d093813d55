"""A template's ground-control stations: their hosts and the components each runs."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from components import kinds
from msctl.assembler import checks
from msctl.assembler.models import NamedComponent, StationEntry
from msctl.assembler.schema import decode
from msctl.errors import InputError

#: ``(kind, name, params)`` of one station component.
StationComponent = tuple[str, str, dict[str, Any]]


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
    components: tuple[StationComponent, ...]


def parse_stations(
    path: Path, entries: list[StationEntry], slot_names: set[str], robots: list[str]
) -> tuple[StationDef, ...]:
    """Every ``[[stations]]`` entry, named apart from the slots and from each other.

    Args:
        path: The template file, for errors.
        entries: The decoded ``stations`` list.
        slot_names: The template's slots.
        robots: Root slots: what a station component may be given as its robot.

    Raises:
        InputError: Naming the file, the field and the fix.
    """
    stations: list[StationDef] = []
    for i, entry in enumerate(entries):
        at = f"stations[{i}]."
        if entry.name in slot_names or any(st.name == entry.name for st in stations):
            raise InputError(
                f"{path}: field {at}name: {entry.name!r} is already a slot or station name"
            )
        components = _components(path, at, entry, robots)
        _check_names_apart(path, at, entry.name, components)
        stations.append(StationDef(entry.name, entry.host, tuple(components)))
    return tuple(stations)


def _components(
    path: Path, at: str, entry: StationEntry, robots: list[str]
) -> list[StationComponent]:
    """A station's components, kind by kind, with the station's ``params.<kind>`` checked."""
    station_kinds = [k.name for k in kinds.placed(kinds.Placement.STATION)]
    out: list[StationComponent] = []
    for kind, given in entry.components.items():
        where = f"{path}: field {at}components.{kind}"
        if kind not in station_kinds:
            raise InputError(
                f"{where}: {kind!r} is not a ground-station component kind",
                hint=f"use one of {', '.join(station_kinds)}",
            )
        kind_params = dict(entry.params.get(kind, {}))
        if not kinds.get(kind).named:  # a named one's are checked with each component's
            checks.check_kind_params(kind, kind_params, f"{path}: field {at}params.{kind}", robots)
        if isinstance(given, list):
            out += _named(path, f"{at}components.{kind}", kind, given, kind_params, robots)
        else:
            out += _counted(where, kind, given, kind_params)
    for kind in entry.params:
        if kind not in entry.components:
            raise InputError(
                f"{path}: field {at}params.{kind}: the station runs no {kind}",
                hint=f"add {kind} to the station's components, or remove its params",
            )
    return out


def _counted(where: str, kind: str, count: Any, params: dict[str, Any]) -> list[StationComponent]:
    """A kind given as a count ``n``: ``kind`` (n = 1) or ``kind_1`` ... ``kind_n``."""
    if kinds.get(kind).named:
        raise InputError(
            f"{where} is {count!r}: each {kind} is named, with its parameters",
            hint=f'write {kind} = [{{ name = "...", ... }}], one table per component '
            f"(see assemblies/two_dragons.toml)",
        )
    if not isinstance(count, int) or isinstance(count, bool):
        raise InputError(
            f"{where} is {count!r}", hint="it must be a count, or a list of named components"
        )
    if not 0 <= count <= kinds.MAX_PER_STATION:
        raise InputError(
            f"{where} is {count}",
            hint=f"a station runs 0 to {kinds.MAX_PER_STATION} components of one kind",
        )
    return [(kind, kind if count == 1 else f"{kind}_{n + 1}", params) for n in range(count)]


def _named(
    path: Path,
    at: str,
    kind: str,
    items: list[Any],
    defaults: dict[str, Any],
    robots: list[str],
) -> list[StationComponent]:
    """A kind given as a list of tables, each with a ``name`` and its parameters (over the
    station's ``params.<kind>``), each checked."""
    checks.check_entries(path, at, items, f"{kind} table")
    if len(items) > kinds.MAX_PER_STATION:
        raise InputError(
            f"{path}: field {at} lists {len(items)} components",
            hint=f"a station runs 0 to {kinds.MAX_PER_STATION} components of one kind",
        )
    out: list[StationComponent] = []
    for i, item in enumerate(items):
        component = decode(path, item, NamedComponent, f"{at}[{i}].").name
        own = {**defaults, **{k: v for k, v in item.items() if k != "name"}}
        where = f"{path}: field {at}[{i}] ({component})"
        checks.check_kind_params(kind, own, where, robots)
        out.append((kind, component, own))
    return out


def _check_names_apart(
    path: Path, at: str, station: str, components: list[StationComponent]
) -> None:
    """No two components of one station share a name (it is their node's name)."""
    seen: dict[str, str] = {}
    for kind, component, _ in components:
        if component in seen:
            raise InputError(
                f"{path}: field {at}components.{kind}: two components of station {station} "
                f"are named {component!r} (a {seen[component]} and a {kind})",
                hint="give each a distinct name: it is its node's name on the graph",
            )
        seen[component] = kind
