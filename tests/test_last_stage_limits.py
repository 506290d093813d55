"""Defence in depth at the last stage (issue 10, findings 1, 3, 8, 9 and 10).

The motor interface and the simulator check every command themselves, whoever published it:
the unit's raw limits (the module's joint limits through the unit's calibration), NaN and inf,
unknown names, duplicates collapsed to the last value, a halt that latches until recover, a
whole message refused when it names more joints than the module has, and effort cut when a
joint turns faster than its max velocity. Every refusal is counted by reason.

The findings are reproduced as they were found: against the emulated CiA 402 drives (real
python-can, real ``canopen``) and the emulated Dynamixel chain (real dynamixel-sdk over a
pty), built by the real builder from a resolved assembly; in simulation against real MuJoCo
(those tests carry the ``e2e`` marker, as the simulator's own tests do).
"""

from __future__ import annotations

import math
import uuid
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from conftest import resolved_assembly, wait_until

from components.assembly import ComponentPlan, ResolvedAssembly
from components.build import build_component
from components.joint_manager import JointManagerConfig, JointManagerCore
from components.joints import JointCalibration, JointSpec
from components.messages import (
    JOINT_STATE,
    JointSample,
    diagnostic_values,
    joint_samples,
    joint_state,
    msg,
)
from components.motor_interface.core import MotorInterfaceCore
from components.motors.base import (
    MotorBackend,
    MotorCommand,
    MotorDiagnostic,
    MotorSpec,
    MotorState,
    RawLimits,
)

SLOT = "limb1"
TRIGGER_REQ = msg("std_srvs/srv/Trigger_Request")


# ------------------------------------------------------------------ a recording bus


class RecordingBackend(MotorBackend):
    """A bus that records every command it is asked to send; reads report ``speeds``."""

    def __init__(self, joints: tuple[str, ...] = ("joint1", "joint2")) -> None:
        super().__init__("fake0", [MotorSpec(j, i + 1, "m") for i, j in enumerate(joints)], {})
        self.written: list[MotorCommand] = []
        self.speeds: dict[str, float] = dict.fromkeys(joints, 0.0)
        self.halts = 0

    def _open(self) -> None:
        pass

    def _close(self) -> None:
        pass

    def _read(self) -> dict[str, MotorState]:
        return {j: MotorState(j, 0.0, v, 0.0) for j, v in self.speeds.items()}

    def _write(self, commands: list[MotorCommand]) -> None:
        self.written.extend(commands)

    def _halt(self) -> None:
        self.halts += 1

    def _diagnostics(self) -> list[MotorDiagnostic]:
        return []


#: joint1: ±2.0 rad, reversed and offset by 0.5 (raw -1.5 .. 2.5); joint2: ±1.0, no offset.
LIMITS = {
    "joint1": RawLimits.of_joint(
        JointSpec("limb1_joint1", lower=-2.0, upper=2.0, max_velocity=3.0, max_effort=10.0),
        JointCalibration(zero_offset=0.5, direction=-1),
    ),
    "joint2": RawLimits.of_joint(
        JointSpec("limb1_joint2", lower=-1.0, upper=1.0, max_velocity=6.0, max_effort=4.0),
        JointCalibration(),
    ),
}


def interface(backend: RecordingBackend | None = None) -> MotorInterfaceCore:
    backend = backend or RecordingBackend()
    core = MotorInterfaceCore("limb1/motor_interface", SLOT, backend, limits=LIMITS)
    core.start(0.0)
    return core


def send(core: Any, now: float, *samples: JointSample) -> None:
    core.on_joint_commands(joint_state(samples), now)


def own_status(core: MotorInterfaceCore, now: float) -> Any:
    return next(s for s in core.diagnostics(now) if s.name == "limb1/motor_interface")


# ------------------------------------------------------------------ the motor interface core


