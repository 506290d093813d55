"""Claims (issue 12, part 2): liveliness tokens saying who drives which module.

Real Zenoh sessions on a loopback router (random port, no multicast), each operator on its
own session as it would be in its own process; then two real operator processes. Every
session is closed at teardown; events are awaited, never slept for.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import logging
import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import quick_peer_settings, quick_router, resolved_assembly, wait_until

from components.claim_guard import NOT_HOLDER, UNCLAIMED, ClaimRule
from components.claims import (
    ClaimInfo,
    ClaimRefused,
    Claims,
    UnknownModuleError,
    claim_key,
    default_holder,
    holder_of,
    parse_claim,
)
from components.comm import Node, drops
from components.comm.session import SessionSettings
from components.executor.core import Core
from components.executor.executor import Executor
from components.executor.interface import InterfaceSpec, Subscribe
from components.messages import JOINT_STATE, JointSample, joint_samples, joint_state

ROOT = Path(__file__).resolve().parents[1]
MODULES = ("limb1", "limb2", "wheel1", "wheel2")


@pytest.fixture
def router_endpoint() -> Iterator[str]:
    """Overrides conftest's: the same real router, without the 0.5 s opening wait."""
    yield from quick_router()


@pytest.fixture
def session_settings(router_endpoint: str) -> SessionSettings:
    """Overrides conftest's: peers that open at once (claims are awaited anyway)."""
    return quick_peer_settings(router_endpoint)


class Operator:
    """One operator: its own session, node and claims watcher."""

    def __init__(self, session: Any, name: str, holder: str) -> None:
        # Quick-opening sessions connect a moment after opening: an operator starts once
        # it reaches the router, as a real one does (msctl waits for its router link).
        wait_until(lambda: list(session.info.routers_zid()), what="the router link")
        self.node = Node(session, name, "/ground1")
        self.claims = Claims(session, 0, MODULES)
        self.holder = holder
        self.changes: list[tuple[str, ClaimInfo | None]] = []
        self.claims.on_change(lambda module, info: self.changes.append((module, info)))

    def claim(self, module: str, take: bool = False) -> Any:
        return self.claims.claim(module, self.holder, self.node, take=take)

    def close(self) -> None:
        self.claims.close()
        self.node.close()


@pytest.fixture
def operators(open_sessions) -> Iterator[Any]:
    made: list[Operator] = []

    def make(name: str, holder: str) -> Operator:
        operator = Operator(open_sessions(), name, holder)
        made.append(operator)
        return operator

    try:
        yield make
    finally:
        for operator in reversed(made):
            operator.close()


# --------------------------------------------------------------------------- pure parts


def test_a_claim_key_round_trips_and_foreign_keys_are_ignored() -> None:
    key = claim_key(3, "limb1", 1_700_000_000_123_456_789, "ana maria@lab/2", "z1", "/g/teleop")
    info = parse_claim(key)
    assert info is not None
    assert (info.module, info.holder, info.node, info.zid) == (
        "limb1",
        "ana maria@lab/2",
        "/g/teleop",
        "z1",
    )
    assert info.since_ns == 1_700_000_000_123_456_789
    assert len(key.split("/")) == 8  # one chunk per field
    assert parse_claim("@ros2_lv/0/z/1/2/NN/%/%/teleop") is None
    assert parse_claim(key.replace("limb1", "limb-1")) is None


def test_the_newest_claim_holds_the_module() -> None:
    older = parse_claim(claim_key(0, "limb1", 10, "a@x", "z1", "/a"))
    newer = parse_claim(claim_key(0, "limb1", 20, "b@y", "z2", "/b"))
    assert holder_of([older, newer]) == newer == holder_of([newer, older])
    assert holder_of([]) is None


def test_default_holder_is_user_at_this_host(monkeypatch) -> None:
    monkeypatch.setenv("MSCTL_HOST", "test-laptop")
    assert default_holder().endswith("@test-laptop")


