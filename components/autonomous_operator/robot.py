"""The robot an autonomous operator's ``main`` gets: the Python API's Robot, on the
component's own node, plus what a supervised operator needs.

It is :class:`components.api.Robot` (syncers, IK, the wheel drive...) over the modules of one
robot of the assembly, with these differences:

* it runs on the component's node and session, which it does not close: the operator shows
  on the graph as its component (``/gc1/steering``), and its commands come from it;
* it claims nothing: the kind is a claim relay (:mod:`components.claims`), so the modules'
  joint managers take its commands as they take their holder's; an operator that forwards
  commands checks them against the claims itself (:meth:`OperatorRobot.subscribe` with
  ``claimed_by``), as the steering does with ``cmd_vel``;
* stopping holds only the modules it commanded: a guardian that never commanded a module
  must not fight whoever drives it when it stops;
* :meth:`~OperatorRobot.drive` steers from this robot's root link (one robot of several);
* :meth:`~OperatorRobot.report` puts a line and values on the operator's status;
  :meth:`~OperatorRobot.subscribe` and :meth:`~OperatorRobot.publisher` reach other topics;
  :meth:`~OperatorRobot.estop` halts the robot's modules at once (:mod:`components.estop`).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from components.api.connect import Robot
from components.api.errors import ApiError
from components.api.joints import JointHandler

# At import, i.e. while the worker builds (see components.autonomous_operator.runner): Pinocchio's
# start must not hold the GIL on the script's thread beside a beating executor.
from components.api.steering import WheelSteering
from components.api.wheels import WheelDrive, wheel_joints


class OperatorRobot(Robot):
    """The robot of one autonomous operator.

    Args:
        node: The component's node (the caller keeps it and its session).
        handlers: The robot's modules.
        assembly: The resolved assembly.
        robot: The robot's name (its root module).
        root_link: Its root link (the frame :meth:`drive` steers in).
        loop: The event loop ``main`` runs on (callbacks are delivered there).
        report: ``report(level, message, values)``: the operator's status.
        guard: Returns the process's claim guard (:meth:`Executor.claim_guard`).
        name: The operator's component name.
    """

    def __init__(
        self,
        node: Any,
        handlers: Sequence[JointHandler],
        assembly: Any,
        robot: str,
        root_link: str,
        loop: asyncio.AbstractEventLoop,
        report: Callable[[int, str, Mapping[str, Any]], None],
        guard: Callable[[], Any] | None = None,
        name: str = "",
    ) -> None:
        kinds = {h.slot: assembly.module(h.slot).kind for h in handlers}
        super().__init__(node.session, node, handlers, kinds, assembly.template, assembly)
        self.robot = robot
        self.root_link = root_link
        self.name = name
        self.loop = loop
        self._report = report
        self._guard = guard
        self._commanded: set[str] = set()
        self._own: list[Any] = []  # subscriptions and publishers, closed with the robot
        self._guarded: list[Any] = []
        self._estop: Any = None
        for handler in self.modules.values():
            handler.before_send = lambda slot=handler.slot: self._commanded.add(slot)

    def __repr__(self) -> str:
        parts = ", ".join(f"{s} ({self.kinds.get(s, '?')})" for s in self.modules)
        return f"<OperatorRobot {self.robot} of {self.template}: {parts}>"

    # ------------------------------------------------------------------ status
    def report(self, message: str, level: str = "ok", **values: Any) -> None:
        """Put ``message`` (and ``values``) on the operator's status; ``level`` is ``ok``,
        ``warn`` or ``error``.

        Raises:
            ValueError: For another level.
        """
        from components.autonomous_operator.core import level_of

        self._report(int(level_of(level)), str(message), values)

    # ------------------------------------------------------------------ topics
    def subscribe(
        self,
        topic: str,
        msg_type: str,
        callback: Callable[[Any], Any],
        claimed_by: Sequence[str] = (),
    ) -> Any:
        """Call ``callback(message)`` on ``main``'s event loop for each sample of ``topic``.

        Args:
            topic: Absolute, or relative to the operator's station namespace.
            msg_type: Its type (``geometry_msgs/msg/Twist``).
            callback: Called on the loop (it may start motions).
            claimed_by: Modules whose claims decide who may send: while any is claimed,
                only its holder's samples are taken (and only when one operator holds every
                claimed one); others are refused and counted. The steering takes
                ``cmd_vel`` so, from the holder of the modules it moves.
        """
        from components.roles import command_rule

        def deliver(message: Any) -> None:
            try:
                self.loop.call_soon_threadsafe(callback, message)
            except RuntimeError:
                pass  # the loop closed: the operator is stopping

        subscription = self.node.subscription(topic, msg_type, deliver, guarded=bool(claimed_by))
        self._own.append(subscription)
        if claimed_by:
            if self._guard is None:
                subscription.close()
                raise ApiError("claimed_by needs the process's claim guard (run as a component)")
            rule = command_rule(self.assembly, claimed_by[0], *claimed_by[1:])
            self._guard().add(subscription, rule)
            self._guarded.append(subscription)
        return subscription

    def publisher(self, topic: str, msg_type: str) -> Any:
        """A publisher on ``topic`` (closed with the robot)."""
        publisher = self.node.publisher(topic, msg_type)
        self._own.append(publisher)
        return publisher

    # ------------------------------------------------------------------ halting
    async def estop(self, modules: Sequence[str] | None = None) -> list[Any]:
        """Halt ``modules`` (default: every module of the robot) at once, through each joint
        manager's ``halt``; each one's :class:`~components.estop.Acknowledgement`."""
        return await asyncio.to_thread(self._halting().halt, modules)

    async def recover(self, modules: Sequence[str] | None = None) -> list[Any]:
        """Undo :meth:`estop`."""
        return await asyncio.to_thread(self._halting().recover, modules)

    def _halting(self) -> Any:
        if self._estop is None:
            from components.estop import Estop

            self._estop = Estop(
                self.node, {s: self.assembly.module(s).namespace for s in self.modules}
            )
        return self._estop

    # ------------------------------------------------------------------ driving
    def drive(self, *slots: str, **tuning: Any) -> Any:
        """A :class:`~components.api.wheels.WheelDrive` over wheel modules ``slots``
        (default: every wheel module of the robot), steering in the robot's root link."""
        urdf = self._urdf("the wheel helper")
        wheels = slots or tuple(self.wheels)
        if not wheels:
            raise ApiError(f"robot {self.robot} has no wheel module")
        handlers = [self.handler(s) for s in wheels]
        steering = WheelSteering(urdf, self.root_link, wheel_joints(handlers))
        geometry = steering.geometry(self.positions())
        return self._adopt(
            WheelDrive(handlers, geometry, steering=steering, positions=self.positions, **tuning)
        )

    # ------------------------------------------------------------------ stopping
    def commanded(self) -> list[str]:
        """The modules this operator has commanded."""
        return sorted(self._commanded)

    async def stop(self) -> None:
        """Cancel every motion and hold the modules this operator commanded (wheels at
        velocity 0, joints where measured); the others are not its to hold."""
        await asyncio.gather(*(c.stop() for c in self._commanders), return_exceptions=True)
        for slot in sorted(self._commanded):
            self.modules[slot].hold()

    async def close(self) -> None:
        """Stop, then close what it declared; the component's node and session stay."""
        if self._closed:
            return
        self._closed = True
        try:
            await self.stop()
            await asyncio.sleep(0.05)  # the holds leave before the node goes
        finally:
            for commander in self._commanders:
                commander.close()
            for handler in self.modules.values():
                handler.close()
            if self._guard is not None:
                for subscription in self._guarded:
                    self._guard().discard(subscription)
            for endpoint in reversed(self._own):
                endpoint.close()
            if self._estop is not None:
                self._estop.close()