def test_raw_limits_are_the_joint_limits_through_the_calibration() -> None:
    limits = LIMITS["joint1"]
    assert (limits.lower, limits.upper) == (pytest.approx(-1.5), pytest.approx(2.5))
    assert (limits.max_velocity, limits.max_effort) == (3.0, 10.0)
    wheel = RawLimits.of_joint(
        JointSpec("w", "continuous", -math.inf, math.inf, 6.0, 2.0), JointCalibration(1.0, -1)
    )
    assert (wheel.lower, wheel.upper) == (-math.inf, math.inf)
    assert limits.admits(2.5, None, None) is None  # the very limit passes
    assert limits.admits(2.5 + 1e-3, None, None) == "refused_position"
    assert limits.admits(None, -3.5, None) == "refused_velocity"
    assert limits.admits(None, None, 10.5) == "refused_effort"
    assert limits.admits(math.nan, None, None) == "refused_nan"
    assert wheel.admits(None, math.inf, None) == "refused_nan"
    assert wheel.admits(1e300, None, None) is None  # a continuous joint has no position limit


def test_out_of_limit_nan_and_unknown_commands_never_reach_the_bus_and_are_counted() -> None:
    backend = RecordingBackend()
    core = interface(backend)
    send(core, 0.1, JointSample("limb1_joint1", 2.4))
    send(core, 0.1, JointSample("limb1_joint2", None, 5.0))
    assert backend.written == [MotorCommand("joint1", 2.4), MotorCommand("joint2", None, 5.0)]
    backend.written.clear()
    refused = [
        JointSample("limb1_joint1", 6.0),  # past the raw upper limit 2.5
        JointSample("limb1_joint2", None, 6.5),  # faster than 6 rad/s
        JointSample("limb1_joint2", None, None, -4.5),  # more than 4 N·m
        JointSample("limb1_joint1", math.nan),
        JointSample("limb1_joint2", None, math.inf),
        JointSample("limb2_joint1", 0.0),  # another module's joint
    ]
    for sample in refused:
        send(core, 0.2, sample)
    assert backend.written == []
    counters = core.counters
    assert counters["refused_position"] == 1
    assert counters["refused_velocity"] == 1
    assert counters["refused_effort"] == 1
    assert counters["refused_nan"] == 2
    assert counters["refused_unknown"] == 1
    status = own_status(core, 0.3)
    assert status.level == 1 and "refused" in status.message
    assert diagnostic_values(status)["refused_position"] == "1"
    assert own_status(core, 10.0).level == 0  # the warning ages out; the counters stay
    assert diagnostic_values(own_status(core, 10.0))["refused_nan"] == "2"


def test_duplicates_collapse_to_the_last_value_one_command_per_joint() -> None:
    """Finding 10: one JointState with 1000 duplicate entries gave about 1000 raw commands."""
    backend = RecordingBackend()
    core = interface(backend)
    flood = joint_state(JointSample("limb1_joint1", 0.001 * i) for i in range(1000))
    core.on_joint_commands(flood, 0.1)
    sent = len(backend.written)
    print(f"\n1000 duplicate entries: {sent} raw command(s) reached the bus")
    assert sent <= 1
    assert core.counters["refused_oversize"] == 1  # 1000 names on a 2-joint bus
    # Within the module's size, a joint named twice gets its last value only.
    send(core, 0.2, JointSample("limb1_joint1", 0.1), JointSample("limb1_joint1", 0.2))
    assert backend.written == [MotorCommand("joint1", 0.2)]
    assert core.counters["duplicates"] == 1


def test_a_message_naming_more_joints_than_the_module_has_is_refused_whole() -> None:
    backend = RecordingBackend()
    core = interface(backend)
    names = ["limb1_joint1", "limb1_joint2"] + [f"x{i}" for i in range(100_000)]
    flood = msg(JOINT_STATE, name=names, position=np.zeros(len(names)))
    core.on_joint_commands(flood, 0.1)
    assert backend.written == []
    assert core.counters["refused_oversize"] == 1
    assert core.counters["refused_unknown"] == 0  # refused whole, not name by name


def test_ragged_arrays_are_refused_whole() -> None:
    backend = RecordingBackend()
    core = interface(backend)
    ragged = msg(
        JOINT_STATE, name=["limb1_joint1", "limb1_joint2"], position=np.array([0.1])
    )  # which joint is 0.1 for?
    core.on_joint_commands(ragged, 0.1)
    assert backend.written == [] and core.counters["refused_malformed"] == 1