# --------------------------------------------------------------------------- on the wire


def test_a_claim_is_seen_by_everyone_and_vanishes_when_released(operators) -> None:
    alice = operators("teleop_alice", "alice@laptop1")
    watcher = operators("watcher", "nobody@base")
    claim = alice.claim("limb1")
    assert alice.claims.holder("limb1") == claim.info  # at once on the claimer's side
    wait_until(lambda: watcher.claims.holder("limb1") == claim.info, what="the claim's token")
    info = watcher.claims.holder("limb1")
    assert (info.holder, info.node) == ("alice@laptop1", "/ground1/teleop_alice")
    assert watcher.changes[-1] == ("limb1", claim.info)
    claim.release()
    wait_until(lambda: watcher.claims.holder("limb1") is None, what="the release")
    assert watcher.changes[-1] == ("limb1", None)
    assert not claim.lost.is_set()


def test_a_claim_on_an_unknown_module_names_the_modules_that_exist(operators) -> None:
    alice = operators("teleop_alice", "alice@laptop1")
    with pytest.raises(UnknownModuleError) as caught:
        alice.claim("limb9")
    assert "limb9" in str(caught.value)
    assert "limb1, limb2, wheel1, wheel2" in str(caught.value)


def test_a_second_claim_is_refused_naming_the_holder_then_takes_over_and_the_first_is_told(
    operators,
) -> None:
    alice = operators("teleop_alice", "alice@laptop1")
    bob = operators("teleop_bob", "bob@laptop2")
    first = alice.claim("limb1")
    told = threading.Event()
    lost_to: list[ClaimInfo] = []
    first.on_lost(lambda new: (lost_to.append(new), told.set()))
    wait_until(lambda: bob.claims.holder("limb1"), what="alice's claim reaching bob")

    with pytest.raises(ClaimRefused) as caught:
        bob.claim("limb1")
    assert caught.value.holder == first.info
    message = str(caught.value)
    assert "claimed by alice@laptop1 (node /ground1/teleop_alice) since " in message
    assert first.info.since_text() in message

    second = bob.claim("limb1", take=True)
    assert told.wait(10.0), "alice was not told she lost limb1"
    assert first.lost.is_set() and not first.held
    assert lost_to == [second.info] and first.lost_to == second.info
    assert second.info.since_ns > first.info.since_ns
    # Alice's token is gone (released by her side when she lost), so bob alone holds it.
    wait_until(
        lambda: [c.holder for c in bob.claims.claims() if c.module == "limb1"] == ["bob@laptop2"],
        what="alice's token withdrawn",
    )
    assert not second.lost.is_set()


def test_current_asks_the_network_not_only_what_the_watcher_has_seen(
    operators, open_sessions
) -> None:
    alice = operators("teleop_alice", "alice@laptop1")
    bob = operators("teleop_bob", "bob@laptop2")
    claim = alice.claim("limb2")
    wait_until(lambda: bob.claims.holder("limb2"), what="alice's claim reaching bob")
    # A watcher made just now has not had its history yet; its query finds the claim.
    late = Claims(bob.node.session, 0, MODULES)
    try:
        assert late.current("limb2") == claim.info
        with pytest.raises(ClaimRefused):
            late.claim("limb2", "bob@laptop2", bob.node)
    finally:
        late.close()


def test_claiming_again_from_the_same_node_is_the_same_claim(operators) -> None:
    alice = operators("teleop_alice", "alice@laptop1")
    first = alice.claim("wheel1")
    assert alice.claim("wheel1") is first
    assert not first.lost.is_set()


def test_a_claim_vanishes_with_its_session(open_sessions, operators) -> None:
    """The operator's process dying (its session closing) withdraws its claims."""
    watcher = operators("watcher", "nobody@base")
    session = open_sessions()
    node = Node(session, "teleop_carol", "/ground1")
    claims = Claims(session, 0, MODULES)
    claim = claims.claim("limb2", "carol@laptop3", node)
    wait_until(lambda: watcher.claims.holder("limb2") == claim.info, what="carol's claim")
    session.close()  # no release: as a crash (the token goes with the session)
    wait_until(lambda: watcher.claims.holder("limb2") is None, what="the claim's withdrawal")


