"""Injections and Overrides, registered by name and applied to cores from data.

An *Injection* extends a core type (adds a capability any robot may want: re-zeroing a joint
at runtime, telemetry). An *Override* alters a core for one robot (a locked joint, a motor
with a reversed encoder). Both are chosen by the assembler from module and unit data and
applied here by name, never by ``if robot == ...`` in a core.

Registering, with the parameters the assembler type-checks at ``msctl assemble``::

    @injection("joint_manager", "rezero", params={"joints": list, "service": str})
    def rezero(core: JointManagerCore, params: dict) -> None: ...

Which modules register a kind's injections and overrides is that kind's entry
(``extensions``) in :mod:`components.kinds`.

Applying (the component builder does this)::

    apply_all(core, "joint_manager", injections=[{"name": "rezero"}], overrides=[...])
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from components.errors import NotFound

Applier = Callable[[Any, dict[str, Any]], None]


class RegistryError(NotFound):
    """An injection or override named in data does not exist for that core kind."""


#: A parameter's accepted Python types (TOML values), e.g. ``str`` or ``(list, str)``.
ParamTypes = type | tuple[type, ...]


@dataclass(frozen=True)
class _Entry:
    kind: str
    name: str
    apply: Applier
    doc: str
    params: Mapping[str, ParamTypes]
    required: tuple[str, ...]
    inputs: Mapping[str, Any]


_INJECTIONS: dict[tuple[str, str], _Entry] = {}
_OVERRIDES: dict[tuple[str, str], _Entry] = {}

_loaded = False


def _load_providers() -> None:
    """Import every kind's extension modules (its entry's ``extensions``), once."""
    global _loaded
    if _loaded:
        return
    _loaded = True
    from components import kinds

    for kind in kinds.registry().values():
        for module in kind.extensions:
            importlib.import_module(module)


def _register(
    table: dict[tuple[str, str], _Entry],
    kind: str,
    name: str,
    params: Mapping[str, ParamTypes],
    required: Iterable[str],
    inputs: Mapping[str, Any] | None = None,
) -> Callable:
    def decorate(fn: Applier) -> Applier:
        key = (kind, name)
        if key in table and table[key].apply is not fn:
            raise ValueError(f"{kind}/{name} is registered twice")
        doc = (fn.__doc__ or "").strip().split("\n")[0]
        table[key] = _Entry(kind, name, fn, doc, dict(params), tuple(required), dict(inputs or {}))
        return fn

    return decorate


def injection(
    kind: str,
    name: str,
    params: Mapping[str, ParamTypes] | None = None,
    required: Iterable[str] = (),
    inputs: Mapping[str, Any] | None = None,
) -> Callable[[Applier], Applier]:
    """Register an injection ``name`` for cores of ``kind``, taking ``params``.

    ``inputs`` names each input it may add to the core (a service, by its default name) with
    its :class:`~components.roles.Role`: the access control guards it on every module whose
    component may carry it (:func:`components.roles.assembly_inputs`).
    """
    return _register(_INJECTIONS, kind, name, params or {}, required, inputs)


def override(
    kind: str,
    name: str,
    params: Mapping[str, ParamTypes] | None = None,
    required: Iterable[str] = (),
) -> Callable[[Applier], Applier]:
    """Register an override ``name`` for cores of ``kind``, taking ``params``."""
    return _register(_OVERRIDES, kind, name, params or {}, required)


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


def declared_inputs(kind: str) -> dict[str, Any]:
    """Inputs the injections of ``kind`` may add, by default name, with their roles."""
    _load_providers()
    out: dict[str, Any] = {}
    for (target, _), entry in _INJECTIONS.items():
        if target == kind:
            out.update(entry.inputs)
    return out


def _lookup(table: dict[tuple[str, str], _Entry], what: str, kind: str, name: str) -> _Entry:
    _load_providers()
    try:
        return table[(kind, name)]
    except KeyError:
        known = sorted(k[1] for k in table if k[0] == kind)
        raise RegistryError(
            f"no {what} named {name!r} for {kind}; known: {', '.join(known) or 'none'}"
        ) from None


def check(what: str, kind: str, spec: Mapping[str, Any]) -> None:
    """Check one ``{"name": ..., **params}`` entry of data against the registry.

    Args:
        what: ``"injection"`` or ``"override"``.
        kind: The component kind it targets.
        spec: The entry.

    Raises:
        RegistryError: If no such extension exists for ``kind``, or a parameter is unknown,
            missing or of the wrong type (the message lists what is accepted).
    """
    table = _INJECTIONS if what == "injection" else _OVERRIDES
    entry = _lookup(table, what, kind, str(spec.get("name")))
    params = {k: v for k, v in spec.items() if k != "name"}
    accepted = ", ".join(sorted(entry.params)) or "none"
    for key, value in params.items():
        types = entry.params.get(key)
        if types is None:
            raise RegistryError(f"{what} {entry.name} has no parameter {key!r}; known: {accepted}")
        allowed = types if isinstance(types, tuple) else (types,)
        number = float in allowed and isinstance(value, int)
        if (isinstance(value, bool) and bool not in allowed) or not (
            isinstance(value, allowed) or number
        ):
            names = " or ".join(t.__name__ for t in allowed)
            raise RegistryError(f"{what} {entry.name}: {key} is {value!r}, it must be a {names}")
    for key in entry.required:
        if key not in params:
            raise RegistryError(f"{what} {entry.name} needs parameter {key!r}")


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