def test_a_halt_latches_until_recover() -> None:
    backend = RecordingBackend()
    core = interface(backend)
    assert core.on_halt(TRIGGER_REQ, 1.0).success
    assert backend.halts == 1 and core.halted
    send(core, 1.1, JointSample("limb1_joint1", 0.5), JointSample("limb1_joint2", 0.2))
    assert backend.written == []
    assert core.counters["refused_halted"] == 2
    status = own_status(core, 1.2)
    assert status.level == 2 and "halted" in status.message
    assert core.on_recover(TRIGGER_REQ, 2.0).success
    send(core, 2.1, JointSample("limb1_joint1", 0.5))
    assert backend.written == [MotorCommand("joint1", 0.5)]


def test_effort_is_cut_when_the_joint_turns_faster_than_its_max_velocity() -> None:
    """Finding 8, last stage: effort mode had no speed bound (3.7 rad/s with a 3.0 limit)."""
    backend = RecordingBackend()
    core = interface(backend)
    send(core, 0.0, JointSample("limb1_joint1", None, None, 5.0))
    backend.speeds["joint1"] = 2.0
    core.tick(0.01)
    assert backend.written == [MotorCommand("joint1", None, None, 5.0)]
    backend.speeds["joint1"] = 3.7  # over 3.0 rad/s, the effort pushing it on
    core.tick(0.02)
    assert backend.written[-1] == MotorCommand("joint1", effort=0.0)
    assert core.counters["speed_cuts"] == 1
    core.tick(0.03)
    assert len(backend.written) == 2  # cut once, not at every tick
    # A new effort along the motion, still too fast: cut at once; a braking one passes.
    send(core, 0.04, JointSample("limb1_joint1", None, None, 4.0))
    assert backend.written[-1] == MotorCommand("joint1", None, None, 0.0)
    send(core, 0.05, JointSample("limb1_joint1", None, None, -4.0))
    assert backend.written[-1] == MotorCommand("joint1", None, None, -4.0)
    # Position and velocity modes are left alone.
    send(core, 0.06, JointSample("limb1_joint1", 1.0))
    core.tick(0.07)
    assert backend.written[-1] == MotorCommand("joint1", 1.0)
    assert core.counters["speed_cuts"] == 2


def test_a_motor_without_limits_is_reported() -> None:
    core = MotorInterfaceCore("m", SLOT, RecordingBackend(), limits={"joint1": LIMITS["joint1"]})
    core.start(0.0)
    status = own_status(core, 0.0)
    assert status.level == 1 and "no raw limits for joint2" in status.message


# ------------------------------------------------------------------ one set of numbers


@pytest.fixture(scope="module")
def resolved(tmp_path_factory: pytest.TempPathFactory) -> Any:
    def get(template: str, unit: str | None = None) -> ResolvedAssembly:
        units = {SLOT: unit} if unit else None
        return resolved_assembly(tmp_path_factory.mktemp(template), template, units)

    return get


def plan_of(assembly: ResolvedAssembly, kind: str, slot: str = SLOT) -> ComponentPlan:
    return next(p for p in assembly.components if p.kind == kind and p.module == slot)


@pytest.mark.parametrize("unit", ["hlv1-limb-01", "gl-limb-01"])
def test_motor_interface_and_joint_manager_use_the_same_raw_limits(resolved, unit: str) -> None:
    assembly = resolved("minimal", unit)
    manager = build_component(plan_of(assembly, "joint_manager"), assembly).core
    # Built, not started: the bus is never opened, only the limits are compared.
    motors = build_component(plan_of(assembly, "motor_interface"), assembly).core
    assert isinstance(manager, JointManagerCore) and isinstance(motors, MotorInterfaceCore)
    assert motors.unlimited == []
    for joint in assembly.module(SLOT).actuated_joints:
        expected = RawLimits.of_joint(joint.spec, joint.calibration)
        assert manager.raw_limits(joint.name) == expected
        assert motors.raw_limits(joint.raw_name) == expected


# ------------------------------------------------------------------ finding 1 on emulated drives


@pytest.fixture
def cia402(resolved) -> Iterator[tuple[MotorInterfaceCore, Any, ResolvedAssembly]]:
    """The H-line limb's motor interface, as built for ``minimal``, on emulated drives."""
    from components.motors.emulation.cia402 import EmulatedCia402Bus

    assembly = resolved("minimal", "hlv1-limb-01")
    module = assembly.module(SLOT)
    channel = f"last-{uuid.uuid4().hex[:12]}"
    counts = {
        j.motor_id: int(j.motor_params.get("counts_per_rev", 4096)) for j in module.actuated_joints
    }
    bus = EmulatedCia402Bus(channel, counts, counts_per_rev=counts).start()
    options = {"channel": channel, "bus_options": {"interface": "virtual"}}
    built = build_component(plan_of(assembly, "motor_interface"), assembly, options)
    core = built.core
    try:
        core.start(0.0)
        assert core.is_open, core.open_error
        yield core, bus, assembly
    finally:
        for resource in built.resources:
            resource.close()
        bus.stop()