# --------------------------------------------------------------------------- two processes

OPERATOR = r"""
import json, sys
from components.claims import ClaimRefused, Claims
from components.comm import Node
from components.comm.session import SessionSettings, open_session

name, holder, take = sys.argv[1], sys.argv[2], sys.argv[3] == "take"
session = open_session(SessionSettings.from_env())
node = Node(session, name, "/ground1")
claims = Claims(session, 0, ["limb1", "limb2"])
def say(**event):
    print(json.dumps(event), flush=True)
try:
    try:
        claim = claims.claim("limb1", holder, node, take=take)
    except ClaimRefused as exc:
        say(event="refused", holder=exc.holder.holder, message=str(exc))
        sys.exit(3)
    claim.on_lost(lambda new: say(event="lost", to=new.holder))
    say(event="claimed", since=claim.info.since)
    sys.stdin.readline()  # run until told to stop
finally:
    claims.close()
    node.close()
    session.close()
"""


class OperatorProcess:
    """A real operator process claiming limb1; its events are JSON lines on stdout."""

    def __init__(self, env: dict[str, str], name: str, holder: str, take: bool = False) -> None:
        self.process = subprocess.Popen(
            [sys.executable, "-c", OPERATOR, name, holder, "take" if take else "ask"],
            env=env,
            cwd=ROOT,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )

    def event(self) -> dict[str, Any]:
        line = self.process.stdout.readline()
        assert line, self.process.stderr.read()
        return json.loads(line)

    def stop(self) -> None:
        if self.process.poll() is None:
            try:
                self.process.stdin.write("\n")
                self.process.stdin.flush()
                self.process.wait(30.0)
            except (BrokenPipeError, subprocess.TimeoutExpired):
                self.process.kill()
                self.process.wait()
        for stream in (self.process.stdin, self.process.stdout, self.process.stderr):
            stream.close()


def test_two_operator_processes_second_refused_then_takes_over_and_first_is_told(
    router_endpoint: str,
) -> None:
    env = {
        **os.environ,
        "MSCTL_ZENOH_CONNECT": router_endpoint,
        "MSCTL_ZENOH_LISTEN": "tcp/127.0.0.1:0",
        "MSCTL_ZENOH_MULTICAST": "0",
        "PYTHONPATH": str(ROOT),
    }
    started: list[OperatorProcess] = []
    try:
        first = OperatorProcess(env, "teleop_a", "alice@laptop1")
        started.append(first)
        assert first.event()["event"] == "claimed"

        second = OperatorProcess(env, "teleop_b", "bob@laptop2")
        started.append(second)
        refused = second.event()
        assert refused["event"] == "refused" and refused["holder"] == "alice@laptop1"
        assert "node /ground1/teleop_a" in refused["message"]
        assert second.process.wait(30.0) == 3

        taker = OperatorProcess(env, "teleop_b", "bob@laptop2", take=True)
        started.append(taker)
        assert taker.event()["event"] == "claimed"
        assert first.event() == {"event": "lost", "to": "bob@laptop2"}
    finally:
        for process in started:
            process.stop()


# --------------------------------------------------------------------------- enforcement


class Commanded(Core):
    """A joint-manager stand-in: keeps every ``joint_set`` it is given."""

    def __init__(self) -> None:
        super().__init__("commanded")
        self.got: list[float] = []

    def on_joint_set(self, message: Any, now: float) -> None:
        self.got.extend(s.position for s in joint_samples(message))


_modules = itertools.count()


def unique_module() -> str:
    """A module name no other test uses (drop counters are per process, per topic)."""
    return f"clm{next(_modules)}_{os.getpid()}"


