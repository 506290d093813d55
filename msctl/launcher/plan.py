"""From the resolved assembly to the processes this computer runs.

Off-robot (this computer is none of the assembly's robot computers) the whole assembly runs
here and every motor interface is replaced by one MuJoCo simulator; on a robot computer only
its own part runs. Components are grouped into executor processes: one per module, one for
the simulator, one per ground-control station's role (kind), and one for each component of a
kind that asks for its own (an autonomous operator), so start-up is a handful of
interpreters, not sixty.

Simulating on robot computers (``msctl up --all --sim``), the assembly still gets one world,
not one per computer: the computer of the first module runs the simulator (it serves every
module's motor interface) and the others only drop their motor interfaces.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

from components import kinds
from components.assembly import ResolvedAssembly
from components.build import buildable, node_name
from components.supervision.contract import this_host

#: What a process or component name may look like: it reaches an argument list, so nothing
#: that could be read as an option, a path or a shell fragment.
SAFE_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_./-]{0,127}$")


@dataclass(frozen=True)
class ComponentRun:
    """One component as the launcher follows it."""

    name: str
    kind: str
    namespace: str
    node_fqn: str
    first_output: str


@dataclass(frozen=True)
class ProcessPlan:
    """One executor process and the components it runs."""

    name: str
    components: tuple[ComponentRun, ...]


@dataclass
class HostPlan:
    """What this computer runs for an assembly.

    Attributes:
        host: This computer.
        simulated: Motor interfaces replaced by the simulator.
        off_robot: This computer is none of the assembly's robot computers.
        processes: The processes to start.
        not_built: Components of this host's part whose kind does not exist in the code yet
            (reported, never replaced by a placeholder).
    """

    host: str
    simulated: bool
    off_robot: bool
    processes: list[ProcessPlan] = field(default_factory=list)
    not_built: list[tuple[str, str]] = field(default_factory=list)

    @property
    def components(self) -> list[ComponentRun]:
        """Every component started, in process order."""
        return [c for p in self.processes for c in p.components]


def _qualify(namespace: str, topic: str) -> str:
    if topic.startswith("/"):
        return topic
    return namespace.rstrip("/") + "/" + topic


def _run(name: str, kind: str, namespace: str) -> ComponentRun:
    output = kinds.get(kind).healthy_output or "diagnostics"
    return ComponentRun(
        name=name,
        kind=kind,
        namespace=namespace,
        node_fqn=_qualify(namespace, node_name(name)),
        first_output=_qualify(namespace, output),
    )


def plan_host(
    assembly: ResolvedAssembly, host: str | None = None, sim: bool | None = None
) -> HostPlan:
    """The processes ``host`` runs for ``assembly``.

    Args:
        assembly: The resolved assembly.
        host: The computer (default: :func:`this_host`).
        sim: Force simulation on (True) or off (False); default: simulate when off-robot.
    """
    host = host or this_host()
    robot_hosts = {m.host for m in assembly.modules}
    off_robot = host not in robot_hosts
    simulated = off_robot if sim is None else sim
    planned = list(assembly.components) if off_robot else assembly.components_on(host)
    # One simulated world per assembly: two would both answer every module's motor topics.
    runs_simulator = simulated and (off_robot or host == assembly.modules[0].host)
    plan = HostPlan(host=host, simulated=simulated, off_robot=off_robot)
    groups: dict[str, list[ComponentRun]] = {}
    for component in planned:
        if simulated and kinds.replaced_in_simulation(component.kind):
            continue  # the simulator stands in for every motor interface
        if not buildable(component.kind):
            plan.not_built.append((component.name, component.kind))
            continue
        # One process per module; a ground station's components, one per role (kind), or
        # one each for a kind that asks for it (an operator's script fails alone).
        group = component.module or f"{component.name.split('/')[0]}_{component.kind}"
        if kinds.get(component.kind).own_process:
            group = component.name.replace("/", "_")
        elif component.module and kinds.get(component.kind).placement is not kinds.Placement.MODULE:
            # A station kind on a module's computer (its own recorder) stays out of the
            # module's process: its I/O never shares an interpreter with the safety path.
            group = f"{component.module}_{component.kind}"
        groups.setdefault(group, []).append(
            _run(component.name, component.kind, component.namespace)
        )
    if runs_simulator:
        stand_ins: dict[str, list[ComponentRun]] = {}
        for kind in kinds.simulators():
            if buildable(kind.name):
                run = _run(kind.component_name, kind.name, kind.namespace)
                stand_ins.setdefault(kind.namespace.strip("/"), []).append(run)
            else:
                plan.not_built.append((kind.component_name, kind.name))
        groups = {**stand_ins, **groups}
    plan.processes = [ProcessPlan(name, tuple(runs)) for name, runs in groups.items()]
    return plan
