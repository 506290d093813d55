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

As the last stage before the (simulated) motors, it checks every command as the motor
interface does: a message naming more joints than the module has, or with arrays that do not
match its names, is refused whole; unknown names, another module's joints, NaN and inf, and
values outside the unit's raw limits are refused; a joint named twice gets its last entry; a
halted module refuses everything until recover; an effort-mode joint faster than its max
velocity gets effort 0. Every refusal is counted by reason (``/sim/diagnostics``).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from components.executor.core import Core
from components.joints import JointSpec
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
    to_time,
    trigger_response,
)
from components.motors.base import READ_PERIOD, RawLimits, check_command, refused_whole
from components.simulator.topics import (
    CLOCK,
    CLOCK_TOPIC,
    SIM_NAMESPACE,
    commands_handler,
    halt_handler,
    module_diagnostics_topic,
    pose_topics,
    recover_handler,
    states_topic,
)
from components.simulator.world import EFFORT, SimWorld

#: Counters of the simulator's command checks: ``refused_oversize`` and
#: ``refused_malformed`` count messages (refused whole), ``duplicates`` entries superseded
#: by a later one for the same joint, ``speed_cuts`` efforts cut to 0 because the joint was
#: faster than its max velocity; the other ``refused_*`` count entries.
COUNTERS = (
    "refused_oversize",
    "refused_malformed",
    "refused_unknown",
    "refused_other_module",
    "refused_halted",
    "refused_nan",
    "refused_position",
    "refused_velocity",
    "refused_effort",
    "duplicates",
    "speed_cuts",
)


class _Motor:
    """What the command check needs of one simulated motor (precomputed once)."""

    __slots__ = ("checks", "index", "limits", "slot")

    def __init__(self, index: int, slot: str, limits: RawLimits) -> None:
        self.index = index
        self.slot = slot
        self.limits = limits
        self.checks = limits.checks()


def world_raw_limits(world: SimWorld) -> dict[str, RawLimits]:
    """Each simulated motor's raw limits: its model limits through the unit's calibration."""
    return {
        j.name: RawLimits.of_joint(
            JointSpec(j.name, "revolute", j.lower, j.upper, j.max_velocity, j.max_effort),
            j.calibration,
        )
        for j in world.joints
    }


