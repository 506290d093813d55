"""Joint Manager core with plain calls and fake time: every ``now`` is a number we pass."""

from __future__ import annotations

import math
import random
import tomllib

import pytest

from components.executor.interface import Serve
from components.executor.registry import RegistryError, apply_all
from components.joint_manager import JointManagerConfig, JointManagerCore, Refusal
from components.joint_manager.calibration_file import (
    CalibrationFileError,
    updated_text,
    write_zero_offsets,
)
from components.joint_manager.interface import JOINT_MANAGER
from components.joints import JointCalibration, JointSpec
from components.messages import (
    ERROR,
    OK,
    STALE,
    WARN,
    JointSample,
    diagnostic_values,
    joint_samples,
    joint_state,
    msg,
)
from components.roles import Role

TRIGGER_REQ = msg("std_srvs/srv/Trigger_Request")
LIST_REQ = msg("msctl_msgs/srv/ListJoints_Request")

J1, J2, WHEEL = "limb1_joint1", "limb1_joint2", "limb1_wheel"


def specs(module: str = "limb1") -> list[JointSpec]:
    return [
        JointSpec(f"{module}_joint1", lower=-1.0, upper=1.0, max_velocity=2.0, max_effort=5.0),
        JointSpec(f"{module}_joint2", lower=-2.0, upper=2.0, max_velocity=1.0, max_effort=3.0),
        JointSpec(
            f"{module}_wheel", type="continuous", lower=-math.inf, upper=math.inf, max_velocity=4.0
        ),
    ]


# joint1 is reversed and offset, joint2 offset only, the wheel uncalibrated.
CAL = {
    "joint1": JointCalibration(zero_offset=0.5, direction=-1),
    "limb1_joint2": JointCalibration(zero_offset=-0.25, direction=1),
}


def make(module: str = "limb1", **config: float) -> JointManagerCore:
    calibration = {k.replace("limb1", module): v for k, v in CAL.items()}
    return JointManagerCore(
        f"{module}_joint_manager",
        module=module,
        joints=specs(module),
        calibration=calibration,
        config=JointManagerConfig(**config),
    )


def state(*samples: JointSample) -> object:
    return joint_state(samples)


def sent(core: JointManagerCore, topic: str) -> list[JointSample]:
    """Take every sample published on ``topic`` (flattened over messages)."""
    return [s for m in core.outbox.take(topic) for s in joint_samples(m)]


def by_name(samples: list[JointSample]) -> dict[str, JointSample]:
    return {s.name: s for s in samples}


def feed(core: JointManagerCore, now: float, **raw_positions: float) -> None:
    """Raw feedback (position only, velocity 0) for the named joints (``joint1=...``)."""
    core.on_joint_states(
        state(*(JointSample(f"{core.module}_{k}", v, 0.0, 0.0) for k, v in raw_positions.items())),
        now,
    )


def feed_calibrated(core: JointManagerCore, now: float, **positions: float) -> None:
    """Feedback given in calibrated space (converted to raw with the core's calibration)."""
    raw = {k: core.calibration(k).to_raw(v) for k, v in positions.items()}
    feed(core, now, **raw)


def approx(value: float | None) -> object:
    return pytest.approx(value, abs=1e-12)


def assert_within_limits(core: JointManagerCore, commands: list[JointSample]) -> None:
    for c in commands:
        spec, cal = core.spec(c.name), core.calibration(c.name)
        margin = core.config.position_margin
        if c.position is not None and spec.bounded:
            p = cal.to_calibrated(c.position)
            assert spec.lower + margin - 1e-12 <= p <= spec.upper - margin + 1e-12, c
        if c.velocity is not None:
            assert abs(c.velocity) <= spec.max_velocity + 1e-12, c
        if c.effort is not None:
            assert abs(c.effort) <= spec.max_effort + 1e-12, c


# ---------------------------------------------------------------------------- calibration


def test_calibration_round_trip_both_ways_position_velocity_effort() -> None:
    core = make()
    core.on_joint_states(
        state(JointSample(J1, 0.7, 0.3, 1.0), JointSample(J2, 0.75, -0.4, 2.0)), now=0.0
    )
    read = by_name(sent(core, "joint_read"))
    # joint1: direction -1, offset 0.5 -> calibrated = -(raw - 0.5); rates flip sign.
    assert read[J1].position == approx(-0.2)
    assert read[J1].velocity == approx(-0.3)
    assert read[J1].effort == approx(-1.0)
    # joint2: direction +1, offset -0.25.
    assert read[J2].position == approx(1.0)
    assert read[J2].velocity == approx(-0.4)
    assert read[J2].effort == approx(2.0)

    # Commanding exactly what was read gives back the raw feedback.
    core.on_joint_set(state(read[J1], read[J2]), now=0.01)
    cmd = by_name(sent(core, "joint_commands"))
    assert cmd[J1].position == approx(0.7)
    assert cmd[J1].velocity == approx(0.3)
    assert cmd[J1].effort == approx(1.0)
    assert cmd[J2].position == approx(0.75)
    assert cmd[J2].velocity == approx(-0.4)
    assert cmd[J2].effort == approx(2.0)
    assert core.counters["clamped"] == 0


def test_calibration_keyed_by_unknown_joint_is_rejected() -> None:
    with pytest.raises(ValueError, match="joint7"):
        JointManagerCore("jm", "limb1", specs(), {"joint7": JointCalibration()})
    with pytest.raises(ValueError, match="limb1_<joint>"):
        JointManagerCore("jm", "limb1", [JointSpec("limb2_joint1")])
    with pytest.raises(ValueError, match="watchdog_timeout"):
        JointManagerConfig(watchdog_timeout=0.0)


