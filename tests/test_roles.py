"""Each input's role, declared once (issue 32, item 2), and what is derived from it.

Every input of every registered kind declares its role; every declared handler exists on the
core it is bound to; an input without a role is refused wherever the roles are read; and the
access control, the sender checks, claims, ``bag play`` and the bridge all read the same
roles (no list of topic names elsewhere). The last tests run real Zenoh sessions on a loopback
router: a joint manager built from the assembly takes ``joint_states`` from its own module's
motor interface only, and drops and counts the others.
"""

from __future__ import annotations

import dataclasses
import re
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import quick_peer_settings, quick_router, resolved_assembly, wait_until

from components import kinds
from components.assembly import ResolvedAssembly
from components.build import build_component, simulator_plan
from components.comm.node import Node
from components.comm.qos import SENSOR
from components.comm.session import SessionSettings, open_session
from components.comm.stats import drops
from components.comm.topics import INTRUDER
from components.executor.executor import Executor
from components.executor.interface import InterfaceSpec, Subscribe
from components.joint_manager.interface import JOINT_MANAGER
from components.messages import JOINT_STATE, JointSample, joint_state
from components.roles import (
    RULES,
    Role,
    RoleError,
    assembly_inputs,
    bind,
    declared_names,
    intruders,
    role_of,
    senders,
)

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def dragon(tmp_path_factory: pytest.TempPathFactory) -> ResolvedAssembly:
    return resolved_assembly(tmp_path_factory.mktemp("roles"), "dragon")


def built_components(assembly: ResolvedAssembly) -> Iterator[Any]:
    """Every component of the assembly that builds without hardware, and the simulator
    standing in for the motor interfaces (closed by the caller)."""
    for plan in assembly.components:
        if kinds.replaced_in_simulation(plan.kind):
            continue  # needs its bus; the simulator serves the same interface
        yield plan.kind, build_component(plan, assembly, {"sim": True})
    for kind in kinds.simulators():
        yield kind.name, build_component(simulator_plan(kind.name), assembly, {"sim": True})


def test_every_input_of_every_kind_declares_a_role_and_every_handler_exists(
    dragon: ResolvedAssembly,
) -> None:
    # The kinds whose interface is data: checked on the declaration itself.
    static = 0
    for kind in kinds.registry().values():
        spec = kinds.resolve(kind.interface) if kind.interface else None
        if isinstance(spec, InterfaceSpec):
            static += 1
            for sub in spec.subscribe:
                assert isinstance(sub.role, Role), (kind.name, sub.topic)
            for serve in spec.serve:
                assert isinstance(serve.role, Role), (kind.name, serve.service)
    assert static >= 4
    # Every component as built (interfaces made per assembly, injections' services too):
    # each input has a role and each handler is a method of the core it is bound to.
    seen: set[str] = set()
    for kind, built in built_components(dragon):
        try:
            seen.add(kind)
            spec = built.spec
            extra = list(getattr(built.core, "extra_serve", ()))
            for name, role, handler in (
                *((s.topic, s.role, s.handler) for s in spec.subscribe),
                *((s.service, s.role, s.handler) for s in (*spec.serve, *extra)),
            ):
                assert isinstance(role, Role), f"{kind}: {name} declares no role"
                assert callable(getattr(built.core, handler, None)), f"{kind}: no {handler}"
            for every in spec.every:
                assert callable(getattr(built.core, every.handler, None)), (kind, every.handler)
        finally:
            built.close()
    assert {"joint_manager", "kinematics_manager", "health_monitor", "simulator"} <= seen


def test_an_input_without_a_role_is_refused_naming_it(dragon: ResolvedAssembly) -> None:
    sneaked = dataclasses.replace(
        JOINT_MANAGER,
        subscribe=(*JOINT_MANAGER.subscribe, Subscribe("joint_goal", JOINT_STATE, "on_joint_set")),
    )
    with pytest.raises(RoleError, match=r"limb1's interface: input\(s\) joint_goal declare no"):
        bind(sneaked, dragon, "limb1")


