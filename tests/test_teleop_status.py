"""The teleop never says MOVING when nothing can move (issue 32, cases 4, 8 and 9).

limb1 and wheel1 of a Dragon run their real joint managers (over emulated motors) in this
process; the teleop opens its real link and screen (textual's Pilot). Another node, as
another shell would, halts limb1 (``msctl estop``) and recovers it, then takes wheel1's
joint manager off the data plane (``msctl down``/``stop``). The screen says why each cannot
move, refuses its keys, and takes them back after the recover. A teleop opened on a stopped
module fails at once, saying so (not "is the assembly up?" after its whole timeout). A
window too small to show the joint list refuses the keys that would move what it hides.

Waits are on events with generous bounds; nothing here measures speed.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from conftest import quick_peer_settings, quick_router, resolved_assembly
from teleop_rig import ModulesRig

from components.assembly import ResolvedAssembly
from components.comm.node import Node
from components.comm.session import SessionSettings, open_session
from components.estop import Estop
from msctl.errors import NetworkError
from msctl.teleop.app import TeleopApp
from msctl.teleop.core import TeleopCore, TeleopSettings
from msctl.teleop.keys import JOINT
from msctl.teleop.link import Link
from msctl.teleop.operator import Operator
from msctl.teleop.watch import FIRST_SEEN_GRACE, RECOVER_GRACE, ModuleStates

SLOTS = ["limb1", "wheel1"]
PATIENCE = 60.0


# ----------------------------------------------------------------------------- the rules
def test_the_rules_say_why_a_module_cannot_move() -> None:
    states = ModuleStates({"limb1": "/limb1", "wheel1": "/wheel1"}, started=0.0)
    assert states.why_not("limb1", 1.0) == ""  # a graph just joined: not gone yet
    assert "GONE" in states.why_not("limb1", FIRST_SEEN_GRACE + 0.1)  # never seen
    states.presence("limb1", True)
    states.report("limb1", True, 10.0)
    assert "limb1 is HALTED" in states.why_not("limb1", 10.0)
    states.recovered("limb1", 11.0)
    states.report("limb1", True, 11.5)  # published before the recover
    assert states.why_not("limb1", 11.5) == ""
    states.report("limb1", True, 11.0 + RECOVER_GRACE + 0.1)  # halted again since
    assert "HALTED" in states.why_not("limb1", 14.0)
    states.presence("limb1", False)
    assert "limb1 is GONE" in states.why_not("limb1", 14.0)


def test_the_core_refuses_a_blocked_target_and_says_why() -> None:
    core = TeleopCore(TeleopSettings(), {"limb1": ("limb1_joint1",), "wheel1": ("w",)})
    assert core.press("w", 0.0) == "move"
    core.tick(0.0)
    core.block("limb1", "limb1 is HALTED", 0.1, "limb1 halted")
    (stop,) = core.tick(0.1)
    assert stop.reason == "limb1 halted"
    assert core.press("w", 0.2) == "refused"
    assert core.view().held_back == "limb1 is HALTED"
    core.select("wheel1")
    assert core.view().held_back == "" and core.press("w", 0.3) == "move"
    core.unblock("limb1")
    core.select("limb1", now=0.4)
    assert core.press("w", 0.5) == "move"


# ----------------------------------------------------------------------------- live
@pytest.fixture(scope="module")
def router_endpoint() -> Iterator[str]:
    yield from quick_router()


@pytest.fixture(scope="module")
def session_settings(router_endpoint: str) -> SessionSettings:
    return quick_peer_settings(router_endpoint)


@pytest.fixture(scope="module")
def dragon(tmp_path_factory: pytest.TempPathFactory) -> ResolvedAssembly:
    return resolved_assembly(tmp_path_factory.mktemp("teleop_status"), "dragon")


@pytest.fixture(scope="module")
def rig(dragon: ResolvedAssembly, session_settings: SessionSettings) -> Iterator[ModulesRig]:
    rig = ModulesRig(dragon, SLOTS, session_settings)
    try:
        yield rig
    finally:
        rig.close()


@pytest.fixture(scope="module")
def shell(rig: ModulesRig, dragon: ResolvedAssembly, session_settings: SessionSettings) -> Any:
    """Another shell's halts and recovers (as ``msctl estop`` sends them)."""
    session = open_session(session_settings)
    node = Node(session, "other_shell")
    estop = Estop(node, {s: dragon.module(s).namespace for s in SLOTS})
    try:
        yield estop
    finally:
        estop.close()
        node.close()
        session.close()


@pytest.fixture
def screen(
    rig: ModulesRig, dragon: ResolvedAssembly, session_settings: SessionSettings
) -> Iterator[Callable[..., TeleopApp]]:
    """A teleop link, operator and app of its own (closed after the test)."""
    opened: list[Any] = []

    def make(**settings: float) -> TeleopApp:
        session = open_session(session_settings)
        opened.append(session)
        node = Node(session, "teleop_status")
        opened.append(node)
        link = Link.open(node, dragon, SLOTS, health=False, timeout=PATIENCE, claim=False)
        opened.append(link)
        for handler in link.handlers.values():
            asyncio.run(handler.wait_ready(PATIENCE))
        core = TeleopCore(
            TeleopSettings(**settings), link.joints(), link.limbs, link.drive_target, JOINT
        )
        operator = Operator(core, link.outputs()).start()
        opened.append(operator)
        return TeleopApp(operator, link, template="dragon")

    try:
        yield make
    finally:
        for thing in reversed(opened):
            thing.close()