# ---------------------------------------------------------------------------- clamps


def test_position_clamped_to_limits_minus_margin_both_sides() -> None:
    core = make(position_margin=0.02)
    core.on_joint_set(state(JointSample(J1, 5.0), JointSample(J2, -9.0)), now=0.0)
    cmd = by_name(sent(core, "joint_commands"))
    # joint1 upper 1.0 - 0.02 = 0.98 calibrated -> raw 0.5 - 0.98.
    assert cmd[J1].position == approx(0.5 - 0.98)
    # joint2 lower -2.0 + 0.02 = -1.98 calibrated -> raw -1.98 - 0.25.
    assert cmd[J2].position == approx(-2.23)
    assert core.counters["clamped"] == 2

    core.on_joint_set(state(JointSample(J1, -1.0)), now=0.1)
    assert sent(core, "joint_commands")[0].position == approx(0.5 + 0.98)
    assert core.counters["clamped"] == 3
    # A command inside the limits is not counted.
    core.on_joint_set(state(JointSample(J1, 0.3)), now=0.2)
    assert sent(core, "joint_commands")[0].position == approx(0.2)
    assert core.counters["clamped"] == 3


def test_velocity_and_effort_magnitudes_clamped() -> None:
    core = make()
    core.on_joint_set(
        state(JointSample(J1, 0.0, 10.0, -50.0), JointSample(J2, 0.0, -10.0, 50.0)), now=0.0
    )
    cmd = by_name(sent(core, "joint_commands"))
    # joint1 is reversed: calibrated +2 (max) is raw -2; calibrated -5 effort is raw +5.
    assert cmd[J1].velocity == approx(-2.0)
    assert cmd[J1].effort == approx(5.0)
    assert cmd[J2].velocity == approx(-1.0)
    assert cmd[J2].effort == approx(3.0)
    assert core.counters["clamped"] == 2


def test_velocity_toward_a_near_limit_becomes_hold() -> None:
    core = make(velocity_limit_lookahead=0.1, position_margin=0.02)
    feed_calibrated(core, 0.0, joint1=0.95, joint2=0.0)
    core.outbox.take()

    # 0.95 + 1.0 * 0.1 crosses 0.98: hold where it is, velocity 0.
    core.on_joint_set(state(JointSample(J1, velocity=1.0)), now=0.01)
    (hold,) = sent(core, "joint_commands")
    assert hold.position == approx(core.calibration("joint1").to_raw(0.95))
    assert hold.velocity == 0.0
    assert core.counters["clamped"] == 1

    # Away from the limit is fine, and the velocity goes out in raw space (sign flipped).
    core.on_joint_set(state(JointSample(J1, velocity=-1.0)), now=0.02)
    (away,) = sent(core, "joint_commands")
    assert (away.position, away.velocity) == (None, approx(1.0))

    # Far from the limits, velocity passes.
    core.on_joint_set(state(JointSample(J2, velocity=0.5)), now=0.03)
    assert sent(core, "joint_commands") == [JointSample(J2, None, 0.5, None)]

    # Already inside the margin band: the hold itself is clamped inside the limits.
    feed_calibrated(core, 0.04, joint1=0.995)
    core.outbox.take()
    core.on_joint_set(state(JointSample(J1, velocity=0.1)), now=0.05)
    (hold,) = sent(core, "joint_commands")
    assert core.calibration("joint1").to_calibrated(hold.position) == approx(0.98)
    assert hold.velocity == 0.0


def test_velocity_mode_joint_is_held_at_the_limit_between_commands() -> None:
    core = make(velocity_limit_lookahead=0.1, position_margin=0.02, watchdog_timeout=0.5)
    feed_calibrated(core, 0.0, joint1=0.5)
    core.on_joint_set(state(JointSample(J1, velocity=1.0)), now=0.0)
    core.outbox.take()
    # No new command (well within the watchdog timeout) while the joint runs up to the limit.
    feed_calibrated(core, 0.2, joint1=0.7)
    assert sent(core, "joint_commands") == []
    feed_calibrated(core, 0.3, joint1=0.9)  # 0.9 + 0.1 crosses 0.98
    (hold,) = sent(core, "joint_commands")
    assert core.calibration("joint1").to_calibrated(hold.position) == approx(0.9)
    assert hold.velocity == 0.0
    assert core.counters["clamped"] == 1
    # Held: no hold storm, and the watchdog has nothing left to stop.
    feed_calibrated(core, 0.35, joint1=0.91)
    core.tick(1.0)
    assert sent(core, "joint_commands") == []
    assert core.counters["watchdog_trips"] == 0


def test_effort_mode_joint_moving_into_a_limit_is_held() -> None:
    core = make(velocity_limit_lookahead=0.1)
    feed_calibrated(core, 0.0, joint1=-0.5)
    core.on_joint_set(state(JointSample(J1, effort=-2.0)), now=0.0)
    assert sent(core, "joint_commands") == [JointSample(J1, None, None, approx(2.0))]
    raw = core.calibration("joint1").to_raw(-0.95)
    # Measured calibrated velocity -0.5 (raw +0.5, the joint is reversed) toward -0.98.
    core.on_joint_states(state(JointSample(J1, raw, 0.5, 2.0)), now=0.2)
    (hold,) = sent(core, "joint_commands")
    assert (hold.position, hold.velocity, hold.effort) == (approx(raw), 0.0, None)


