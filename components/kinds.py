"""The component-kind registry: one typed entry per kind, declared beside its package.

Every component kind is described once, as a :class:`ComponentKind` in its package's
``kind.py`` (``components/joint_manager/kind.py`` declares ``KIND``): its parameters (config
dataclasses), its builder and interface, the output that shows it healthy, what it stands in
for in simulation, where it runs, what the assembler gives it from its module, and the modules
that register its injections and overrides. The assembler, launcher, health monitor and worker
derive every list they need from here, so a new kind is one file and one line in
:data:`BUILTIN`; other packages add kinds through the ``msctl.component_kinds`` entry-point
group (python-can's ``can.interface`` group is the model), each entry loading a
:class:`ComponentKind`.

Entries are plain data with ``"module:attribute"`` references, imported only when used, so
``msctl assemble`` and the launcher read the registry without importing MuJoCo or Pinocchio.
"""

from __future__ import annotations

import dataclasses
import importlib
import math
import re
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from enum import Enum
from typing import Any

from components.errors import NotFound

#: The kinds that ship with msctl: modules each holding one ``KIND``.
BUILTIN: tuple[str, ...] = (
    "components.motor_interface.kind",
    "components.joint_manager.kind",
    "components.health_monitor.kind",
    "components.location_publisher.kind",
    "components.kinematics_manager.kind",
    "components.simulator.kind",
    "components.data_monitor.kind",
    "components.data_archiver.kind",
    "components.bridge.kind",
    "components.human_operator.kind",
    "components.autonomous_operator.kind",
)
#: Entry-point group through which other packages add kinds.
ENTRY_POINT_GROUP = "msctl.component_kinds"
#: The kind an injection or override applies to when its entry names no ``component``.
DEFAULT_EXTENSION_TARGET = "joint_manager"
#: Most components of one kind one ground station may run (a typo of 100,000,000 must fail
#: at ``msctl assemble``, not exhaust memory).
MAX_PER_STATION = 64


class Placement(Enum):
    """Where components of a kind run."""

    MODULE = "module"  #: one per module that lists it, on the module's computer
    STATION = "station"  #: on a ground station, counted in the template's ``stations``
    ASSEMBLY = "assembly"  #: one for the whole assembly, added by the launcher (the simulator)


class KindError(NotFound):
    """An unknown kind, or parameters a kind does not accept; the message names both."""


@dataclass(frozen=True)
class ComponentKind:
    """Everything msctl knows about one component kind.

    Attributes:
        name: The kind's name in data (``joint_manager``).
        summary: One line for listings.
        placement: Where its components run.
        config: ``"module:Class"`` of the config dataclasses whose fields are its parameters
            (each field one parameter, with its type, range check and docs).
        builder: ``"module:function"`` building it (see :mod:`components.build`); ``None``
            for a kind the assembler plans but no code runs yet (reported by the launcher,
            never replaced by a placeholder).
        interface: ``"module:attribute"`` of its interface declaration (an ``InterfaceSpec``,
            or the function making one).
        healthy_output: A topic it publishes soon after starting (relative to its namespace,
            or absolute) that the launcher waits for to call it healthy.
        stands_in_for: Kinds it replaces in simulation (the simulator: ``motor_interface``).
        module_facts: What the assembler copies from the module into its parameters (see
            :data:`MODULE_FACTS`).
        structural: Other parameters its builder reads, which the assembler or the module's
            component entry sets (``link``, ``chain``...).
        checks: Parameter -> ``"module:function"`` checking that parameter's value (raises
            ``ValueError`` naming what is wrong), for values no dataclass describes.
        extensions: Modules registering its injections and overrides (imported on lookup).
        namespace: Its namespace when it belongs to no module or station (``/sim``).
        not_rebuilt_alone: Why one of its components cannot be rebuilt inside its running
            process while the process's other components run on (``msctl restart
            --only``), or ``""`` when it can.
        claim_relay: It forwards commands to joint managers (``joint_set``) only after
            checking, on its own inputs, that they come from the holder of the module's
            claim; joint managers then take its commands as the holder's (see
            :func:`components.roles.command_rule`). A module-placed relay forwards to its
            own module, a station-placed one to any.
        own_process: Each of its components runs in a process of its own rather than with
            the other components of its kind on its station or module, so that one failing
            (an operator's script raising) is restarted alone.
        named: A station lists each of its components by name, with its own parameters
            (``autonomous_operator = [{ name = "steering", script = "steering" }]``); a bare
            count is refused.
        validate: ``"module:function"`` checking a component's parameters as a whole,
            called as ``function(params, robots)`` with the template's robots (their root
            slots); raises ``ValueError`` naming what is wrong.
        niceness: How far below the robot's safety path its process runs for CPU (a Unix
            nice value, 0 to 19) when they share a computer, as off-robot everything does.
            Work that can wait milliseconds without harm (recording, aggregating health)
            says so, and a halt is not queued behind its bursts. A process of several
            kinds takes the lowest (see :func:`process_niceness`). Lowering a priority
            needs no privilege; raising one would, so the safety path stays at 0.
        preload: Modules its components import only once they run (a library loaded
            lazily, so that commands which never run it stay quick: psutil for a health
            monitor), which the fork server imports once before forking, where every
            worker of the kind would import them again.
    """

    name: str
    summary: str
    placement: Placement
    config: tuple[str, ...] = ()
    builder: str | None = None
    interface: str | None = None
    healthy_output: str | None = None
    stands_in_for: tuple[str, ...] = ()
    module_facts: tuple[str, ...] = ()
    structural: tuple[str, ...] = ()
    checks: Mapping[str, str] = dataclasses.field(default_factory=dict)
    extensions: tuple[str, ...] = ()
    namespace: str = ""
    not_rebuilt_alone: str = ""
    claim_relay: bool = False
    own_process: bool = False
    named: bool = False
    validate: str | None = None
    niceness: int = 0
    preload: tuple[str, ...] = ()

    @property
    def runnable(self) -> bool:
        """Whether code exists that runs this kind (a builder and a healthy output)."""
        return self.builder is not None and self.healthy_output is not None

    @property
    def component_name(self) -> str:
        """The name of its one component, for an assembly-wide kind (``sim/simulator``)."""
        return f"{self.namespace.strip('/')}/{self.name}"

    def config_classes(self) -> list[type]:
        """Its config dataclasses, imported."""
        return [resolve(path) for path in self.config]

    def parameter_names(self) -> list[str]:
        """Every parameter it accepts: config fields, module facts, structural ones."""
        names: list[str] = []
        for cls in self.config_classes():
            names += [f.name for f in dataclasses.fields(cls) if f.init and _is_scalar(f)]
        names += [*self.module_facts, *self.structural, *self.checks]
        if self.extensions:
            names += ["injections", "overrides"]
        return list(dict.fromkeys(names))


