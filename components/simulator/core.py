"""The simulator core: every module's motor interface, served by one simulated world.

To each module's joint manager the simulator is that module's motor interface: it reads
``/<slot>/joint_commands`` and publishes ``/<slot>/joint_states`` (raw joint space) and motor
``/<slot>/diagnostics``, and serves ``/<slot>/motors/halt`` and ``/<slot>/motors/recover``, as
:mod:`components.motor_interface` does on hardware. On top of that it publishes what only a
simulator knows: the ground-truth pose of each robot's root link and its own diagnostics
(real-time factor, step rate, simulated time) under ``/sim``.

Time is passed in, as for every core: :meth:`SimulatorCore.tick` advances the physics by the
wall time elapsed since the previous tick times the speed factor. A late world catches up a
few steps per tick, and by at most ``max_catch_up`` seconds of wall time in all: a world that
cannot keep up falls behind (the real-time factor in diagnostics says so) and keeps publishing,
instead of spending ever longer catching up.

Rates (states, diagnostics) are in wall time, because the joint managers and everything above
run on wall time; at speed 1 wall time and simulated time advance together.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from components.executor.core import Core
from components.messages import (
    ERROR,
    JOINT_STATE,
    OK,
    POSE_STAMPED,
    WARN,
    diagnostic_array,
    diagnostic_status,
    header,
    joint_samples,
    msg,
    trigger_response,
)
from components.simulator.world import SimWorld

#: Namespace of what belongs to the simulator itself (pose ground truth, diagnostics).
SIM_NAMESPACE = "/sim"


@dataclass(frozen=True)
class SimulatorConfig:
    """Timing of the simulator (wall-clock seconds unless said otherwise).

    Attributes:
        speed: Simulated seconds per wall-clock second (1: real time; 5: five times faster,
            for tests).
        tick_period: How often the executor calls :meth:`SimulatorCore.tick`; one physics
            step per tick at speed 1 with the default 2 ms model time step.
        state_period: Seconds between two ``joint_states`` of a module (200 Hz). A module
            that received a command also publishes at the first tick after it, so the
            effect of a command is seen one physics step later, not one period later.
        pose_period: Seconds between two ground-truth poses.
        diagnostics_period: Seconds between two diagnostics (and the real-time factor window).
        max_catch_up: Largest wall time the world catches up after a stall; beyond it the
            simulated time is given up (counted as dropped).
        catch_up_rate: A tick takes at most this many times its nominal number of steps,
            so a late world catches up over several short ticks and keeps publishing states,
            rather than stalling everything in one long tick.
        frame_id: Frame of the ground-truth poses.
        command_timeout: Seconds without commands after which a joint turning in velocity
            mode is stopped, as the real motor interface does (behind the joint manager's
            own watchdog): the simulator never keeps a last velocity either.
    """

    speed: float = 1.0
    tick_period: float = 0.002
    state_period: float = 0.005
    pose_period: float = 0.01
    diagnostics_period: float = 1.0
    max_catch_up: float = 0.1
    catch_up_rate: float = 4.0
    frame_id: str = "world"
    command_timeout: float = 1.0

    def __post_init__(self) -> None:
        for name in (
            "speed",
            "tick_period",
            "state_period",
            "pose_period",
            "diagnostics_period",
            "max_catch_up",
            "catch_up_rate",
        ):
            value = getattr(self, name)
            if not (value > 0 and math.isfinite(value)):
                raise ValueError(f"SimulatorConfig.{name} must be a finite number > 0, not {value}")


def states_topic(slot: str) -> str:
    """The absolute ``joint_states`` topic of a module."""
    return f"/{slot}/joint_states"


def commands_topic(slot: str) -> str:
    """The absolute ``joint_commands`` topic of a module."""
    return f"/{slot}/joint_commands"


def module_diagnostics_topic(slot: str) -> str:
    """The absolute ``diagnostics`` topic of a module (shared with its joint manager)."""
    return f"/{slot}/diagnostics"


def pose_topics(roots: Sequence[str]) -> list[tuple[str, str]]:
    """(root link, topic) pairs of the ground-truth poses.

    The first robot's root is ``/sim/base_pose``; with several robots every root also has
    ``/sim/<root link>/pose``, so a ground station subscribes to the one robot it needs.
    """
    pairs = [(roots[0], f"{SIM_NAMESPACE}/base_pose")] if roots else []
    if len(roots) > 1:
        pairs.extend((root, f"{SIM_NAMESPACE}/{root}/pose") for root in roots)
    return pairs


def commands_handler(slot: str) -> str:
    """Name of the core's handler for ``/<slot>/joint_commands``."""
    return f"on_joint_commands_{slot}"