def test_stop_holds_every_commanded_joint() -> None:
    core = make()
    feed_calibrated(core, 0.0, joint1=0.2, joint2=0.1)
    core.on_joint_set(state(JointSample(J1, velocity=0.3)), now=0.0)
    core.outbox.take()
    core.stop(0.1)
    assert sent(core, "joint_commands") == [JointSample(J1, approx(0.3), 0.0, None)]


def test_velocity_only_command_without_fresh_state_is_refused() -> None:
    core = make(stale_timeout=1.0)
    core.on_joint_set(state(JointSample(J1, velocity=0.2)), now=0.0)
    assert sent(core, "joint_commands") == []
    assert core.counters["refused_no_state"] == 1
    feed_calibrated(core, 1.0, joint1=0.0)
    core.on_joint_set(state(JointSample(J1, velocity=0.2)), now=2.5)  # feedback 1.5 s old
    assert sent(core, "joint_commands") == []
    assert core.counters["refused_no_state"] == 2
    # An effort-only command pushes toward a limit just as well: refused the same way.
    core.on_joint_set(state(JointSample(J1, effort=1.0)), now=2.5)
    assert sent(core, "joint_commands") == []
    assert core.counters["refused_no_state"] == 3
    # A continuous joint needs no position to stay within limits.
    core.on_joint_set(state(JointSample(WHEEL, velocity=9.0)), now=2.5)
    assert sent(core, "joint_commands") == [JointSample(WHEEL, None, 4.0, None)]


def test_nothing_out_of_limits_is_ever_sent_under_random_commands() -> None:
    rng = random.Random(7)
    core = make()
    names = [J1, J2, WHEEL]
    now = 0.0
    for _ in range(400):
        now += 0.01
        if rng.random() < 0.3:
            core.on_joint_states(
                state(*(JointSample(n, rng.uniform(-3, 3), 0.0, 0.0) for n in names)), now
            )
        fields = rng.choice([(1, 1, 1), (1, 0, 0), (0, 1, 0), (0, 0, 1), (0, 1, 1)])
        picked = rng.sample(names, rng.randint(1, 3))
        samples = [
            JointSample(
                n,
                *(rng.uniform(-20, 20) if on else None for on in fields),
            )
            for n in picked
        ]
        core.on_joint_set(state(*samples), now)
        core.tick(now)
    commands = sent(core, "joint_commands")
    assert len(commands) > 200
    assert_within_limits(core, commands)


# ---------------------------------------------------------------------------- refusals


def test_nan_and_inf_refused_counted_and_nothing_sent() -> None:
    core = make()
    core.on_joint_set(state(JointSample(J1, math.nan)), now=0.0)
    core.on_joint_set(state(JointSample(J1, 0.1, math.inf)), now=0.0)
    core.on_joint_set(state(JointSample(J2, None, None, -math.inf)), now=0.0)
    assert sent(core, "joint_commands") == []
    assert core.counters["refused_nan"] == 3
    # One bad joint does not spoil the others in the same message.
    core.on_joint_set(state(JointSample(J1, math.nan), JointSample(J2, 0.5)), now=0.1)
    assert sent(core, "joint_commands") == [JointSample(J2, 0.25, None, None)]
    assert core.counters["refused_nan"] == 4


def test_unknown_and_other_module_joints_refused_and_counted_apart() -> None:
    core = make()
    # Two messages: one naming more entries than the module's three joints is refused whole.
    core.on_joint_set(
        state(
            JointSample("limb1_joint9", 0.0),  # our prefix, not our joint
            JointSample("joint1", 0.0),  # raw name: not a data-plane name
        ),
        now=0.0,
    )
    core.on_joint_set(
        state(
            JointSample("limb2_joint1", 0.0),  # another module's joint
            JointSample("wheel3_drive", 0.0),
        ),
        now=0.0,
    )
    assert sent(core, "joint_commands") == []
    counters = core.counters
    assert counters["refused_unknown"] == 2
    assert counters["refused_other_module"] == 2
    status = core.diagnostics(0.0).status[0]
    assert status.level == STALE  # no joint_states yet outranks WARN
    assert "wheel3" in status.message
    assert diagnostic_values(status)["refused_other_module"] == "2"


def test_subset_messages_only_velocity_only_some_joints() -> None:
    core = make()
    feed_calibrated(core, 0.0, joint1=0.0, joint2=0.0)
    core.outbox.take()
    core.on_joint_set(state(JointSample(J2, 1.5)), now=0.01)
    assert sent(core, "joint_commands") == [JointSample(J2, approx(1.25), None, None)]
    core.on_joint_set(state(JointSample(J1, velocity=0.5), JointSample(J2, velocity=0.5)), 0.02)
    cmd = sent(core, "joint_commands")
    assert cmd == [JointSample(J1, None, approx(-0.5), None), JointSample(J2, None, 0.5, None)]
    # Mixed field sets go out as one message per set, never with invented values.
    core.on_joint_set(state(JointSample(J1, 0.1)), now=0.03)
    core.on_joint_set(joint_state([JointSample(WHEEL, None, 1.0, None)]), now=0.03)
    assert [m.name for m in core.outbox.take("joint_commands")] == [[J1], [WHEEL]]


# ---------------------------------------------------------------------------- watchdog


