"""What puts the teleop core's commands on the data plane, one output per mode.

* :class:`JointJog`: joint mode. A position joint is jogged with the joint syncer's
  ``speed_safe`` step (position commands advancing at the speed, never more than ``delta``
  from the measured position); a velocity joint (a wheel) gets velocity commands. Everything
  goes through the module's ``joint_set``, so the joint manager's limits, watchdog and halt
  apply.
* :class:`TipJog`: IK mode. The IK syncer's ``speed_safe`` step, ticked by the teleop: the tip
  moves at the twist, each waypoint inside a ball around the *measured* tip and each joint
  command inside a ball around the measured joints, solved by the limb's own IK.
* :class:`TwistDrive`: drive mode. ``geometry_msgs/msg/Twist`` (or ``TwistStamped``) on the
  assembly's ``cmd_vel``.

A stop holds what moved: a position joint at its last command while it is within ``delta``
of the measurement (the joint syncer's own stop semantics; holding at the measurement would
let a loaded limb sag by its tracking error at every stop), else where it is measured; a
velocity joint at velocity 0; the drive with a zero Twist.

Outputs are called from one thread (the operator's); they are not thread-safe.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any, Protocol

import numpy as np

from components.api.errors import JointNotReadyError
from components.api.joints import JointHandler
from components.api.planner import SPEED_SAFE, SyncPlanner, SyncSettings
from components.messages import JointSample, header, msg
from msctl.teleop.core import Move, Stop

TWIST = "geometry_msgs/msg/Twist"
TWIST_STAMPED = "geometry_msgs/msg/TwistStamped"

#: The jog's ball around the measured position (rad or m): a joint that does not follow is
#: never commanded more than this ahead of where it is.
JOG_DELTA = 0.1


class Output(Protocol):
    """One mode's way onto the wire."""

    def move(self, move: Move) -> Any:
        """Put one motion command on the wire; returns what was sent."""

    def stop(self, stop: Stop) -> Any:
        """Put the one stop command on the wire; returns what was sent."""

    def close(self) -> None:
        """Release what it declared (idempotent)."""


def hold_samples(handler: JointHandler, names: Iterable[str], delta: float) -> list[JointSample]:
    """Commands that stop ``names`` of one module where they are.

    A position joint is held at its last command while that is within ``delta`` of the
    measurement, else at the measurement; a velocity joint, or one with no position known,
    at velocity 0.
    """
    measured = handler.positions()
    out = []
    for name in names:
        info = handler.joints[name]
        at = measured.get(name)
        last = handler.last_command.get(name)
        if info.control == "velocity" or (at is None and last is None):
            out.append(JointSample(name, None, 0.0, None))
        elif last is not None and (at is None or abs(last - at) <= delta):
            out.append(JointSample(name, last, None, None))
        else:
            out.append(JointSample(name, at, None, None))
    return out


class JointJog:
    """Joint mode: one joint at a time, through its module's ``joint_set``.

    Args:
        handlers: The modules, by slot.
        delta: The ball around the measured position no command leaves.
        limit_margin: Distance kept from the joint limits (the joint manager's margin, so
            what is sent is what the joint does).
    """

    def __init__(
        self,
        handlers: Mapping[str, JointHandler],
        delta: float = JOG_DELTA,
        limit_margin: float = 0.02,
    ) -> None:
        self.handlers = dict(handlers)
        self.delta = delta
        self.limit_margin = limit_margin
        self._planner: SyncPlanner | None = None
        self._jogged: str | None = None

    def move(self, move: Move) -> list[JointSample]:
        """Advance the jogged joint by one step.

        Raises:
            JointNotReadyError: If the joint's position is not known yet.
        """
        assert move.joint is not None
        handler = self.handlers[move.target]
        info = handler.joints[move.joint]
        speed = move.velocity[0]
        if info.control == "velocity":
            return handler.send([JointSample(info.name, None, speed, None)])
        measured = handler.positions().get(info.name)
        if measured is None:
            raise JointNotReadyError(
                f"no joint_read for {info.name} yet: is {handler.slot}'s joint manager running "
                "(`msctl ps`)?"
            )
        if move.first or self._jogged != info.name or self._planner is None:
            last = handler.last_command.get(info.name)
            settings = SyncSettings(delta=self.delta, limit_margin=self.limit_margin)
            self._planner = SyncPlanner(
                [info.name],
                [info.lower],
                [info.upper],
                [info.max_velocity],
                settings,
                None if last is None else [last],
            )
            self._jogged = info.name
        # The speed is the keys' (scaled with q/z), capped by the joint's own limit.
        self._planner.speed = np.minimum([abs(speed)], [info.max_velocity])
        step = self._planner.step(
            SPEED_SAFE, np.array([measured]), move.dt, velocity=np.array([speed])
        )
        return handler.send({info.name: float(step.command[0])})

    def stop(self, stop: Stop) -> list[JointSample]:
        """Hold the jogged joint."""
        assert stop.joint is not None
        handler = self.handlers[stop.target]
        self._planner = None
        return handler.send(hold_samples(handler, [stop.joint], self.delta))

    def close(self) -> None:
        """Nothing of its own (the handlers belong to the link)."""


