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

from components.autonomous_operator.cores.posture import PostureCore


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
    core = PostureCore(joints, tolerance, settle, still_after, report_period)
    correction = None

    def driving() -> bool:
        for handler in wheels:
            for state in handler.states().values():
                if state.velocity is not None and abs(state.velocity) > moving_speed:
                    return True
        return False

    while True:
        correcting = correction is not None and not correction.done()
        step = core.step(loop.time(), robot.positions(), driving(), correcting)
        if step.correct_to is not None:
            correction = limbs.lerp(step.correct_to)
        if step.status is not None:
            message, values = step.status
            robot.report(message, **values)
        await asyncio.sleep(period)