def test_watchdog_zeroes_velocity_and_holds_when_commands_stop() -> None:
    core = make(watchdog_timeout=0.5)
    feed_calibrated(core, 0.0, joint1=0.1, joint2=0.0)
    core.on_joint_set(state(JointSample(J1, velocity=0.3)), now=0.0)
    core.outbox.take()
    for t in (0.1, 0.3, 0.5):
        core.tick(t)
    assert sent(core, "joint_commands") == []

    # The joint moved meanwhile; the hold is where it is now, not where it was.
    feed_calibrated(core, 0.52, joint1=0.25)
    core.tick(0.55)
    (hold,) = sent(core, "joint_commands")
    assert hold.name == J1
    assert core.calibration("joint1").to_calibrated(hold.position) == approx(0.25)
    assert hold.velocity == 0.0
    assert core.counters["watchdog_trips"] == 1
    manager = core.diagnostics(0.56).status[0]
    assert manager.level == ERROR
    assert "watchdog" in manager.message and J1 in manager.message
    # Tripped once: no hold storm at every tick.
    core.tick(0.6)
    core.tick(1.5)
    assert sent(core, "joint_commands") == []
    # A new command rearms it.
    feed_calibrated(core, 1.5, joint1=0.25)
    core.on_joint_set(state(JointSample(J1, velocity=0.1)), now=1.5)
    assert len(sent(core, "joint_commands")) == 1
    assert core.diagnostics(1.5).status[0].level == OK


def test_watchdog_is_fed_by_commands() -> None:
    core = make(watchdog_timeout=0.5)
    for t in (0.0, 0.3, 0.6, 0.9):
        feed_calibrated(core, t, joint2=0.0)
        core.on_joint_set(state(JointSample(J2, velocity=0.2)), now=t)
        core.tick(t + 0.2)
    assert core.counters["watchdog_trips"] == 0
    # Last command at 0.9: still fed at 1.39, expired at 1.41.
    feed_calibrated(core, 1.3, joint2=0.08)
    core.outbox.take()
    core.tick(1.39)
    assert sent(core, "joint_commands") == [] and core.counters["watchdog_trips"] == 0
    core.tick(1.41)
    assert sent(core, "joint_commands") == [JointSample(J2, approx(0.08 - 0.25), 0.0, None)]
    assert core.counters["watchdog_trips"] == 1


def test_watchdog_holds_moving_position_joints_and_leaves_settled_ones() -> None:
    core = make(watchdog_timeout=0.5)
    feed_calibrated(core, 0.0, joint1=0.0, joint2=0.0)
    core.on_joint_set(state(JointSample(J1, 0.9), JointSample(J2, 0.0)), now=0.0)
    core.outbox.take()
    # joint1 is still on its way (0.4 of 0.9, moving); joint2 reached its target.
    core.on_joint_states(
        state(
            JointSample(J1, core.calibration("joint1").to_raw(0.4), -0.5, 0.0),
            JointSample(J2, core.calibration("joint2").to_raw(0.0), 0.0, 0.0),
        ),
        now=0.5,
    )
    core.tick(0.6)
    (hold,) = sent(core, "joint_commands")
    assert hold.name == J1
    assert core.calibration("joint1").to_calibrated(hold.position) == approx(0.4)
    assert hold.velocity == 0.0


def test_watchdog_leaves_a_sagging_settled_joint_and_holds_a_stalled_one() -> None:
    """At rest near its target (a loaded servo's steady-state error) a joint is settled: its
    target stays, so the pose does not walk down after every motion. At rest far from it
    (stalled against something) it is held where it is, so it stops pushing."""
    core = make(watchdog_timeout=0.5)
    feed_calibrated(core, 0.0, joint1=0.0, joint2=0.0)
    core.on_joint_set(state(JointSample(J1, 0.5), JointSample(J2, 0.8)), now=0.0)
    core.outbox.take()
    feed_calibrated(core, 0.5, joint1=0.47, joint2=0.3)  # both still: 0.03 sag, 0.5 stall
    core.tick(0.6)
    (hold,) = sent(core, "joint_commands")
    assert hold.name == J2
    assert core.calibration("joint2").to_calibrated(hold.position) == approx(0.3)
    core.tick(1.5)
    assert sent(core, "joint_commands") == []  # joint1 kept its target of 0.5


# ---------------------------------------------------------------------------- halt / recover


def test_halt_holds_at_once_and_refuses_until_recover() -> None:
    core = make()
    feed_calibrated(core, 0.0, joint1=0.3, joint2=-0.5)
    core.on_joint_set(state(JointSample(J1, velocity=0.5)), now=0.0)
    core.outbox.take()

    response = core.on_halt(TRIGGER_REQ, now=0.1)
    assert response.success is True
    assert "halted" in response.message and "recover" in response.message
    holds = by_name(sent(core, "joint_commands"))
    assert core.calibration("joint1").to_calibrated(holds[J1].position) == approx(0.3)
    assert core.calibration("joint2").to_calibrated(holds[J2].position) == approx(-0.5)
    assert holds[J1].velocity == holds[J2].velocity == 0.0
    # No position ever measured for the wheel: velocity 0 is the only safe command.
    assert holds[WHEEL] == JointSample(WHEEL, None, 0.0, None)
    assert WHEEL in response.message

    core.on_joint_set(state(JointSample(J1, 0.2), JointSample(J2, 0.1)), now=0.2)
    assert sent(core, "joint_commands") == []
    assert core.counters["refused_halted"] == 2
    assert core.diagnostics(0.2).status[0].level == ERROR

    recovered = core.on_recover(TRIGGER_REQ, now=0.3)
    assert recovered.success is True and "recovered" in recovered.message
    core.on_joint_set(state(JointSample(J1, 0.2)), now=0.3)
    assert sent(core, "joint_commands") == [JointSample(J1, approx(0.3), None, None)]
    assert "nothing to recover" in core.on_recover(TRIGGER_REQ, now=0.4).message


