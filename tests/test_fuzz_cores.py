"""Property-based fuzzing of the command path's cores (issue 10): the joint manager, the motor
interface (with a backend recording what it is asked) and the simulator (a small real MuJoCo
world that records every command it is given).

Inputs: JointState commands with NaN, inf, huge values, duplicates, ragged arrays (names,
position, velocity and effort of different lengths), unknown names, another module's names
and more names than the module has, interleaved with feedback, halts, recovers and ticks.

Properties:

* no exception escapes a handler;
* no command outside the raw limits reaches the backend (or the simulated motors, or, from
  the joint manager, ``joint_commands``);
* the counters account for every refused sample: a message is refused whole (one count), or
  each of its entries is sent, refused under one reason, or superseded by a later duplicate.
"""

from __future__ import annotations

import math
from typing import Any

import mujoco
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from components.assembly import JointPlan
from components.joint_manager import JointManagerCore
from components.joints import JointCalibration, JointSpec
from components.messages import JOINT_STATE, joint_samples, msg
from components.motor_interface.core import MotorInterfaceCore
from components.motors.base import (
    LIMIT_TOLERANCE,
    MotorBackend,
    MotorCommand,
    MotorDiagnostic,
    MotorSpec,
    MotorState,
    RawLimits,
)
from components.simulator.core import SimulatorConfig, SimulatorCore
from components.simulator.world import SimWorld

FUZZ = settings(max_examples=60, deadline=None)
TRIGGER_REQ = msg("std_srvs/srv/Trigger_Request")

# ------------------------------------------------------------------ one small module

#: limb1: a revolute joint (reversed and offset), a 0.04 m finger, a continuous wheel.
SPECS = (
    JointSpec("limb1_joint1", "revolute", -2.0, 2.0, 3.0, 10.0),
    JointSpec("limb1_finger", "prismatic", 0.0, 0.04, 0.1, 40.0),
    JointSpec("limb1_wheel", "continuous", -math.inf, math.inf, 6.0, 2.0),
)
CALIBRATION = {
    "limb1_joint1": JointCalibration(0.5, -1),
    "limb1_finger": JointCalibration(-0.0376, -1),
    "limb1_wheel": JointCalibration(0.0, 1),
}
LIMITS = {s.name: RawLimits.of_joint(s, CALIBRATION[s.name]) for s in SPECS}
RAW = {s.name: s.name.removeprefix("limb1_") for s in SPECS}
TOLERANCE = 1e-9

NAMES = st.sampled_from(
    [s.name for s in SPECS]
    + ["limb1_joint9", "joint1", "limb2_joint1", "", "limb1_" + "x" * 300, "wheel3_drive"]
)
VALUES = st.one_of(
    st.floats(-3.0, 3.0),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([math.nan, math.inf, -math.inf, 1e308, -1e308, 0.0, 2.5, -1.5, 0.04]),
)


def arrays(size: int) -> st.SearchStrategy[list[float]]:
    """Empty (not given), the right length, or ragged."""
    return st.one_of(
        st.just([]),
        st.lists(VALUES, min_size=size, max_size=size),
        st.lists(VALUES, max_size=size + 2),
    )


@st.composite
def joint_states(draw: Any, names: st.SearchStrategy[str] = NAMES, most: int = 6) -> Any:
    """A JointState: duplicates, unknown names, ragged arrays, NaN/inf/huge values."""
    chosen = draw(st.lists(names, max_size=most))
    size = len(chosen)
    return msg(
        JOINT_STATE,
        name=chosen,
        position=np.array(draw(arrays(size)), dtype=np.float64),
        velocity=np.array(draw(arrays(size)), dtype=np.float64),
        effort=np.array(draw(arrays(size)), dtype=np.float64),
    )


ACTIONS = st.lists(
    st.one_of(
        st.tuples(st.just("command"), joint_states()),
        st.tuples(st.just("feedback"), joint_states(st.sampled_from([s.name for s in SPECS]), 3)),
        st.tuples(st.sampled_from(["halt", "recover", "tick"]), st.none()),
    ),
    min_size=1,
    max_size=12,
)


def _slack(limit: float) -> float:
    """What a motor may see past ``limit``: the documented float-noise slack of its checks
    (LIMIT_TOLERANCE, relative), and this test's own rounding."""
    return LIMIT_TOLERANCE * max(1.0, abs(limit)) + TOLERANCE if math.isfinite(limit) else 0.0


def within(name: str, position: Any, velocity: Any, effort: Any) -> bool:
    lim = LIMITS[name]
    return (
        (
            position is None
            or lim.lower - _slack(lim.lower) <= position <= lim.upper + _slack(lim.upper)
        )
        and (velocity is None or abs(velocity) <= lim.max_velocity + _slack(lim.max_velocity))
        and (effort is None or abs(effort) <= lim.max_effort + _slack(lim.max_effort))
    )