def halt_handler(slot: str) -> str:
    """Name of the core's handler for ``/<slot>/motors/halt``."""
    return f"on_halt_{slot}"


def recover_handler(slot: str) -> str:
    """Name of the core's handler for ``/<slot>/motors/recover``."""
    return f"on_recover_{slot}"


class SimulatorCore(Core):
    """Steps a :class:`SimWorld` in (scaled) real time and serves every module's motors.

    Handlers: :meth:`on_joint_commands` (every module's ``joint_commands``), :meth:`tick`,
    and per module ``on_halt_<slot>`` / ``on_recover_<slot>`` (see :func:`halt_handler`).

    Args:
        name: Component name (``sim``).
        world: The simulated world (the core steps it; the builder closes it).
        config: Timing; defaults when omitted.
        timer: A high-resolution clock used only to measure how long physics takes (the
            ``load`` in diagnostics); ``None`` in fake-time tests, where load is not reported.

    Attributes:
        world: The world.
        config: The timing in use.
        steps: Physics steps taken since start.
        dropped: Simulated seconds given up because ticks came too late to catch up.
        refused_unknown: Command entries naming no simulated motor.
    """

    def __init__(
        self,
        name: str,
        world: SimWorld,
        config: SimulatorConfig | None = None,
        timer: Callable[[], float] | None = None,
    ) -> None:
        super().__init__(name)
        self.world = world
        self.config = config or SimulatorConfig()
        self._timer = timer
        self.slots = tuple(world.modules)
        self._names = {
            slot: [world.joints[i].name for i in world.modules[slot]] for slot in self.slots
        }
        self._pose_topics = pose_topics(tuple(world.roots))
        self.steps = 0
        self.dropped = 0.0
        self.refused_unknown = 0
        self.refused_nan = 0
        self._last: float | None = None
        self._debt = 0.0
        self._max_steps = max(
            1,
            math.ceil(
                self.config.catch_up_rate
                * self.config.tick_period
                * self.config.speed
                / world.timestep
            ),
        )
        self._next_state = dict.fromkeys(self.slots, -math.inf)
        self._commanded: set[str] = set()
        self._spinning: dict[str, float] = {}  # joint -> when it was last given a velocity
        self.watchdog_stops = 0
        self._next_pose = -math.inf
        self._next_diagnostics = -math.inf
        self._window_start: float | None = None
        self._window_sim = 0.0
        self._window_steps = 0
        self._window_states = 0
        self._window_busy = 0.0
        self.real_time_factor: float | None = None
        self.step_rate: float | None = None
        self.state_rate: float | None = None
        self.load: float | None = None
        self._halted: set[str] = set()
        self.refused_other_module = 0
        for slot in self.slots:
            setattr(self, commands_handler(slot), functools.partial(self.on_module_commands, slot))
            setattr(self, halt_handler(slot), functools.partial(self.on_halt, slot))
            setattr(self, recover_handler(slot), functools.partial(self.on_recover, slot))

    # ------------------------------------------------------------------ lifecycle
    def start(self, now: float) -> None:
        """Start the clock and publish the initial states."""
        self._last = now
        self._window_start = now
        self._publish_due(now, force=True)

    def stop(self, now: float) -> None:
        """Hold every motor where it is (a stopping motor interface leaves motors halted)."""
        self.world.hold()

    # ------------------------------------------------------------------ commands
    def on_module_commands(self, slot: str, message: Any, now: float) -> None:
        """``/<slot>/joint_commands``: like a real motor interface, only that module's joints.

        A joint of another module named on this topic is refused and counted, as the module's
        own motor interface would refuse it (it does not drive that joint).
        """
        self.on_joint_commands(message, now, slot)

    def on_joint_commands(self, message: Any, now: float, slot: str | None = None) -> None:
        """Raw commands: each named joint gets its position, speed or effort.

        Joint names are assembly-unique. Names the world does not drive, joints of another
        module than ``slot`` (when given), and non-finite values are counted and skipped.
        """
        world = self.world
        for sample in joint_samples(message):
            if not world.has_joint(sample.name):
                self.refused_unknown += 1
                continue
            if slot is not None and world.joint(sample.name).module != slot:
                self.refused_other_module += 1
                continue
            values = (sample.position, sample.velocity, sample.effort)
            if any(v is not None and not math.isfinite(v) for v in values):
                self.refused_nan += 1
                continue
            world.command(sample.name, *values)
            self._commanded.add(world.joint(sample.name).module)
            if sample.position is None and sample.velocity:
                self._spinning[sample.name] = now
            else:
                self._spinning.pop(sample.name, None)
        self._react(now)

    def on_halt(self, slot: str, request: Any, now: float) -> Any:
        """``/<slot>/motors/halt``: hold the module's motors where they are."""
        self.world.hold(self._names[slot])
        self._halted.add(slot)
        return trigger_response(True, f"{slot}: simulated motors halted")

    def on_recover(self, slot: str, request: Any, now: float) -> Any:
        """``/<slot>/motors/recover``: simulated motors have no faults to clear."""
        self._halted.discard(slot)
        return trigger_response(True, f"{slot}: simulated motors have no faults")

    # ------------------------------------------------------------------ stepping
    def tick(self, now: float) -> None:
        """Advance the physics to ``now`` (scaled by the speed) and publish what is due."""
        if self._last is None:
            self.start(now)
            return
        if self._spinning:
            timeout = self.config.command_timeout
            for name in [n for n, at in self._spinning.items() if now - at > timeout]:
                self.world.command(name, None, 0.0, None)
                del self._spinning[name]
                self.watchdog_stops += 1
        steps = self._catch_up(now)
        self._publish_due(now, force=False, stepped=steps > 0)

    def _catch_up(self, now: float) -> int:
        """Step the physics up to ``now``; returns the number of steps taken."""
        assert self._last is not None
        elapsed = max(now - self._last, 0.0)
        self._last = now
        cfg = self.config
        self._debt += elapsed * cfg.speed
        limit = cfg.max_catch_up * cfg.speed
        if self._debt > limit:
            self.dropped += self._debt - limit
            self._debt = limit
        dt = self.world.timestep
        # A hair of tolerance so float error on exact multiples does not lose a step.
        steps = min(int(self._debt / dt + 1e-6), self._max_steps)
        if steps > 0:
            self._step(steps, now)
        return steps

    def _step(self, steps: int, now: float) -> None:
        dt = self.world.timestep
        self._debt -= steps * dt
        started = self._timer() if self._timer else 0.0
        self.world.step(steps)
        if self._timer:
            self._window_busy += self._timer() - started
        self.steps += steps
        self._window_steps += steps
        self._window_sim += steps * dt
        self.world.sync_viewer(now)

    def _react(self, now: float) -> None:
        """Show a command's effect now: catch up, take one step ahead, publish the modules.

        Waiting for the next tick would add up to a tick period to every command-to-state
        latency. The simulated clock may lead the (scaled) wall clock by at most one step
        for this; the following ticks simply wait until the wall clock has caught up.
        """
        if self._last is None or not self._commanded:
            return
        self._catch_up(now)
        if self._debt > -0.5 * self.world.timestep:
            self._step(1, now)
        self._publish_due(now, force=False, stepped=True)

    # ------------------------------------------------------------------ publishing
    def _publish_due(self, now: float, force: bool, stepped: bool = True) -> None:
        cfg = self.config
        stamp = self.stamp(now)
        for slot in self.slots:
            if not (
                force or now >= self._next_state[slot] or (stepped and slot in self._commanded)
            ):
                continue
            self._commanded.discard(slot)
            # Keep the cadence (next = previous + period) unless a stall left it behind.
            due = self._next_state[slot] + cfg.state_period
            self._next_state[slot] = due if due > now else now + cfg.state_period
            self.publish(states_topic(slot), self.joint_states(slot, stamp))
            self._window_states += 1
        if force or now >= self._next_pose:
            self._next_pose = now + cfg.pose_period
            for root, topic in self._pose_topics:
                self.publish(topic, self.pose(root, stamp))
        if force or now >= self._next_diagnostics:
            self._next_diagnostics = now + cfg.diagnostics_period
            self._close_window(now)
            self.publish(f"{SIM_NAMESPACE}/diagnostics", self.diagnostics(stamp))
            for slot in self.slots:
                self.publish(module_diagnostics_topic(slot), self.module_diagnostics(slot, stamp))

    def _close_window(self, now: float) -> None:
        start = self._window_start
        if start is not None and now > start:
            wall = now - start
            self.real_time_factor = self._window_sim / wall
            self.step_rate = self._window_steps / wall
            self.state_rate = self._window_states / wall / max(len(self.slots), 1)
            self.load = self._window_busy / wall if self._timer else None
        self._window_start = now
        self._window_sim = 0.0
        self._window_steps = 0
        self._window_states = 0
        self._window_busy = 0.0

    def joint_states(self, slot: str, stamp: float) -> Any:
        """A module's ``joint_states`` (raw space) at wall-clock ``stamp``."""
        state = self.world.raw_state(slot)
        return msg(
            JOINT_STATE,
            header=header(stamp),
            name=list(state.names),
            position=np.ascontiguousarray(state.position, dtype=np.float64),
            velocity=np.ascontiguousarray(state.velocity, dtype=np.float64),
            effort=np.ascontiguousarray(state.effort, dtype=np.float64),
        )

    def pose(self, root: str, stamp: float) -> Any:
        """A root link's ground-truth ``geometry_msgs/PoseStamped`` in the world frame."""
        position, quat = self.world.root_pose(root)
        return msg(
            POSE_STAMPED,
            header=header(stamp, self.config.frame_id),
            pose=msg(
                "geometry_msgs/msg/Pose",
                position=msg(
                    "geometry_msgs/msg/Point",
                    x=float(position[0]),
                    y=float(position[1]),
                    z=float(position[2]),
                ),
                orientation=msg(
                    "geometry_msgs/msg/Quaternion",
                    w=float(quat[0]),
                    x=float(quat[1]),
                    y=float(quat[2]),
                    z=float(quat[3]),
                ),
            ),
        )

    def diagnostics(self, stamp: float) -> Any:
        """``/sim/diagnostics``: real-time factor, step rate, simulated time, divergence."""
        cfg = self.config
        level, notes = OK, []
        rtf = self.real_time_factor
        if rtf is not None and rtf < 0.9 * cfg.speed:
            level = WARN
            notes.append(
                f"falling behind: real-time factor {rtf:.2f} for speed {cfg.speed:g} "
                "(a slower speed, or a lighter machine load, lets it keep up)"
            )
        if self.world.resets or not self.world.finite():
            level = ERROR
            notes.append(f"physics diverged ({self.world.resets} resets)")
        values: dict[str, Any] = {
            "real_time_factor": _fmt(rtf),
            "speed": f"{cfg.speed:g}",
            "step_rate_hz": _fmt(self.step_rate, ".1f"),
            "state_rate_hz": _fmt(self.state_rate, ".1f"),
            "sim_time": f"{self.world.time:.3f}",
            "timestep": f"{self.world.timestep:g}",
            "steps": self.steps,
            "dropped_s": f"{self.dropped:.3f}",
            "resets": self.world.resets,
            "joints": len(self.world.joints),
            "refused_unknown": self.refused_unknown,
            "refused_nan": self.refused_nan,
        }
        if self.load is not None:
            values["load"] = f"{self.load:.3f}"
        status = diagnostic_status(
            f"{self.name}/world", level, "; ".join(notes) or "OK", "mujoco", values
        )
        return diagnostic_array([status], stamp)

    def module_diagnostics(self, slot: str, stamp: float) -> Any:
        """A module's motor diagnostics, named as its motor interface names them."""
        world = self.world
        halted = slot in self._halted
        statuses = [
            diagnostic_status(
                f"{slot}/bus",
                OK,
                "simulated (MuJoCo)" + (", halted" if halted else ""),
                hardware_id="mujoco",
                values={"joints": len(self._names[slot])},
            )
        ]
        state = world.raw_state(slot)
        for name, effort in zip(state.names, state.effort, strict=True):
            statuses.append(
                diagnostic_status(
                    name,
                    OK,
                    "ok",
                    hardware_id="mujoco",
                    values={"mode": world.mode_of(name), "effort": f"{effort:.4g}"},
                )
            )
        return diagnostic_array(statuses, stamp)

    # ------------------------------------------------------------------ topics
    @property
    def pose_topics(self) -> list[tuple[str, str]]:
        """(root link, topic) pairs of the ground-truth poses."""
        return list(self._pose_topics)


def _fmt(value: float | None, spec: str = ".3f") -> str:
    return "" if value is None else format(value, spec)
