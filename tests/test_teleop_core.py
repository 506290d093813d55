"""The teleop core with plain calls and fake time: keys to commands in every mode, speed
scaling, the rate limit, the deadman's two timeouts and exactly one stop, then silence."""

from __future__ import annotations

import itertools

import pytest

from msctl.teleop.core import Deadman, Move, Stop, TeleopCore, TeleopSettings
from msctl.teleop.keys import DRIVE, DRIVE_MOVES, IK, IK_MOVES, JOINT

PERIOD = 0.05
MODULES = {"limb1": ("limb1_joint1", "limb1_joint2"), "wheel1": ("wheel1_wheel_left",)}


def core(mode: str = JOINT, **settings: float) -> TeleopCore:
    return TeleopCore(
        TeleopSettings(**settings),
        MODULES,
        limbs=("limb1", "limb2"),
        drive_target="/cmd_vel",
        mode=mode,
    )


def run(
    c: TeleopCore,
    start: float,
    end: float,
    keys: list[tuple[float, str]] = (),
    step: float = 0.001,
) -> list[tuple[float, object]]:
    """Tick every ``step`` seconds from ``start`` to ``end``, pressing ``keys`` (time, key)
    at their times; every command with its time."""
    pending = sorted(keys)
    out = []
    t = start
    while t <= end + 1e-12:
        while pending and pending[0][0] <= t + 1e-12:
            c.press(pending.pop(0)[1], t)
        out.extend((t, command) for command in c.tick(t))
        t = round(t + step, 9)
    return out


def held(key: str, start: float, until: float, repeat: float = 0.033) -> list[tuple[float, str]]:
    """A key held as a terminal reports it: the press, then repeats after 0.5 s."""
    events = [(start, key)]
    t = start + 0.5
    while t <= until:
        events.append((round(t, 3), key))
        t += repeat
    return events


# ------------------------------------------------------------------------------ the deadman
def test_deadman_is_long_until_the_first_repeat_then_short() -> None:
    d = Deadman(0.6, 0.15)
    assert not d.alive(0.0)
    d.event("w", 0.0)
    assert d.alive(0.59) and not d.alive(0.6)
    d.event("w", 0.5)  # the first repeat
    assert d.repeating and d.alive(0.64) and not d.alive(0.65)
    d.event("s", 0.6)  # another key: a new press, the long timeout again
    assert not d.repeating and d.alive(1.19)
    d.release()
    assert not d.alive(0.61) and d.expiry() is None


def test_the_same_key_after_the_deadman_ran_out_is_a_new_press() -> None:
    d = Deadman(0.6, 0.15)
    d.event("w", 0.0)
    d.event("w", 0.7)
    assert not d.repeating and d.expiry() == pytest.approx(1.3)


# --------------------------------------------------------------------------- key to command
def test_a_motion_key_gives_a_command_at_once() -> None:
    c = core()
    assert c.press("w", 10.0) == "move"
    (move,) = c.tick(10.0)
    assert move == Move(JOINT, "limb1", "limb1_joint1", (0.2,), PERIOD, True)
    assert c.moving


def test_joint_mode_s_jogs_the_other_way_and_selection_picks_module_and_joint() -> None:
    c = core()
    assert c.press("down", 0.0) == "select"
    c.press("s", 0.0)
    (move,) = c.tick(0.0)
    assert (move.target, move.joint, move.velocity) == ("limb1", "limb1_joint2", (-0.2,))
    c.stop("test", 0.0)
    c.tick(0.0)
    assert c.press("tab", 1.0) == "select" and c.module == "wheel1"
    assert c.press("down", 1.0) == "select" and c.joint == "wheel1_wheel_left"  # wraps
    assert c.press("left", 1.0) == "select" and c.module == "limb1"
    assert c.joint == "limb1_joint2"  # each module keeps its joint