#: Module facts a kind may ask for, and what the assembler puts in its parameters.
MODULE_FACTS: dict[str, str] = {
    "joints": "the module's actuated joints (assembly names)",
    "bus": "the module's bus kind (a motor backend name)",
    "channel": "the module's bus channel",
    "thresholds": "the module's [health] table, unit values over module values",
}


def resolve(path: str) -> Any:
    """Import ``"module:attribute"`` (dotted attributes allowed)."""
    module_name, _, attribute = path.partition(":")
    value: Any = importlib.import_module(module_name)
    for part in attribute.split("."):
        value = getattr(value, part)
    return value


_kinds: dict[str, ComponentKind] | None = None


def _entry_point_kinds() -> Iterable[tuple[str, Any]]:
    from importlib.metadata import entry_points

    for entry in entry_points(group=ENTRY_POINT_GROUP):
        yield f"entry point {entry.name} ({entry.value})", entry.load


#: A dotted module name (a kind's ``preload``).
_MODULE_NAME = re.compile(r"^[A-Za-z_]\w*(\.[A-Za-z_]\w*)*$")


def registry() -> dict[str, ComponentKind]:
    """Every kind by name: the built-in ones, then those of installed entry points.

    Raises:
        KindError: If two entries declare one name, or an entry is not a ComponentKind.
    """
    global _kinds
    if _kinds is not None:
        return _kinds
    found: dict[str, ComponentKind] = {}
    sources: dict[str, str] = {}
    loaders: list[tuple[str, Callable[[], Any]]] = [
        (module, lambda module=module: importlib.import_module(module)) for module in BUILTIN
    ]
    loaders += list(_entry_point_kinds())
    for source, load in loaders:
        loaded = load()
        entries = getattr(loaded, "KINDS", None) or [getattr(loaded, "KIND", loaded)]
        for entry in entries:
            if not isinstance(entry, ComponentKind):
                raise KindError(f"{source}: {entry!r} is not a ComponentKind")
            if not (isinstance(entry.niceness, int) and 0 <= entry.niceness <= 19):
                raise KindError(
                    f"{source}: kind {entry.name!r} has niceness {entry.niceness!r}; "
                    "use a whole number from 0 (the safety path's) to 19"
                )
            if not isinstance(entry.preload, tuple) or not all(
                isinstance(m, str) and _MODULE_NAME.match(m) for m in entry.preload
            ):
                raise KindError(
                    f"{source}: kind {entry.name!r} has preload {entry.preload!r}; "
                    'use a tuple of module names ("psutil", "mcap.writer")'
                )
            if entry.name in found:
                raise KindError(
                    f"component kind {entry.name!r} is declared twice: by {sources[entry.name]} "
                    f"and by {source}"
                )
            found[entry.name] = entry
            sources[entry.name] = source
    _kinds = found
    return found


