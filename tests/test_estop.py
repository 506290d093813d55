"""``msctl estop`` / ``msctl recover`` (issue 12, part 3).

Inner loop: real Zenoh sessions on a loopback router, stand-in joint managers serving the
real ``halt``/``recover`` Trigger services (one of them silent), the real ``msctl`` command.
End to end: a simulated Dragon (``msctl up --detach``): after ``msctl estop`` a ``joint_set``
from the module's claim holder moves nothing (the joint manager counts it refused) until
``msctl recover``. Events are awaited, never slept for; no time is asserted.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import quick_peer_settings, quick_router, wait_until
from running import Up

from components.claims import Claims
from components.comm import Node
from components.comm.qos import QoS
from components.comm.session import SessionSettings, open_session
from components.estop import Estop
from components.executor.core import Core
from components.executor.interface import InterfaceSpec, Serve, Subscribe
from components.messages import (
    DIAGNOSTIC_ARRAY,
    JOINT_STATE,
    TRIGGER,
    JointSample,
    joint_samples,
    joint_state,
    msg,
)

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def router_endpoint() -> Iterator[str]:
    """Overrides conftest's: the same real router, without the 0.5 s opening wait."""
    yield from quick_router()


@pytest.fixture
def session_settings(router_endpoint: str) -> SessionSettings:
    """Overrides conftest's: peers that open at once (answers are awaited anyway)."""
    return quick_peer_settings(router_endpoint)


class StandIn:
    """A joint manager's halt and recover (a node named joint_manager in the module's
    namespace), answering at once, or never when ``silent``; the answers to its first
    ``lose`` halts are lost (a radio link that closed while they were on it)."""

    def __init__(self, session: Any, slot: str, silent: bool = False, lose: int = 0) -> None:
        self.node = Node(session, "joint_manager", f"/{slot}")
        self.calls: list[str] = []
        self.pending: list[Any] = []

        def serve(verb: str) -> Any:
            def answer(pending: Any) -> None:
                self.calls.append(verb)
                if silent or (verb == "halt" and self.calls.count("halt") <= lose):
                    self.pending.append(pending)  # never answered
                    return
                pending.reply(msg(f"{TRIGGER}_Response", success=True, message=f"{verb} done"))

            return answer

        for verb in ("halt", "recover"):
            self.node.service(verb, TRIGGER, serve(verb), deferred=True)

    def close(self) -> None:
        self.node.close()


def msctl(env: dict[str, str], *args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "msctl", *args],
        env=env,
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


@pytest.fixture
def env(router_endpoint: str, tmp_path: Path) -> dict[str, str]:
    return {
        **os.environ,
        "MSCTL_HOME": str(tmp_path / "home"),  # no resolved assembly: the graph decides
        "MSCTL_HOST": "test-laptop",
        "MSCTL_ZENOH_CONNECT": router_endpoint,
        "MSCTL_ZENOH_LISTEN": "tcp/127.0.0.1:0",
        "MSCTL_ZENOH_MULTICAST": "0",
        "PYTHONPATH": str(ROOT),
    }


@pytest.fixture
def modules(open_sessions) -> Iterator[Any]:
    made: list[StandIn] = []

    def make(slot: str, silent: bool = False, lose: int = 0) -> StandIn:
        session = open_sessions()
        wait_until(lambda: list(session.info.routers_zid()), what="the router link")
        made.append(StandIn(session, slot, silent, lose))
        return made[-1]

    try:
        yield make
    finally:
        for module in made:
            module.close()


def test_estop_calls_every_modules_halt_at_once_with_its_time(open_sessions, modules) -> None:
    limbs = [modules(slot) for slot in ("limb1", "limb2", "wheel1")]
    session = open_sessions()
    wait_until(lambda: list(session.info.routers_zid()), what="the router link")
    node = Node(session, "operator", "/ground1")
    try:
        with Estop(node, ["limb1", "limb2", "wheel1"]) as estop:

            def halted() -> Any:
                answers = estop.halt(timeout=5.0)
                return answers if all(a.ok for a in answers) else None

            answers = wait_until(halted, 20.0, "every module's halt answered")
            assert [a.module for a in answers] == ["limb1", "limb2", "wheel1"]
            assert all(a.message == "halt done" and a.seconds >= 0 for a in answers)
            assert all("halt" in m.calls for m in limbs)
            (recovered,) = estop.recover(["limb2"], timeout=5.0)
            assert recovered.ok and recovered.module == "limb2"
            assert limbs[1].calls[-1] == "recover" and "recover" not in limbs[0].calls
            with pytest.raises(KeyError, match="no module limb9 here; modules: limb1, limb2"):
                estop.halt(["limb9"])
    finally:
        node.close()