@pytest.mark.parametrize("fed", [False, True], ids=["never_fed", "feedback_lost"])
def test_a_halted_manager_without_feedback_publishes_error_not_stale(fed: bool) -> None:
    """The halt is a known failure an operator must see; "no news" must not hide it."""
    core = make(stale_timeout=1.0, diagnostics_period=1.0)
    if fed:
        feed_calibrated(core, 0.0, joint1=0.3, joint2=-0.5, wheel=0.0)
    core.on_halt(TRIGGER_REQ, now=0.1)
    core.outbox.take()
    core.tick(2.5)  # no joint_states for 2.5 s (or ever): stale as well as halted
    (diag,) = core.outbox.take("diagnostics")
    manager = diag.status[0]
    assert manager.level == ERROR
    assert "halted" in manager.message and "no joint_states" in manager.message
    assert [s.level for s in diag.status[1:]] == [STALE, STALE, STALE]  # joints: no news
    # Recovered and still without feedback: back to STALE, not OK.
    core.on_recover(TRIGGER_REQ, now=2.6)
    assert core.diagnostics(2.7).status[0].level == STALE


def test_a_tripped_watchdog_without_feedback_publishes_error_not_stale() -> None:
    core = make(watchdog_timeout=0.5, stale_timeout=1.0)
    feed_calibrated(core, 0.0, joint1=0.1)
    core.on_joint_set(state(JointSample(J1, velocity=0.3)), now=0.0)
    core.tick(0.6)
    assert core.counters["watchdog_trips"] == 1
    manager = core.diagnostics(3.0).status[0]
    assert manager.level == ERROR and "watchdog" in manager.message


# ---------------------------------------------------------------------------- joint_read


def test_joint_read_change_at_once_in_one_batch_and_keepalive_otherwise() -> None:
    core = make(read_position_threshold=1e-3, keepalive_period=1.0)
    feed_calibrated(core, 0.0, joint1=0.0, joint2=0.0, wheel=0.0)
    first = core.outbox.take("joint_read")
    assert len(first) == 1 and list(first[0].name) == [J1, J2, WHEEL]

    feed_calibrated(core, 0.1, joint1=0.0005, joint2=0.0, wheel=0.0)  # below threshold
    assert core.outbox.take("joint_read") == []

    feed_calibrated(core, 0.2, joint1=0.01, joint2=-0.02, wheel=0.0)
    (batch,) = core.outbox.take("joint_read")
    assert list(batch.name) == [J1, J2]
    assert list(batch.position) == [approx(0.01), approx(-0.02)]

    core.tick(0.5)
    assert core.outbox.take("joint_read") == []
    feed_calibrated(core, 0.9, joint1=0.0105, joint2=-0.02, wheel=0.0)
    core.tick(1.0)
    (keepalive,) = core.outbox.take("joint_read")
    assert list(keepalive.name) == [J1, J2, WHEEL]
    assert keepalive.position[0] == approx(0.0105)

    # Stale joints are not kept alive as if they were fresh.
    core.tick(2.0)
    assert core.outbox.take("joint_read") == []


def test_diagnostics_manager_and_per_joint() -> None:
    core = make(diagnostics_period=1.0)
    core.tick(0.0)
    (diag,) = core.outbox.take("diagnostics")
    assert [s.level for s in diag.status] == [STALE, STALE, STALE, STALE]
    feed_calibrated(core, 0.5, joint1=0.25, joint2=0.0, wheel=0.0)
    core.tick(0.6)
    assert core.outbox.take("diagnostics") == []  # not yet due
    core.tick(1.0)
    (diag,) = core.outbox.take("diagnostics")
    manager, j1 = diag.status[0], diag.status[1]
    assert manager.level == OK and manager.name == "limb1_joint_manager"
    values = diagnostic_values(manager)
    assert values["clamped"] == "0" and values["watchdog_trips"] == "0"
    assert j1.name == f"limb1_joint_manager/{J1}" and j1.level == OK
    assert float(diagnostic_values(j1)["position"]) == approx(0.25)

    core.on_joint_set(state(JointSample(J1, 7.0)), now=1.1)
    diag = core.diagnostics(1.2)
    assert diag.status[0].level == WARN and diag.status[1].level == WARN
    assert "clamped" in diag.status[1].message
    assert diag.status[2].level == OK


# ---------------------------------------------------------------------------- services


def test_list_joints_response() -> None:
    core = make()
    before = core.on_joints(LIST_REQ, now=0.0)
    assert before.module == "limb1"
    assert math.isnan(before.joints[0].position) and before.joints[0].age == math.inf
    core.on_joint_states(state(JointSample(J1, 0.7, 0.3, 1.0)), now=1.0)
    response = core.on_joints(LIST_REQ, now=1.25)
    assert [j.name for j in response.joints] == [J1, J2, WHEEL]
    info = response.joints[0]
    assert (info.type, info.lower, info.upper) == ("revolute", -1.0, 1.0)
    assert (info.max_velocity, info.max_effort, info.locked) == (2.0, 5.0, False)
    assert (info.position, info.velocity, info.effort) == (approx(-0.2), approx(-0.3), -1.0)
    assert info.age == approx(0.25)
    assert response.joints[2].type == "continuous" and response.joints[2].upper == math.inf


