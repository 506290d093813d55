"""posture: holds the limbs' posture while the robot drives.

While any wheel turns (its measured speed above ``moving_speed``), the limbs keep the pose
they had when the driving began: a limb joint that strays from it by more than
``tolerance`` for ``settle`` seconds (pushed by the ground, dragged by a wheel, jogged by
mistake) is brought back, every joint of the limb together along a straight line in joint
space (the API's ``JointSyncer.lerp``, bounded steps around the measurement, at ``speed``).
When the wheels stop, the limbs are free again: a pose set while standing still (a
steering operator turning the wheel modules, an operator jogging a joint) is the one held
from the next drive on.

The pose is taken from the measurement, so a loaded limb's sag is part of it, and a
correction never ratchets a joint further down.

Station data::

    autonomous_operator = [{ name = "posture", script = "posture", params = { tolerance = 0.05 } }]
"""

from __future__ import annotations

import asyncio
import math


async def main(
    robot,
    tolerance: float = 0.05,
    settle: float = 0.3,
    moving_speed: float = 0.05,
    still_after: float = 1.0,
    speed: float = 0.4,
    period: float = 0.1,
    report_period: float = 1.0,
):
    """Hold ``robot``'s limbs while it drives, until stopped.

    Args:
        robot: The operator's robot.
        tolerance: Radians (metres) a limb joint may stray before it is brought back.
        settle: Seconds it must stay astray first (a wheel's jolt is not a new pose).
        moving_speed: A wheel turning faster than this (rad/s) means the robot drives.
        still_after: Seconds every wheel must stay slower before the drive is over (a
            wheel slowing for a moment is no new start: the pose held stays).
        speed: Largest joint speed of a correction (rad/s).
        period: Seconds between two checks.
        report_period: Seconds between status reports.
    """
    for name, value in (
        ("tolerance", tolerance),
        ("settle", settle),
        ("moving_speed", moving_speed),
        ("still_after", still_after),
        ("speed", speed),
        ("period", period),
        ("report_period", report_period),
    ):
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"posture: {name} must be a positive number, not {value}")
    if not robot.limbs or not robot.wheels:
        robot.report(f"nothing to hold: {robot.robot} has no limbs or no wheels", "warn")
        while True:  # stays up (and says why) rather than being restarted over and over
            await asyncio.sleep(3600.0)
    limbs = robot.syncer(*robot.limbs, speed=speed)
    joints = [
        name
        for slot in robot.limbs
        for name, info in robot.handler(slot).joints.items()
        if not info.locked and info.control == "position"
    ]
    wheels = [robot.handler(slot) for slot in robot.wheels]
    loop = asyncio.get_running_loop()
    posture: dict[str, float] | None = None
    astray_since: float | None = None
    correction = None
    corrections = 0
    moved_at = -math.inf  # when a wheel last turned
    worst_seen = 0.0
    next_report = 0.0

    def driving() -> bool:
        for handler in wheels:
            for state in handler.states().values():
                if state.velocity is not None and abs(state.velocity) > moving_speed:
                    return True
        return False

    while True:
        now = loop.time()
        measured = robot.positions()
        worst_joint, worst = "", 0.0
        if driving():
            moved_at = now
        if now - moved_at < still_after:
            if posture is None:
                posture = {j: measured[j] for j in joints if j in measured}
                astray_since = None
            for joint, held in posture.items():
                off = abs(measured.get(joint, held) - held)
                if off > worst:
                    worst_joint, worst = joint, off
            worst_seen = max(worst_seen, worst)
            busy = correction is not None and not correction.done()
            if worst > tolerance and not busy:
                astray_since = now if astray_since is None else astray_since
                if now - astray_since >= settle:
                    correction = limbs.lerp(posture)
                    corrections += 1
                    astray_since = None
            elif worst <= tolerance:
                astray_since = None
        else:
            posture = None  # standing still: the limbs are free
            astray_since = None
        if now >= next_report:
            next_report = now + report_period
            state = (
                f"holding {len(posture)} joints; worst {worst_joint or '-'} {worst:.3f} rad off"
                if posture is not None
                else "not driving: limbs free"
            )
            robot.report(
                state,
                corrections=corrections,
                tolerance=tolerance,
                worst_seen=f"{worst_seen:.3f}",
                holding=posture is not None,
            )
        await asyncio.sleep(period)