def test_a_halt_that_reached_nobody_goes_again_until_its_deadline(open_sessions, modules) -> None:
    # A module whose route lapsed (its link flapped): the router knows no server for its
    # halt for a moment. The halt is sent again until the deadline, not given up at once.
    import threading

    session = open_sessions()
    wait_until(lambda: list(session.info.routers_zid()), what="the router link")
    node = Node(session, "operator", "/ground1")
    back = threading.Timer(0.5, lambda: modules("limb1"))
    try:
        with Estop(node, ["limb1"]) as estop:
            back.start()
            (answer,) = estop.halt(timeout=20.0)
            assert answer.ok and answer.message == "halt done", answer
            assert answer.seconds is not None and answer.seconds > 0
        with Estop(node, ["limb9"]) as nowhere:
            (absent,) = nowhere.halt(timeout=0.5)
            assert not absent.ok and "no server of /limb9/halt" in absent.message
    finally:
        back.join()
        node.close()


def test_a_halt_whose_answer_was_lost_is_sent_again_and_acknowledged(
    open_sessions, modules
) -> None:
    # A radio link that closed while the halt or its answer was on it lost it for good:
    # nothing resends it when the link reopens. The e-stop sends it again while it has no
    # answer, the earlier copies still waiting, until its deadline.
    lossy = modules("limb1", lose=2)
    modules("limb2")
    session = open_sessions()
    wait_until(lambda: list(session.info.routers_zid()), what="the router link")
    node = Node(session, "operator", "/ground1")
    try:
        with Estop(node, ["limb1", "limb2"]) as estop:
            wait_until(
                lambda: all(a.ok for a in estop.recover(timeout=5.0)) or None,
                20.0,
                "both modules answering",
            )
            answers = estop.halt(timeout=20.0)
            assert [(a.module, a.ok, a.message) for a in answers] == [
                ("limb1", True, "halt done"),
                ("limb2", True, "halt done"),
            ]
            assert lossy.calls.count("halt") == 3  # two answers lost, the third came
    finally:
        node.close()


def test_msctl_estop_names_each_module_and_a_silent_one_fails_the_command(env, modules) -> None:
    modules("limb1")
    silent = modules("limb2", silent=True)
    wait_until(lambda: "/limb2/halt" in msctl(env, "service", "list").stdout, 60.0, "the services")
    result = msctl(env, "estop", "--json", "--timeout", "1")
    assert result.returncode == 5, result.stdout + result.stderr
    document = json.loads(result.stdout)
    rows = {r["module"]: r for r in document["modules"]}
    assert set(rows) == {"limb1", "limb2"} and document["acknowledged"] is False
    assert rows["limb1"]["ok"] and rows["limb1"]["seconds"] is not None
    assert not rows["limb2"]["ok"] and rows["limb2"]["seconds"] is None
    assert "limb2 did not acknowledge" in result.stderr
    assert "stop them at the robot" in result.stderr
    # It was asked (again while it did not answer: an answer lost is asked for again), it
    # just never answered.
    assert silent.calls and set(silent.calls) == {"halt"}

    # Named modules only; the human form: one line per module with its time.
    named = msctl(env, "estop", "limb1")
    assert named.returncode == 0, named.stdout + named.stderr
    (line,) = [line for line in named.stdout.splitlines() if line.startswith("limb1")]
    assert "halted" in line and " ms" in line and "halt done" in line
    assert "limb2" not in named.stdout
    recovered = msctl(env, "recover", "limb1")
    assert recovered.returncode == 0 and "recovered" in recovered.stdout


@pytest.mark.e2e
def test_msctl_estop_names_the_planned_modules_whose_joint_manager_is_gone(env, modules) -> None:
    """The resolved Dragon here plans four modules: wheel2's joint manager never started and
    limb2's has stopped. Both are asked all the same and named as not acknowledging (exit 5),
    by estop and by recover; the two that run answer."""
    from msctl.assembler import resolve
    from msctl.assembler.store import write_resolution

    write_resolution(Path(env["MSCTL_HOME"]) / "assembly", resolve("dragon", {}), mjcf=False)
    modules("limb1")
    modules("wheel1")
    modules("limb2").close()  # it ran, and stopped
    wait_until(lambda: "/wheel1/halt" in msctl(env, "service", "list").stdout, 60.0, "the services")
    for verb in ("estop", "recover"):
        result = msctl(env, verb, "--json", "--timeout", "1")
        assert result.returncode == 5, result.stdout + result.stderr
        document = json.loads(result.stdout)
        ok = {r["module"]: r["ok"] for r in document["modules"]}
        assert ok == {"limb1": True, "limb2": False, "wheel1": True, "wheel2": False}
        assert "not on the graph: limb2, wheel2 (asked all the same)" in document["notes"]
        (line,) = [x for x in result.stderr.splitlines() if x.startswith("error:")]
        verb_said = "halt" if verb == "estop" else "recover"
        assert f"{verb_said}: limb2, wheel2 did not acknowledge" in line, line