def test_interface_declares_handlers_that_exist() -> None:
    core = make()
    for sub in JOINT_MANAGER.subscribe:
        assert callable(getattr(core, sub.handler))
    for srv in JOINT_MANAGER.serve:
        assert callable(getattr(core, srv.handler))
    assert [e.period for e in JOINT_MANAGER.every] == [0.02]
    assert {p.topic for p in JOINT_MANAGER.publish} == {
        "joint_read",
        "joint_commands",
        "diagnostics",
    }
    assert JOINT_MANAGER.output("joint_commands").msg_type == "sensor_msgs/msg/JointState"
    assert {s.srv_type for s in JOINT_MANAGER.serve} == {
        "std_srvs/srv/Trigger",
        "msctl_msgs/srv/ListJoints",
    }
    assert core.extra_serve == []


# ---------------------------------------------------------------------------- overrides


def test_locked_joint_override_holds_refuses_and_warns() -> None:
    core = make()
    apply_all(
        core,
        "joint_manager",
        overrides=[{"name": "locked_joint", "joint": "joint2", "position": 0.3}],
    )
    core.start(0.0)
    assert sent(core, "joint_commands") == [JointSample(J2, approx(0.05), 0.0, None)]

    feed_calibrated(core, 0.0, joint1=0.0, joint2=0.3)
    core.outbox.take()
    core.on_joint_set(state(JointSample(J1, 0.2), JointSample(J2, -1.0)), now=0.1)
    cmd = by_name(sent(core, "joint_commands"))
    assert cmd[J1].position == approx(0.3)  # the other joint is untouched
    assert cmd[J2] == JointSample(J2, approx(0.05), 0.0, None)  # re-asserted hold
    assert core.counters["refused_locked"] == 1
    core.on_joint_set(state(JointSample(J2, velocity=0.5)), now=0.2)
    assert sent(core, "joint_commands") == [JointSample(J2, approx(0.05), 0.0, None)]
    assert core.counters["refused_locked"] == 2

    diag = core.diagnostics(0.3)
    j2 = diag.status[2]
    assert j2.level == WARN and "locked" in j2.message
    assert diagnostic_values(j2)["locked"] == "True"
    assert diag.status[0].level == WARN
    assert [j.locked for j in core.on_joints(LIST_REQ, 0.3).joints] == [False, True, False]

    # Halt and the watchdog keep it at the lock position, not where it drifted.
    feed_calibrated(core, 0.4, joint2=0.31)
    core.outbox.take()
    core.on_halt(TRIGGER_REQ, 0.4)
    assert by_name(sent(core, "joint_commands"))[J2].position == approx(0.05)


def test_locked_joint_defaults_to_current_position_and_accepts_full_name() -> None:
    core = make()
    apply_all(core, "joint_manager", overrides=[{"name": "locked_joint", "joint": J1}])
    core.start(0.0)
    assert sent(core, "joint_commands") == []  # nothing known to hold yet
    core.on_joint_states(state(JointSample(J1, 0.4, 0.0, 0.0)), now=0.1)
    assert sent(core, "joint_commands") == [JointSample(J1, approx(0.4), 0.0, None)]
    core.on_joint_set(state(JointSample(J1, 0.0)), now=0.2)
    assert sent(core, "joint_commands") == [JointSample(J1, approx(0.4), 0.0, None)]
    assert core.counters["refused_locked"] == 1
    with pytest.raises(ValueError, match="joint9"):
        apply_all(core, "joint_manager", overrides=[{"name": "locked_joint", "joint": "joint9"}])


def test_command_filter_hook_rewrites_and_is_still_clamped() -> None:
    core = make()

    def double(command: JointSample, now: float) -> JointSample:
        return command._replace(position=command.position * 2)

    def veto(command: JointSample, now: float) -> Refusal:
        return Refusal("refused_by_test", "no")

    core.add_command_filter("joint2", double)
    core.on_joint_set(state(JointSample(J2, 0.5), JointSample(J1, 0.5)), now=0.0)
    cmd = by_name(sent(core, "joint_commands"))
    assert cmd[J2].position == approx(0.75)  # 1.0 - 0.25
    assert cmd[J1].position == approx(0.0)
    core.on_joint_set(state(JointSample(J2, 1.5)), now=0.1)  # 3.0 -> clamped to 1.98
    assert sent(core, "joint_commands")[0].position == approx(1.73)
    core.add_command_filter(J1, veto)
    core.on_joint_set(state(JointSample(J1, 0.5)), now=0.2)
    assert sent(core, "joint_commands") == []
    assert core.counters["refused_by_test"] == 1


def test_unknown_injection_or_override_name_is_a_registry_error() -> None:
    core = make()
    with pytest.raises(RegistryError, match="rezero"):
        apply_all(core, "joint_manager", injections=[{"name": "telemetry"}])
    with pytest.raises(RegistryError, match="locked_joint"):
        apply_all(core, "joint_manager", overrides=[{"name": "frozen_joint", "joint": "joint1"}])
    assert core.extra_serve == []


# ---------------------------------------------------------------------------- rezero

UNIT_TOML = """\
# Unit calibration for limb 4 (serial H-0004).
hostname = "limb4-nuc"   # onboard computer

[bus]
channel = "can0"
motor_ids = [
  [1, 2],
]

[joints.joint1]
# measured 2024-05-02
zero_offset = 0.5  # rad
direction = -1

[joints.joint2]
direction = 1

[[overrides]]
name = "locked_joint"
joint = "joint3"
"""


