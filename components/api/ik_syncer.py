"""The IK syncer: the joint syncer's modes in Cartesian space, over one or several limbs.

Each tick, for every limb of the motion:

1. the measured tip pose is the forward kinematics of the measured joints (``joint_read``);
2. the next Cartesian waypoint is taken from the last one (or from the measured tip after a
   desync) toward the target: position interpolated on the straight line, orientation by
   slerp, the step bounded by a ball around the *measured* tip (``delta_position`` metres,
   ``delta_angle`` radians) and by the speeds; in ``lerp`` every limb covers the same
   fraction of its way, in ``asap`` each limb (and position and orientation) goes on its own;
3. the waypoint is solved with the limb's own :class:`~components.kinematics_manager.ik.IkSolver`,
   warm-started from the last joint command;
4. the joint solution goes through the joint syncer's planner (``lerp``), so the joint
   commands also stay inside the L-infinity ball of ``delta`` around the measured joints.

The solver runs here rather than through the kinematics manager's ``ik_target`` topic: the
syncer must see the joint solution to bound it around the measured joints (the paper's
safety property holds in joint space, where a motor can be damaged), it solves one small
step per tick warm-started from its own last command (the manager solves from the measured
state, which lags the command), and a topic round trip per tick would add latency and a
second commander to the limb. It is the same solver with the same settings and limit margin,
built from the same composed URDF, so both give the same answers.

Targets are poses of each limb's tip in the limb's base frame (as ``ik_target``): a
``pinocchio.SE3``, a 3-vector (position; orientation kept), or ``(xyz, quaternion xyzw)``.
Chains of fewer than 6 joints follow position only.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pinocchio as pin

from components.api.errors import JointNotReadyError, UnknownJointError
from components.api.joints import JointHandler
from components.api.motion import Motion
from components.api.planner import ASAP, LERP, SPEED_SAFE, UNSAFE, SyncPlanner, SyncSettings
from components.api.syncer import Commander
from components.config import require

log = logging.getLogger(__name__)

_EPS = 1e-9


@dataclass(frozen=True)
class IkSyncSettings:
    """Tuning of an IK syncer. Lengths in m, angles in rad.

    Attributes:
        delta_position: Radius of the ball around the measured tip position that every
            waypoint stays in (and the drift that still counts as in sync).
        delta_angle: The same for the tip orientation (angle between the two).
        delta: The joint syncer's L-infinity ball around the measured joints.
        tolerance_position: A tip has arrived this close to its target.
        tolerance_angle: ...and this close in orientation (chains of 6+ joints).
        speed: Largest tip speed (m/s).
        angular_speed: Largest tip rotation speed (rad/s).
        joint_speed: Largest joint command speed (rad/s); each joint's limit caps it too.
        rate: Commands per second.
        limit_margin: Distance kept from the joint limits.
        ik_budget: Solver iterations per waypoint (a tick's compute bound).
    """

    delta_position: float = 0.03
    delta_angle: float = 0.15
    delta: float = 0.15
    tolerance_position: float = 0.01
    tolerance_angle: float = 0.05
    speed: float = 0.05
    angular_speed: float = 0.3
    joint_speed: float = 1.0
    rate: float = 40.0
    limit_margin: float = 0.02
    ik_budget: int = 60

    def __post_init__(self) -> None:
        require(
            self,
            positive=(
                "delta_position",
                "delta_angle",
                "delta",
                "tolerance_position",
                "tolerance_angle",
                "speed",
                "angular_speed",
                "joint_speed",
                "rate",
                "ik_budget",
            ),
        )

    def joint_settings(self) -> SyncSettings:
        """The joint syncer settings the IK syncer's joint step uses."""
        return SyncSettings(
            delta=self.delta,
            tolerance=1.0,  # arrival is judged in Cartesian space
            speed=self.joint_speed,
            rate=self.rate,
            limit_margin=self.limit_margin,
        )


def pose_of(value: Any, keep: pin.SE3) -> pin.SE3:
    """A target as an SE3: an SE3, a 3-vector (``keep``'s orientation), or (xyz, quat xyzw).

    Raises:
        ValueError: For anything else.
    """
    if isinstance(value, pin.SE3):
        return value.copy()
    array = np.asarray(value, dtype=object)
    if array.shape == (3,):
        return pin.SE3(keep.rotation.copy(), np.asarray(value, dtype=float))
    if len(value) == 2:
        xyz, quat = value
        x, y, z, w = (float(v) for v in quat)
        rotation = pin.Quaternion(w, x, y, z).normalized().toRotationMatrix()
        return pin.SE3(rotation, np.asarray(xyz, dtype=float))
    raise ValueError(
        f"a tip target is an SE3, a position [x, y, z] or ([x, y, z], [qx, qy, qz, qw]), "
        f"not {value!r}"
    )


def pose_gap(a: pin.SE3, b: pin.SE3) -> tuple[float, float]:
    """Distance (m) and angle (rad) between two poses."""
    distance = float(np.linalg.norm(b.translation - a.translation))
    angle = float(np.linalg.norm(pin.log3(a.rotation.T @ b.rotation)))
    return distance, angle


def interpolate(a: pin.SE3, b: pin.SE3, fraction: float, turn: float | None = None) -> pin.SE3:
    """The pose ``fraction`` of the way from ``a`` to ``b``: straight line for the position,
    slerp (constant angular speed about one axis) for the orientation; ``turn`` is a separate
    fraction for the orientation (``asap``)."""
    turn = fraction if turn is None else turn
    translation = a.translation + fraction * (b.translation - a.translation)
    rotation = a.rotation @ pin.exp3(turn * pin.log3(a.rotation.T @ b.rotation))
    return pin.SE3(rotation, translation)


@dataclass
class _Limb:
    """One limb of an IK syncer: its joints, model, solver and Cartesian command."""

    handler: JointHandler
    names: tuple[str, ...]
    solver: Any
    position_only: bool
    last_pose: pin.SE3 | None = None
    last_q: np.ndarray | None = None

    @property
    def slot(self) -> str:
        return self.handler.slot


@dataclass
class Line:
    """One limb's way in a motion: from ``start`` to ``goal``, ``progress`` along it.

    Attributes:
        start: The tip pose where the motion began (the last waypoint, or the measured tip).
        goal: The target.
        progress: Fraction of the way the position has been commanded (0..1).
        turned: Fraction of the way the orientation has been commanded (0..1; equals
            ``progress`` except in ``asap``).
    """

    start: pin.SE3
    goal: pin.SE3
    progress: float = 0.0
    turned: float = 0.0

    def at(self, progress: float, turned: float | None = None) -> pin.SE3:
        """The pose at a fraction of the way."""
        return interpolate(self.start, self.goal, progress, turned)


class CartesianPlanner:
    """The Cartesian step of the IK syncer, pure (no I/O, ``dt`` passed in).

    Waypoints stay on each limb's line from start to goal: a lagging tip holds the progress
    back (the next waypoint is the farthest point of the line within ``delta_position`` of
    the measured tip, and within ``delta_angle`` in orientation), it never bends the line.

    Args:
        settings: Balls, tolerances, speeds.
    """

    def __init__(self, settings: IkSyncSettings) -> None:
        self.settings = settings
        self.held = 0

    def reach(
        self, line: Line, measured: pin.SE3, dt: float, position_only: bool
    ) -> tuple[float, float]:
        """How far along ``line`` the next waypoint may go: (position, orientation) fractions,
        never behind the current ones (a tip that drifted off holds the waypoint still)."""
        s = self.settings
        origin = line.start.translation
        way = line.goal.translation - origin
        length = float(np.linalg.norm(way))
        progress = line.progress
        if length > _EPS:
            # |origin + p * way - measured| <= delta: a quadratic in p; its larger root.
            lean = origin - measured.translation
            a = length * length
            b = 2.0 * float(way @ lean)
            c = float(lean @ lean) - s.delta_position**2
            disc = b * b - 4.0 * a * c
            farthest = (-b + math.sqrt(disc)) / (2.0 * a) if disc >= 0 else -math.inf
            progress = min(farthest, line.progress + s.speed * dt / length, 1.0)
            if progress < line.progress:
                self.held += 1
                progress = line.progress
        else:
            progress = 1.0
        turned = 1.0
        turn = pose_gap(line.start, line.goal)[1]
        if not position_only and turn > _EPS:
            now = line.at(line.turned, line.turned)
            twist = pose_gap(now, measured)[1]
            room = max(s.delta_angle - twist, 0.0)
            turned = min(line.turned + min(room, s.angular_speed * dt) / turn, 1.0)
        return progress, turned

    def arrived(self, measured: pin.SE3, goal: pin.SE3, position_only: bool) -> bool:
        """Whether the measured tip is within tolerance of the goal."""
        distance, angle = pose_gap(measured, goal)
        return distance <= self.settings.tolerance_position and (
            position_only or angle <= self.settings.tolerance_angle
        )

    def bounded(self, start: pin.SE3, moved: pin.SE3, measured: pin.SE3) -> pin.SE3:
        """``moved`` pulled back toward ``start`` into the balls around ``measured``
        (``speed_safe``)."""
        line = Line(start, moved)
        progress, turned = self.reach(line, measured, math.inf, False)
        return line.at(progress, turned)


class IkSyncer(Commander):
    """Cartesian motions of one or several limb tips, moved together.

    Args:
        chains: ``(handler, chain plan)`` per limb (:class:`~components.assembly.ChainPlan`:
            base link, tip link, joints).
        urdf_text: The composed URDF of the assembly.
        settings: Balls, tolerances, speeds.
    """

    def __init__(
        self,
        chains: Sequence[tuple[JointHandler, Any]],
        urdf_text: str,
        settings: IkSyncSettings | None = None,
    ) -> None:
        from components.kinematics_manager.ik import IkSettings, IkSolver
        from components.kinematics_manager.model import chain_model

        super().__init__([h for h, _ in chains])
        self.settings = settings or IkSyncSettings()
        self.cartesian = CartesianPlanner(self.settings)
        ik_settings = IkSettings(limit_margin=self.settings.limit_margin)
        self.limbs: dict[str, _Limb] = {}
        for handler, chain in chains:
            model = chain_model(urdf_text, chain.base_link, chain.tip_link, chain.joints or None)
            solver = IkSolver(model, ik_settings)
            self.limbs[handler.slot] = _Limb(
                handler, tuple(model.joint_names), solver, model.nq < 6
            )
        self._planners: dict[str, SyncPlanner] = {}

    # ------------------------------------------------------------------ state
    def _measured_q(self, limb: _Limb) -> np.ndarray:
        positions = limb.handler.positions()
        missing = [n for n in limb.names if n not in positions]
        if missing:
            raise JointNotReadyError(
                f"no measured position yet for {', '.join(missing)} (no joint_read)"
            )
        return np.array([positions[n] for n in limb.names])

    def tip(self, slot: str | None = None) -> pin.SE3:
        """The measured tip pose of a limb (default: the only one) in its base frame."""
        limb = self._limb(slot)
        return limb.solver.chain.tip(self._measured_q(limb))

    def tips(self) -> dict[str, pin.SE3]:
        """Every limb's measured tip pose."""
        return {slot: self.tip(slot) for slot in self.limbs}

    def _limb(self, slot: str | None) -> _Limb:
        if slot is None:
            if len(self.limbs) != 1:
                raise UnknownJointError(f"name the limb: one of {', '.join(self.limbs)}")
            return next(iter(self.limbs.values()))
        try:
            return self.limbs[slot]
        except KeyError:
            raise UnknownJointError(
                f"no limb {slot!r} in this IK syncer; limbs: {', '.join(self.limbs)}"
            ) from None

    # ------------------------------------------------------------------ motions
    def lerp(self, targets: Any) -> Motion:
        """Every tip on its straight line (slerp for orientation), all covering the same
        fraction of their way per step, inside the balls around the measured state."""
        return self._start(LERP, targets)

    def asap(self, targets: Any) -> Motion:
        """Each tip, position and orientation each on its own, inside the balls."""
        return self._start(ASAP, targets)

    def unsafe(self, targets: Any) -> Motion:
        """Each tip's joints sent the IK solution of the target at once (limits still apply)."""
        return self._start(UNSAFE, targets)

    def speed_safe(self, twists: Any, duration: float | None = None) -> Motion:
        """Tips moving at ``twists`` (``{slot: (linear xyz m/s, angular xyz rad/s)}`` in the
        base frame, or a bare linear velocity), inside the balls; for ``duration`` seconds
        (then resolves True) or until another motion or a stop."""
        if not isinstance(twists, Mapping):
            twists = {self._limb(None).slot: twists}
        parsed: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        for slot, twist in twists.items():
            limb = self._limb(slot)
            array = np.asarray(twist, dtype=float)
            if array.shape == (3,):
                parsed[limb.slot] = (array, np.zeros(3))
            elif array.shape in ((2, 3), (6,)):
                flat = array.reshape(6)
                parsed[limb.slot] = (flat[:3], flat[3:])
            else:
                raise ValueError(f"twist for {slot}: give [vx, vy, vz] or ([v], [w]), not {twist}")
        return self._launch_motion(SPEED_SAFE, {}, parsed, duration)

    def _start(self, mode: str, targets: Any) -> Motion:
        if not isinstance(targets, Mapping):
            targets = {self._limb(None).slot: targets}
        goals: dict[str, pin.SE3] = {}
        for slot, value in targets.items():
            limb = self._limb(slot)
            goals[limb.slot] = pose_of(value, self.tip(limb.slot))
        return self._launch_motion(mode, goals, {}, None)

    def _launch_motion(
        self,
        mode: str,
        goals: dict[str, pin.SE3],
        twists: dict[str, tuple[np.ndarray, np.ndarray]],
        duration: float | None,
    ) -> Motion:
        slots = list(goals or twists)
        lines = {}
        for slot in slots:
            start = self.prepare(slot)
            if slot in goals:
                lines[slot] = Line(start, goals[slot])
        description = f"ik {mode} {'+'.join(slots)}"

        async def body(motion: Motion) -> None:
            await self._drive(mode, lines, twists, motion, duration)

        return self._launch(description, body)

    def prepare(self, slot: str) -> pin.SE3:
        """Start a limb's next motion: from its last joint command while the joints are near
        it, else from the measured joints; returns the tip pose it starts from.

        Every motion does this first; a caller that ticks :meth:`step` itself (the teleop's
        tip jog) calls it at the start of each of its motions.

        Raises:
            JointNotReadyError: If a joint of the limb has no measured position yet.
        """
        limb = self._limb(slot)
        measured_q = self._measured_q(limb)  # every joint heard from, or a clear error
        start = limb.solver.chain.tip(measured_q)
        # Continue from the last joint command while the joints are near it: restarting
        # from the measurement would drop a loaded limb by its tracking error.
        sent = [limb.handler.last_command.get(n) for n in limb.names]
        limb.last_q = None
        if all(v is not None for v in sent):
            q_sent = np.array(sent, dtype=float)
            if np.abs(q_sent - measured_q).max() <= self.settings.delta:
                limb.last_q = q_sent
                start = limb.solver.chain.tip(q_sent)
        # speed_safe steps on from the last waypoint: this motion's first is its start.
        limb.last_pose = start
        self._planners[limb.slot] = self._new_planner(limb)
        return start

    def step(
        self,
        mode: str,
        lines: Mapping[str, Line],
        twists: Mapping[str, tuple[np.ndarray, np.ndarray]],
        dt: float,
    ) -> bool:
        """One tick: waypoints, IK, joint step, commands sent. Returns whether every limb
        arrived (never for ``speed_safe``)."""
        slots = list(lines or twists)
        measured_q = {s: self._measured_q(self.limbs[s]) for s in slots}
        measured = {s: self.limbs[s].solver.chain.tip(measured_q[s]) for s in slots}
        waypoints: dict[str, pin.SE3] = {}
        if mode == SPEED_SAFE:
            for s in slots:
                linear, angular = twists[s]
                limb = self.limbs[s]
                start = limb.last_pose
                if (
                    start is None
                    or pose_gap(start, measured[s])[0] > 2 * self.settings.delta_position
                ):
                    start = measured[s]
                moved = pin.SE3(
                    pin.exp3(angular * dt) @ start.rotation, start.translation + linear * dt
                )
                waypoints[s] = self.cartesian.bounded(start, moved, measured[s])
        elif mode == UNSAFE:
            for s in slots:
                lines[s].progress = lines[s].turned = 1.0
                waypoints[s] = lines[s].goal
        else:
            reach = {
                s: self.cartesian.reach(lines[s], measured[s], dt, self.limbs[s].position_only)
                for s in slots
            }
            if mode == LERP:
                # One fraction for every limb (and for position and orientation alike).
                common = min(min(r) for r in reach.values())
                common = max(common, min(lines[s].progress for s in slots))
                reach = {s: (common, common) for s in slots}
            for s in slots:
                lines[s].progress, lines[s].turned = reach[s]
                waypoints[s] = lines[s].at(*reach[s])
        for s in slots:
            limb = self.limbs[s]
            warm = limb.last_q if limb.last_q is not None else measured_q[s]
            solution = limb.solver.solve(waypoints[s], warm, budget=self.settings.ik_budget)
            planner = self._planner(limb)
            joint_mode = UNSAFE if mode == UNSAFE else LERP
            command = planner.step(joint_mode, measured_q[s], dt, target=solution.q).command
            limb.last_q = solution.q
            limb.last_pose = waypoints[s]
            limb.handler.send(dict(zip(limb.names, command.tolist(), strict=True)))
        if mode == SPEED_SAFE:
            return False
        return all(
            lines[s].progress >= 1.0
            and lines[s].turned >= 1.0
            and self.cartesian.arrived(measured[s], lines[s].goal, self.limbs[s].position_only)
            for s in slots
        )

    def _planner(self, limb: _Limb) -> SyncPlanner:
        planner = self._planners.get(limb.slot)
        if planner is None:
            planner = self._planners[limb.slot] = self._new_planner(limb)
        return planner

    def _new_planner(self, limb: _Limb) -> SyncPlanner:
        infos = [limb.handler.joints[n] for n in limb.names]
        return SyncPlanner(
            limb.names,
            [i.lower for i in infos],
            [i.upper for i in infos],
            [i.max_velocity for i in infos],
            self.settings.joint_settings(),
            limb.last_q,
        )

    async def _drive(
        self,
        mode: str,
        lines: Mapping[str, Line],
        twists: Mapping[str, tuple[np.ndarray, np.ndarray]],
        motion: Motion,
        duration: float | None,
    ) -> None:
        loop = asyncio.get_running_loop()
        period = 1.0 / self.settings.rate
        began = previous = wake = loop.time()
        while True:
            now = loop.time()
            dt = min(now - previous, 2 * period) if now > previous else period
            previous = now
            arrived = self.step(mode, lines, twists, dt)
            if arrived or (duration is not None and now - began >= duration):
                motion.finish(True)
                return
            wake += period
            await asyncio.sleep(max(wake - loop.time(), 0.0))


def straightness(points: Sequence[np.ndarray], start: np.ndarray, end: np.ndarray) -> float:
    """Largest distance (m) of ``points`` from the segment ``start`` -> ``end``."""
    axis = end - start
    length = float(np.linalg.norm(axis))
    worst = 0.0
    for p in points:
        if length < _EPS:
            worst = max(worst, float(np.linalg.norm(p - start)))
            continue
        t = min(max(float((p - start) @ axis) / length**2, 0.0), 1.0)
        worst = max(worst, float(np.linalg.norm(p - (start + t * axis))))
    return worst if math.isfinite(worst) else math.inf