def test_msctl_estop_refuses_an_unknown_module_naming_those_that_exist(env, modules) -> None:
    modules("limb1")
    modules("wheel1")
    wait_until(lambda: "/wheel1/halt" in msctl(env, "service", "list").stdout, 60.0, "the services")
    result = msctl(env, "estop", "limb9")
    assert result.returncode == 2, result.stdout + result.stderr
    assert "no module limb9 in the running assembly" in result.stderr
    assert "modules: limb1, wheel1" in result.stderr or "modules: wheel1, limb1" in result.stderr


def test_msctl_estop_with_nothing_running_says_so(env) -> None:
    result = msctl(env, "estop")
    assert result.returncode == 4, result.stdout + result.stderr
    assert "no module to reach" in result.stderr


class Backlogged(Core):
    """A core whose samples pile up: what it handled, in order."""

    SPEC = InterfaceSpec(
        subscribe=(Subscribe("joint_states", JOINT_STATE, "on_states", QoS(depth=100)),),
        serve=(
            Serve("halt", TRIGGER, "on_halt", urgent=True),
            Serve("recover", TRIGGER, "on_recover"),
        ),
    )

    def __init__(self) -> None:
        super().__init__("backlogged")
        self.log: list[str] = []
        self.arrived = 0

    def on_states(self, message: Any, now: float) -> None:
        self.log.append("sample")

    def on_halt(self, request: Any, now: float) -> Any:
        self.log.append("halt")
        return msg(f"{TRIGGER}_Response", success=True, message="halted")

    def on_recover(self, request: Any, now: float) -> Any:
        self.log.append("recover")
        return msg(f"{TRIGGER}_Response", success=True, message="recovered")


def test_a_halt_is_handled_before_a_backlog_of_samples(open_sessions) -> None:
    """The joint manager's halt is urgent: answered as soon as the running handler ends,
    ahead of every queued sample (a recover, not urgent, waits its turn)."""
    from components.executor.executor import Executor

    session = open_sessions()
    wait_until(lambda: list(session.info.routers_zid()), what="the router link")
    core = Backlogged()
    operator = Node(open_sessions(), "operator", "/ground1")
    with Executor(session=session) as executor:
        component = executor.add(core, Backlogged.SPEC, "/limb7", "joint_manager")
        feeder = operator.publisher("/limb7/joint_states", JOINT_STATE)
        sample = joint_state([JointSample("limb7_joint1", 0.0, None, None)])

        (subscription,) = [e for e in component.node._owned if hasattr(e, "received")]

        def piled() -> bool:
            # Nothing is handled while the executor does not spin: they wait in its queue.
            if subscription.received < 20:
                feeder.publish(sample)
                return False
            return True

        wait_until(piled, 30.0, "twenty samples queued")
        halt = operator.client("/limb7/halt", TRIGGER)
        recover = operator.client("/limb7/recover", TRIGGER)
        recovered = recover.call_async(recover.request_type()(), 10.0)
        halted = halt.call_async(halt.request_type()(), 10.0)
        wait_until(lambda: executor._urgent, 30.0, "the halt request queued")
        while not (halted.done.is_set() and recovered.done.is_set()):
            executor.spin_once(0.05)
        assert halted.result().message == "halted" and recovered.result().success
        assert core.log[0] == "halt", core.log[:5]
        assert core.log.index("recover") > 20, core.log  # behind the twenty queued samples
        assert component.errors == 0
    operator.close()


# --------------------------------------------------------------------------- end to end


@pytest.fixture(scope="module")
def dragon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Up]:
    up = Up(tmp_path_factory.mktemp("estop") / "home", "dragon")
    try:
        yield up
    finally:
        up.down()


