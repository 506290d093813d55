"""Building components from the resolved assembly: kind name -> builder, looked up lazily.

A builder turns one planned component (``ComponentPlan``) of a resolved assembly into a Core
and the Interface it is bound with. The launcher and tests build through here, so a new
component kind is one module and one line in :data:`BUILDERS`, never an ``if kind == ...``.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from components.assembly import ComponentPlan, ResolvedAssembly
    from components.executor.core import Core
    from components.executor.executor import Component, Executor
    from components.executor.interface import InterfaceSpec

#: Component kind -> "module:function" building it. Kinds without an entry are not built
#: yet; the launcher reports them instead of starting a placeholder.
BUILDERS: dict[str, str] = {
    "joint_manager": "components.joint_manager.build:build",
    "motor_interface": "components.motor_interface.build:build",
    "simulator": "components.simulator.build:build",
    "health_monitor": "components.health.build:build",
    "kinematics_manager": "components.kinematics.build:build",
    "location_publisher": "components.location.build:build",
}


@dataclass(frozen=True)
class KindInfo:
    """How a running component of a kind shows itself on the data plane.

    Attributes:
        first_output: A topic it publishes soon after starting (relative to its namespace,
            or absolute), which the launcher waits for to call it healthy.
    """

    first_output: str


#: The launcher's view of each kind, so it can judge health without building anything.
KINDS: dict[str, KindInfo] = {
    "joint_manager": KindInfo("diagnostics"),
    "motor_interface": KindInfo("joint_states"),
    "simulator": KindInfo("/sim/diagnostics"),
    "health_monitor": KindInfo("health"),
    # Diagnostics go out at start, before any joint_read; tip_pose needs joint angles first.
    "kinematics_manager": KindInfo("diagnostics"),
    # Every location publisher writes tf (the root-link one at start, from static edges).
    "location_publisher": KindInfo("tf"),
}


def node_name(component: str) -> str:
    """The node a component runs as, in its module's namespace: the last part of its name.

    ``limb1/joint_manager`` runs as ``/limb1/joint_manager``, ``limb1/location_tip`` as
    ``/limb1/location_tip``: one rule, so the launcher and the health monitor know every
    node's name from the plan alone, and two components of one kind never share a node.
    """
    return component.rsplit("/", 1)[-1].replace("-", "_")


#: The one simulated world that replaces every motor interface off-robot.
SIMULATOR_COMPONENT = "sim/simulator"


class BuildError(ValueError):
    """A component that cannot be built from the assembly; the message says which and why."""


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
    """

    core: Core
    spec: InterfaceSpec
    namespace: str
    node_name: str
    resources: list[Any] = field(default_factory=list)
    on_bound: Callable[[Executor, Component], None] | None = None

    def close(self) -> None:
        """Release the resources (idempotent where they are)."""
        for resource in reversed(self.resources):
            try:
                resource.close()
            except Exception:
                pass


Builder = Callable[["ComponentPlan", "ResolvedAssembly", Mapping[str, Any]], BuiltComponent]


def buildable(kind: str) -> bool:
    """Whether a builder exists for ``kind`` (checked without importing it: fast)."""
    import importlib.util

    target = BUILDERS.get(kind)
    if target is None:
        return False
    module_name = target.partition(":")[0]
    try:
        return importlib.util.find_spec(module_name) is not None
    except ModuleNotFoundError:
        return False


def _builder(kind: str) -> Builder:
    try:
        target = BUILDERS[kind]
    except KeyError:
        raise BuildError(f"no builder for component kind {kind!r}") from None
    module_name, _, function = target.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name == module_name or (exc.name and module_name.startswith(exc.name + ".")):
            raise BuildError(f"component kind {kind!r} is not implemented yet") from None
        raise
    return getattr(module, function)


def build_component(
    plan: ComponentPlan, assembly: ResolvedAssembly, options: Mapping[str, Any] | None = None
) -> BuiltComponent:
    """Build one planned component.

    Args:
        plan: The component's entry in the resolved assembly.
        assembly: The whole resolved assembly (for module data).
        options: Run-time choices (e.g. ``{"sim": True, "speed": 1.0}``).

    Raises:
        BuildError: If the kind has no builder or the plan is inconsistent.
    """
    return _builder(plan.kind)(plan, assembly, options or {})