def test_ik_mode_maps_arrows_ik_and_shifted_letters_to_tip_twists() -> None:
    c = core(IK)
    expected = {
        "up": (0.03, 0, 0, 0, 0, 0),
        "left": (0, 0.03, 0, 0, 0, 0),
        "k": (0, 0, -0.03, 0, 0, 0),
        "W": (0, 0, 0, 0, 0.2, 0),
        "D": (0, 0, 0, 0, 0, -0.2),
        "Q": (0, 0, 0, 0.2, 0, 0),
    }
    t = 0.0
    for key, velocity in expected.items():
        c.press(key, t)
        (move,) = [x for x in c.tick(t) if isinstance(x, Move)]
        assert move.mode == IK and move.target == "limb1" and move.joint is None
        assert move.velocity == pytest.approx(velocity)
        t += 0.1  # a period and more: each key's command goes out at once
    assert set(IK_MOVES) == {"up", "down", "left", "right", "i", "k", *"QEWSAD"}
    assert c.press("tab", t) == "select" and c.limb == "limb2"


def test_drive_mode_is_teleop_twist_keyboards_layout() -> None:
    c = core(DRIVE)
    expected = {
        "i": (0.2, 0.0, 0.0),
        "u": (0.2, 0.0, 0.5),
        ".": (-0.2, 0.0, 0.5),
        "J": (0.0, 0.2, 0.0),
        ">": (-0.2, -0.2, 0.0),
    }
    t = 0.0
    for key, velocity in expected.items():
        c.press(key, t)
        moves = [cmd for cmd in c.tick(t) if isinstance(cmd, Move)]
        assert moves[-1].target == "/cmd_vel"
        assert moves[-1].velocity == pytest.approx(velocity)
        t += 0.1
    assert len(DRIVE_MOVES) == 16


def test_drive_k_and_any_unbound_key_stop_at_once() -> None:
    c = core(DRIVE)
    c.press("i", 0.0)
    c.tick(0.0)
    assert c.press("k", 0.01) == "stop"
    assert c.tick(0.01) == [Stop(DRIVE, "/cmd_vel", None, "k")]
    c.press("i", 0.02)
    c.tick(0.02)
    assert c.press("y", 0.03) == "stop"
    assert c.tick(0.03) == [Stop(DRIVE, "/cmd_vel", None, "key y")]


# --------------------------------------------------------------------------------- speeds
def test_q_and_z_scale_the_joint_speed_by_11_and_09_within_bounds() -> None:
    c = core(max_joint_speed=0.25)
    assert c.press("q", 0.0) == "speed"
    assert c.speeds["joint_speed"] == pytest.approx(0.22)
    c.press("z", 0.0)
    assert c.speeds["joint_speed"] == pytest.approx(0.198)
    for _ in range(10):
        c.press("q", 0.0)
    assert c.speeds["joint_speed"] == pytest.approx(0.25)  # the ceiling
    for _ in range(200):
        c.press("z", 0.0)
    assert c.speeds["joint_speed"] == pytest.approx(0.002)  # 1 % of the start
    assert "joint_speed" in c.note


def test_drive_speed_keys_scale_linear_and_angular_as_teleop_twist_keyboard() -> None:
    c = core(DRIVE)
    c.press("w", 0.0)
    assert (c.speeds["drive_speed"], c.speeds["drive_turn"]) == pytest.approx((0.22, 0.5))
    c.press("c", 0.0)
    assert (c.speeds["drive_speed"], c.speeds["drive_turn"]) == pytest.approx((0.22, 0.45))
    c.press("q", 0.0)
    assert (c.speeds["drive_speed"], c.speeds["drive_turn"]) == pytest.approx((0.242, 0.495))
    # IK's q/z scale its two speeds and leave drive's alone.
    c.set_mode(IK, 0.0)
    c.press("z", 0.0)
    assert c.speeds["tip_speed"] == pytest.approx(0.027)
    assert c.speeds["tip_turn"] == pytest.approx(0.18)
    assert c.speeds["drive_speed"] == pytest.approx(0.242)


def test_a_speed_change_applies_to_the_next_command_without_stopping() -> None:
    c = core()
    c.press("w", 0.0)
    c.tick(0.0)
    c.press("q", 0.01)
    commands = c.tick(0.05)
    assert [type(x) for x in commands] == [Move]
    assert commands[0].velocity == pytest.approx((0.22,))


