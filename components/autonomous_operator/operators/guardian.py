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
import math
from collections.abc import Mapping

from components.config import positive_numbers
from components.messages import joint_samples
from components.safety import SafetyLimits, robot_limits

POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
IMU = "sensor_msgs/msg/Imu"
JOINT_STATE = "sensor_msgs/msg/JointState"
#: The fraction of its threshold the tilt must fall under before the guardian arms again.
REARM = 0.8

log = logging.getLogger("msctl.guardian")


def tilt_of(w: float, x: float, y: float, z: float) -> float:
    """The angle (rad) between a body's up axis and the vertical, from its orientation."""
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    if not math.isfinite(norm) or norm < 1e-9:
        return math.nan
    x, y = x / norm, y / norm
    cos = 1.0 - 2.0 * (x * x + y * y)  # the z component of the body's up axis
    return math.acos(max(-1.0, min(1.0, cos)))


def default_attitude(robot) -> str:
    """The simulator's ground-truth pose of the robot's root link."""
    from components.simulator.core import pose_topics

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
    topic = attitude or default_attitude(robot)
    loop = asyncio.get_running_loop()
    state = {"tilt": math.nan, "tilt_at": -math.inf, "worst_tilt": 0.0}
    tripped: list[str] = []  # why it halted, while it has not armed again
    halts: list[str] = []
    halting = asyncio.Lock()
    pending: set[asyncio.Task] = set()  # halts under way (kept: a task nobody holds may vanish)

    # Position joints the modules' joint managers command, with their calibration (the
    # commands to the motors are raw positions; the handlers' readings are calibrated).
    calibrations = {}
    for slot in robot.modules:
        for joint in robot.assembly.module(slot).joints:
            if joint.actuated and joint.control == "position":
                calibrations[joint.name] = joint.calibration
    commanded: dict[str, float] = {}  # joint -> its latest command (calibrated)
    astray: dict[str, float] = {}  # joint -> since when it is astray

    async def halt(why: str) -> None:
        async with halting:
            if tripped:
                return
            tripped.append(why)
            answers = await robot.estop()
            acked = [a for a in answers if a.ok]
            timing = ", ".join(
                f"{a.module} {a.seconds * 1e3:.0f} ms" if a.seconds is not None else a.module
                for a in acked
            )
            failed = [a.module for a in answers if not a.ok]
            halts.append(why)
            log.warning("halted %s: %s (acknowledged: %s)", robot.robot, why, timing or "none")
            robot.report(
                f"HALTED {robot.robot}: {why}; acknowledged: {timing or 'none'}"
                + (f"; NO ANSWER from {', '.join(failed)}" if failed else "")
                + " (msctl recover undoes it)",
                "error",
                halts=len(halts),
            )

    def on_attitude(message) -> None:
        q = message.pose.orientation if attitude_type == POSE_STAMPED else message.orientation
        tilt = tilt_of(q.w, q.x, q.y, q.z)
        if math.isnan(tilt):
            return
        state["tilt"], state["tilt_at"] = tilt, loop.time()
        state["worst_tilt"] = max(state["worst_tilt"], tilt)
        if limits.max_tilt is not None and tilt > limits.max_tilt and not tripped:
            why = (
                f"body tilt {tilt:.3f} rad ({math.degrees(tilt):.1f} deg) > {limits.max_tilt:g}"
                " rad (module data [safety] max_tilt)"
            )
            task = loop.create_task(halt(why))
            pending.add(task)
            task.add_done_callback(pending.discard)

    def on_commands(message) -> None:
        for sample in joint_samples(message):
            calibration = calibrations.get(sample.name)
            if calibration is not None and sample.position is not None:
                commanded[sample.name] = calibration.to_calibrated(sample.position)

    watching_tilt = bool(topic) and limits.max_tilt is not None
    if watching_tilt:
        robot.subscribe(topic, attitude_type, on_attitude)
    if limits.max_tracking_error is not None:
        for slot in robot.modules:
            namespace = robot.assembly.module(slot).namespace.rstrip("/")
            robot.subscribe(f"{namespace}/joint_commands", JOINT_STATE, on_commands)
    next_report = 0.0
    while True:
        now = loop.time()
        worst_joint, worst = "", 0.0
        if limits.max_tracking_error is not None:
            measured = robot.positions()
            for joint, command in commanded.items():
                at = measured.get(joint)
                if at is None:
                    continue
                off = abs(at - command)
                if off > worst:
                    worst_joint, worst = joint, off
                if off > limits.max_tracking_error:
                    since = astray.setdefault(joint, now)
                    if now - since >= limits.tracking_grace and not tripped:
                        await halt(
                            f"{joint} {off:.2f} away from its command for "
                            f"{now - since:.1f} s > {limits.max_tracking_error:g} "
                            "(module data [safety] max_tracking_error)"
                        )
                else:
                    astray.pop(joint, None)
        tilt = state["tilt"]
        if tripped:
            level_tilt = limits.max_tilt is None or (
                not math.isnan(tilt) and tilt < REARM * limits.max_tilt
            )
            if level_tilt and not astray:
                tripped.clear()  # armed again (the halt stays until msctl recover)
                log.info("armed again: tilt %.3f rad, no joint astray", tilt)
        if now >= next_report and not tripped:
            next_report = now + report_period
            stale = watching_tilt and now - state["tilt_at"] > stale_after
            robot.report(
                f"watching {robot.robot}: tilt "
                + ("?" if math.isnan(tilt) else f"{math.degrees(tilt):.1f} deg")
                + f", worst tracking {worst_joint or '-'} {worst:.3f}"
                + (f"; no attitude on {topic} for {stale_after:g} s" if stale else ""),
                "warn" if stale else "ok",
                attitude=topic or "none",
                max_tilt=limits.max_tilt,
                max_tracking_error=limits.max_tracking_error,
                tracking_grace=limits.tracking_grace,
                worst_tilt=f"{state['worst_tilt']:.3f}",
                halts=len(halts),
            )
        await asyncio.sleep(period)
