"""Operator presence with plain calls and fake time: the pure rules, then the joint manager's
hold that follows them (motors held, commands refused, health saying why, counted)."""

from __future__ import annotations

import math

import pytest

from components.joint_manager import JointManagerCore
from components.joint_manager.presence import BACK, LOST, OperatorPresence, Station
from components.joints import JointSpec
from components.messages import (
    ERROR,
    OK,
    JointSample,
    diagnostic_values,
    joint_samples,
    joint_state,
    msg,
)

GC1 = Station("gc1", "ground1")
GC2 = Station("gc2", "ground2")
TRIGGER = msg("std_srvs/srv/Trigger_Request")


def watch(*stations: Station, timeout: float = 3.0, start: float = 0.0) -> OperatorPresence:
    presence = OperatorPresence(stations or (GC1,), timeout)
    presence.start(start)
    return presence


# ---------------------------------------------------------------------------- the rules


def test_a_station_lost_for_more_than_the_threshold_holds_the_module() -> None:
    presence = watch()
    presence.on_station("gc1", True, 0.5)
    assert presence.update(1.0) is None and presence.attended
    presence.on_station("gc1", False, 10.0)
    assert presence.update(13.0) is None  # exactly the threshold: not yet
    assert not presence.held
    assert presence.update(13.001) == LOST
    assert presence.held and presence.holds == 1
    assert presence.update(20.0) is None  # said once
    assert presence.reason(20.0) == "no operator: gc1 (ground1) unreachable for 10.0 s"


def test_the_hold_lifts_the_moment_a_station_is_visible_again() -> None:
    presence = watch()
    presence.on_station("gc1", True, 0.0)
    presence.on_station("gc1", False, 1.0)
    assert presence.update(5.0) == LOST
    presence.on_station("gc1", True, 9.5)
    assert presence.update(9.5) == BACK
    assert not presence.held
    said = presence.lifted(10.0, window=5.0)
    assert said is not None
    assert "gc1 (ground1) visible again after 8.5 s" in said
    assert presence.lifted(14.6, window=5.0) is None  # said for the window only


def test_a_blip_shorter_than_the_threshold_never_holds() -> None:
    presence = watch()
    presence.on_station("gc1", True, 0.0)
    for t in range(1, 20, 2):  # gone 2.9 s of every 3: a flapping link, never 3 s
        presence.on_station("gc1", False, float(t))
        assert presence.update(t + 2.9) is None
        presence.on_station("gc1", True, t + 2.95)
        assert presence.update(t + 2.95) is None
    assert presence.holds == 0


def test_one_station_of_several_suffices() -> None:
    presence = watch(GC1, GC2)
    presence.on_station("gc1", True, 0.0)
    presence.on_station("gc2", True, 0.0)
    presence.on_station("gc1", False, 1.0)
    assert presence.update(100.0) is None and presence.visible() == ["gc2"]
    presence.on_station("gc2", False, 100.0)
    assert presence.update(103.5) == LOST
    assert presence.reason(103.5) == (
        "no operator: gc1 (ground1), gc2 (ground2) unreachable for 3.5 s"
    )
    presence.on_station("gc2", True, 104.0)  # either one brings it back
    assert presence.update(104.0) == BACK


def test_a_visible_claim_holder_attends_the_module_alone() -> None:
    # An operator at the robot itself claims it (msctl teleop does): the ground's cut
    # link does not hold what that operator drives.
    presence = watch()
    presence.on_station("gc1", True, 0.0)
    presence.on_holder("tech@hl-limb-01", 1.0)
    presence.on_station("gc1", False, 2.0)
    assert presence.update(60.0) is None and presence.attended
    presence.on_holder(None, 60.0)  # released (or cut off: the robot cannot tell)
    assert presence.update(63.0) is None
    assert presence.update(63.1) == LOST


def test_a_link_cut_takes_holder_and_station_in_either_order_and_names_both() -> None:
    for order in ("holder first", "station first"):
        presence = watch()
        presence.on_station("gc1", True, 0.0)
        presence.on_holder("ann@ground1", 0.5)
        if order == "holder first":
            presence.on_holder(None, 10.0)
            presence.on_station("gc1", False, 10.01)
        else:
            presence.on_station("gc1", False, 10.0)
            presence.on_holder(None, 10.01)
        assert presence.update(13.5) == LOST, order
        assert presence.reason(13.5).startswith(
            "no operator: claim holder ann@ground1, gc1 (ground1) unreachable for 3."
        ), order