def reset() -> None:
    """Forget the registry (tests that install entry points use this)."""
    global _kinds
    _kinds = None


def names() -> list[str]:
    """Every kind's name, in declaration order."""
    return list(registry())


def get(name: str) -> ComponentKind:
    """The kind called ``name``.

    Raises:
        KindError: If there is none (the message lists the known kinds).
    """
    try:
        return registry()[name]
    except KeyError:
        raise KindError(f"unknown component kind {name!r}; known: {', '.join(names())}") from None


def extension_target(entry: Mapping[str, Any]) -> str:
    """The kind an injection or override entry applies to (its ``component``, else
    :data:`DEFAULT_EXTENSION_TARGET`)."""
    return str(entry.get("component", DEFAULT_EXTENSION_TARGET))


def placed(placement: Placement) -> list[ComponentKind]:
    """The kinds placed so (``Placement.STATION``: what a template's stations may list)."""
    return [k for k in registry().values() if k.placement is placement]


def stand_ins(name: str) -> list[ComponentKind]:
    """The kinds that replace ``name`` in simulation (the simulator for motor interfaces)."""
    return [k for k in registry().values() if name in k.stands_in_for]


def replaced_in_simulation(name: str) -> bool:
    """Whether components of kind ``name`` do not run when the assembly is simulated."""
    return bool(stand_ins(name))


def process_niceness(kind_names: Iterable[str]) -> int:
    """The nice value of a process running components of these kinds: the lowest of their
    :attr:`ComponentKind.niceness` (a module's process, holding its joint manager, runs at
    the joint manager's 0 whatever else it holds)."""
    return min((get(name).niceness for name in kind_names), default=0)


def simulators() -> list[ComponentKind]:
    """The assembly-wide kinds that run only in simulation, standing in for others."""
    return [k for k in placed(Placement.ASSEMBLY) if k.stands_in_for]


def _is_scalar(f: dataclasses.Field[Any]) -> bool:
    # A nested dataclass (KinematicsConfig.ik) is flattened through its own entry in config.
    factory = f.default_factory
    return factory is dataclasses.MISSING or not dataclasses.is_dataclass(factory)


def check_params(
    kind: ComponentKind, params: Mapping[str, Any], robots: Iterable[str] | None = None
) -> None:
    """Check a component's parameters against its kind: names, types, ranges, and the kind's
    own check of them as a whole (:attr:`ComponentKind.validate`, given ``robots``: the
    template's robots by root slot, when known).

    Raises:
        KindError: Naming the parameter, what is wrong and what is accepted.
    """
    known = kind.parameter_names()
    for key in params:
        if key not in known:
            raise KindError(
                f"{kind.name} has no parameter {key!r}; known: {', '.join(sorted(known))}"
            )
    for cls in kind.config_classes():
        own = {f.name: f for f in dataclasses.fields(cls) if f.init and _is_scalar(f)}
        values = {k: v for k, v in params.items() if k in own}
        for key, value in values.items():
            if isinstance(value, bool) or not isinstance(value, int | float | str):
                raise KindError(f"{kind.name} parameter {key} is {value!r}: give a number")
            if isinstance(value, float) and not math.isfinite(value):
                raise KindError(f"{kind.name} parameter {key} is {value}: give a finite number")
        try:
            cls(**_typed(own, values))
        except (TypeError, ValueError) as exc:
            raise KindError(f"{kind.name} parameters: {exc}") from None
    for key, path in kind.checks.items():
        if key in params:
            try:
                resolve(path)(params[key])
            except (TypeError, ValueError) as exc:
                raise KindError(f"{kind.name} parameter {key}: {exc}") from None
    if kind.validate is not None:
        try:
            resolve(kind.validate)(params, None if robots is None else tuple(robots))
        except (TypeError, ValueError) as exc:
            raise KindError(f"{kind.name}: {exc}") from None


def _typed(fields: Mapping[str, dataclasses.Field[Any]], values: Mapping[str, Any]) -> dict:
    out: dict[str, Any] = {}
    for key, value in values.items():
        annotation = str(fields[key].type)
        if annotation == "int":
            if not isinstance(value, int):
                raise ValueError(f"{key} must be a whole number, not {value!r}")
            out[key] = value
        elif annotation == "float":
            if not isinstance(value, int | float):
                raise ValueError(f"{key} must be a number, not {value!r}")
            out[key] = float(value)
        else:
            out[key] = value
    return out