class Commanding:
    """An executor running a guarded ``joint_set`` under ``rule``, in a thread."""

    def __init__(self, session: Any, rule: ClaimRule) -> None:
        self.core = Commanded()
        spec = InterfaceSpec(subscribe=(Subscribe("joint_set", JOINT_STATE, "on_joint_set"),))
        self.executor = Executor(session=session)
        self.component = self.executor.add(
            self.core, spec.claimed(("joint_set",), rule), f"/{rule.module}", "joint_manager"
        )
        self.topic = f"/{rule.module}/joint_set"
        self.thread = threading.Thread(target=self.executor.run, daemon=True)
        self.thread.start()

    def refused(self, reason: str) -> int:
        return drops.count(self.topic, reason)

    def sees(self, module: str, holder: str | None) -> None:
        """Wait until this executor's claims watcher has ``holder`` (or nobody) on ``module``."""

        def seen() -> bool:
            info = self.executor.claim_guard().claims.holder(module)
            return (info and info.holder) == holder

        wait_until(seen, 10.0, f"the manager seeing {holder or 'nobody'} hold {module}")

    def stop(self) -> None:
        self.executor.stop()
        self.thread.join(10.0)
        assert not self.thread.is_alive()


@pytest.fixture
def commanding(open_sessions) -> Iterator[Any]:
    made: list[Commanding] = []

    def make(rule: ClaimRule) -> Commanding:
        made.append(Commanding(open_sessions(), rule))
        return made[-1]

    try:
        yield make
    finally:
        for item in made:
            item.stop()


def send_until(send: Any, done: Any, timeout: float = 10.0) -> Any:
    """Send repeatedly until ``done()``: a first sample may precede its route or token."""

    def attempt() -> Any:
        if not done():
            send()
            time.sleep(0.02)
        return done()

    return wait_until(attempt, timeout)


def test_a_claimed_module_takes_joint_set_only_from_the_holder(
    operators, commanding, caplog
) -> None:
    caplog.set_level(logging.INFO, logger="msctl.comm")
    module = unique_module()
    manager = commanding(ClaimRule(module))
    alice = operators("teleop_alice", "alice@laptop1")
    bob = operators("teleop_bob", "bob@laptop2")
    alice.claims.modules = bob.claims.modules = None  # any module name
    to_module = f"/{module}/joint_set"
    from_alice = alice.node.publisher(to_module, JOINT_STATE)
    from_bob = bob.node.publisher(to_module, JOINT_STATE)
    got = manager.core.got

    def command(value: float) -> Any:
        return joint_state([JointSample("j", value, None, None)])

    # Unclaimed (an open assembly): anyone's commands are taken.
    send_until(lambda: from_bob.publish(command(1.0)), lambda: 1.0 in got)
    send_until(lambda: from_alice.publish(command(2.0)), lambda: 2.0 in got)

    # Alice claims: bob is refused, counted, warned about once naming the holder.
    claim = alice.claim(module)
    manager.sees(module, "alice@laptop1")
    send_until(lambda: from_bob.publish(command(3.0)), lambda: manager.refused(NOT_HOLDER) >= 3)
    send_until(lambda: from_alice.publish(command(4.0)), lambda: 4.0 in got)
    assert 3.0 not in got
    (warned,) = [
        r.getMessage()
        for r in caplog.records
        if r.levelno == logging.WARNING and r.getMessage().startswith(f"{to_module}: refused")
    ]
    assert "node /ground1/teleop_bob" in warned
    assert f"{module} is claimed by alice@laptop1 (node /ground1/teleop_alice) since" in warned

    # Bob takes it over: now alice is refused and bob is taken.
    bob.claim(module, take=True)
    assert claim.lost.wait(10.0)
    manager.sees(module, "bob@laptop2")
    before = manager.refused(NOT_HOLDER)
    send_until(
        lambda: from_alice.publish(command(5.0)),
        lambda: manager.refused(NOT_HOLDER) >= before + 3,
    )
    send_until(lambda: from_bob.publish(command(6.0)), lambda: 6.0 in got)
    assert 5.0 not in got and 3.0 not in got