def test_the_names_and_the_assembly_inputs_come_from_the_declarations(
    dragon: ResolvedAssembly,
) -> None:
    names = declared_names()
    assert names["joint_set"] is Role.COMMAND and names["ik_target"] is Role.COMMAND
    assert names["cmd_vel"] is Role.COMMAND  # a robot's own input
    assert names["joint_commands"] is Role.RAW and names["motors/halt"] is Role.RAW
    assert names["rezero"] is Role.RAW  # declared by its injection
    # Declared twice (feedback to the joint manager, telemetry to the health monitor): the
    # stricter wins.
    assert names["joint_states"] is Role.FEEDBACK
    assert names["halt"] is Role.HALT and names["recover"] is Role.CONTROL
    assert names["joint_read"] is Role.TELEMETRY and names["joints"] is Role.QUERY
    assert role_of("/limb1/motors/halt") is Role.RAW
    assert role_of("/limb1/joint_reed") is None
    assert role_of("/some/other/robot/joint_states") is Role.FEEDBACK
    found = assembly_inputs(dragon)
    assert found["/limb1/joint_states"].role is Role.FEEDBACK
    assert found["/limb1/joint_states"].host == "hl-limb-01"
    assert found["/wheel2/joint_commands"].role is Role.RAW
    assert found["/cmd_vel"].role is Role.COMMAND and found["/cmd_vel"].module is None
    assert "/gc1/data_monitor/alarms" not in found  # private names are the node's own


def test_the_senders_and_claims_come_from_the_roles(dragon: ResolvedAssembly) -> None:
    assert senders(Role.FEEDBACK, dragon, "limb1", "joint_states") == (
        "/limb1/motor_interface",
        "/sim/simulator",
    )
    assert senders(Role.RAW, dragon, "wheel1", "/wheel1/joint_commands") == (
        "/wheel1/joint_manager",
    )
    assert senders(Role.COMMAND, dragon, "limb1", "joint_set") is None
    bound = {s.topic: s for s in bind(JOINT_MANAGER, dragon, "limb1").subscribe}
    assert bound["joint_states"].senders == ("/limb1/motor_interface", "/sim/simulator")
    assert bound["joint_set"].claim is not None and bound["joint_set"].senders is None
    assert bound["joint_set"].claim.relays == ("/limb1/kinematics_manager",)
    # Every rule is complete: who may write it, said in words.
    assert all(rule.who for rule in RULES.values())


def test_the_access_control_guards_every_declared_input_by_its_role(
    dragon: ResolvedAssembly,
) -> None:
    from msctl.net.acl import guarded_inputs

    guarded = {g.topic: g for g in guarded_inputs(dragon)}
    raw = guarded["/limb1/joint_commands"]
    assert raw.hosts == {"hl-limb-01"} and not raw.operators and not raw.stations
    feedback = guarded["/limb1/joint_states"]
    assert feedback.hosts == {"hl-limb-01"} and not feedback.operators
    command = guarded["/limb1/joint_set"]
    assert command.operators and command.stations and command.hosts == {"hl-limb-01"}
    assert guarded["/cmd_vel"].operators and not guarded["/cmd_vel"].hosts
    assert guarded["/limb1/halt"].operators and guarded["/limb1/halt"].hosts == {"hl-limb-01"}
    assert "/limb1/joints" not in guarded  # a question: anyone may ask
    # Everything the roles name, the access control guards (and nothing else).
    wanted = {t for t, i in assembly_inputs(dragon).items() if RULES[i.role].hosts}
    assert set(guarded) == wanted


def test_no_list_of_input_names_is_written_outside_the_declarations() -> None:
    # The places that once listed topics by hand now ask components.roles.
    for path in (
        "msctl/net/acl.py",
        "msctl/recorder/player.py",
        "components/bridge/core.py",
        "components/bridge/relay.py",
        "msctl/net/doctor.py",
    ):
        text = (REPO / path).read_text(encoding="utf-8")
        code = re.sub(r'"""(?:.|\n)*?"""|#[^\n]*', "", text)  # docstrings and comments
        for name in ("joint_commands", "joint_states", "ik_target", "motors/halt", "rezero"):
            assert f'"{name}"' not in code, (path, name)


