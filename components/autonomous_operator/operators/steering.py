"""steering: the robot's ``cmd_vel`` turned into wheel velocities and crab-steering headings.

A Twist on ``cmd_vel`` (``geometry_msgs/msg/Twist``) asks for a body velocity: forward
``linear.x``, sideways ``linear.y`` and a turn ``angular.z``. This operator:

* takes it only from the holder of the robot's modules' claims while any is claimed (the
  robot's ``subscribe(..., claimed_by=...)``: the joint managers' own rule, one level up);
* refuses a Twist with NaN or infinity and clamps one above ``max_speed`` / ``max_turn``,
  counting each on its status, never failing on one;
* ramps the body velocity toward it (``acceleration``) and sends each wheel module its wheel
  velocities (the API's :class:`~components.api.wheels.WheelDrive`, from the geometry at the
  measured limb angles), ``rate`` times a second while anything moves, then one zero and
  silence: the joint managers' watchdogs stop the wheels if this operator dies;
* when the Twist has a sideways part, and the limbs are in a pose that can turn the wheel
  modules (see ``examples/dragon_square.py``), stops, points every module along the
  direction with the limbs (the API's :class:`~components.api.steering.WheelSteering`,
  ``steer_path``), and drives along it without turning the body; a Twist straight ahead
  turns them back. Limbs that cannot steer (lying straight) drive what the wheels can, and
  the sideways part is counted as dropped;
* stops (ramping down) when no Twist came for ``timeout`` seconds: a sender that died
  without its stop does not leave the robot driving.

Station data::

    autonomous_operator = [{ name = "steering", script = "steering", params = { max_speed = 0.4 } }]
"""

from __future__ import annotations

import asyncio
import math

from components.autonomous_operator.drive import (
    STILL,
    Ramp,
    TwistGate,
    aligned,
    crab_direction,
)
from components.config import positive_numbers
from components.messages import JointSample
from components.robots import robot_cmd_vel

TWIST = "geometry_msgs/msg/Twist"
TWIST_STAMPED = "geometry_msgs/msg/TwistStamped"