def test_cia402_goal_past_the_raw_limit_after_halt_never_reaches_the_drive(cia402) -> None:
    """Finding 1: a goal of 6.0 rad on a ±2.0 rad joint, sent after a halt, was executed."""
    core, bus, assembly = cia402
    joint2, joint1 = assembly.module(SLOT).joint("joint2"), assembly.module(SLOT).joint("joint1")

    def goal(plan: Any) -> float:
        params = plan.motor_params
        per_rad = params["counts_per_rev"] * params["gear_ratio"] / (2 * math.pi)
        return bus.drive(plan.motor_id).read_object(0x607A) / per_rad

    before = goal(joint2)
    assert core.on_halt(TRIGGER_REQ, 1.0).success
    send(core, 1.1, JointSample("limb1_joint2", 6.0))
    assert core.counters["refused_halted"] == 1
    assert core.on_recover(TRIGGER_REQ, 2.0).success
    send(core, 2.1, JointSample("limb1_joint2", 6.0))  # not halted: the raw limits refuse it
    assert core.counters["refused_position"] == 1
    # A legal goal on joint1 after it: once the drive has that one, joint2's would be there.
    sentinel = joint1.calibration.to_raw(0.3)

    def sentinel_arrived() -> bool:
        # Sent again at each poll, with the executor's tick between, as the backend tests do:
        # a drive that missed a heartbeat on a loaded machine drops commands until it is
        # picked up again.
        send(core, 2.2, JointSample("limb1_joint1", sentinel))
        core.tick(2.2)
        return abs(goal(joint1) - sentinel) < 1e-3

    wait_until(sentinel_arrived, 30.0, "joint1's goal on the drive", interval=0.1)
    print(f"\nCiA 402: joint2 goal {goal(joint2):.4f} rad after 6.0 was sent (before {before:.4f})")
    assert goal(joint2) == pytest.approx(before, abs=1e-3)
    limits = core.raw_limits("joint2")
    assert limits.lower < goal(joint2) < limits.upper


def test_dynamixel_goal_past_the_raw_limit_never_reaches_the_servo(resolved) -> None:
    """Finding 1: 3.14 rad on a ±1.9 rad Dynamixel joint was executed."""
    from components.motors.emulation.dynamixel import EmulatedDynamixelChain

    assembly = resolved("minimal", "gl-limb-01")
    module = assembly.module(SLOT)
    joints = module.actuated_joints
    chain = EmulatedDynamixelChain(
        ids=[j.motor_id for j in joints], models={j.motor_id: j.motor_model for j in joints}
    )
    options = {"channel": chain.port, "bus_options": {"latency_timer_ms": 40.0}}
    try:
        built = build_component(plan_of(assembly, "motor_interface"), assembly, options)
        core = built.core
        try:
            core.start(0.0)
            assert core.is_open, core.open_error
            joint2, joint1 = module.joint("joint2"), module.joint("joint1")
            assert (joint2.lower, joint2.upper) == (-1.9, 1.9)

            def goal(plan: Any) -> float:
                ticks = chain.register(plan.motor_id, "goal_position")
                return (ticks - 2048) * 2 * math.pi / 4096

            before = goal(joint2)
            send(core, 0.1, JointSample("limb1_joint2", 3.14))
            sentinel = joint1.calibration.to_raw(0.4)

            def sentinel_arrived() -> bool:
                send(core, 0.2, JointSample("limb1_joint1", sentinel))
                core.tick(0.2)
                return abs(goal(joint1) - sentinel) < 4e-3

            wait_until(sentinel_arrived, 30.0, "joint1's goal on the servo", interval=0.1)
            print(f"\nDynamixel: joint2 goal {goal(joint2):.4f} rad after 3.14 was sent")
            assert goal(joint2) == pytest.approx(before, abs=4e-3)
            assert core.counters["refused_position"] == 1
        finally:
            for resource in built.resources:
                resource.close()
    finally:
        chain.close()