def test_a_claim_released_long_before_the_cut_is_not_named() -> None:
    presence = watch()
    presence.on_station("gc1", True, 0.0)
    presence.on_holder("ann@ground1", 1.0)
    presence.on_holder(None, 2.0)  # released; the station still watches
    presence.on_station("gc1", False, 100.0)
    assert presence.update(104.0) == LOST
    assert presence.reason(104.0) == "no operator: gc1 (ground1) unreachable for 4.0 s"


def test_a_new_claim_holder_during_a_hold_lifts_it() -> None:
    presence = watch()
    presence.on_station("gc1", True, 0.0)
    presence.on_station("gc1", False, 1.0)
    assert presence.update(4.5) == LOST
    presence.on_holder("tech@hl-limb-01", 8.0)
    assert presence.update(8.0) == BACK
    assert "claim holder tech@hl-limb-01 visible again" in str(presence.lifted(8.0, 5.0))


def test_start_up_grace_the_ground_coming_up_late_within_the_threshold_holds_nothing() -> None:
    presence = watch(start=100.0)
    assert presence.update(102.0) is None
    presence.on_station("gc1", True, 102.0)  # the ground came up 2 s after the robot
    assert presence.update(200.0) is None and presence.holds == 0


def test_start_up_nobody_ever_watching_holds_after_the_threshold_and_says_so() -> None:
    presence = watch(start=100.0)
    assert presence.update(103.0) is None
    assert presence.update(103.01) == LOST
    assert presence.reason(104.0) == ("no operator since start: gc1 (ground1) not seen for 4.0 s")
    presence.on_station("gc1", True, 110.0)  # the ground came up 10 s late: it lifts
    assert presence.update(110.0) == BACK


def test_events_before_start_start_the_watch() -> None:
    presence = OperatorPresence([GC1], 3.0)
    presence.on_station("gc1", False, 5.0)  # the first thing it hears
    assert presence.update(8.0) is None
    assert presence.update(8.5) == LOST


def test_without_stations_only_a_claim_holder_attends() -> None:
    presence = OperatorPresence([], 2.0)
    presence.start(0.0)
    assert presence.update(2.5) == LOST
    assert presence.reason(2.5) == "no operator since start: no claim holder not seen for 2.5 s"
    presence.on_holder("ann@laptop", 3.0)
    assert presence.update(3.0) == BACK


def test_bad_settings_are_refused() -> None:
    for timeout in (0.0, -1.0, math.inf, math.nan):
        with pytest.raises(ValueError, match="operator_timeout"):
            OperatorPresence([GC1], timeout)
    with pytest.raises(ValueError, match="named twice"):
        OperatorPresence([GC1, Station("gc1", "ground9")], 3.0)
    with pytest.raises(KeyError, match="no station 'gc9'"):
        watch().on_station("gc9", True, 1.0)


# ---------------------------------------------------------------------------- the joint manager

J1, WHEEL = "limb1_joint1", "limb1_wheel"


def manager(timeout: float = 3.0) -> JointManagerCore:
    joints = [
        JointSpec(J1, lower=-1.0, upper=1.0, max_velocity=2.0, max_effort=5.0),
        JointSpec(WHEEL, type="continuous", lower=-math.inf, upper=math.inf, max_velocity=4.0),
    ]
    core = JointManagerCore(
        "limb1/joint_manager",
        module="limb1",
        joints=joints,
        presence=OperatorPresence([GC1], timeout),
    )
    core.start(0.0)
    core.on_station("gc1", True, 0.1)
    return core


def commands(core: JointManagerCore) -> dict[str, JointSample]:
    return {s.name: s for m in core.outbox.take("joint_commands") for s in joint_samples(m)}


def feed(core: JointManagerCore, now: float, position: float = 0.2) -> None:
    core.on_joint_states(joint_state([JointSample(J1, position, 0.0, 0.0)]), now)


def manager_status(core: JointManagerCore, now: float) -> tuple[int, str, dict[str, str]]:
    status = core.diagnostics(now).status[0]
    return int(status.level), status.message, diagnostic_values(status)