def well_formed(message: Any) -> bool:
    n = len(message.name)
    arrays_ok = all(len(a) in (0, n) for a in (message.position, message.velocity, message.effort))
    return arrays_ok


# ------------------------------------------------------------------ the motor interface


class RecordingBackend(MotorBackend):
    """Records every command; reads back ``speed`` for each motor."""

    def __init__(self) -> None:
        super().__init__("fuzz0", [MotorSpec(RAW[s.name], i + 1, "m") for i, s in enumerate(SPECS)])
        self.written: list[MotorCommand] = []
        self.speed = 0.0

    def _open(self) -> None:
        pass

    def _close(self) -> None:
        pass

    def _read(self) -> dict[str, MotorState]:
        return {m.joint: MotorState(m.joint, 0.0, self.speed, 0.0) for m in self.motors}

    def _write(self, commands: list[MotorCommand]) -> None:
        self.written.extend(commands)

    def _halt(self) -> None:
        pass

    def _diagnostics(self) -> list[MotorDiagnostic]:
        return []


MOTOR_ENTRY_COUNTERS = (
    "refused_not_open",
    "refused_halted",
    "refused_unknown",
    "refused_nan",
    "refused_position",
    "refused_velocity",
    "refused_effort",
    "duplicates",
)


@FUZZ
@given(ACTIONS, st.floats(0.0, 20.0))
def test_motor_interface_never_forwards_a_command_out_of_limits(actions: Any, speed: float) -> None:
    backend = RecordingBackend()
    backend.speed = speed
    core = MotorInterfaceCore("limb1/motor_interface", "limb1", backend, limits={
        raw: LIMITS[full] for full, raw in RAW.items()})  # fmt: skip
    core.start(0.0)
    now = 0.0
    for kind, message in actions:
        now += 0.05
        before = core.counters
        written = len(backend.written)
        if kind in ("command", "feedback"):  # both arrive as commands here
            core.on_joint_commands(message, now)
            after = core.counters
            sent = len(backend.written) - written
            n = len(message.name)
            if n > len(SPECS) or not well_formed(message):
                whole = after["refused_oversize"] + after["refused_malformed"]
                assert whole == before["refused_oversize"] + before["refused_malformed"] + 1
                assert sent == 0
            else:
                refused = sum(after[c] - before[c] for c in MOTOR_ENTRY_COUNTERS)
                assert sent + refused == n, (message, before, after)
        elif kind == "halt":
            core.on_halt(TRIGGER_REQ, now)
        elif kind == "recover":
            core.on_recover(TRIGGER_REQ, now)
        else:
            core.tick(now)
        for command in backend.written[written:]:
            full = f"limb1_{command.joint}"
            assert within(full, command.position, command.velocity, command.effort), command
    core.diagnostics(now)


# ------------------------------------------------------------------ the joint manager

MANAGER_ENTRY_COUNTERS = (
    "duplicates",
    "refused_nan",
    "refused_unknown",
    "refused_other_module",
    "refused_locked",
    "refused_halted",
    "refused_no_state",
)


def empty_entries(core: JointManagerCore, message: Any) -> int:
    """Known joints named with no value at all: skipped, not refused (nothing to do)."""
    latest = {s.name: s for s in joint_samples(message)}
    return sum(
        1
        for s in latest.values()
        if s.name in CALIBRATION and s.position is None and s.velocity is None and s.effort is None
    )


@FUZZ
@given(ACTIONS)
def test_joint_manager_never_publishes_a_command_out_of_limits(actions: Any) -> None:
    core = JointManagerCore("limb1/joint_manager", "limb1", SPECS, CALIBRATION)
    now = 0.0
    for kind, message in actions:
        now += 0.05
        before = core.counters
        if kind == "command":
            core.on_joint_set(message, now)
            after = core.counters
            sent = sum(len(m.name) for m in core.outbox.on("joint_commands"))
            n = len(message.name)
            if n > len(SPECS) or not well_formed(message):
                whole = after["refused_oversize"] + after["refused_malformed"]
                assert whole == before["refused_oversize"] + before["refused_malformed"] + 1
                assert sent == 0
            elif core.halted:
                assert sum(after[c] - before[c] for c in MANAGER_ENTRY_COUNTERS) == n
            else:
                refused = sum(after[c] - before[c] for c in MANAGER_ENTRY_COUNTERS)
                assert sent + refused + empty_entries(core, message) == n, (message, after)
        elif kind == "feedback":
            core.on_joint_states(message, now)
        elif kind == "halt":
            core.on_halt(TRIGGER_REQ, now)
        elif kind == "recover":
            core.on_recover(TRIGGER_REQ, now)
        else:
            core.tick(now)
        for published in core.outbox.take("joint_commands"):
            for sample in joint_samples(published):
                assert within(*sample), sample
                lo, hi = core.command_range(sample.name)
                if sample.position is not None and math.isfinite(lo):
                    p = CALIBRATION[sample.name].to_calibrated(sample.position)
                    assert lo - TOLERANCE <= p <= hi + TOLERANCE, sample
        core.outbox.take()
    core.diagnostics(now)