def test_rezero_injection_rewrites_offsets_and_the_toml_file(tmp_path) -> None:
    path = tmp_path / "H-0004.toml"
    path.write_text(UNIT_TOML)
    core = make()
    apply_all(
        core,
        "joint_manager",
        injections=[{"name": "rezero", "calibration_file": str(path), "max_shift": 1.0}],
    )
    assert core.extra_serve == [
        Serve("rezero", "msctl_msgs/srv/Rezero", "on_rezero", role=Role.RAW)
    ]

    core.on_joint_states(
        state(
            JointSample(J1, 0.8, 0.0, 0.0),
            JointSample(J2, -0.1, 0.0, 0.0),
            JointSample(WHEEL, 12.5, 0.0, 0.0),
        ),
        now=0.0,
    )
    core.outbox.take()
    response = core.on_rezero(TRIGGER_REQ, 0.1)
    assert response.success is True, response.message
    assert str(path) in response.message
    assert core.calibration("joint1") == JointCalibration(0.8, -1)
    assert core.calibration("joint2") == JointCalibration(-0.1, 1)
    assert core.calibration("wheel") == JointCalibration(12.5, 1)
    assert core.latest(J1).position == approx(0.0)

    text = path.read_text()
    # Comments, other tables and key order survive; only the offsets changed.
    assert "# measured 2024-05-02\nzero_offset = 0.8  # rad\ndirection = -1\n" in text
    assert "[joints.joint2]\nzero_offset = -0.1\ndirection = 1\n" in text
    assert text.startswith("# Unit calibration for limb 4 (serial H-0004).\n")
    data = tomllib.loads(text)
    assert data["joints"] == {
        "joint1": {"zero_offset": 0.8, "direction": -1},
        "joint2": {"zero_offset": -0.1, "direction": 1},
        "wheel": {"zero_offset": 12.5, "direction": 1},
    }
    assert data["overrides"] == [{"name": "locked_joint", "joint": "joint3"}]
    assert data["bus"] == {"channel": "can0", "motor_ids": [[1, 2]]}
    # No temporary file left behind; the previous file kept beside it (tests/test_rezero_safety).
    assert sorted(p.name for p in tmp_path.iterdir() if not p.name.endswith(".bak")) == [path.name]

    # New commands use the new zero: calibrated 0.1 on joint1 is raw 0.8 - 0.1.
    core.on_joint_set(state(JointSample(J1, 0.1)), now=0.2)
    assert sent(core, "joint_commands")[0].position == approx(0.7)


def test_rezero_named_joints_and_refusals_change_nothing(tmp_path) -> None:
    path = tmp_path / "unit.toml"
    path.write_text("[joints]\njoint1 = { zero_offset = 0.5, direction = -1 }\n")
    core = make()
    apply_all(
        core,
        "joint_manager",
        injections=[
            {"name": "rezero", "joints": ["joint1"], "calibration_file": str(path), "max_shift": 1}
        ],
    )
    no_state = core.on_rezero(TRIGGER_REQ, 0.0)
    assert no_state.success is False and J1 in no_state.message

    feed(core, 0.0, joint1=0.9, joint2=0.3)
    inline = core.on_rezero(TRIGGER_REQ, 0.1)
    assert inline.success is False and "[joints.<name>]" in inline.message
    assert path.read_text() == "[joints]\njoint1 = { zero_offset = 0.5, direction = -1 }\n"
    assert core.calibration("joint1") == JointCalibration(0.5, -1)

    path.write_text("[joints.joint1]\nzero_offset = 0.5\ndirection = -1\n")
    ok = core.on_rezero(TRIGGER_REQ, 0.2)
    assert ok.success is True
    assert core.calibration("joint1").zero_offset == 0.9
    assert core.calibration("joint2").zero_offset == -0.25  # not named: untouched
    assert tomllib.loads(path.read_text())["joints"] == {
        "joint1": {"zero_offset": 0.9, "direction": -1}
    }


def test_rezero_without_file_and_bad_params() -> None:
    core = make()
    apply_all(
        core, "joint_manager", injections=[{"name": "rezero", "joints": "joint2", "max_shift": 1}]
    )
    feed(core, 0.0, joint2=0.3)
    response = core.on_rezero(TRIGGER_REQ, 0.1)
    assert response.success is True and "not saved" in response.message
    assert core.calibration("joint2").zero_offset == 0.3
    with pytest.raises(ValueError, match="already serves"):
        apply_all(core, "joint_manager", injections=[{"name": "rezero"}])
    with pytest.raises(ValueError, match="calibration_fil"):
        apply_all(make(), "joint_manager", injections=[{"name": "rezero", "calibration_fil": "x"}])


def test_rezero_keeps_a_pinned_joint_physically_where_it_is() -> None:
    core = make()
    apply_all(
        core,
        "joint_manager",
        injections=[{"name": "rezero", "joints": ["joint2"], "max_shift": 1.0}],
        overrides=[{"name": "locked_joint", "joint": "joint2", "position": 0.3}],
    )
    feed(core, 0.0, joint2=0.05)
    assert core.on_rezero(TRIGGER_REQ, 0.1).success
    core.outbox.take()
    core.on_halt(TRIGGER_REQ, 0.2)
    assert by_name(sent(core, "joint_commands"))[J2].position == approx(0.05)


