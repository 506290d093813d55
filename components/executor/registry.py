"""Injections and Overrides, registered by name and applied to cores from data.

An *Injection* extends a core type (adds a capability any robot may want: re-zeroing a joint
at runtime, telemetry). An *Override* alters a core for one robot (a locked joint, a motor
with a reversed encoder). Both are chosen by the assembler from module and unit data and
applied here by name, never by ``if robot == ...`` in a core.

Registering::

    @injection("joint_manager", "rezero")
    def rezero(core: JointManagerCore, params: dict) -> None: ...

Applying (the component builder does this)::

    apply_all(core, "joint_manager", injections=[{"name": "rezero"}], overrides=[...])
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

Applier = Callable[[Any, dict[str, Any]], None]


class RegistryError(LookupError):
    """An injection or override named in data does not exist for that core kind."""


@dataclass(frozen=True)
class _Entry:
    kind: str
    name: str
    apply: Applier
    doc: str


_INJECTIONS: dict[tuple[str, str], _Entry] = {}
_OVERRIDES: dict[tuple[str, str], _Entry] = {}

#: Modules that register injections/overrides, imported on first lookup so registration
#: needs no import side effect elsewhere.
PROVIDERS: list[str] = [
    "components.joint_manager.injections",
    "components.overrides",
]
_loaded = False


def _load_providers() -> None:
    global _loaded
    if _loaded:
        return
    _loaded = True
    for module in PROVIDERS:
        try:
            importlib.import_module(module)
        except ModuleNotFoundError as exc:
            if exc.name != module:
                raise


def _register(table: dict[tuple[str, str], _Entry], kind: str, name: str) -> Callable:
    def decorate(fn: Applier) -> Applier:
        key = (kind, name)
        if key in table and table[key].apply is not fn:
            raise ValueError(f"{kind}/{name} is registered twice")
        table[key] = _Entry(kind, name, fn, (fn.__doc__ or "").strip().split("\n")[0])
        return fn

    return decorate


def injection(kind: str, name: str) -> Callable[[Applier], Applier]:
    """Register an injection ``name`` for cores of ``kind``."""
    return _register(_INJECTIONS, kind, name)


def override(kind: str, name: str) -> Callable[[Applier], Applier]:
    """Register an override ``name`` for cores of ``kind``."""
    return _register(_OVERRIDES, kind, name)


def available(kind: str | None = None) -> dict[str, list[tuple[str, str]]]:
    """Registered names (with their one-line doc), for listings and error messages."""
    _load_providers()
    return {
        "injections": sorted(
            (k[1], e.doc) for k, e in _INJECTIONS.items() if kind is None or k[0] == kind
        ),
        "overrides": sorted(
            (k[1], e.doc) for k, e in _OVERRIDES.items() if kind is None or k[0] == kind
        ),
    }


def _lookup(table: dict[tuple[str, str], _Entry], what: str, kind: str, name: str) -> _Entry:
    _load_providers()
    try:
        return table[(kind, name)]
    except KeyError:
        known = sorted(k[1] for k in table if k[0] == kind)
        raise RegistryError(
            f"no {what} named {name!r} for {kind}; known: {', '.join(known) or 'none'}"
        ) from None


def apply_all(
    core: Any,
    kind: str,
    injections: Iterable[Mapping[str, Any]] = (),
    overrides: Iterable[Mapping[str, Any]] = (),
) -> None:
    """Apply injections then overrides (each ``{"name": ..., **params}``) to ``core``.

    Overrides go last so that a robot's alteration wins over a generic extension.

    Raises:
        RegistryError: If a name is unknown for that kind (nothing is applied then).
    """
    plan = [(_lookup(_INJECTIONS, "injection", kind, i["name"]), i) for i in injections]
    plan += [(_lookup(_OVERRIDES, "override", kind, o["name"]), o) for o in overrides]
    for entry, spec in plan:
        entry.apply(core, {k: v for k, v in spec.items() if k != "name"})