def test_claims_required_refuses_everyone_but_relays_until_claimed(operators, commanding) -> None:
    module = unique_module()
    alice = operators("teleop_alice", "alice@laptop1")
    relay = operators("kinematics_manager", "robot@limb")
    alice.claims.modules = None
    manager = commanding(ClaimRule(module, relays=("/ground1/kinematics_manager",), required=True))
    to_module = f"/{module}/joint_set"
    from_alice = alice.node.publisher(to_module, JOINT_STATE)
    from_relay = relay.node.publisher(to_module, JOINT_STATE)
    got = manager.core.got

    def command(value: float) -> Any:
        return joint_state([JointSample("j", value, None, None)])

    send_until(lambda: from_alice.publish(command(1.0)), lambda: manager.refused(UNCLAIMED) >= 3)
    send_until(lambda: from_relay.publish(command(2.0)), lambda: 2.0 in got)
    claim = alice.claim(module)
    send_until(lambda: from_alice.publish(command(3.0)), lambda: 3.0 in got)
    send_until(lambda: from_relay.publish(command(4.0)), lambda: 4.0 in got)
    # Released: closed again (required), the relay still taken.
    claim.release()
    manager.sees(module, None)
    before = manager.refused(UNCLAIMED)
    send_until(
        lambda: from_alice.publish(command(5.0)), lambda: manager.refused(UNCLAIMED) >= before + 3
    )
    assert 1.0 not in got and 5.0 not in got


def test_a_rule_over_several_modules_takes_only_an_operator_holding_all_it_claims() -> None:
    """A Twist steering every wheel (the steering operator's cmd_vel): one operator must
    hold whatever of them is claimed; free ones restrict nobody unless claims are required."""
    alice = parse_claim(claim_key(0, "wheel1", 10, "alice@laptop1", "za", "/g/teleop_alice"))
    alice2 = parse_claim(claim_key(0, "wheel2", 11, "alice@laptop1", "za", "/g/teleop_alice"))
    bob = parse_claim(claim_key(0, "wheel2", 12, "bob@laptop2", "zb", "/g/teleop_bob"))
    rule = ClaimRule("wheel1", relays=("/g/guardian",), also=("wheel2",))
    assert rule.modules == ("wheel1", "wheel2")
    assert rule.senders({})[0] is None  # nothing claimed: anyone
    assert rule.senders({"wheel1": alice})[0] == {"/g/teleop_alice@za", "/g/guardian"}
    assert rule.senders({"wheel1": alice, "wheel2": alice2})[0] == {
        "/g/teleop_alice@za",
        "/g/guardian",
    }
    senders, why, reason = rule.senders({"wheel1": alice, "wheel2": bob})
    assert senders == {"/g/guardian"} and reason == NOT_HOLDER
    assert "claimed by different operators" in why and "wheel2 by bob@laptop2" in why
    required = ClaimRule("wheel1", also=("wheel2",), required=True)
    senders, why, reason = required.senders({"wheel1": alice})
    assert senders == frozenset() and reason == UNCLAIMED and why.startswith("wheel2 takes")


def test_a_holders_claim_names_its_session_too(operators, commanding, open_sessions) -> None:
    """Another process's node of the same name is not the holder."""
    module = unique_module()
    manager = commanding(ClaimRule(module))
    alice = operators("teleop", "alice@laptop1")
    impostor = operators("teleop", "mallory@laptop9")  # same node name, another session
    alice.claims.modules = None
    alice.claim(module)
    manager.sees(module, "alice@laptop1")
    to_module = f"/{module}/joint_set"
    from_alice = alice.node.publisher(to_module, JOINT_STATE)
    from_impostor = impostor.node.publisher(to_module, JOINT_STATE)
    got = manager.core.got
    send_until(
        lambda: from_impostor.publish(joint_state([JointSample("j", 9.0, None, None)])),
        lambda: manager.refused(NOT_HOLDER) >= 3,
    )
    send_until(
        lambda: from_alice.publish(joint_state([JointSample("j", 1.0, None, None)])),
        lambda: 1.0 in got,
    )
    assert 9.0 not in got