# ------------------------------------------------------------------ the joint manager's part


def manager(**config: float) -> JointManagerCore:
    joints = [
        JointSpec("limb1_joint1", lower=-2.0, upper=2.0, max_velocity=3.0, max_effort=10.0),
        JointSpec("limb1_wheel", "continuous", -math.inf, math.inf, 6.0, 2.0),
    ]
    return JointManagerCore(
        "limb1/joint_manager", SLOT, joints, config=JointManagerConfig(**config)
    )


def commands(core: JointManagerCore) -> list[JointSample]:
    return [s for m in core.outbox.take("joint_commands") for s in joint_samples(m)]


def calibrated(core: JointManagerCore, sample: JointSample) -> float:
    assert sample.position is not None
    return core.calibration(sample.name).to_calibrated(sample.position)


def test_joint_manager_refuses_a_flood_whole_and_counts_it() -> None:
    core = manager()
    core.on_joint_states(joint_state([JointSample("limb1_joint1", 0.0, 0.0, 0.0)]), 0.0)
    names = [f"limb1_joint{i}" for i in range(100_000)]
    flood = msg(JOINT_STATE, name=names, position=np.zeros(len(names)))
    core.on_joint_set(flood, 0.1)
    core.on_joint_states(flood, 0.1)
    assert commands(core) == []
    counters = core.counters
    assert counters["refused_oversize"] == 1 and counters["feedback_oversize"] == 1
    assert counters["refused_unknown"] == 0 and counters["feedback_rejected"] == 0
    # The feedback kept from before the flood is intact, and commands still work.
    core.on_joint_set(joint_state([JointSample("limb1_joint1", 0.5)]), 0.2)
    (sent,) = commands(core)
    assert calibrated(core, sent) == pytest.approx(0.5)
    ragged = msg(JOINT_STATE, name=["limb1_joint1", "limb1_wheel"], position=np.array([0.1]))
    core.on_joint_set(ragged, 0.3)
    assert commands(core) == [] and core.counters["refused_malformed"] == 1


def test_joint_manager_sends_one_command_per_joint_for_duplicates() -> None:
    """Finding 10 at the main gate: duplicates collapse to the last value."""
    core = manager()
    core.on_joint_set(joint_state(JointSample("limb1_joint1", 0.001 * i) for i in range(1000)), 0)
    assert commands(core) == []  # 1000 names for a 2-joint module: refused whole
    core.on_joint_set(
        joint_state([JointSample("limb1_joint1", 0.1), JointSample("limb1_joint1", 0.3)]), 0.1
    )
    (sent,) = commands(core)
    assert calibrated(core, sent) == pytest.approx(0.3)
    assert core.counters["duplicates"] == 1


def speeds(core: JointManagerCore, now: float, **velocities: float) -> None:
    """Feedback: each named joint at position 0 turning at the given speed."""
    samples = [JointSample(f"limb1_{k}", 0.0, v, 0.0) for k, v in velocities.items()]
    core.on_joint_states(joint_state(samples), now)


def test_joint_manager_cuts_effort_above_max_velocity() -> None:
    """Finding 8: in effort mode a joint reached 3.7 rad/s (limit 3.0), a wheel 11 (limit 6)."""
    core = manager()
    speeds(core, 0.0, joint1=0.0, wheel=0.0)
    core.on_joint_set(joint_state([JointSample("limb1_joint1", None, None, 8.0)]), 0.01)
    core.on_joint_set(joint_state([JointSample("limb1_wheel", None, None, 2.0)]), 0.01)
    assert [s.effort for s in commands(core)] == [8.0, 2.0]
    # Still within the limits of speed: nothing to cut.
    speeds(core, 0.02, joint1=2.9)
    assert commands(core) == []
    speeds(core, 0.03, joint1=3.7, wheel=11.0)
    cut = {s.name: s for s in commands(core)}
    assert cut["limb1_joint1"] == JointSample("limb1_joint1", None, None, 0.0)
    assert cut["limb1_wheel"] == JointSample("limb1_wheel", None, None, 0.0)
    assert core.counters["speed_cuts"] == 2
    speeds(core, 0.04, wheel=11.0)
    assert commands(core) == []  # cut once
    # A new effort along the motion while too fast is cut at once; a braking one passes.
    core.on_joint_set(joint_state([JointSample("limb1_wheel", None, None, 1.0)]), 0.05)
    core.on_joint_set(joint_state([JointSample("limb1_wheel", None, None, -1.0)]), 0.06)
    assert [s.effort for s in commands(core)] == [0.0, -1.0]