@dataclass(frozen=True)
class SimulatorConfig:
    """Timing of the simulator (wall-clock seconds unless said otherwise).

    Attributes:
        speed: Simulated seconds per wall-clock second (1: real time; 5: five times faster,
            for tests).
        tick_period: How often the executor calls :meth:`SimulatorCore.tick`; one physics
            step per tick at speed 1 with the default 2 ms model time step.
        state_period: Seconds between two ``joint_states`` of a module: the real motor
            interface's 100 Hz (:data:`~components.motors.base.READ_PERIOD`). A module
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
    state_period: float = READ_PERIOD
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
        limits: Raw limits per joint (assembly name); by default :func:`world_raw_limits`,
            the model's limits (the module data's) through each unit's calibration.

    Attributes:
        world: The world.
        config: The timing in use.
        steps: Physics steps taken since start.
        dropped: Simulated seconds given up because ticks came too late to catch up.
    """

    def __init__(
        self,
        name: str,
        world: SimWorld,
        config: SimulatorConfig | None = None,
        timer: Callable[[], float] | None = None,
        limits: Mapping[str, RawLimits] | None = None,
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
        given = {**world_raw_limits(world), **(limits or {})}
        self._motors = {
            j.name: _Motor(i, j.module, given[j.name]) for i, j in enumerate(world.joints)
        }
        self._sizes = {slot: len(names) for slot, names in self._names.items()}
        self._counters = dict.fromkeys(COUNTERS, 0)
        self._efforts: set[str] = set()  # joints in effort mode, watched for speed
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
        for slot in self.slots:
            setattr(self, commands_handler(slot), functools.partial(self.on_module_commands, slot))
            setattr(self, halt_handler(slot), functools.partial(self.on_halt, slot))
            setattr(self, recover_handler(slot), functools.partial(self.on_recover, slot))

    # ------------------------------------------------------------------ read access
    @property
    def counters(self) -> dict[str, int]:
        """A copy of the command-check counters (cumulative since construction)."""
        return dict(self._counters)

    @property
    def refused_unknown(self) -> int:
        """Command entries naming no simulated motor."""
        return self._counters["refused_unknown"]

    @property
    def refused_nan(self) -> int:
        """Command entries carrying NaN or inf."""
        return self._counters["refused_nan"]

    @property
    def refused_other_module(self) -> int:
        """Command entries naming another module's joint on a module's topic."""
        return self._counters["refused_other_module"]

    def raw_limits(self, joint: str) -> RawLimits:
        """The raw limits a joint's commands are checked against (assembly name)."""
        return self._motors[joint].limits

    def halted(self, slot: str) -> bool:
        """Whether a module's ``motors/halt`` was called and ``motors/recover`` not since."""
        return slot in self._halted

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

        Joint names are assembly-unique. Checked as a motor interface checks them (see the
        module's docstring); ``slot``, when given, is the module whose topic it came on.
        """
        counters = self._counters
        refused = refused_whole(message, len(self._motors) if slot is None else self._sizes[slot])
        if refused is not None:
            counters[refused] += 1
            return
        # The last entry per joint wins: one command per joint however often it is named.
        latest = {sample.name: sample for sample in joint_samples(message)}
        if len(latest) != len(message.name):
            counters["duplicates"] += len(message.name) - len(latest)
        world = self.world
        for name, position, velocity, effort in latest.values():
            motor = self._motors.get(name)
            if motor is None:
                counters["refused_unknown"] += 1
                continue
            if slot is not None and motor.slot != slot:
                counters["refused_other_module"] += 1
                continue
            if motor.slot in self._halted:
                counters["refused_halted"] += 1
                continue
            reason = check_command(motor.checks, position, velocity, effort)
            if reason is not None:
                counters[reason] += 1
                continue
            if position is None and velocity is None and effort is not None:
                if self._too_fast(name, effort):
                    effort = 0.0
                    counters["speed_cuts"] += 1
                self._efforts.add(name)
            else:
                self._efforts.discard(name)
            world.command(name, position, velocity, effort)
            self._commanded.add(motor.slot)
            if position is None and velocity:
                self._spinning[name] = now
            else:
                self._spinning.pop(name, None)
        self._react(now)

    def _too_fast(self, name: str, raw_effort: float) -> bool:
        """Whether a raw effort pushes a joint already above its max velocity on."""
        world = self.world
        speed = world.velocity(name)  # model space: bring the effort there too
        effort = world.joint(name).calibration.rate_to_calibrated(raw_effort)
        return abs(speed) > self._motors[name].checks[2] and effort * speed > 0

    def _cut_fast_efforts(self) -> None:
        """Effort mode has no speed bound of its own: a joint turning faster than its max
        velocity with its effort pushing it on gets effort 0 (an effort that brakes stays)."""
        world = self.world
        for name in sorted(self._efforts):
            index = self._motors[name].index
            if world.mode[index] != EFFORT:
                self._efforts.discard(name)  # held by the world (a reset)
                continue
            target = float(world.target[index])  # model space
            if target and self._too_fast(name, world.joint(name).calibration.rate_to_raw(target)):
                world.command(name, None, None, 0.0)
                self._counters["speed_cuts"] += 1

    def on_halt(self, slot: str, request: Any, now: float) -> Any:
        """``/<slot>/motors/halt``: hold the module's motors where they are; refuse every
        command to them until ``motors/recover``."""
        names = self._names[slot]
        self.world.hold(names)
        self._halted.add(slot)
        for name in names:
            self._spinning.pop(name, None)
            self._efforts.discard(name)
        return trigger_response(
            True, f"{slot}: simulated motors halted; commands refused until motors/recover"
        )

    def on_recover(self, slot: str, request: Any, now: float) -> Any:
        """``/<slot>/motors/recover``: accept commands again (simulated motors have no
        faults to clear)."""
        self._halted.discard(slot)
        return trigger_response(True, f"{slot}: simulated motors accept commands again")

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
        if self._efforts:
            self._cut_fast_efforts()
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
            # The simulated clock, as ROS simulators give it (use_sim_time): what a test or
            # a tool times the world by when it runs behind the wall clock.
            self.publish(CLOCK_TOPIC, msg(CLOCK, clock=to_time(self.world.time)))
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
            **self._counters,
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