# ------------------------------------------------------------------------------ the rate
def test_commands_go_out_at_the_rate_while_the_key_is_held() -> None:
    c = core()
    # Ticks every millisecond, many more than the rate: the core paces itself.
    moves = [(t, m) for t, m in run(c, 0.0, 2.0, held("w", 0.0, 2.0)) if isinstance(m, Move)]
    times = [t for t, _ in moves]
    gaps = [b - a for a, b in itertools.pairwise(times)]
    assert min(gaps) >= PERIOD - 1e-9
    assert len(moves) == pytest.approx(2.0 / PERIOD + 1, abs=1)
    assert moves[0][1].first and not any(m.first for _, m in moves[1:])
    assert all(m.dt == pytest.approx(PERIOD) for _, m in moves)


def test_key_repeats_faster_than_the_rate_do_not_add_commands() -> None:
    c = core()
    c.press("w", 0.0)
    assert len(c.tick(0.0)) == 1
    for t in (0.01, 0.02, 0.03, 0.04):
        c.press("w", t)
        assert c.tick(t) == []
    assert len(c.tick(0.05)) == 1


def test_a_late_tick_gives_one_command_with_dt_capped_at_two_periods() -> None:
    c = core()
    run(c, 0.0, 0.5, held("w", 0.0, 0.5, repeat=0.02))
    c.press("w", 0.6)  # repeats come, no tick until 0.7
    (move,) = c.tick(0.7)  # the thread slept: one command, never a catch-up burst
    assert move.dt == pytest.approx(2 * PERIOD)
    assert c.tick(0.7) == [] and c.next_wake(0.7) == pytest.approx(0.75)


# ---------------------------------------------------------------------- exactly one stop
def test_the_deadman_gives_exactly_one_stop_at_the_timeout_then_silence() -> None:
    c = core()
    c.press("w", 0.0)  # a tap: no repeat
    commands = run(c, 0.0, 5.0)
    stops = [(t, x) for t, x in commands if isinstance(x, Stop)]
    assert len(stops) == 1
    t_stop, stop = stops[0]
    assert stop == Stop(JOINT, "limb1", "limb1_joint1", "deadman")
    assert t_stop == pytest.approx(0.6)
    assert commands[-1][1] is stop  # silence after it
    assert not c.moving and c.next_wake(5.0) is None


def test_after_repeats_the_stop_comes_the_short_timeout_after_the_last_key() -> None:
    c = core()
    keys = held("w", 0.0, 1.0, repeat=0.033)
    last_key = keys[-1][0]
    commands = run(c, 0.0, 3.0, keys)
    stops = [t for t, x in commands if isinstance(x, Stop)]
    assert stops == [pytest.approx(last_key + 0.15, abs=0.0015)]
    moves = [t for t, x in commands if isinstance(x, Move)]
    assert max(moves) < last_key + 0.15


def test_the_stop_is_due_within_one_period_of_the_timeout_when_ticked_at_the_rate() -> None:
    c = core()
    c.press("w", 0.0)
    # Ticks only at next_wake, as the operator thread does.
    t = 0.0
    seen = []
    for _ in range(100):
        seen.extend((t, x) for x in c.tick(t))
        wake = c.next_wake(t)
        if wake is None:
            break
        t = wake
    (t_stop,) = [t for t, x in seen if isinstance(x, Stop)]
    assert 0.6 <= t_stop <= 0.6 + PERIOD


@pytest.mark.parametrize(
    ("how", "reason"),
    [
        (lambda c, t: c.set_mode(IK, t), "mode changed"),
        (lambda c, t: c.stop("focus lost", t), "focus lost"),
        (lambda c, t: c.stop("quit", t), "quit"),
        (lambda c, t: c.press("down", t), "another joint"),
        (lambda c, t: c.press("tab", t), "another module"),
        (lambda c, t: c.press("x", t), "key x"),
        (lambda c, t: c.press("2", t), "mode changed"),
    ],
)
def test_every_way_to_end_a_motion_gives_one_stop(how, reason) -> None:
    c = core()
    run(c, 0.0, 0.9, held("w", 0.0, 1.0))
    how(c, 0.95)
    commands = run(c, 0.95, 3.0)
    assert commands == [(0.95, Stop(JOINT, "limb1", "limb1_joint1", reason))]
    # A second reason to stop, with nothing moving, says nothing.
    c.stop("again", 3.0)
    assert c.tick(3.0) == [] and c.stops == 1