def test_the_gripper_reaches_both_ends_with_a_margin_relative_to_its_range(resolved) -> None:
    """Finding 9: a fixed 0.02 m margin on the 0.04 m finger left only the midpoint."""
    assembly = resolved("minimal", "hlv1-limb-01")
    core = build_component(plan_of(assembly, "joint_manager"), assembly).core
    assert isinstance(core, JointManagerCore)
    finger = assembly.module(SLOT).joint("finger_left")
    lower, upper = finger.lower, finger.upper
    assert (lower, upper) == (0.0, 0.04)
    tolerance = 0.05 * (upper - lower)  # the margin: at most 5 % of the range, 2 mm here
    reached = []
    for goal in (lower, upper):
        core.on_joint_set(joint_state([JointSample(finger.name, goal)]), 0.0)
        (sent,) = commands(core)
        reached.append(calibrated(core, sent))
    print(f"\ngripper: commands 0.0 and 0.04 m reach {reached[0]:.4f} and {reached[1]:.4f} m")
    assert reached[0] == pytest.approx(lower, abs=tolerance + 1e-12)
    assert reached[1] == pytest.approx(upper, abs=tolerance + 1e-12)
    assert reached[1] - reached[0] >= 0.85 * (upper - lower)  # 0.036 of 0.04 m
    # A long joint keeps the absolute margin.
    assert core.command_range("joint2") == pytest.approx((-1.98, 1.98))


# ------------------------------------------------------------------ the simulator (real MuJoCo)


def simulator(assembly: ResolvedAssembly) -> Any:
    from components.simulator.core import SimulatorConfig, SimulatorCore
    from components.simulator.world import SimWorld

    core = SimulatorCore(
        "sim", SimWorld.from_assembly(assembly), SimulatorConfig(command_timeout=60)
    )
    core.start(0.0)
    return core


def run(core: Any, now: float, seconds: float) -> float:
    for _ in range(round(seconds / 0.002)):
        now += 0.002
        core.tick(now)
    return now


@pytest.mark.e2e
@pytest.mark.parametrize("template", ["minimal", "dragon"])
def test_simulator_and_joint_manager_use_the_same_raw_limits(resolved, template: str) -> None:
    assembly = resolved(template)
    core = simulator(assembly)
    for module in assembly.modules:
        if not module.actuated_joints:
            continue
        manager = build_component(plan_of(assembly, "joint_manager", module.slot), assembly).core
        for joint in module.actuated_joints:
            theirs, ours = manager.raw_limits(joint.name), core.raw_limits(joint.name)
            # The model stores limits to 6 digits: the same numbers within that.
            for field in ("lower", "upper", "max_velocity", "max_effort"):
                assert getattr(ours, field) == pytest.approx(getattr(theirs, field), rel=1e-5)


@pytest.mark.e2e
def test_simulation_refuses_a_command_past_the_joint_manager_clamp(resolved) -> None:
    """Finding 1 in simulation: a raw command went past the joint manager's clamp."""
    assembly = resolved("minimal")
    core = simulator(assembly)
    manager = build_component(plan_of(assembly, "joint_manager"), assembly).core
    name = "limb1_joint2"
    cal = assembly.joint(name).calibration
    clamp = manager.command_range(name)
    for calibrated_goal in (6.0, -6.0):
        core.on_module_commands(
            SLOT, joint_state([JointSample(name, cal.to_raw(calibrated_goal))]), 0.0
        )
    now = run(core, 0.0, 1.5)
    reached = core.world.position(name)
    print(f"\nsim: {name} at {reached:.4f} rad after goals of ±6.0 (clamp {clamp[1]:.2f})")
    assert core.counters["refused_position"] == 2
    assert clamp[0] < reached < clamp[1]
    assert abs(reached) < 0.05  # it stayed where it was
    # NaN, another module's joint (none in this assembly: unknown), an unknown name.
    core.on_module_commands(SLOT, joint_state([JointSample(name, math.nan)]), now)
    core.on_module_commands(SLOT, joint_state([JointSample("limb2_joint2", 0.5)]), now)
    core.on_joint_commands(joint_state([JointSample("limb1_nothing", 0.5)]), now)
    counters = core.counters
    assert counters["refused_nan"] == 1
    assert counters["refused_unknown"] == 2
    # A legal goal still moves it.
    core.on_module_commands(SLOT, joint_state([JointSample(name, cal.to_raw(0.5))]), now)
    run(core, now, 1.5)
    assert core.world.position(name) == pytest.approx(0.5, abs=0.03)
    status = core.diagnostics(now).status[0]
    assert diagnostic_values(status)["refused_position"] == "2"


