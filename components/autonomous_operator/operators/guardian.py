"""guardian: e-stops the robot when its body tilts or a joint stops following its command.

It watches, on the data plane:

* the body's tilt: the angle between its up axis and the vertical, from an attitude topic
  (``attitude``: a ``geometry_msgs/msg/PoseStamped`` or a ``sensor_msgs/msg/Imu``; by
  default the simulator's ground truth of the robot's root link, which stands in for an
  IMU on the body);
* each position joint's tracking error: its joint manager's command to the motors
  (``joint_commands``) against its measurement (``joint_read``), for longer than the grace.

Beyond a threshold it halts every module of the robot at once (:mod:`components.estop`,
each joint manager's ``halt``), once, and says why on its status (ERROR). It arms again
once the tilt is back under 80 % of its threshold and no joint is astray, so an operator
who recovers a robot still tilted (``msctl recover``) can right it without being halted
again on the way.

The thresholds are module data, the tightest of the robot's modules' ``[safety]`` tables
(:mod:`components.safety`): ``max_tilt``, ``max_tracking_error``, ``tracking_grace``. A
parameter given here tightens them further.

Station data::

    autonomous_operator = [{ name = "guardian", script = "guardian" }]
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Mapping

from components.autonomous_operator.cores.guardian import (
    REARM,
    GuardianCore,
    Status,
    acknowledged,
    tilt_of,
)
from components.config import positive_numbers
from components.messages import joint_samples
from components.safety import SafetyLimits, robot_limits

__all__ = ["REARM", "default_attitude", "limits_for", "main", "tilt_of"]

POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
IMU = "sensor_msgs/msg/Imu"
JOINT_STATE = "sensor_msgs/msg/JointState"

log = logging.getLogger("msctl.guardian")


def default_attitude(robot) -> str:
    """The simulator's ground-truth pose of the robot's root link."""
    from components.simulator.topics import pose_topics

    topics = dict(pose_topics(tuple(robot.assembly.root_links)))
    return topics.get(robot.root_link, "")


def limits_for(robot, given: Mapping[str, float]) -> SafetyLimits:
    """The robot's limits from module data, tightened by the parameters given (> 0)."""
    data = robot_limits(robot.assembly.module(s).safety for s in robot.modules)
    out = {}
    for name in ("max_tilt", "max_tracking_error", "tracking_grace"):
        ours, theirs = given.get(name, 0.0), getattr(data, name)
        if ours and ours > 0:
            out[name] = ours if theirs is None else min(ours, theirs)
        else:
            out[name] = theirs
    return SafetyLimits(**out)


async def main(
    robot,
    attitude: str = "",
    attitude_type: str = POSE_STAMPED,
    max_tilt: float = 0.0,
    max_tracking_error: float = 0.0,
    tracking_grace: float = 0.0,
    period: float = 0.05,
    stale_after: float = 1.0,
    report_period: float = 1.0,
):
    """Watch ``robot`` until stopped; halt it beyond its limits.

    Args:
        robot: The operator's robot.
        attitude: The body's attitude topic (default: the simulator's pose of the root link).
        attitude_type: Its type: ``geometry_msgs/msg/PoseStamped`` or ``sensor_msgs/msg/Imu``.
        max_tilt: Tighter than the module data's (rad); 0: the data's.
        max_tracking_error: Tighter than the module data's (rad or m); 0: the data's.
        tracking_grace: Shorter than the module data's (s); 0: the data's.
        period: Seconds between two checks of the tracking errors.
        stale_after: Seconds without an attitude after which the status warns.
        report_period: Seconds between status reports.
    """
    if attitude_type not in (POSE_STAMPED, IMU):
        raise ValueError(f"guardian: attitude_type must be {POSE_STAMPED} or {IMU}")
    positive_numbers("guardian", period=period, stale_after=stale_after)
    limits = limits_for(
        robot,
        {
            "max_tilt": max_tilt,
            "max_tracking_error": max_tracking_error,
            "tracking_grace": tracking_grace,
        },
    )
    core = GuardianCore(
        robot.robot,
        limits,
        _calibrations(robot),
        attitude or default_attitude(robot),
        stale_after,
        report_period,
    )
    loop = asyncio.get_running_loop()
    halting = asyncio.Lock()
    pending: set[asyncio.Task] = set()  # halts under way (kept: a task nobody holds may vanish)

    def report(status: Status) -> None:
        robot.report(status.message, status.level, **status.values)

    async def halt(why: str) -> None:
        async with halting:
            answers = await robot.estop()
            log.warning("halted %s: %s (acknowledged: %s)", robot.robot, why, acknowledged(answers))
            report(core.halted(why, answers))

    def on_attitude(message) -> None:
        q = message.pose.orientation if attitude_type == POSE_STAMPED else message.orientation
        why = core.orientation(q.w, q.x, q.y, q.z, loop.time())
        if why:
            task = loop.create_task(halt(why))
            pending.add(task)
            task.add_done_callback(pending.discard)

    def on_commands(message) -> None:
        core.commands((sample.name, sample.position) for sample in joint_samples(message))

    if core.watching_tilt:
        robot.subscribe(core.attitude, attitude_type, on_attitude)
    if core.watching_tracking:
        for slot in robot.modules:
            namespace = robot.assembly.module(slot).namespace.rstrip("/")
            robot.subscribe(f"{namespace}/joint_commands", JOINT_STATE, on_commands)
    while True:
        step = core.step(loop.time(), robot.positions() if core.watching_tracking else {})
        if step.halt:
            await halt(step.halt)
        if step.armed_again:
            log.info("armed again: tilt %.3f rad, no joint astray", core.tilt)
        if step.status is not None:
            report(step.status)
        await asyncio.sleep(period)


def _calibrations(robot) -> dict:
    """The position joints the modules' joint managers command, with their calibration."""
    return {
        joint.name: joint.calibration
        for slot in robot.modules
        for joint in robot.assembly.module(slot).joints
        if joint.actuated and joint.control == "position"
    }