class Watch:
    """limb1's measured joints and its joint manager's counters, from the data plane."""

    def __init__(self, node: Node) -> None:
        self.lock = threading.Lock()
        self.read: dict[str, float] = {}
        self.counters: dict[str, str] = {}
        node.subscription("/limb1/joint_read", JOINT_STATE, self._on_read)
        node.subscription("/limb1/diagnostics", DIAGNOSTIC_ARRAY, self._on_diagnostics)

    def _on_read(self, message: Any) -> None:
        with self.lock:
            for sample in joint_samples(message):
                if sample.position is not None:
                    self.read[sample.name] = sample.position

    def _on_diagnostics(self, message: Any) -> None:
        for status in message.status:
            values = {kv.key: kv.value for kv in status.values}
            if "refused_halted" in values and values.get("module") == "limb1":
                with self.lock:
                    self.counters = values

    def position(self, joint: str) -> float | None:
        with self.lock:
            return self.read.get(joint)

    def refused_halted(self) -> int:
        with self.lock:
            return int(self.counters.get("refused_halted", 0))

    def halted(self) -> bool:
        with self.lock:
            return self.counters.get("halted") == "True"


@pytest.mark.e2e
def test_e2e_after_estop_joint_set_moves_nothing_until_recover(dragon: Up) -> None:
    session = open_session(dragon.settings())
    node = Node(session, "teleop_alice", "/ground1")
    claims = Claims(session, 0, ["limb1", "limb2", "wheel1", "wheel2"])
    try:
        watch = Watch(node)
        wait_until(lambda: watch.position("limb1_joint4") is not None, 60.0, "limb1 joint_read")
        # Alice holds limb1: her claim does not stop anyone's halt.
        claims.claim("limb1", "alice@laptop1", node)
        joint_set = node.publisher("/limb1/joint_set", JOINT_STATE)

        result = dragon.msctl("estop", "--json")
        assert result.returncode == 0, result.stdout + result.stderr
        document = json.loads(result.stdout)
        assert {r["module"] for r in document["modules"]} == {"limb1", "limb2", "wheel1", "wheel2"}
        assert all(r["ok"] and r["seconds"] is not None for r in document["modules"])
        wait_until(watch.halted, 30.0, "limb1's diagnostics saying halted")

        start = watch.position("limb1_joint4")
        target = start + (0.3 if start < 0.5 else -0.3)
        command = joint_state([JointSample("limb1_joint4", target, None, None)])
        refused = watch.refused_halted()
        farthest = 0.0

        def refused_many() -> bool:
            nonlocal farthest
            joint_set.publish(command)
            farthest = max(farthest, abs(watch.position("limb1_joint4") - start))
            return watch.refused_halted() >= refused + 20

        # Twenty of the holder's commands reached the joint manager and were refused.
        wait_until(refused_many, 60.0, "joint_set refused while halted", interval=0.02)
        assert farthest < 0.02, (start, farthest)

        result = dragon.msctl("recover")
        assert result.returncode == 0, result.stdout + result.stderr
        assert result.stdout.count("recovered") >= 4

        def arrived() -> bool:
            # Most of the way (a loaded joint tracks a little short of its target): it moves
            # ten times farther than the bound it kept while halted.
            joint_set.publish(command)
            return abs(watch.position("limb1_joint4") - start) > 0.2

        wait_until(arrived, 60.0, "joint_set moving limb1_joint4 after recover", interval=0.05)
    finally:
        claims.close()
        node.close()
        session.close()


@pytest.mark.e2e
def test_e2e_a_script_under_msctl_run_is_refused_a_module_an_operator_holds(
    dragon: Up, tmp_path: Path
) -> None:
    script = tmp_path / "nudge.py"
    script.write_text(
        "async def main(robot):\n    await robot.syncer('limb2').lerp({'joint2': 0.1})\n",
        encoding="utf-8",
    )
    session = open_session(dragon.settings())
    node = Node(session, "teleop_bob", "/ground1")
    claims = Claims(session, 0)
    try:
        wait_until(lambda: list(session.info.routers_zid()), 30.0, "the router link")
        claims.claim("limb2", "bob@laptop2", node)
        result = dragon.msctl("run", str(script), timeout=120.0)
        assert result.returncode == 1, result.stdout + result.stderr
        assert "ModuleClaimedError" in result.stderr
        assert "claimed by bob@laptop2 (node /ground1/teleop_bob)" in result.stderr
        listed = json.loads(dragon.msctl("claims", "--json").stdout)["claims"]
        assert [(c["module"], c["holder"]) for c in listed] == [("limb2", "bob@laptop2")]
    finally:
        claims.close()
        node.close()
        session.close()