def test_no_stop_when_nothing_moved() -> None:
    c = core()
    c.stop("focus lost", 0.0)
    c.set_mode(DRIVE, 0.0)
    c.press("k", 0.0)
    assert run(c, 0.0, 2.0) == []
    # A key pressed and withdrawn before any tick: no command, so no stop either.
    c.press("i", 3.0)
    c.stop("focus lost", 3.0)
    assert run(c, 3.0, 5.0) == []


def test_a_direction_change_on_the_same_joint_is_no_stop() -> None:
    c = core()
    c.press("w", 0.0)
    c.tick(0.0)
    c.press("s", 0.03)
    assert c.tick(0.03) == []  # the rate limit holds it a period
    (move,) = c.tick(0.05)
    assert move.velocity == (-0.2,) and not move.first


def test_a_key_after_the_deadman_ran_out_gets_the_stop_first_then_a_new_motion() -> None:
    c = core()
    c.press("w", 0.0)
    c.tick(0.0)
    c.press("w", 0.7)  # no tick since 0.0: the deadman ran out at 0.6
    stop, move = c.tick(0.7)
    assert isinstance(stop, Stop) and stop.reason == "deadman"
    assert isinstance(move, Move) and move.first


def test_modes_without_anything_to_command_are_refused() -> None:
    c = TeleopCore(modules=MODULES)
    assert c.press("2", 0.0) == "refused" and "IK mode needs a limb" in c.note
    assert c.press("3", 0.0) == "refused" and "drive mode needs" in c.note
    assert c.mode == JOINT
    with pytest.raises(ValueError, match="IK mode needs a limb"):
        TeleopCore(modules=MODULES, mode=IK)
    with pytest.raises(ValueError, match="unknown mode"):
        TeleopCore(modules=MODULES, mode="fly")


def test_settings_are_checked() -> None:
    with pytest.raises(ValueError, match="rate"):
        TeleopSettings(rate=0.0)
    with pytest.raises(ValueError, match="joint_speed"):
        TeleopSettings(joint_speed=2.0, max_joint_speed=1.0)


def test_select_by_name() -> None:
    c = core()
    c.select("wheel1")
    assert (c.module, c.joint) == ("wheel1", "wheel1_wheel_left")
    c.select("limb1", "limb1_joint2")
    assert c.joint == "limb1_joint2"
    with pytest.raises(KeyError, match="modules: limb1, wheel1"):
        c.select("limb9")


# --------------------------------------------------------------------- claims taken over
def test_a_module_taken_over_stops_its_motion_once_and_refuses_its_keys() -> None:
    c = core()
    c.press("w", 0.0)
    c.tick(0.0)
    c.block("limb1", "limb1 was taken over by bob@gc2", 0.01)
    assert c.tick(0.01) == [Stop(JOINT, "limb1", "limb1_joint1", "claim lost")]
    assert c.press("w", 0.02) == "refused" and "bob@gc2" in c.note
    assert run(c, 0.02, 2.0) == []
    # Another module is still commanded; the drive (the whole robot) is not.
    c.press("tab", 2.0)
    assert c.press("w", 2.0) == "move" and c.tick(2.0)
    c.set_mode(DRIVE, 2.1)
    assert c.press("i", 2.2) == "refused"
    assert c.view().blocked == {"limb1": "limb1 was taken over by bob@gc2"}
    c.unblock("limb1")
    assert c.press("i", 2.3) == "move"


def test_blocking_a_module_that_is_not_moving_sends_nothing() -> None:
    c = core(DRIVE)
    c.block("wheel1", "taken", 0.0)
    assert run(c, 0.0, 1.0) == []