def test_the_dragons_command_inputs_are_guarded_by_their_modules_claims(tmp_path: Path) -> None:
    from components.build import build_component

    dragon = resolved_assembly(tmp_path, "dragon")
    assert dragon.claims == "open"
    for plan in dragon.components:
        if plan.kind not in ("joint_manager", "kinematics_manager"):
            continue
        built = build_component(plan, dragon, {"sim": True})
        try:
            guarded = {s.topic: s.claim for s in built.spec.subscribe if s.claim is not None}
        finally:
            built.close()
        topic = "joint_set" if plan.kind == "joint_manager" else "ik_target"
        relays = ("/limb1/kinematics_manager",) if plan.module == "limb1" else ()
        if plan.module == "limb2":
            relays = ("/limb2/kinematics_manager",)
        assert guarded == {topic: ClaimRule(plan.module, relays, required=False)}, plan.name


# --------------------------------------------------------------------------- the template


@pytest.fixture
def assemblies(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A private copy of the shipped templates and module types."""
    import shutil

    copy = tmp_path / "assemblies"
    shutil.copytree(ROOT / "assemblies", copy, ignore=shutil.ignore_patterns("__pycache__"))
    monkeypatch.setenv("MSCTL_ASSEMBLIES_DIR", str(copy))
    return copy


def test_claims_required_is_checked_at_assemble_and_carried_in_the_lock(
    assemblies: Path,
) -> None:
    from components.assembly import decode_lock, encode_lock
    from msctl.assembler import resolve
    from msctl.errors import InputError

    template = assemblies / "dragon.toml"
    text = template.read_text()
    template.write_text('claims = "required"\n' + text)
    resolution = resolve("dragon")
    assert resolution.lock.claims == "required"
    assert decode_lock(encode_lock(resolution.lock)).claims == "required"
    template.write_text('claims = "sometimes"\n' + text)
    with pytest.raises(InputError) as caught:
        resolve("dragon")
    message = str(caught.value)
    assert f"{template}: field claims is 'sometimes'" in message
    assert 'claims = "required"' in message


def test_a_lock_written_before_claims_reads_as_open(tmp_path: Path) -> None:
    from components.assembly import decode_lock, encode_lock

    document = json.loads(encode_lock(resolved_assembly(tmp_path, "dragon").lock))
    del document["claims"]
    assert decode_lock(json.dumps(document)).claims == "open"


# --------------------------------------------------------------------------- msctl claims


def run_msctl(router_endpoint: str, *args: str) -> subprocess.CompletedProcess:
    env = {
        **os.environ,
        "MSCTL_ZENOH_CONNECT": router_endpoint,
        "MSCTL_ZENOH_LISTEN": "tcp/127.0.0.1:0",
        "MSCTL_ZENOH_MULTICAST": "0",
        "PYTHONPATH": str(ROOT),
    }
    return subprocess.run(
        [sys.executable, "-m", "msctl", *args],
        env=env,
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60.0,
    )


def test_msctl_claims_lists_module_holder_node_and_since(router_endpoint, operators) -> None:
    empty = run_msctl(router_endpoint, "claims", "--json")
    assert empty.returncode == 0, empty.stderr
    assert json.loads(empty.stdout) == {"claims": []}

    alice = operators("teleop_alice", "alice@laptop1")
    bob = operators("teleop_bob", "bob@laptop2")
    first = alice.claim("limb1")
    second = bob.claim("wheel2")
    listed = run_msctl(router_endpoint, "claims", "--json")
    assert listed.returncode == 0, listed.stderr
    rows = json.loads(listed.stdout)["claims"]
    assert [(r["module"], r["holder"], r["node"], r["holds"]) for r in rows] == [
        ("limb1", "alice@laptop1", "/ground1/teleop_alice", True),
        ("wheel2", "bob@laptop2", "/ground1/teleop_bob", True),
    ]
    assert rows[0]["since"] == pytest.approx(first.info.since)
    assert rows[1]["since"] == pytest.approx(second.info.since)

    table = run_msctl(router_endpoint, "claims")
    assert table.returncode == 0, table.stderr
    lines = [line for line in table.stdout.splitlines() if "limb1" in line]
    assert len(lines) == 1 and "alice@laptop1" in lines[0] and "/ground1/teleop_alice" in lines[0]


# --------------------------------------------------------------------------- scripts


def test_a_script_claims_what_it_commands_and_is_told_what_others_hold(
    operators, open_sessions
) -> None:
    """The Python API (``msctl run``): a module is claimed at its first command or syncer,
    one held by an operator is refused naming them, one taken over refuses the next command."""
    from components.api import ClaimLostError, ModuleClaimedError, Robot
    from components.api.joints import JointHandler, JointInfo

    alice = operators("teleop_alice", "alice@laptop1")
    session = open_sessions()
    wait_until(lambda: list(session.info.routers_zid()), what="the router link")
    node = Node(session, "api_script", "/")
    handlers = [
        JointHandler(node, slot, [JointInfo(f"{slot}_joint1", "revolute", -1, 1, 1, 1)])
        for slot in ("limb1", "limb2")
    ]
    claims = Claims(session, 0, ["limb1", "limb2"])
    robot = Robot(session, node, handlers, {"limb1": "limb", "limb2": "limb"}, claims=claims)
    try:
        held = alice.claim("limb1")
        wait_until(lambda: claims.holder("limb1"), what="alice's claim reaching the script")
        with pytest.raises(ModuleClaimedError) as caught:
            robot.syncer("limb1")
        assert caught.value.holder == held.info
        assert "claimed by alice@laptop1 (node /ground1/teleop_alice) since" in str(caught.value)
        with pytest.raises(ModuleClaimedError):
            robot.handler("limb1").send({"joint1": 0.1})

        robot.handler("limb2").send({"joint1": 0.2})
        assert robot.claimed() == ["limb2"]
        wait_until(
            lambda: (
                (alice.claims.holder("limb2") or None)
                and alice.claims.holder("limb2").node == "/api_script"
            ),
            what="the script's claim reaching alice",
        )
        alice.claim("limb2", take=True)
        wait_until(lambda: not robot.claimed(), what="the script learning it lost limb2")
        with pytest.raises(ClaimLostError, match="taken over by alice@laptop1"):
            robot.handler("limb2").send({"joint1": 0.3})
    finally:
        asyncio.run(robot.close())
        session.close()


def test_a_claim_seen_no_longer_held_is_already_known_lost_and_to_whom() -> None:
    """Losing a claim releases its token, a network call that can take a while on a loaded
    computer: meanwhile a script seeing the claim gone must already read it as lost."""
    from components.claims import Claim

    in_undeclare, finish = threading.Event(), threading.Event()

    class SlowToken:
        def undeclare(self) -> None:
            in_undeclare.set()
            finish.wait(30.0)

    class Owner:
        def _forget(self, claim: Claim) -> None:
            pass

    def info(holder: str, since_ns: int) -> ClaimInfo:
        key = f"@msctl/claim/0/limb2/{since_ns}/{holder}/zid/%node"
        return ClaimInfo("limb2", holder, "/node", since_ns / 1e9, "zid", key)

    claim = Claim(Owner(), info("script@pc", 1), SlowToken())  # type: ignore[arg-type]
    taker = info("alice@laptop1", 2)
    losing = threading.Thread(target=claim._lose, args=(taker,))
    losing.start()
    try:
        assert in_undeclare.wait(30.0)
        assert not claim.held
        assert claim.lost.is_set() and claim.lost_to == taker
    finally:
        finish.set()
        losing.join(30.0)