@pytest.mark.e2e
def test_simulated_halt_latches_per_module_until_recover(resolved) -> None:
    assembly = resolved("dragon")
    core = simulator(assembly)
    now = run(core, 0.0, 0.3)
    targets = {"limb1_joint2": 0.3, "limb2_joint2": 0.3}

    def goal(*names: str) -> Any:
        samples = [JointSample(n, assembly.joint(n).calibration.to_raw(targets[n])) for n in names]
        return joint_state(samples)

    assert core.on_halt_limb1(TRIGGER_REQ, now).success
    held = core.world.position("limb1_joint2")
    core.on_joint_commands(goal("limb1_joint2", "limb2_joint2"), now)
    core.on_joint_commands_limb1(goal("limb1_joint2"), now)
    assert core.counters["refused_halted"] == 2
    now = run(core, now, 1.0)
    # Held where it was (a position servo under the limb's weight sags a few hundredths).
    assert core.world.position("limb1_joint2") == pytest.approx(held, abs=0.05)
    assert core.world.position("limb2_joint2") == pytest.approx(0.3, abs=0.05)  # not halted
    assert core.halted("limb1") and not core.halted("limb2")
    assert core.on_recover_limb1(TRIGGER_REQ, now).success
    core.on_joint_commands_limb1(goal("limb1_joint2"), now)
    run(core, now, 1.0)
    assert core.world.position("limb1_joint2") == pytest.approx(0.3, abs=0.05)


@pytest.mark.e2e
def test_simulator_refuses_floods_and_collapses_duplicates(resolved) -> None:
    assembly = resolved("minimal")
    core = simulator(assembly)
    names = [f"limb1_joint{i}" for i in range(100_000)]
    core.on_module_commands(SLOT, msg(JOINT_STATE, name=names, position=np.ones(len(names))), 0.0)
    dups = joint_state(JointSample("limb1_joint2", 0.001 * i) for i in range(1000))
    core.on_module_commands(SLOT, dups, 0.0)
    assert core.counters["refused_oversize"] == 2
    assert core.counters["refused_unknown"] == 0
    cal = assembly.joint("limb1_joint2").calibration
    twice = [
        JointSample("limb1_joint2", cal.to_raw(0.6)),
        JointSample("limb1_joint2", cal.to_raw(0.2)),
    ]
    core.on_module_commands(SLOT, joint_state(twice), 0.0)
    assert core.counters["duplicates"] == 1
    run(core, 0.0, 1.0)
    assert core.world.position("limb1_joint2") == pytest.approx(0.2, abs=0.03)


@pytest.mark.e2e
@pytest.mark.parametrize(
    ("template", "name"), [("dragon", "wheel1_wheel_left"), ("minimal", "limb1_joint5")]
)
def test_simulated_effort_mode_is_speed_bound(resolved, template: str, name: str) -> None:
    """Finding 8 in simulation: full effort spun a wheel to 180 rad/s (limit 6), a limb joint
    to 39 rad/s (limit 3), with nothing to stop it."""
    assembly = resolved(template)
    core = simulator(assembly)
    now = run(core, 0.0, 0.5)
    spec, cal = assembly.joint(name).spec, assembly.joint(name).calibration
    core.on_joint_commands(
        joint_state([JointSample(name, None, None, cal.rate_to_raw(spec.max_effort))]), now
    )
    peak = 0.0
    for _ in range(1000):
        now += 0.002
        core.tick(now)
        peak = max(peak, abs(core.world.velocity(name)))
    print(f"\nsim effort mode: {name} peaked at {peak:.2f} rad/s (max {spec.max_velocity:g})")
    assert core.counters["speed_cuts"] >= 1
    assert peak <= 1.2 * spec.max_velocity  # one physics step of full effort past the bound