async def until(pilot: Any, predicate: Callable[[], Any], what: str) -> Any:
    deadline = time.monotonic() + PATIENCE
    while not (value := predicate()):
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {PATIENCE} s: {what}")
        await pilot.pause(0.05)
    return value


def text_of(app: TeleopApp, selector: str) -> str:
    from textual.widgets import Static

    return str(app.query_one(selector, Static).render())


def test_after_an_estop_from_another_shell_w_is_refused_and_the_screen_says_halted(
    screen: Callable[..., TeleopApp], shell: Estop, rig: ModulesRig
) -> None:
    # A held key's deadman that outlasts a loaded machine's pauses (not what is tested).
    app = screen(first_timeout=600.0, repeat_timeout=600.0)

    async def scenario() -> None:
        async with app.run_test(size=(140, 40)) as pilot:
            await until(pilot, lambda: app.link.why_not("limb1") == "", "limb1 seen")
            (answer,) = await asyncio.to_thread(shell.halt, ["limb1"])
            assert answer.ok, answer.message
            await until(pilot, lambda: "limb1" in app.unable, "limb1 known halted")
            await pilot.press("w")
            await pilot.pause(0.3)
            deadman = text_of(app, "#deadman")
            assert "MOVING " not in deadman and "NOT MOVING: limb1 is HALTED" in deadman
            assert "limb1 HALTED" in text_of(app, "#claims")
            assert app.operator.moves_sent == 0
            # Recovered from the other shell: the keys move again.
            (answer,) = await asyncio.to_thread(shell.recover, ["limb1"])
            assert answer.ok, answer.message
            await until(pilot, lambda: "limb1" not in app.unable, "limb1 known recovered")
            await pilot.press("w")
            await until(pilot, lambda: app.operator.moves_sent > 0, "w moving limb1")
            assert "MOVING" in text_of(app, "#deadman")

    try:
        asyncio.run(scenario())
    finally:
        if rig.managers["limb1"].core.halted:
            shell.recover(["limb1"])


def test_a_short_window_keeps_the_selected_joint_in_view_and_a_tiny_one_refuses_the_keys(
    screen: Callable[..., TeleopApp],
) -> None:
    app = screen()

    async def scenario() -> None:
        # 40x10 (the size it disappeared at): the help gives way; the selected joint shows.
        async with app.run_test(size=(40, 10)) as pilot:
            app.operator.select("limb1", "limb1_joint4")
            await pilot.pause(0.3)
            assert app.target_shown()
            assert "> limb1_joint4" in text_of(app, "#target")
            # Smaller still, nothing of the list can show: the keys that move are refused.
            await pilot.resize_terminal(40, 6)
            await pilot.pause(0.3)
            assert not app.target_shown()
            await pilot.press("w")
            await pilot.pause(0.3)
            assert app.operator.moves_sent == 0
            assert "too small" in app.status and "MOVING " not in text_of(app, "#deadman")
            # Made large enough again, the same key moves.
            await pilot.resize_terminal(120, 40)
            await pilot.pause(0.3)
            assert app.target_shown()
            await pilot.press("w")
            await until(pilot, lambda: app.operator.moves_sent > 0, "w moving limb1")

    asyncio.run(scenario())


def test_a_module_taken_down_elsewhere_is_gone_on_screen_and_a_new_teleop_fails_at_once(
    screen: Callable[..., TeleopApp],
    rig: ModulesRig,
    dragon: ResolvedAssembly,
    session_settings: SessionSettings,
) -> None:
    app = screen()

    async def scenario() -> None:
        async with app.run_test(size=(140, 40)) as pilot:
            await until(pilot, lambda: app.link.why_not("wheel1") == "", "wheel1 seen")
            app.operator.select("wheel1")
            (component,) = [c for c in rig.executor.components if c.name == "wheel1/joint_manager"]
            rig.executor.post(lambda: rig.executor.remove(component))
            await until(pilot, lambda: "GONE" in app.unable.get("wheel1", ""), "wheel1 gone")
            await pilot.press("w")
            await pilot.pause(0.3)
            assert "NOT MOVING: wheel1 is GONE" in text_of(app, "#deadman")
            assert app.operator.moves_sent == 0

    asyncio.run(scenario())
    # A teleop opened now on the stopped module: refused at once, saying so.
    session = open_session(session_settings)
    node = Node(session, "late_teleop")
    started = time.monotonic()
    try:
        with pytest.raises(NetworkError, match="wheel1 not running") as refused:
            Link.open(node, dragon, ["limb1", "wheel1"], health=False, timeout=120.0, claim=False)
        assert "is the assembly up" not in str(refused.value)
        # Well before the bound it was given (a wait for the joint manager's answer).
        assert time.monotonic() - started < 60.0
    finally:
        node.close()
        session.close()