def test_the_manager_holds_every_joint_refuses_commands_and_says_why() -> None:
    core = manager()
    feed(core, 1.0)
    core.on_joint_set(joint_state([JointSample(WHEEL, None, 1.5, None)]), 1.0)
    assert commands(core)[WHEEL].velocity == 1.5
    core.on_station("gc1", False, 2.0)
    for t in (2.5, 3.0, 4.9):
        feed(core, t)
        core.on_joint_set(joint_state([JointSample(WHEEL, None, 1.5, None)]), t)
        core.tick(t)
    core.outbox.take()
    core.tick(5.01)  # 3.01 s without an operator
    held = commands(core)
    assert held[WHEEL].velocity == 0.0  # the wheel stops
    assert held[J1].position == pytest.approx(0.2) and held[J1].velocity == 0.0
    assert core.presence_held and not core.halted
    level, message, values = manager_status(core, 5.5)
    assert level == ERROR
    assert "no operator: gc1 (ground1) unreachable for 3.5 s" in message
    assert values["presence_holds"] == "1" and values["operators"] == "none: held"
    # Each joint says it too: the module's health monitor reads the joints' statuses.
    for joint in core.diagnostics(5.5).status[1:]:
        assert int(joint.level) == ERROR
        assert joint.message.startswith("held: no operator: gc1 (ground1) unreachable for 3.5 s")
    core.on_joint_set(joint_state([JointSample(WHEEL, None, 1.5, None)]), 6.0)
    assert commands(core) == {}
    assert core.counters["refused_no_operator"] == 1
    assert "held until one is visible" in manager_status(core, 6.0)[1]


def test_the_operator_back_lifts_the_hold_and_commands_move_again() -> None:
    core = manager()
    feed(core, 1.0)
    core.on_station("gc1", False, 2.0)
    core.tick(5.1)
    assert core.presence_held
    core.outbox.take()
    core.on_station("gc1", True, 9.0)
    assert not core.presence_held
    assert commands(core) == {}  # nothing moves by itself: held until commanded
    feed(core, 9.5)
    level, message, values = manager_status(core, 9.5)
    assert level == OK
    assert "operator back: gc1 (ground1) visible again after 7.0 s" in message
    assert values["operators"] == "gc1"
    for joint in core.diagnostics(9.5).status[1:]:  # what the module's health shows
        assert "operator back: gc1 (ground1)" in joint.message, joint.message
    core.on_joint_set(joint_state([JointSample(WHEEL, None, 1.0, None)]), 9.5)
    assert commands(core)[WHEEL].velocity == 1.0
    feed(core, 20.0)
    assert "operator back" not in manager_status(core, 20.0)[1]  # said for its window only


def test_a_halt_asked_for_stays_after_the_operator_returns_until_recover() -> None:
    core = manager()
    feed(core, 1.0)
    core.on_halt(TRIGGER, 1.5)
    core.on_station("gc1", False, 2.0)
    core.tick(5.5)
    assert core.presence_held and core.halted
    core.on_station("gc1", True, 8.0)
    assert not core.presence_held and core.halted  # the operator's return lifts only its own
    core.outbox.take()
    core.on_joint_set(joint_state([JointSample(WHEEL, None, 1.0, None)]), 8.5)
    assert commands(core) == {} and core.counters["refused_halted"] == 1
    level, message, _ = manager_status(core, 8.5)
    assert level == ERROR and "halted: commands refused until recover" in message
    core.on_recover(TRIGGER, 9.0)
    feed(core, 9.0)
    core.on_joint_set(joint_state([JointSample(WHEEL, None, 1.0, None)]), 9.0)
    assert commands(core)[WHEEL].velocity == 1.0


def test_recover_does_not_lift_the_presence_hold_and_says_so() -> None:
    core = manager()
    core.on_station("gc1", False, 2.0)
    core.tick(5.5)
    response = core.on_recover(TRIGGER, 6.0)
    assert response.success
    assert "still held: no operator: gc1 (ground1) unreachable for 4.0 s" in response.message
    assert core.presence_held


def test_a_manager_without_presence_never_holds_for_it() -> None:
    core = JointManagerCore(
        "limb1/joint_manager",
        module="limb1",
        joints=[JointSpec(WHEEL, type="continuous", lower=-math.inf, upper=math.inf)],
    )
    core.start(0.0)
    core.on_station("gc1", False, 1.0)  # a stray event: ignored
    core.tick(1000.0)
    assert not core.presence_held
    assert manager_status(core, 1000.0)[2]["operators"] == "not watched"
