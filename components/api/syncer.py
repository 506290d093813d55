"""The joint syncer: safe, synchronized motions of the joints of one or several modules.

A :class:`JointSyncer` runs one motion at a time. Each motion is an asyncio task that, at
``settings.rate``, reads the measured state from the handlers, asks the
:class:`~components.api.planner.SyncPlanner` for the next command and publishes it on each
module's ``joint_set``. The commands keep coming for the whole motion, which is what the joint
managers' watchdogs expect; when the motion ends the last command (the target) stays, and a
stop holds the joints at their measured positions.

Starting a motion cancels the one running on this syncer, and any motion of another syncer
(joint or IK) commanding the same modules: one module has one commander at a time.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Coroutine, Mapping, Sequence
from typing import Any

import numpy as np

from components.api.errors import JointNotReadyError, RobotClosedError, UnknownJointError
from components.api.joints import JointHandler
from components.api.motion import Motion
from components.api.planner import ASAP, LERP, SPEED_SAFE, UNSAFE, SyncPlanner, SyncSettings

log = logging.getLogger(__name__)


class Commander:
    """What every syncer shares: its modules, its one running motion, stopping.

    Args:
        handlers: The modules commanded.
    """

    def __init__(self, handlers: Sequence[JointHandler]) -> None:
        if not handlers:
            raise ValueError("a syncer needs at least one module")
        self.handlers: dict[str, JointHandler] = {h.slot: h for h in handlers}
        self._task: asyncio.Task[None] | None = None
        self._motion: Motion | None = None
        self.closed = False

    @property
    def motion(self) -> Motion | None:
        """The running motion, if any."""
        m = self._motion
        return m if m is not None and not m.done() else None

    def _launch(
        self, description: str, body: Callable[[Motion], Coroutine[Any, Any, None]]
    ) -> Motion:
        if self.closed:
            raise RobotClosedError(f"{description}: the robot connection is closed")
        self.cancel()
        for handler in self.handlers.values():
            other = handler.commander
            if other is not None and other is not self:
                other.cancel()
            handler.commander = self
        motion = Motion(description)
        self._motion = motion
        self._task = asyncio.get_running_loop().create_task(self._guard(motion, body))
        return motion

    async def _guard(
        self, motion: Motion, body: Callable[[Motion], Coroutine[Any, Any, None]]
    ) -> None:
        try:
            await body(motion)
        except asyncio.CancelledError:
            motion.finish(False)
            raise
        except Exception as exc:  # reaches the awaiting script, not the event loop
            log.exception("%s failed", motion.description)
            motion.fail(exc)

    def cancel(self) -> None:
        """Cancel the running motion (its awaitable gives False); the joints keep the last
        command, which is within ``delta`` of where they were measured."""
        task, self._task = self._task, None
        if task is not None and not task.done():
            task.cancel()
        if self._motion is not None:
            self._motion.finish(False)

    async def stop(self) -> None:
        """Cancel the running motion and hold every joint at its measured position (velocity
        0 for wheels): the clean stop of a script, never a halt."""
        task = self._task
        self.cancel()
        if task is not None:
            await asyncio.gather(task, return_exceptions=True)
        for handler in self.handlers.values():
            handler.hold()

    def close(self) -> None:
        """Cancel the running motion and refuse new ones."""
        self.cancel()
        self.closed = True


class JointSyncer(Commander):
    """Synchronized joint motions over one or several modules.

    Args:
        handlers: The modules (their joints, minus locked ones, are the syncer's joints).
        settings: Ball radius, arrival tolerance, speed, rate.

    Example::

        syncer = JointSyncer([robot.handler("limb1")])
        await syncer.lerp({"limb1_joint2": 0.5, "limb1_joint4": -0.8})
    """

    def __init__(
        self, handlers: Sequence[JointHandler], settings: SyncSettings | None = None
    ) -> None:
        super().__init__(handlers)
        self.settings = settings or SyncSettings()
        self._owner: dict[str, JointHandler] = {}
        for handler in self.handlers.values():
            for name, info in handler.joints.items():
                if not info.locked:
                    self._owner[name] = handler
        self.resyncs = 0

    @property
    def joints(self) -> tuple[str, ...]:
        """Every joint this syncer drives (assembly names)."""
        return tuple(self._owner)

    def resolve(self, name: str) -> str:
        """The assembly name of ``name``; a short name (``joint3``) is accepted when exactly
        one module has it.

        Raises:
            UnknownJointError: If no module (or more than one) has it, or it is locked.
        """
        if name in self._owner:
            return name
        matches = [f"{slot}_{name}" for slot in self.handlers if f"{slot}_{name}" in self._owner]
        if len(matches) == 1:
            return matches[0]
        locked = [
            n
            for h in self.handlers.values()
            for n, i in h.joints.items()
            if i.locked and n in (name, f"{h.slot}_{name}")
        ]
        if locked:
            raise UnknownJointError(f"joint {locked[0]} is locked (an override pins it)")
        if matches:
            raise UnknownJointError(f"joint {name!r} is ambiguous: {', '.join(matches)}")
        raise UnknownJointError(
            f"no joint {name!r} in {', '.join(self.handlers)}; joints: {', '.join(self._owner)}"
        )

    def measured(self, names: Sequence[str] | None = None) -> dict[str, float]:
        """The latest measured positions of ``names`` (default: every joint)."""
        out: dict[str, float] = {}
        for handler in self.handlers.values():
            out.update(handler.positions())
        wanted = self.joints if names is None else names
        return {n: out[n] for n in wanted if n in out}

    # ------------------------------------------------------------------ motions
    def lerp(self, target: Mapping[str, float]) -> Motion:
        """All named joints move together on a straight line in joint space; every step is
        the farthest point toward the target within ``delta`` of the measured state."""
        return self._start(LERP, target)

    def asap(self, target: Mapping[str, float]) -> Motion:
        """Each named joint moves toward its target on its own, within ``delta`` of its
        measured position."""
        return self._start(ASAP, target)

    def unsafe(self, target: Mapping[str, float]) -> Motion:
        """Each named joint is sent its target at once (limits still apply; no ball)."""
        return self._start(UNSAFE, target)

    def speed_safe(self, velocities: Mapping[str, float], duration: float | None = None) -> Motion:
        """Position commands advancing at ``velocities`` (rad/s), each within ``delta`` of
        the measured position. Runs ``duration`` seconds (then resolves True and the joints
        stay at the last command), or until another motion or a stop when None."""
        return self._start(SPEED_SAFE, velocities, duration)

    def _start(
        self, mode: str, values: Mapping[str, float], duration: float | None = None
    ) -> Motion:
        goal = {self.resolve(name): float(value) for name, value in values.items()}
        bad = [n for n, v in goal.items() if not np.isfinite(v)]
        if bad:
            raise ValueError(f"{mode}: non-finite value for {', '.join(bad)}")
        names = tuple(goal)
        measured = self.measured(names)
        missing = [n for n in names if n not in measured]
        if missing:
            raise JointNotReadyError(
                f"{mode}: no measured position yet for {', '.join(missing)} (no joint_read; "
                "wait for the robot to be ready, e.g. `await handler.wait_ready()`)"
            )
        planner = self.planner(names)
        values_array = np.array([goal[n] for n in names])
        slots = sorted({self._owner[n].slot for n in names})
        description = f"{mode} {'+'.join(slots)} ({len(names)} joints)"

        async def body(motion: Motion) -> None:
            await self._drive(planner, mode, values_array, motion, duration)

        return self._launch(description, body)

    def planner(self, names: Sequence[str]) -> SyncPlanner:
        """A planner for ``names``, continuing from the last commands sent to them."""
        infos = [self._owner[n].joints[n] for n in names]
        sent = {n: self._owner[n].last_command.get(n) for n in names}
        last = None
        if names and all(v is not None for v in sent.values()):
            last = [sent[n] for n in names]
        return SyncPlanner(
            names,
            [i.lower for i in infos],
            [i.upper for i in infos],
            [i.max_velocity for i in infos],
            self.settings,
            last,
        )

    def send(self, names: Sequence[str], command: np.ndarray) -> None:
        """Publish one position command per module and remember it as the last command."""
        per_module: dict[str, dict[str, float]] = {}
        for name, value in zip(names, command.tolist(), strict=True):
            per_module.setdefault(self._owner[name].slot, {})[name] = value
        for slot, commands in per_module.items():
            self.handlers[slot].send(commands)

    async def _drive(
        self,
        planner: SyncPlanner,
        mode: str,
        values: np.ndarray,
        motion: Motion,
        duration: float | None,
    ) -> None:
        loop = asyncio.get_running_loop()
        period = self.settings.period
        names = planner.names
        began = previous = loop.time()
        wake = began
        target = None if mode == SPEED_SAFE else values
        velocity = values if mode == SPEED_SAFE else None
        warned = False
        ticks = 0
        while True:
            now = loop.time()
            # A late tick must not turn into a big step: dt is capped at two periods.
            dt = min(now - previous, 2 * period) if now > previous else period
            previous = now
            current = self.measured(names)
            measured = np.array([current[n] for n in names])
            step = planner.step(mode, measured, dt, target=target, velocity=velocity)
            if step.resynced:
                self.resyncs += 1
                # At a motion's start the last command is usually stale (another motion, or
                # none): following from the measurement then is routine, not news. Later it
                # means the joints lag (blocked, or slower than asked): say so once.
                if ticks == 0 or warned:
                    log.debug("%s: resynchronized from the measurement", motion.description)
                else:
                    warned = True
                    log.warning(
                        "%s: the joints lag the command by more than %g; following on from "
                        "where they are (blocked, or asked to move faster than they can?)",
                        motion.description,
                        self.settings.delta,
                    )
            self.send(names, step.command)
            ticks += 1
            if step.arrived or (duration is not None and now - began >= duration):
                motion.finish(True)
                return
            wake += period
            await asyncio.sleep(max(wake - loop.time(), 0.0))