# --------------------------------------------------------------------------- run time
@pytest.fixture(scope="module")
def router_endpoint() -> Iterator[str]:
    yield from quick_router()


@pytest.fixture(scope="module")
def session_settings(router_endpoint: str) -> SessionSettings:
    return quick_peer_settings(router_endpoint)


def test_a_joint_manager_takes_joint_states_from_its_own_motor_interface_only(
    dragon: ResolvedAssembly, session_settings: SessionSettings
) -> None:
    built = build_component(dragon.component("limb1/joint_manager"), dragon)
    executor = Executor(settings=session_settings)
    executor.add(built.core, built.spec, built.namespace, built.node_name)
    runner = threading.Thread(target=executor.run, daemon=True)
    runner.start()
    session = open_session(session_settings)
    motors = Node(session, "motor_interface", "/limb1")
    player = Node(session, "bag_play", "/")
    joint = dragon.module("limb1").actuated_joints[0]
    raw_name = joint.spec.name
    try:
        own = motors.publisher("joint_states", JOINT_STATE, SENSOR)
        foreign = player.publisher("/limb1/joint_states", JOINT_STATE, SENSOR)
        refused = drops.count("/limb1/joint_states", INTRUDER)

        def latest() -> float | None:
            sample = built.core.latest(raw_name)
            return None if sample is None else sample.position

        def send(publisher: Any, position: float) -> None:
            publisher.publish(joint_state([JointSample(raw_name, position, 0.0, 0.0)]))

        raw = joint.calibration.to_raw(0.1)
        wait_until(
            lambda: send(own, raw) or (latest() is not None and abs(latest() - 0.1) < 1e-6),
            30.0,
            "the motor interface's joint_states taken",
        )
        # A recording replayed onto the live module (another node): dropped and counted.
        wait_until(
            lambda: (
                send(foreign, joint.calibration.to_raw(0.5))
                or drops.count("/limb1/joint_states", INTRUDER) >= refused + 5
            ),
            30.0,
            "the foreign joint_states refused",
        )
        assert abs(latest() - 0.1) < 1e-6
    finally:
        motors.close()
        player.close()
        session.close()
        executor.stop()
        runner.join(timeout=10.0)
        built.close()


def test_intruders_are_named_from_the_graph_by_role(dragon: ResolvedAssembly) -> None:
    publishers = {
        "/limb1/joint_states": ["/limb1/motor_interface", "/bag_play"],
        "/limb1/joint_commands": ["/limb1/joint_manager"],
        "/limb1/joint_set": ["/ground1/teleop"],  # a command: claims decide, not the graph
    }
    found = intruders(dragon, publishers)
    assert [(i.topic, i.node, i.role) for i in found] == [
        ("/limb1/joint_states", "/bag_play", Role.FEEDBACK)
    ]


def test_doctor_names_a_publisher_the_roles_do_not_allow(
    dragon: ResolvedAssembly, session_settings: SessionSettings
) -> None:
    from msctl.net import doctor

    session = open_session(session_settings)
    motors = Node(session, "motor_interface", "/limb1")
    stray = Node(session, "bag_play", "/")
    try:
        motors.publisher("joint_states", JOINT_STATE, SENSOR)

        def seen_ok() -> Any:
            finding = doctor.senders("here", session, dragon)
            return finding if finding.status == doctor.OK else None

        assert "only their own components" in wait_until(seen_ok, 30.0, "senders OK").detail
        stray.publisher("/limb1/joint_states", JOINT_STATE, SENSOR)

        def seen_stray() -> Any:
            finding = doctor.senders("here", session, dragon)
            return finding if finding.status == doctor.WARN else None

        finding = wait_until(seen_stray, 30.0, "the stray publisher named")
        assert finding.detail.startswith(
            "/bag_play publishes /limb1/joint_states (feedback: only /limb1/motor_interface, "
            "/sim/simulator may)"
        ), finding.detail
    finally:
        motors.close()
        stray.close()
        session.close()
