"""Who may say what: the role of every input, declared once, and everything derived from it.

Every input of an interface (each ``Subscribe`` and ``Serve`` of an
:class:`~components.executor.interface.InterfaceSpec`, and the inputs a whole robot has, such
as its ``cmd_vel``) declares its :class:`Role`. What each role means is one
:class:`RoleRule` in :data:`RULES`, and every place that once listed topic names by hand asks
this module instead:

- the routers' access control (:func:`msctl.net.acl.guarded_inputs`): which computers and
  identities may write each input;
- the runtime check of who published (the publisher's GID against the graph's tokens,
  :class:`~components.comm.topics.Subscription`'s ``senders``): raw motor commands only from
  the module's own joint manager, feedback only from its own motor interface (or what stands
  in for it in simulation), commands only from the module's claim holder
  (:func:`bind`, which the builders of the components with such inputs call: joint manager,
  motor interface, kinematics manager; the simulator asks :func:`senders` per module);
- ``msctl bag play``'s refusals (:func:`role_of`, :func:`moves`): a recording never drives,
  stops or speaks for a running robot's motors unless asked (commands) or remapped away
  (feedback, raw commands); the bridge's exclusion
  (:func:`components.bridge.core.refused_into_msctl`): a ROS node never speaks for them;
- ``msctl doctor``'s check that nothing but the declared senders publishes a module's raw
  commands and feedback (:func:`intruders`).

A topic two interfaces declare differently (``joint_states``: feedback for the joint manager,
telemetry for the health monitor) takes the stricter role (:attr:`RoleRule.rank`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from enum import Enum
from typing import TYPE_CHECKING, Any

from components.errors import ConfigError

if TYPE_CHECKING:
    from components.claim_guard import ClaimRule
    from components.executor.interface import InterfaceSpec


class Role(Enum):
    """What an input is, and so who may write it."""

    COMMAND = "command"  #: moves the module: operators and the claim holder (and relays)
    RAW = "raw_command"  #: motor level: the module's own joint manager, on its own computer
    FEEDBACK = "feedback"  #: the motors' readings: the module's own motor interface
    HALT = "halt"  #: stops the module: its computer and operators, never blocked by a claim
    CONTROL = "control"  #: a request that changes its state (recover): its computer, operators
    TELEMETRY = "telemetry"  #: data it reads: whoever publishes it
    QUERY = "query"  #: a question it answers (its joints): anyone in the fleet may ask


@dataclass(frozen=True)
class RoleRule:
    """What a role means to each place that enforces it.

    Attributes:
        who: Who may write it, in words (errors and ``msctl net config --explain``).
        rank: The stricter of two roles declared for one topic wins (higher is stricter).
        hosts: Computers the routers let write it: ``module`` (the module's own),
            ``publishers`` (those running a component that publishes it),
            ``publishers_or_module`` (those, else the module's own), ``""`` (not guarded:
            anyone in the fleet).
        operators: Operator identities (and ground stations forwarding them) may write it.
        stations: Ground-station computers may write it on their own account.
        own_senders: At run time, only the module's own components that declare the
            topic as their output (and what stands in for them in simulation) are taken:
            the joint manager for raw commands, the motor interface for feedback.
        claimed: Kept on the module's claim holder at run time (:mod:`components.claims`).
        moves: It drives, stops, or speaks for a robot's motors: ``bag play`` refuses it
            onto a running assembly and the bridge's ``--all`` never carries it from ROS.
    """

    who: str
    rank: int
    hosts: str
    operators: bool = False
    stations: bool = False
    own_senders: bool = False
    claimed: bool = False
    moves: bool = False


#: Every role's rule: the one table the access control, the sender checks, claims, ``bag
#: play``, the bridge and ``doctor`` read.
RULES: dict[Role, RoleRule] = {
    Role.RAW: RoleRule(
        "the module's own joint manager, on the module's computer",
        rank=6,
        hosts="module",
        own_senders=True,
        moves=True,
    ),
    Role.FEEDBACK: RoleRule(
        "the module's own motor interface (the simulator in simulation)",
        rank=5,
        hosts="module",
        own_senders=True,
        moves=True,
    ),
    Role.HALT: RoleRule(
        "the module's computer and operators", rank=4, hosts="module", operators=True, moves=True
    ),
    Role.COMMAND: RoleRule(
        "operators holding the module's claim (and the components relaying them)",
        rank=3,
        hosts="publishers",
        operators=True,
        stations=True,
        claimed=True,
        moves=True,
    ),
    Role.CONTROL: RoleRule(
        "the module's computer and operators", rank=2, hosts="module", operators=True, moves=True
    ),
    Role.TELEMETRY: RoleRule("whoever publishes it", rank=1, hosts="publishers_or_module"),
    Role.QUERY: RoleRule("anyone in the fleet", rank=0, hosts=""),
}


class RoleError(ConfigError):
    """An input declared without a role (or with something that is not a :class:`Role`)."""


def rule(role: Role) -> RoleRule:
    """The rule of ``role``."""
    return RULES[role]


def stricter(a: Role | None, b: Role | None) -> Role | None:
    """The stricter of two roles (either may be ``None``: undeclared)."""
    if a is None or b is None:
        return a or b
    return a if RULES[a].rank >= RULES[b].rank else b


# --------------------------------------------------------------------------- declarations
def inputs(spec: InterfaceSpec, extra_serve: Iterable[Any] = ()) -> list[tuple[str, Any]]:
    """Every input of ``spec`` (and of services a core added), as ``(name, declaration)``."""
    out: list[tuple[str, Any]] = [(s.topic, s) for s in spec.subscribe]
    out += [(s.service, s) for s in (*spec.serve, *extra_serve)]
    return out


def undeclared(spec: InterfaceSpec, extra_serve: Iterable[Any] = ()) -> list[str]:
    """The inputs of ``spec`` whose role is missing or not a :class:`Role`."""
    return [name for name, d in inputs(spec, extra_serve) if not isinstance(d.role, Role)]


def check_declared(owner: str, spec: InterfaceSpec, extra_serve: Iterable[Any] = ()) -> None:
    """Refuse an interface with an input of no role.

    Raises:
        RoleError: Naming ``owner`` (a kind, a component), the inputs, and the roles.
    """
    missing = undeclared(spec, extra_serve)
    if missing:
        raise RoleError(
            f"{owner}: input(s) {', '.join(missing)} declare no role; give each one "
            f"role=Role.<{'|'.join(r.name for r in Role)}> (components.roles)"
        )


def _static_specs() -> list[tuple[str, InterfaceSpec]]:
    """Every registered kind's interface that is declared as data (not made per assembly)."""
    from components import kinds
    from components.executor.interface import InterfaceSpec

    out = []
    for kind in kinds.registry().values():
        spec = kinds.resolve(kind.interface) if kind.interface else None
        if isinstance(spec, InterfaceSpec):
            out.append((kind.name, spec))
    return out


def extension_inputs(kind: str) -> dict[str, Role]:
    """Inputs the registered injections of ``kind`` may add (default names), by role."""
    from components.executor import registry as extensions

    return extensions.declared_inputs(kind)


def robot_inputs() -> dict[str, Role]:
    """Inputs a whole robot has, relative to its namespace (its ``cmd_vel``)."""
    from components.robots import ROBOT_INPUTS

    return dict(ROBOT_INPUTS)


def declared_names() -> dict[str, Role]:
    """Every input name the registered kinds, their injections and robots declare (relative
    to a module's or robot's namespace, ``motors/halt``), each with its strictest role.

    Raises:
        RoleError: If a registered kind's interface has an input of no role.
    """
    names: dict[str, Role] = {}

    def add(name: str, role: Role | None) -> None:
        if role is not None and not name.startswith("~"):
            names[name.strip("/")] = stricter(names.get(name.strip("/")), role)  # type: ignore[assignment]

    for kind, spec in _static_specs():
        check_declared(f"component kind {kind}", spec)
        for name, declaration in inputs(spec):
            add(name, declaration.role)
        for name, role in extension_inputs(kind).items():
            add(name, role)
    for name, role in robot_inputs().items():
        add(name, role)
    return names


def role_of(topic: str, names: Mapping[str, Role] | None = None) -> Role | None:
    """The role of a fully qualified topic or service, by the declared names it ends with
    (``/limb1/motors/halt`` ends with ``motors/halt``: raw); ``None`` when none is declared.

    Without an assembly this is what a name can tell: a topic named like a module's input
    is taken as one, whatever namespace it is in (a bag may come from another assembly).
    """
    names = declared_names() if names is None else names
    parts = [p for p in topic.split("/") if p]
    found: Role | None = None
    for start in range(len(parts)):
        found = stricter(found, names.get("/".join(parts[start:])))
    return found


def moves(role: Role | None) -> bool:
    """Whether an input of ``role`` drives, stops or speaks for a robot's motors."""
    return role is not None and RULES[role].moves


# --------------------------------------------------------------------------- an assembly
@dataclass(frozen=True)
class ModuleInput:
    """One input of an assembly, fully qualified.

    Attributes:
        topic: Its name (``/limb1/joint_set``).
        name: As its interface declares it (``joint_set``, relative to the module).
        role: Its (strictest) role.
        module: The module it belongs to (``None``: a robot's, such as ``/cmd_vel``).
        host: The computer of that module (of the robot's root module for a robot's).
    """

    topic: str
    name: str
    role: Role
    module: str | None
    host: str


def assembly_inputs(assembly: Any) -> dict[str, ModuleInput]:
    """Every input of every module of ``assembly`` (its module-placed components', the
    inputs what stands in for them in simulation serves on every module, their injections'),
    and every robot's own inputs (``cmd_vel`` of a mobile robot), by topic.

    Raises:
        RoleError: If a registered kind's interface has an input of no role.
    """
    from components import kinds
    from components.executor.interface import InterfaceSpec

    found: dict[str, ModuleInput] = {}
    module_host = {m.slot: m.host for m in assembly.modules}
    namespaces = {m.slot: m.namespace.rstrip("/") for m in assembly.modules}

    def add(name: str, role: Role | None, slot: str | None, host: str, base: str) -> None:
        if role is None or name.startswith("~"):
            return
        topic = qualify(name, base)
        old = found.get(topic)
        role = stricter(old.role if old else None, role)  # type: ignore[assignment]
        found[topic] = ModuleInput(topic, name, role, slot if old is None else old.module, host)

    for component in assembly.components:
        kind = kinds.get(component.kind)
        spec = kinds.resolve(kind.interface) if kind.interface else None
        if not isinstance(spec, InterfaceSpec) or component.module is None:
            continue  # station kinds read across modules; their inputs are their own
        slot = component.module
        check_declared(f"component kind {kind.name}", spec)
        for name, declaration in inputs(spec):
            add(name, declaration.role, slot, module_host[slot], namespaces[slot])
        for name, role in extension_inputs(kind.name).items():
            add(name, role, slot, module_host[slot], namespaces[slot])
    # What a stand-in (the simulator) serves exists on every module, bus or no bus.
    for kind in kinds.registry().values():
        if not kinds.stand_ins(kind.name) or not kind.interface:
            continue
        spec = kinds.resolve(kind.interface)
        if isinstance(spec, InterfaceSpec):
            check_declared(f"component kind {kind.name}", spec)
            for slot, base in namespaces.items():
                for name, declaration in inputs(spec):
                    add(name, declaration.role, slot, module_host[slot], base)
    from components.robots import robot_inputs_of

    for topic, (role, root) in robot_inputs_of(assembly).items():
        add(topic, role, None, module_host.get(root, ""), "")
    return found


def senders(role: Role | None, assembly: Any, slot: str, name: str) -> tuple[str, ...] | None:
    """The only nodes input ``name`` of ``role`` of module ``slot`` takes samples from at
    run time (fully qualified), or ``None``: anyone (commands are kept on claim holders).

    For a role with :attr:`RoleRule.own_senders`, the module's components whose kind's
    interface declares ``name`` as an output (the joint manager writes ``joint_commands``,
    the motor interface ``joint_states``), and the assembly-wide kinds standing in for those
    kinds in simulation (the simulator serves every module's motors): a sender that is not
    running never publishes, so naming both is safe.
    """
    if role is None or not RULES[role].own_senders:
        return None
    from components import kinds
    from components.build import node_name
    from components.executor.interface import InterfaceSpec

    namespace = assembly.module(slot).namespace.rstrip("/")
    if name.startswith(f"{namespace}/"):
        name = name[len(namespace) + 1 :]  # as the module's interfaces declare it
    writers = []
    for kind in kinds.registry().values():
        spec = kinds.resolve(kind.interface) if kind.interface else None
        if isinstance(spec, InterfaceSpec) and any(p.topic == name for p in spec.publish):
            writers.append(kind.name)
    nodes = [
        f"{plan.namespace.rstrip('/')}/{node_name(plan.name)}"
        for plan in assembly.components
        if plan.kind in writers and plan.module == slot
    ]
    if not nodes:
        # Not planned (a bare test assembly): the names they would run under.
        nodes += [f"{namespace}/{writer}" for writer in writers]
    for writer in writers:
        nodes += [f"/{stand_in.component_name}" for stand_in in kinds.stand_ins(writer)]
    return tuple(dict.fromkeys(nodes))


def command_rule(assembly: Any, slot: str, *more: str) -> ClaimRule:
    """The claim rule of module ``slot``'s command inputs, from the resolved assembly (with
    ``more`` modules: of an input that moves them all, such as the steering's ``cmd_vel``).

    Relays are the planned components of kinds marked ``claim_relay`` in the kind registry:
    those of the modules themselves, and those of ground stations (they command any module).
    """
    from components import kinds
    from components.build import node_name
    from components.claim_guard import ClaimRule

    modules = (slot, *more)
    relays = []
    for plan in assembly.components:
        entry = kinds.registry().get(plan.kind)
        if (
            entry is None
            or not entry.claim_relay
            or not (plan.module is None or plan.module in modules)
        ):
            continue
        relays.append(f"{plan.namespace.rstrip('/')}/{node_name(plan.name)}")
    return ClaimRule(slot, tuple(relays), required=assembly.claims == "required", also=more)


def bind(spec: InterfaceSpec, assembly: Any, slot: str) -> InterfaceSpec:
    """``spec`` of a component of module ``slot``, with each input's run-time rule from its
    role: raw commands and feedback only from their senders (:func:`senders`), commands
    only from the module's claim holder (:func:`command_rule`).

    Raises:
        RoleError: If an input declares no role.
    """
    check_declared(f"{slot}'s interface", spec)
    subscribe = []
    for sub in spec.subscribe:
        role = sub.role
        if RULES[role].claimed:
            sub = dataclasses.replace(sub, claim=command_rule(assembly, slot))
        nodes = senders(role, assembly, slot, sub.topic)
        if nodes is not None:
            sub = dataclasses.replace(sub, senders=nodes)
        subscribe.append(sub)
    return dataclasses.replace(spec, subscribe=tuple(subscribe))


def qualify(name: str, base: str) -> str:
    """``name`` under namespace ``base`` (``/limb1``), unless already absolute."""
    return name if name.startswith("/") else f"{base}/{name}"


# --------------------------------------------------------------------------- the live graph
@dataclass(frozen=True)
class Intruder:
    """A publisher on an input its role does not let it write.

    Attributes:
        topic: The input.
        role: Its role.
        node: The publishing node.
        allowed: The nodes that may.
    """

    topic: str
    role: Role
    node: str
    allowed: tuple[str, ...]


def intruders(assembly: Any, publishers: Mapping[str, Iterable[str]]) -> list[Intruder]:
    """Publishers on the assembly's sender-checked inputs that the roles do not allow.

    Args:
        assembly: The resolved assembly.
        publishers: Topic -> fully qualified nodes publishing it (from the graph).
    """
    out = []
    for topic, found in sorted(assembly_inputs(assembly).items()):
        if found.module is None:
            continue
        allowed = senders(found.role, assembly, found.module, found.name)
        if allowed is None:
            continue
        for node in sorted(set(publishers.get(topic, ()))):
            if node not in allowed:
                out.append(Intruder(topic, found.role, node, allowed))
    return out
