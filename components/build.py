"""Building components from the resolved assembly: each kind's builder, looked up lazily.

A builder turns one planned component (``ComponentPlan``) of a resolved assembly into a Core
and the Interface it is bound with. The launcher and tests build through here; which builder
a kind has is its entry in :mod:`components.kinds`, never an ``if kind == ...``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, TypeVar

from components.errors import ConfigError

if TYPE_CHECKING:
    from components.assembly import ComponentPlan, ResolvedAssembly
    from components.executor.core import Core
    from components.executor.executor import Component, Executor
    from components.executor.interface import InterfaceSpec

T = TypeVar("T")
_log = logging.getLogger(__name__)


def node_name(component: str) -> str:
    """The node a component runs as, in its module's namespace: the last part of its name.

    ``limb1/joint_manager`` runs as ``/limb1/joint_manager``, ``limb1/location_tip`` as
    ``/limb1/location_tip``: one rule, so the launcher and the health monitor know every
    node's name from the plan alone, and two components of one kind never share a node.
    """
    return component.rsplit("/", 1)[-1].replace("-", "_")


class BuildError(ConfigError):
    """A component that cannot be built from the assembly; the message says which and why."""


def config_from_params(plan: ComponentPlan, config_type: type[T]) -> T:
    """``config_type`` (a dataclass) from the plan's params that are its fields; the others
    (a kind's structural params, injections, overrides) are left to the builder.

    Raises:
        BuildError: If a field is out of range or of the wrong type, naming the component.
    """
    import dataclasses

    names = {f.name for f in dataclasses.fields(config_type)}  # type: ignore[arg-type]
    try:
        return config_type(**{k: v for k, v in plan.params.items() if k in names})
    except (TypeError, ValueError) as exc:
        raise BuildError(f"{plan.name}: {exc}") from exc


@dataclass
class BuiltComponent:
    """A core ready for an executor.

    Attributes:
        core: The component's logic.
        spec: Its interface (topics, services, timers).
        namespace: ROS namespace of its node (the module's, e.g. ``/limb1``).
        node_name: Node name on the graph (e.g. ``joint_manager``).
        resources: Things to close after the executor stops (a motor bus, a simulated world).
        on_bound: Called as ``on_bound(executor, component)`` once the core is added to its
            executor and before it runs, for components that need the executor's session or
            its :meth:`~components.executor.executor.Executor.call_soon` (the health
            monitor's graph watcher). What it opens goes into ``resources``. Whoever runs
            built components calls it: :func:`components.executor.runner.run_built` does.
        extension_defaults: Extension name -> parameters the builder knows better than the
            data (the unit file a re-zero saves to), given to the extension unless set.
        failed: Why the component cannot go on (an operator's script raised), set by the
            component itself before it stops its executor; the process then exits with a
            failure (1), and its supervisor starts it again (``""``: it has not failed).
    """

    core: Core
    spec: InterfaceSpec
    namespace: str
    node_name: str
    resources: list[Any] = field(default_factory=list)
    on_bound: Callable[[Executor, Component], None] | None = None
    extension_defaults: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    failed: str = ""

    def close(self) -> None:
        """Release the resources (idempotent where they are)."""
        for resource in reversed(self.resources):
            what = repr(resource)  # taken before closing: a closed file forgets its name
            try:
                resource.close()
            except Exception as exc:  # the others are closed still; say which one failed
                where = f"{self.namespace.rstrip('/')}/{self.node_name}"
                _log.warning("%s: closing %s failed: %s", where, what, exc, exc_info=True)


Builder = Callable[["ComponentPlan", "ResolvedAssembly", Mapping[str, Any]], BuiltComponent]


def buildable(kind: str) -> bool:
    """Whether code runs ``kind``: a registered kind with a builder that can be found
    (checked without importing it: fast)."""
    import importlib.util

    from components import kinds

    entry = kinds.registry().get(kind)
    if entry is None or not entry.runnable or entry.builder is None:
        return False
    module_name = entry.builder.partition(":")[0]
    try:
        return importlib.util.find_spec(module_name) is not None
    except ModuleNotFoundError:
        return False


def _builder(kind: str) -> Builder:
    from components import kinds

    try:
        entry = kinds.get(kind)
    except kinds.KindError as exc:
        raise BuildError(str(exc)) from None
    if entry.builder is None:
        raise BuildError(f"component kind {kind!r} is not implemented yet")
    module_name = entry.builder.partition(":")[0]
    try:
        return kinds.resolve(entry.builder)
    except ModuleNotFoundError as exc:
        if exc.name == module_name or (exc.name and module_name.startswith(exc.name + ".")):
            raise BuildError(f"component kind {kind!r} is not implemented yet") from None
        raise


def build_component(
    plan: ComponentPlan, assembly: ResolvedAssembly, options: Mapping[str, Any] | None = None
) -> BuiltComponent:
    """Build one planned component, then apply its injections and overrides.

    The assembler put each kind's injections and overrides in its plan's params (module
    data, then unit data) and checked them against the registry; they are applied here, to
    every kind alike, so one aimed at a kind is never silently dropped.

    Args:
        plan: The component's entry in the resolved assembly.
        assembly: The whole resolved assembly (for module data).
        options: Run-time choices (e.g. ``{"sim": True, "speed": 1.0}``).

    Raises:
        BuildError: If the kind has no builder, the plan is inconsistent, or an injection
            or override does not apply.
    """
    from components.executor.registry import RegistryError, apply_all

    built = _builder(plan.kind)(plan, assembly, options or {})
    defaults = built.extension_defaults
    injections = [{**defaults.get(i["name"], {}), **i} for i in plan.params.get("injections", ())]
    overrides = [{**defaults.get(o["name"], {}), **o} for o in plan.params.get("overrides", ())]
    if injections or overrides:
        try:
            apply_all(built.core, plan.kind, injections, overrides)
        except (RegistryError, ValueError) as exc:
            built.close()
            raise BuildError(f"{plan.name}: {exc}") from exc
    return built


def simulator_plan(kind: str) -> ComponentPlan:
    """The plan of an assembly-wide stand-in (the simulator), which no lock file lists."""
    from components import kinds
    from components.assembly import ComponentPlan

    entry = kinds.get(kind)
    return ComponentPlan(
        name=entry.component_name, kind=kind, host="", module=None, namespace=entry.namespace
    )