def test_toml_updater_edge_cases(tmp_path) -> None:
    crlf = "[joints.joint1]\r\nzero_offset = 1.0 # old\r\n"
    assert (
        updated_text(crlf, {"joint1": -0.125})
        == "[joints.joint1]\r\nzero_offset = -0.125 # old\r\n"
    )
    spaced = '[ joints . "joint1" ]  # quoted key\nzero_offset=3\n'
    assert (
        updated_text(spaced, {"joint1": 1e-7})
        == '[ joints . "joint1" ]  # quoted key\nzero_offset=1e-07\n'
    )
    no_newline = 'hostname = "x"'
    assert tomllib.loads(updated_text(no_newline, {"joint1": 0.25}, {"joint1": -1})) == {
        "hostname": "x",
        "joints": {"joint1": {"zero_offset": 0.25, "direction": -1}},
    }
    with pytest.raises(CalibrationFileError, match="not valid TOML"):
        updated_text("[joints.joint1\n", {"joint1": 0.0})
    with pytest.raises(CalibrationFileError, match="finite"):
        updated_text("", {"joint1": math.nan})
    missing = tmp_path / "nope.toml"
    with pytest.raises(CalibrationFileError, match=r"nope\.toml"):
        write_zero_offsets(missing, {"joint1": 0.0})
    path = tmp_path / "unit.toml"
    path.write_text(crlf)
    path.chmod(0o640)
    write_zero_offsets(path, {"joint1": 2.5})
    assert path.read_bytes() == b"[joints.joint1]\r\nzero_offset = 2.5 # old\r\n"
    assert path.stat().st_mode & 0o777 == 0o640


# ---------------------------------------------------------------------------- independence


def test_two_managers_in_one_process_share_no_state() -> None:
    arm, leg = make("limb1"), make("limb2")
    apply_all(arm, "joint_manager", overrides=[{"name": "locked_joint", "joint": "joint1"}])
    apply_all(leg, "joint_manager", injections=[{"name": "rezero"}])
    assert arm.extra_serve == [] and len(leg.extra_serve) == 1
    assert not hasattr(arm, "on_rezero")

    feed(arm, 0.0, joint1=0.1, joint2=0.0)
    feed(leg, 0.0, joint1=0.1, joint2=0.0)
    arm.outbox.take()
    leg.outbox.take()
    # The same command, seen by both: each takes its own module's joints only.
    command = state(JointSample("limb1_joint2", 0.5), JointSample("limb2_joint1", 0.5))
    arm.on_joint_set(command, 0.1)
    leg.on_joint_set(command, 0.1)
    assert sent(arm, "joint_commands") == [JointSample("limb1_joint2", approx(0.25), None, None)]
    assert sent(leg, "joint_commands") == [JointSample("limb2_joint1", approx(0.0), None, None)]
    assert arm.counters["refused_other_module"] == 1 and leg.counters["refused_other_module"] == 1

    # limb1's lock does not lock limb2's joint1; halting one leaves the other running.
    leg.on_joint_set(state(JointSample("limb2_joint1", 0.2)), 0.2)
    assert len(sent(leg, "joint_commands")) == 1
    arm.on_halt(TRIGGER_REQ, 0.3)
    assert arm.halted and not leg.halted
    leg.on_joint_set(state(JointSample("limb2_joint2", 0.2)), 0.3)
    assert sent(leg, "joint_commands") == [JointSample("limb2_joint2", approx(-0.05), None, None)]
    assert leg.counters["refused_locked"] == 0 and leg.counters["refused_halted"] == 0
    assert [j.locked for j in leg.on_joints(LIST_REQ, 0.3).joints] == [False, False, False]


def test_velocity_and_rezero_need_a_fresh_position_not_just_fresh_velocity() -> None:
    # An encoder that starts reporting NaN positions (or a motor interface sending positions
    # in a batch of their own that stops) while velocities keep coming: the position is stale.
    core = make(stale_timeout=1.0)
    apply_all(core, "joint_manager", injections=[{"name": "rezero", "joints": ["joint1"]}])
    feed_calibrated(core, 0.0, joint1=0.0)
    for t in (0.5, 1.0, 1.5, 2.0):
        core.on_joint_states(state(JointSample(J1, math.nan, 0.0, 0.0)), t)
    core.outbox.take()
    # A bounded joint in velocity mode with a 2 s old position could run through its limit.
    core.on_joint_set(state(JointSample(J1, velocity=0.5)), now=2.0)
    assert sent(core, "joint_commands") == []
    assert core.counters["refused_no_state"] == 1
    # Re-zeroing on a 2 s old position would save a wrong offset.
    response = core.on_rezero(TRIGGER_REQ, 2.0)
    assert not response.success and "limb1_joint1" in response.message
    assert core.calibration("joint1") == CAL["joint1"]


@pytest.mark.parametrize(
    "params, where",
    [
        ({"watchdog_timeout": 0}, "watchdog_timeout"),
        ({"position_margin": "2cm"}, "position_margin"),
    ],
)
def test_builder_refuses_a_bad_config_param_naming_the_component(params, where) -> None:
    from dataclasses import replace

    from components.assembly import from_document
    from components.build import BuildError, build_component
    from msctl.assembler import resolve

    assembly = from_document(resolve("minimal").document)
    plan = assembly.component("limb1/joint_manager")
    bad = replace(plan, params={**plan.params, **params})
    # A BuildError is what the worker reports as "cannot build <component>" (exit 3); a bare
    # ValueError/TypeError escaped it as a traceback.
    with pytest.raises(BuildError, match=rf"limb1/joint_manager.*{where}"):
        build_component(bad, assembly, {})