async def attach_robot(
    node: Any,
    assembly: Any,
    slots: Sequence[str],
    timeout: float,
    **robot: Any,
) -> OperatorRobot:
    """The modules ``slots``' joint handlers on ``node``, once every joint manager answers
    and every joint has a reading (asked again until ``timeout``: an operator may start
    before the robot's components).

    Raises:
        ApiError: If a module stays silent (naming it).
    """
    deadline = time.monotonic() + timeout

    async def handler(slot: str) -> JointHandler:
        controls = {j.name: j.control for j in assembly.module(slot).joints}
        while True:
            try:
                return await JointHandler.create(node, slot, controls, timeout=2.0)
            except ApiError:
                if time.monotonic() > deadline:
                    raise
            await asyncio.sleep(0.5)

    results = await asyncio.gather(*(handler(s) for s in slots), return_exceptions=True)
    handlers = [r for r in results if isinstance(r, JointHandler)]
    failures = [r for r in results if isinstance(r, BaseException)]
    if failures:
        for made in handlers:
            made.close()
        raise failures[0]
    try:
        for made in handlers:
            await made.wait_ready(max(deadline - time.monotonic(), 1.0))
    except BaseException:
        for made in handlers:
            made.close()
        raise
    return OperatorRobot(node, handlers, assembly, **robot)