async def main(
    robot,
    cmd_vel: str = "",
    stamped: bool = False,
    max_speed: float = 0.5,
    max_turn: float = 1.0,
    timeout: float = 0.5,
    rate: float = 40.0,
    acceleration: float = 0.5,
    angular_acceleration: float = 1.5,
    steer_tolerance: float = 0.05,
    crab: bool = True,
    report_period: float = 1.0,
):
    """Drive ``robot`` from its ``cmd_vel`` until stopped.

    Args:
        robot: The operator's robot.
        cmd_vel: The topic (default: the robot's, ``/cmd_vel`` for a lone robot).
        stamped: It carries ``TwistStamped``.
        max_speed: Largest linear speed (m/s); faster Twists are clamped.
        max_turn: Largest turn rate (rad/s); faster Twists are clamped.
        timeout: Seconds without a Twist after which the robot ramps to a stop.
        rate: Wheel commands per second while moving.
        acceleration: m/s².
        angular_acceleration: rad/s².
        steer_tolerance: Radians within which a module counts as facing the direction.
        crab: Steer the wheel modules for sideways Twists (when the limbs can).
        report_period: Seconds between status reports.
    """
    positive_numbers(
        "steering",
        timeout=timeout,
        rate=rate,
        acceleration=acceleration,
        angular_acceleration=angular_acceleration,
        steer_tolerance=steer_tolerance,
        report_period=report_period,
    )
    gate = TwistGate(max_speed, max_turn)
    ramp = Ramp(acceleration, angular_acceleration)
    topic = cmd_vel or robot_cmd_vel(robot.assembly, robot.robot)
    drive = robot.drive()
    limbs = robot.syncer(*robot.limbs) if robot.limbs else None
    if limbs is not None and crab:
        # The limbs' kinematics are built now, not when the first Twist is waiting (that
        # takes a second on a busy machine, while the robot should already be driving).
        await asyncio.to_thread(drive.steering_joints)
    loop = asyncio.get_running_loop()
    wake = asyncio.Event()
    state = {"target": STILL, "at": -math.inf, "dropped": 0, "steered": 0, "sent_zero": True}

    def on_twist(message) -> None:
        velocity = gate.take(message.twist if stamped else message)
        if velocity is None:
            return
        state["target"] = velocity
        state["at"] = loop.time()
        wake.set()

    # Only from the holder of every claimed module it moves: wheels and the limbs that steer.
    robot.subscribe(topic, TWIST_STAMPED if stamped else TWIST, on_twist, list(robot.modules))

    owner = {name: slot for slot, h in drive.handlers.items() for name in h.joints}

    def send(velocity) -> None:
        v, u, w = velocity
        rows: dict[str, list[JointSample]] = {}
        for name, speed in drive.speeds(v, w, u).items():
            rows.setdefault(owner[name], []).append(JointSample(name, None, speed))
        for slot, samples in rows.items():
            drive.handlers[slot].send(samples)

    def target(now: float):
        return state["target"] if now - state["at"] <= timeout else STILL

    async def ramp_to_still() -> None:
        period = 1.0 / rate
        while not ramp.still:
            send(ramp.step(STILL, period))
            await asyncio.sleep(period)
        send(STILL)

    async def steer(direction: float) -> bool:
        """Point the modules along ``direction``; False when the limbs cannot."""
        if limbs is None or not crab:
            return False
        joints = drive.steering_joints()
        if not all(joints.values()):
            return False
        if all(aligned(h, direction, steer_tolerance) for h in drive.headings().values()):
            return True
        await ramp_to_still()
        for waypoint in drive.steer_path(direction):
            await limbs.lerp(waypoint)
        state["steered"] += 1
        drive.refresh()
        return True

    async def reports() -> None:
        from components.comm.stats import drops

        while True:
            v, u, w = ramp.current
            moving = not ramp.still
            robot.report(
                f"driving {v:+.2f} m/s, {u:+.2f} m/s sideways, {w:+.2f} rad/s"
                if moving
                else f"still; waiting for Twists on {topic}",
                "warn" if gate.refused else "ok",
                topic=topic,
                twists=gate.taken,
                refused=gate.refused,
                clamped=gate.clamped,
                ignored=gate.ignored,
                not_holder=drops.count(topic, "not_holder") + drops.count(topic, "unclaimed"),
                sideways_dropped=state["dropped"],
                steered=state["steered"],
                last_refusal=gate.last_refusal,
            )
            await asyncio.sleep(report_period)

    reporter = asyncio.create_task(reports())
    period = 1.0 / rate
    heading_for = None  # the direction the modules were last pointed along
    stepped = loop.time()  # when the ramp last stepped
    try:
        while True:
            now = loop.time()
            # The ramp follows the clock, not the count of steps: a late loop (a busy
            # machine) takes the time it lost, up to a few periods.
            dt = min(max(now - stepped, 0.0), 4 * period)
            stepped = now
            goal = target(now)
            if ramp.still and goal == STILL:
                if not state["sent_zero"]:
                    send(STILL)  # one zero, then silence
                    state["sent_zero"] = True
                heading_for = None  # the next motion checks where the modules face
                wake.clear()
                try:
                    await asyncio.wait_for(wake.wait(), timeout=1.0)
                except TimeoutError:
                    pass
                stepped = loop.time() - period  # a motion from rest starts with one step
                continue
            if ramp.still:
                drive.refresh()  # a motion from rest: the geometry at the limbs' angles now
            direction = crab_direction(goal)
            if direction is not None and direction != heading_for:
                # Once per direction (and per motion from rest): the kinematics cost
                # milliseconds, too much for every command.
                if not await steer(direction) and abs(goal[1]) > 1e-6:
                    state["dropped"] += 1  # sideways asked, and the limbs cannot steer
                heading_for = direction
                goal = target(loop.time())
            send(ramp.step(goal, dt))
            state["sent_zero"] = False
            await asyncio.sleep(period)
    finally:
        reporter.cancel()
        if not ramp.still or not state["sent_zero"]:
            send(STILL)