# ------------------------------------------------------------------ the simulator

MJCF = """
<mujoco>
  <option timestep="0.002"/>
  <worldbody>
    <body name="limb1_base_link">
      <body name="arm">
        <joint name="limb1_joint1" type="hinge" axis="0 0 1" limited="true" range="-2 2"/>
        <geom type="capsule" size="0.02" fromto="0 0 0 0.2 0 0" mass="0.5"/>
        <body name="finger">
          <joint name="limb1_finger" type="slide" axis="1 0 0" limited="true" range="0 0.04"/>
          <geom type="box" size="0.01 0.01 0.01" mass="0.05"/>
        </body>
      </body>
      <body name="wheel" pos="0 0.3 0">
        <joint name="limb1_wheel" type="hinge" axis="0 1 0"/>
        <geom type="cylinder" size="0.05 0.01" mass="0.2"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <general joint="limb1_joint1" gainprm="50" biasprm="0 -50 -5" biastype="affine"
             forcelimited="true" forcerange="-10 10"/>
    <general joint="limb1_finger" gainprm="200" biasprm="0 -200 -20" biastype="affine"
             forcelimited="true" forcerange="-40 40"/>
    <velocity joint="limb1_wheel" kv="1" forcelimited="true" forcerange="-2 2"/>
  </actuator>
</mujoco>
"""


class RecordingWorld(SimWorld):
    """The real world, recording every command it is given (raw values)."""

    def __init__(self) -> None:
        plans = [
            (
                "limb1",
                JointPlan(
                    name=s.name,
                    raw_name=RAW[s.name],
                    type=s.type,  # type: ignore[arg-type]
                    max_velocity=s.max_velocity,
                    max_effort=s.max_effort,
                    lower=s.lower if s.bounded else None,
                    upper=s.upper if s.bounded else None,
                    zero_offset=CALIBRATION[s.name].zero_offset,
                    direction=CALIBRATION[s.name].direction,
                    control="velocity" if s.type == "continuous" else "position",
                ),
            )
            for s in SPECS
        ]
        super().__init__(mujoco.MjModel.from_xml_string(MJCF), plans, ["limb1_base_link"])
        self.commands: list[tuple[str, Any, Any, Any]] = []

    def command(self, name: str, position: Any = None, velocity: Any = None, effort: Any = None):
        self.commands.append((name, position, velocity, effort))
        super().command(name, position, velocity, effort)


SIM_ENTRY_COUNTERS = (
    "refused_unknown",
    "refused_other_module",
    "refused_halted",
    "refused_nan",
    "refused_position",
    "refused_velocity",
    "refused_effort",
    "duplicates",
)


@FUZZ
@given(ACTIONS, st.booleans())
def test_simulator_never_drives_a_motor_out_of_limits(actions: Any, on_module: bool) -> None:
    world = RecordingWorld()
    core = SimulatorCore("sim", world, SimulatorConfig(command_timeout=0.2))
    core.start(0.0)
    now = 0.0
    for kind, message in actions:
        now += 0.004
        before = core.counters
        given = len(world.commands)
        if kind in ("command", "feedback"):
            if on_module:
                core.on_joint_commands_limb1(message, now)
            else:
                core.on_joint_commands(message, now)
            after = core.counters
            sent = len(world.commands) - given
            n = len(message.name)
            if n > len(SPECS) or not well_formed(message):
                whole = after["refused_oversize"] + after["refused_malformed"]
                assert whole == before["refused_oversize"] + before["refused_malformed"] + 1
                assert sent == 0
            else:
                refused = sum(after[c] - before[c] for c in SIM_ENTRY_COUNTERS)
                assert sent + refused == n, (message, before, after)
        elif kind == "halt":
            core.on_halt_limb1(TRIGGER_REQ, now)
        elif kind == "recover":
            core.on_recover_limb1(TRIGGER_REQ, now)
        else:
            core.tick(now)
        for command in world.commands[given:]:
            assert within(*command), command
    assert world.finite()
    core.diagnostics(now)