class TipJog:
    """IK mode: a limb's tip moved at a twist with the IK syncer's bounded steps.

    Args:
        syncer: An :class:`~components.api.ik_syncer.IkSyncer` over the limbs.
    """

    def __init__(self, syncer: Any) -> None:
        self.syncer = syncer
        # The screen's own kinematics data per limb: pinocchio writes its results into a
        # model's data, and the operator's thread is solving IK in the syncer's meanwhile.
        self._views = {
            slot: (limb.solver.chain.model, limb.solver.chain.model.createData())
            for slot, limb in syncer.limbs.items()
        }

    def tip(self, slot: str) -> Any:
        """The measured tip pose of a limb in its base frame, for the screen (its thread
        only); None until every joint of the chain has a reading."""
        import pinocchio as pin

        limb = self.syncer.limbs[slot]
        positions = limb.handler.positions()
        if any(n not in positions for n in limb.names):
            return None
        model, data = self._views[slot]
        pin.forwardKinematics(model, data, np.array([positions[n] for n in limb.names]))
        return pin.updateFramePlacement(model, data, limb.solver.chain.tip_frame).copy()

    def move(self, move: Move) -> dict[str, float]:
        """One IK step of the limb toward where the twist takes its tip.

        Raises:
            JointNotReadyError: If a joint of the limb has no measured position yet.
        """
        if move.first:
            self.syncer.prepare(move.target)
        velocity = np.asarray(move.velocity, dtype=float)
        self.syncer.step(SPEED_SAFE, {}, {move.target: (velocity[:3], velocity[3:])}, move.dt)
        handler = self.syncer.limbs[move.target].handler
        return {n: handler.last_command[n] for n in self.syncer.limbs[move.target].names}

    def stop(self, stop: Stop) -> list[JointSample]:
        """Hold the limb's chain joints."""
        limb = self.syncer.limbs[stop.target]
        delta = self.syncer.settings.delta
        return limb.handler.send(hold_samples(limb.handler, limb.names, delta))

    def close(self) -> None:
        """Nothing of its own."""


class TwistDrive:
    """Drive mode: Twists on ``cmd_vel``.

    Args:
        node: The node publishing.
        topic: The ``cmd_vel`` topic.
        stamped: Publish ``TwistStamped`` (header stamp and ``frame_id``) instead.
        frame_id: The stamped Twist's frame (the robot's root link).
        clock: Wall-clock seconds for stamps.
    """

    def __init__(
        self,
        node: Any,
        topic: str,
        stamped: bool = False,
        frame_id: str = "",
        clock: Any = None,
    ) -> None:
        import time

        self.topic = topic
        self.stamped = stamped
        self.frame_id = frame_id
        self.clock = clock or time.time
        self.publisher = node.publisher(topic, TWIST_STAMPED if stamped else TWIST)

    def twist(self, vx: float, vy: float, wz: float) -> Any:
        """The message for a planar twist."""
        twist = msg(
            TWIST,
            linear=msg("geometry_msgs/msg/Vector3", x=float(vx), y=float(vy), z=0.0),
            angular=msg("geometry_msgs/msg/Vector3", x=0.0, y=0.0, z=float(wz)),
        )
        if not self.stamped:
            return twist
        return msg(TWIST_STAMPED, header=header(self.clock(), self.frame_id), twist=twist)

    def move(self, move: Move) -> Any:
        """Publish the twist."""
        message = self.twist(*move.velocity)
        self.publisher.publish(message)
        return message

    def stop(self, stop: Stop) -> Any:
        """Publish one zero twist."""
        message = self.twist(0.0, 0.0, 0.0)
        self.publisher.publish(message)
        return message

    def close(self) -> None:
        """Undeclare the publisher (idempotent)."""
        self.publisher.close()
