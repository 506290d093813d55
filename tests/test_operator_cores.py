"""The shipped operators' cores (guardian, posture): plain calls, fake time."""

from __future__ import annotations

import math

from components.autonomous_operator.cores.guardian import Answer, GuardianCore
from components.autonomous_operator.cores.posture import PostureCore
from components.joints import JointCalibration
from components.safety import SafetyLimits


def _quaternion_tilted(angle: float) -> tuple[float, float, float, float]:
    """(w, x, y, z) of a rotation by ``angle`` about the x axis."""
    return math.cos(angle / 2), math.sin(angle / 2), 0.0, 0.0


def _guardian(**limits: float) -> GuardianCore:
    return GuardianCore(
        "dragon",
        SafetyLimits(**limits),
        {"joint1": JointCalibration(zero_offset=0.5, direction=-1)},
        attitude="/dragon/root_pose",
        stale_after=1.0,
        report_period=1.0,
    )


def test_the_guardian_trips_once_on_a_tilt_and_arms_again_once_level() -> None:
    core = _guardian(max_tilt=0.5)
    assert core.orientation(*_quaternion_tilted(0.3), now=0.0) == ""
    why = core.orientation(*_quaternion_tilted(0.6), now=0.1)
    assert why.startswith("body tilt 0.600 rad") and "max_tilt" in why
    assert core.orientation(*_quaternion_tilted(0.7), now=0.2) == ""  # tripped already
    status = core.halted(why, [Answer("limb1", True, 0.012), Answer("wheel2", False)])
    assert status.level == "error" and status.values == {"halts": 1}
    assert "acknowledged: limb1 12 ms; NO ANSWER from wheel2" in status.message
    # Under the threshold but not under 80 % of it: still tripped, no status while it is.
    core.orientation(*_quaternion_tilted(0.45), now=0.3)
    assert core.step(0.3, {}) == type(core.step(0.3, {}))()
    core.orientation(*_quaternion_tilted(0.39), now=0.4)
    step = core.step(0.4, {})
    assert step.armed_again and not core.tripped and step.status is not None
    assert core.orientation(*_quaternion_tilted(0.6), now=0.5)  # trips again
    assert math.isclose(core.worst_tilt, 0.7)


def test_a_joint_astray_halts_after_its_grace_only() -> None:
    core = _guardian(max_tracking_error=0.1, tracking_grace=0.5)
    core.commands([("joint1", 0.5 - 0.2), ("other", 1.0), ("joint1", None)])
    assert core.commanded == {"joint1": 0.2}  # calibrated; unknown joints ignored
    assert core.step(0.0, {"joint1": 0.5}).halt == ""  # astray from now on
    assert core.step(0.4, {"joint1": 0.5}).halt == ""
    halt = core.step(0.5, {"joint1": 0.5}).halt
    assert halt == (
        "joint1 0.30 away from its command for 0.5 s > 0.1"
        " (module data [safety] max_tracking_error)"
    )
    back = core.step(0.6, {"joint1": 0.25})  # back within the error: armed again
    assert back.armed_again and core.astray == {}


def test_the_guardian_s_status_says_what_it_watches_and_warns_when_the_attitude_is_stale() -> None:
    core = _guardian(max_tilt=0.5, max_tracking_error=0.1)
    first = core.step(0.0, {})
    assert first.status is not None and first.status.level == "warn"
    assert "no attitude on /dragon/root_pose for 1 s" in first.status.message
    assert core.step(0.5, {}).status is None  # one status a report period
    core.orientation(*_quaternion_tilted(0.1), now=0.9)
    status = core.step(1.0, {}).status
    assert status is not None and status.level == "ok"
    assert status.message == "watching dragon: tilt 5.7 deg, worst tracking - 0.000"
    assert status.values["attitude"] == "/dragon/root_pose" and status.values["halts"] == 0
    nothing = GuardianCore("dragon", SafetyLimits(), {}, "", 1.0, 1.0)
    assert not nothing.watching_tilt and not nothing.watching_tracking


def _posture() -> PostureCore:
    return PostureCore(["a", "b"], tolerance=0.05, settle=0.3, still_after=1.0, report_period=1.0)


def test_posture_holds_the_pose_of_the_drive_s_start_and_corrects_after_settling() -> None:
    core = _posture()
    pose = {"a": 0.1, "b": -0.2, "c": 9.0}
    first = core.step(0.0, pose, driving=True, correcting=False)
    assert core.posture == {"a": 0.1, "b": -0.2} and first.correct_to is None
    assert first.status == (
        "holding 2 joints; worst - 0.000 rad off",
        {"corrections": 0, "tolerance": 0.05, "worst_seen": "0.000", "holding": True},
    )
    pushed = {"a": 0.2, "b": -0.2}
    assert core.step(0.1, pushed, driving=True, correcting=False).correct_to is None
    assert core.step(0.3, pushed, driving=True, correcting=False).correct_to is None
    assert core.step(0.4, pushed, driving=True, correcting=False).correct_to == {
        "a": 0.1,
        "b": -0.2,
    }
    # While a correction runs, none is started again.
    for t in (0.5, 0.8, 0.9):
        assert core.step(t, pushed, driving=True, correcting=True).correct_to is None
    status = core.step(1.0, pushed, driving=True, correcting=False).status
    assert status is not None and status[0] == "holding 2 joints; worst a 0.100 rad off"
    assert status[1]["corrections"] == 1 and status[1]["worst_seen"] == "0.100"


def test_posture_frees_the_limbs_once_the_wheels_stay_still() -> None:
    core = _posture()
    core.step(0.0, {"a": 0.1, "b": 0.0}, driving=True, correcting=False)
    core.step(0.9, {"a": 0.5, "b": 0.0}, driving=False, correcting=False)  # a wheel slows
    assert core.posture == {"a": 0.1, "b": 0.0}
    free = core.step(1.0, {"a": 0.5, "b": 0.0}, driving=False, correcting=False)
    assert core.posture is None and free.correct_to is None
    assert free.status is not None and free.status[0] == "not driving: limbs free"
    core.step(1.5, {"a": 0.5, "b": 0.0}, driving=True, correcting=False)
    assert core.posture == {"a": 0.5, "b": 0.0}  # the pose set while still is the one held
