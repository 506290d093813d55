"""Who may write what: a router's access control, derived from the component interfaces.

Every router enforces at its edge, on ingress, by the identity of the link a message comes in
on: components of its own computer reach it over plain TCP on loopback (subject ``local``),
other computers and operators over mutual TLS (subject = the certificate's common name).

The guarded inputs are every input of every module (its module-placed components' topics
and services, what stands in for them in simulation, their injections') and every robot's
own (``cmd_vel``), each with the role its interface declares (:mod:`components.roles`).
Who may write each one follows from the role alone:

- raw motor commands (``joint_commands``, ``motors/...``, ``rezero``) and feedback
  (``joint_states``): only the module's own computer;
- halts and control requests (``halt``, ``recover``): the module's computer and operators;
- commands (``joint_set``, ``ik_target``, ``cmd_vel``): operators and ground stations, plus
  whichever computer runs a component whose interface publishes it (the module's own
  kinematics manager writes ``joint_set``);
- telemetry: the computers whose components publish it, else the module's computer;
- questions (``joints``): anyone in the fleet (a read);
- supervisor and agent requests (``/msctl/...``): only operators.

A ground station's router forwards its operators' commands, so a robot's router also takes
operator-only traffic from ground-station links (the station checked the operator at its own
edge). Reads (subscriptions, liveliness, replies) are open to the whole fleet; a link that
matches no subject (no certificate from the fleet CA) is denied everything.

Zenoh applies an explicit ``deny`` before any ``allow``; the rules allow the fleet broadly and
deny each guarded key to every subject not allowed to write it.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from components.assembly import ResolvedAssembly

#: Subject id of this computer's own components (plain TCP on loopback).
LOCAL = "local"
#: Subject id of every operator identity.
OPERATORS = "operators"
#: Subject id of the ROS enclaves with an identity from the fleet CA.
ROS_ENCLAVES = "ros_enclaves"
#: Messages a writer sends.
WRITES = ["put", "delete", "query"]
#: Messages any member of the fleet may send: reading, serving, liveliness.
READS = [
    "declare_subscriber",
    "declare_queryable",
    "reply",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
]
ALL_MESSAGES = WRITES + READS


@dataclass(frozen=True)
class GuardedInput:
    """One input somebody must be allowed to write.

    Attributes:
        topic: Its fully qualified name (``/limb1/joint_set``).
        hosts: Computers allowed to write it.
        operators: Whether operators (and ground stations forwarding them) may.
        stations: Whether ground-station computers may, on their own account.
        why: The rule it follows, for ``msctl net config --explain`` and tests.
    """

    topic: str
    hosts: frozenset[str]
    operators: bool = False
    stations: bool = False
    why: str = ""


@dataclass
class FleetPrincipals:
    """The identities an ACL names.

    Attributes:
        robots: Robot computers (host names).
        stations: Ground-station computers.
        operators: Operator common names (``operator:alice``), revoked ones left out.
        enclaves: ROS enclaves (``/field/viewer``) with an identity from the fleet CA: they
            read and write like any member, never a guarded input.
        certificates: Name -> the CN of its current certificate (``robot1#9f3a01c2``),
            which a subject names: a certificate revoked or replaced has another CN and
            matches nobody. A name missing here is admitted by no certificate.
    """

    robots: list[str]
    stations: list[str]
    operators: list[str] = field(default_factory=list)
    enclaves: list[str] = field(default_factory=list)
    certificates: dict[str, str] = field(default_factory=dict)


def principals(
    assembly: ResolvedAssembly,
    operators: Iterable[str],
    enclaves: Iterable[str] = (),
    certificates: Mapping[str, str] | None = None,
) -> FleetPrincipals:
    """Robot and station computers from the assembly, operators, enclaves and the CN of
    each one's certificate as given."""
    robots = [h for h, role in assembly.lock.host_plans.items() if role.role == "robot"]
    stations = [h for h, role in assembly.lock.host_plans.items() if role.role == "ground"]
    for host in assembly.hosts:
        if host not in robots and host not in stations:
            robots.append(host)
    return FleetPrincipals(
        robots, stations, sorted(operators), sorted(enclaves), dict(certificates or {})
    )


def guarded_inputs(assembly: ResolvedAssembly) -> list[GuardedInput]:
    """Every input of every module, with who may write it, from its declared role (see the
    module docstring and :data:`components.roles.RULES`)."""
    from components import kinds
    from components.executor.interface import InterfaceSpec
    from components.roles import RULES, assembly_inputs, qualify

    publishers: dict[str, set[str]] = {}
    namespaces = {m.slot: m.namespace.rstrip("/") for m in assembly.modules}
    for component in assembly.components:
        kind = kinds.get(component.kind)
        spec = kinds.resolve(kind.interface) if kind.interface else None
        if not isinstance(spec, InterfaceSpec) or component.module is None:
            continue
        for publish in spec.publish:
            topic = qualify(publish.topic, namespaces[component.module])
            publishers.setdefault(topic, set()).add(component.host)
    guarded = []
    for topic, found in sorted(assembly_inputs(assembly).items()):
        rule = RULES[found.role]
        if not rule.hosts:
            continue  # a question: anyone in the fleet may ask
        writers = publishers.get(topic, set())
        if rule.hosts == "module":
            hosts = {found.host}
        elif rule.hosts == "publishers":
            hosts = writers
        else:
            hosts = writers or {found.host}
        guarded.append(
            GuardedInput(
                topic,
                frozenset(hosts),
                operators=rule.operators,
                stations=rule.stations,
                why=f"{found.role.value}: {rule.who}",
            )
        )
    return guarded


def placed(guarded: list[GuardedInput], placement: Mapping[str, str]) -> list[GuardedInput]:
    """The same inputs, each writer computer replaced by the one that actually runs its part.

    Args:
        guarded: Inputs with writers where the template places the components.
        placement: Template computer -> the computer that runs its part (``msctl up``
            off-robot: every one of them -> this computer).
    """
    return [
        GuardedInput(
            g.topic, frozenset(placement.get(h, h) for h in g.hosts), g.operators, g.stations, g.why
        )
        for g in guarded
    ]


def placed_principals(fleet: FleetPrincipals, placement: Mapping[str, str]) -> FleetPrincipals:
    """The computers of ``fleet`` where ``placement`` runs them: a computer that runs robot
    parts is a robot computer, and a station is left a station only if it runs no robot part
    (its ACL then follows the robot rules: its own components write the modules' inputs)."""
    robots = list(dict.fromkeys(placement.get(h, h) for h in fleet.robots))
    stations = [
        s for s in dict.fromkeys(placement.get(h, h) for h in fleet.stations) if s not in robots
    ]
    return FleetPrincipals(
        robots, stations, list(fleet.operators), list(fleet.enclaves), dict(fleet.certificates)
    )


def key_expr(topic: str, domain: int) -> str:
    """The key expression covering a topic's or service's data keys (every type, hash)."""
    return f"{domain}/{topic.strip('/')}/**"


def router_acl(
    host: str, fleet: FleetPrincipals, guarded: list[GuardedInput], domain: int = 0
) -> dict[str, Any]:
    """The ``access_control`` block of ``host``'s router."""
    station_router = host in fleet.stations
    subjects: list[dict[str, Any]] = [{"id": LOCAL, "link_protocols": ["tcp"]}]

    def certified(names: Iterable[str]) -> list[str]:
        # By certificate, never by name: an empty list would leave the subject matching
        # any link, so a subject nobody's certificate names is left out instead.
        return [fleet.certificates[n] for n in names if n in fleet.certificates]

    for other in [*fleet.robots, *fleet.stations]:
        if other != host and certified([other]):
            subjects.append({"id": _host_subject(other), "cert_common_names": certified([other])})
    if certified(fleet.operators):
        subjects.append({"id": OPERATORS, "cert_common_names": certified(fleet.operators)})
    if certified(fleet.enclaves):
        subjects.append({"id": ROS_ENCLAVES, "cert_common_names": certified(fleet.enclaves)})
    every = [s["id"] for s in subjects]

    def subject_of(name: str) -> str:
        return LOCAL if name == host else _host_subject(name)

    def allowed(entry: GuardedInput) -> set[str]:
        ids = {subject_of(h) for h in entry.hosts}
        if entry.operators and fleet.operators:
            ids.add(OPERATORS)
        if entry.stations or (entry.operators and not station_router):
            # On a robot router, station links carry the operators the station let in.
            ids.update(subject_of(s) for s in fleet.stations)
        return ids & set(every)

    rules: list[dict[str, Any]] = [
        {
            "id": "fleet-egress",
            "permission": "allow",
            "flows": ["egress"],
            "messages": ALL_MESSAGES,
            "key_exprs": ["**", "@ros2_lv/**", "@msctl/**"],
        },
        {
            "id": "fleet-reads",
            "permission": "allow",
            "flows": ["ingress"],
            "messages": READS,
            "key_exprs": ["**", "@ros2_lv/**", "@msctl/**"],
        },
        {
            "id": "fleet-writes",
            "permission": "allow",
            "flows": ["ingress"],
            "messages": WRITES,
            "key_exprs": [f"{domain}/**"],
        },
    ]
    policies: list[dict[str, Any]] = [{"rules": [r["id"] for r in rules], "subjects": every}]
    # One deny rule per set of excluded subjects keeps the block small: dragon's dozens of
    # inputs fall into a handful of groups.
    groups: dict[tuple[str, ...], list[str]] = {}
    for entry in guarded:
        denied = tuple(s for s in every if s not in allowed(entry))
        if denied:
            groups.setdefault(denied, []).append(key_expr(entry.topic, domain))
    requests = (OPERATORS,) if station_router else (OPERATORS, *map(subject_of, fleet.stations))
    request_denied = tuple(s for s in every if s not in requests)
    if request_denied:
        groups.setdefault(request_denied, []).append(f"{domain}/msctl/**")
    for index, (denied, keys) in enumerate(sorted(groups.items())):
        rule_id = f"guarded-{index}"
        rules.append(
            {
                "id": rule_id,
                "permission": "deny",
                "flows": ["ingress"],
                "messages": WRITES,
                "key_exprs": sorted(keys),
            }
        )
        policies.append({"rules": [rule_id], "subjects": list(denied)})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def _host_subject(host: str) -> str:
    return f"host:{host}"
