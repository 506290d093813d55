"""The simulator core and world with fake time: real MuJoCo, the shipped assemblies, no Zenoh.

Commands go in as a joint manager sends them (raw ``sensor_msgs/JointState``) and states come
out of the core's outbox, so these tests see exactly what the data plane would carry.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from conftest import resolved_assembly

from components.assembly import (
    ComponentPlan,
    ResolvedAssembly,
)
from components.build import BuildError, build_component
from components.messages import (
    JointSample,
    diagnostic_values,
    joint_samples,
    joint_state,
)
from components.simulator.core import SimulatorConfig, SimulatorCore
from components.simulator.interface import simulator_interface
from components.simulator.world import SimulationError, SimWorld, max_real_time_factor

pytestmark = pytest.mark.e2e


@pytest.fixture(scope="module")
def assembly(tmp_path_factory: pytest.TempPathFactory):
    """Resolve a shipped template once per module (default units): name -> assembly."""

    def get(name: str) -> ResolvedAssembly:
        return resolved_assembly(tmp_path_factory.mktemp(name), name)

    return get


def make(assembly: ResolvedAssembly, **config: float) -> SimulatorCore:
    core = SimulatorCore("sim", SimWorld.from_assembly(assembly), SimulatorConfig(**config))
    core.start(0.0)
    return core


def run(core: SimulatorCore, start: float, seconds: float, period: float = 0.002) -> float:
    """Tick the core every ``period`` of fake wall time for ``seconds``; returns the new now."""
    now = start
    for _ in range(round(seconds / period)):
        now += period
        core.tick(now)
    return now


def mean_velocity(
    core: SimulatorCore, now: float, name: str, seconds: float, period: float = 0.002
) -> tuple[float, float]:
    """Tick for ``seconds``; the new now and ``name``'s mean velocity over them."""
    total, steps = 0.0, round(seconds / period)
    for _ in range(steps):
        now += period
        core.tick(now)
        total += core.world.velocity(name)
    return now, total / steps


def command(core: SimulatorCore, now: float, *samples: JointSample) -> None:
    core.on_joint_commands(joint_state(samples), now)


def latest_state(core: SimulatorCore, slot: str) -> dict[str, JointSample]:
    message = core.outbox.on(f"/{slot}/joint_states")[-1]
    return {s.name: s for s in joint_samples(message)}


def test_position_command_moves_the_joint_and_raw_space_round_trips(assembly) -> None:
    a = assembly("minimal")
    core = make(a)
    joint = a.joint("limb1_joint3")
    cal = joint.calibration
    assert cal.zero_offset != 0.0  # the round trip below would prove nothing otherwise
    target = 0.8
    command(core, 0.0, JointSample("limb1_joint3", cal.to_raw(target), None, None))
    now = run(core, 0.0, 0.2)
    midway = core.world.position("limb1_joint3")
    assert 0.05 < midway < target  # moving, at the drive's speed, not teleported
    assert midway <= joint.spec.max_velocity * 0.2 + 0.02
    run(core, now, 1.3)
    assert core.world.position("limb1_joint3") == pytest.approx(target, abs=0.01)
    # joint_states carry raw space: the unit's calibration applied inversely.
    raw = latest_state(core, "limb1")["limb1_joint3"]
    assert cal.to_calibrated(raw.position) == pytest.approx(
        core.world.position("limb1_joint3"), abs=1e-9
    )
    assert raw.velocity is not None and raw.effort is not None


def test_velocity_mode_tracks_the_speed_and_switching_back_holds(assembly) -> None:
    a = assembly("minimal")
    core = make(a)
    cal = a.joint("limb1_joint5").calibration
    command(core, 0.0, JointSample("limb1_joint5", None, cal.rate_to_raw(0.6), None))
    now = run(core, 0.0, 0.5)
    assert core.world.mode_of("limb1_joint5") == "velocity"
    assert core.world.velocity("limb1_joint5") == pytest.approx(0.6, abs=0.03)
    reported = latest_state(core, "limb1")["limb1_joint5"]
    assert cal.rate_to_calibrated(reported.velocity) == pytest.approx(0.6, abs=0.03)
    # A hold as the joint manager sends it: position where it is, velocity 0. Position wins.
    here = core.world.position("limb1_joint5")
    command(core, now, JointSample("limb1_joint5", cal.to_raw(here), 0.0, None))
    run(core, now, 0.5)
    assert core.world.mode_of("limb1_joint5") == "position"
    assert abs(core.world.velocity("limb1_joint5")) < 0.01
    assert core.world.position("limb1_joint5") == pytest.approx(here, abs=0.05)


def test_a_velocity_left_without_commands_is_stopped_like_a_real_motor_interface(
    assembly,
) -> None:
    a = assembly("minimal")
    core = make(a, command_timeout=0.3)
    cal = a.joint("limb1_joint5").calibration
    command(core, 0.0, JointSample("limb1_joint5", None, cal.rate_to_raw(0.6), None))
    now = run(core, 0.0, 0.25)
    assert core.world.velocity("limb1_joint5") == pytest.approx(0.6, abs=0.05)
    run(core, now, 0.4)  # commands stopped (a dead joint manager): past the timeout
    assert abs(core.world.velocity("limb1_joint5")) < 0.05
    assert core.watchdog_stops == 1


def test_a_module_topic_takes_only_that_module_s_joints(assembly) -> None:
    a = assembly("dragon")
    core = make(a)
    before = core.world.position("wheel1_wheel_left")
    cal = a.joint("wheel1_wheel_left").calibration
    # A wheel's joint named on limb1's topic: refused, as limb1's motor interface would.
    core.on_joint_commands_limb1(
        joint_state([JointSample("wheel1_wheel_left", None, cal.rate_to_raw(3.0), None)]), 0.0
    )
    run(core, 0.0, 0.3)
    assert core.refused_other_module == 1
    # Only the robot settling on the ground moves it; nowhere near the 3 rad/s asked.
    assert abs(core.world.velocity("wheel1_wheel_left")) < 0.3
    assert core.world.position("wheel1_wheel_left") == pytest.approx(before, abs=0.1)


def test_wheel_velocity_on_the_ground_and_effort_mode(assembly) -> None:
    a = assembly("dragon")
    # One command, then seconds of driving: no command watchdog in the way here.
    core = make(a, command_timeout=60.0)
    now = run(core, 0.0, 0.5)  # land
    cal = a.joint("wheel1_wheel_left").calibration
    command(core, now, JointSample("wheel1_wheel_left", None, cal.rate_to_raw(3.0), None))
    now = run(core, now, 0.5)
    # One wheel driving a Dragon scrubs and hops (2.2-2.9 rad/s from one step to the next,
    # any change of the model moves the pattern): its mean speed is what tracks the command.
    now, speed = mean_velocity(core, now, "wheel1_wheel_left", 0.5)
    assert speed == pytest.approx(3.0, abs=0.5)
    # More than the joint's limit is refused (the last stage's raw limits): it keeps its speed.
    command(core, now, JointSample("wheel1_wheel_left", None, cal.rate_to_raw(100.0), None))
    assert core.counters["refused_velocity"] == 1
    now = run(core, now, 0.5)
    now, speed = mean_velocity(core, now, "wheel1_wheel_left", 0.5)
    assert speed == pytest.approx(3.0, abs=0.5)
    command(core, now, JointSample("limb1_joint7", None, None, 0.0))
    assert core.world.mode_of("limb1_joint7") == "effort"


def test_limits_are_enforced_by_the_model(assembly) -> None:
    a = assembly("minimal")
    core = make(a, command_timeout=60.0)  # one velocity command, held into the stop
    spec = a.joint("limb1_joint3").spec
    cal = a.joint("limb1_joint3").calibration
    # A raw velocity command drives straight into the upper limit (no joint manager here).
    command(core, 0.0, JointSample("limb1_joint3", None, cal.rate_to_raw(2.0), None))
    highest = -math.inf
    now = 0.0
    for _ in range(1500):
        now += 0.002
        core.tick(now)
        highest = max(highest, core.world.position("limb1_joint3"))
    # Soft constraint: a brief overshoot at full speed into the stop, then pushed back.
    assert highest <= spec.upper + 0.03
    assert core.world.position("limb1_joint3") == pytest.approx(spec.upper, abs=0.02)
    # An out-of-range position target is refused at the last stage (raw limits) and the
    # joint stays where it is; a target at the limit itself is reached.
    command(core, now, JointSample("limb1_joint3", cal.to_raw(-10.0), None, None))
    assert core.counters["refused_position"] == 1
    now = run(core, now, 0.5)
    assert core.world.position("limb1_joint3") == pytest.approx(spec.upper, abs=0.02)
    command(core, now, JointSample("limb1_joint3", cal.to_raw(spec.lower), None, None))
    run(core, now, 4.0)
    assert core.world.position("limb1_joint3") == pytest.approx(spec.lower, abs=0.02)
    assert core.world.finite()


def test_dragon_rests_on_the_ground_for_two_seconds(assembly) -> None:
    a = assembly("dragon")
    core = make(a)
    run(core, 0.0, 2.0)
    world = core.world
    assert world.time == pytest.approx(2.0, abs=1e-6)
    assert world.finite() and world.resets == 0
    position, quat = world.root_pose(a.root_links[0])
    assert 0.0 < position[2] < 0.5  # on the ground, not fallen through nor flying
    assert np.linalg.norm(quat) == pytest.approx(1.0)
    base_speed = np.linalg.norm(world.data.qvel[:3])
    assert base_speed < 0.05  # resting
    pose = core.outbox.on("/sim/base_pose")[-1]
    assert pose.header.frame_id == "world"
    assert pose.pose.position.z == pytest.approx(position[2])


def test_states_at_100_hz_and_more_and_real_time_factor_reported(assembly) -> None:
    a = assembly("dragon")
    core = make(a)
    run(core, 0.0, 2.0)
    for slot in ("limb1", "limb2", "wheel1", "wheel2"):
        assert len(core.outbox.on(f"/{slot}/joint_states")) >= 2.0 * 100
    diagnostics = core.outbox.on("/sim/diagnostics")[-1].status[0]
    values = diagnostic_values(diagnostics)
    assert float(values["real_time_factor"]) == pytest.approx(1.0, abs=0.01)
    assert float(values["step_rate_hz"]) >= 500
    assert float(values["state_rate_hz"]) >= 100
    assert float(values["sim_time"]) == pytest.approx(2.0, abs=0.01)
    assert diagnostics.level == 0
    # Each module also gets motor diagnostics on its own topic, as from a motor interface.
    module = core.outbox.on("/limb1/diagnostics")[-1]
    assert {s.name for s in module.status} >= {"limb1/bus", "limb1_joint1"}


def test_clock_carries_the_simulated_time_even_when_it_falls_behind(assembly) -> None:
    """``/clock`` (rosgraph_msgs/Clock) says the world's own time, every pose period: what
    a test times the world by when the machine is too busy for real time."""
    from components.messages import from_time

    core = make(assembly("minimal"))
    now = run(core, 0.0, 1.0)
    clocks = [from_time(m.clock) for m in core.outbox.on("/clock")]
    assert len(clocks) >= 90 and clocks == sorted(clocks)
    assert clocks[-1] == pytest.approx(core.world.time, abs=0.011)
    now += 5.0  # a 5 s stall: the world catches up only max_catch_up of it
    core.tick(now)
    run(core, now, 0.05)
    assert from_time(core.outbox.on("/clock")[-1].clock) == pytest.approx(
        core.world.time, abs=0.011
    )
    assert core.world.time < 1.0 + 0.1 + 0.05 + 0.01


def test_speed_factor_and_capped_catch_up(assembly) -> None:
    a = assembly("minimal")
    core = make(a, speed=4.0)
    now = run(core, 0.0, 1.0)
    assert core.world.time == pytest.approx(4.0, abs=0.01)
    # A 5 s stall is caught up for max_catch_up of wall time only, a few steps per tick.
    before = core.world.time
    now += 5.0
    core.tick(now)
    assert core.world.time - before == pytest.approx(4 * 0.002 * 4.0, abs=1e-6)
    now = run(core, now, 0.1)
    assert core.world.time - before == pytest.approx((0.1 + 0.1) * 4.0, abs=0.01)
    assert core.dropped == pytest.approx(4.9 * 4.0, abs=0.01)
    core.tick(now + 0.9)  # closes the diagnostics window: it fell behind
    status = core.outbox.on("/sim/diagnostics")[-1].status[0]
    assert status.level == 1 and "falling behind" in status.message


def test_a_command_is_seen_one_step_later_not_one_period_later(assembly) -> None:
    a = assembly("minimal")
    core = make(a, state_period=0.05)
    now = run(core, 0.0, 0.1)
    count = len(core.outbox.on("/limb1/joint_states"))
    cal = a.joint("limb1_joint3").calibration
    command(core, now, JointSample("limb1_joint3", None, cal.rate_to_raw(1.0), None))
    states = core.outbox.on("/limb1/joint_states")
    assert len(states) == count + 1  # at once, not at the next 50 ms period
    moved = {s.name: s for s in joint_samples(states[-1])}["limb1_joint3"]
    assert abs(moved.velocity) > 0.01
    # The simulated clock leads by one step at most, however many commands arrive.
    for _ in range(20):
        command(core, now, JointSample("limb1_joint3", None, cal.rate_to_raw(1.0), None))
    assert core.world.time == pytest.approx(now + 0.002, abs=1e-9)
    now = run(core, now, 1.0)
    assert core.world.time == pytest.approx(now, abs=0.0021)


def test_unknown_and_nan_commands_counted_and_skipped(assembly) -> None:
    a = assembly("minimal")
    core = make(a)
    command(core, 0.0, JointSample("limb9_joint1", 1.0, None, None))
    command(core, 0.0, JointSample("limb1_joint3", math.nan, None, None))
    assert core.refused_unknown == 1 and core.refused_nan == 1
    run(core, 0.0, 0.2)
    assert core.world.finite()


def test_halt_service_holds_the_module(assembly) -> None:
    a = assembly("minimal")
    core = make(a)
    cal = a.joint("limb1_joint3").calibration
    command(core, 0.0, JointSample("limb1_joint3", None, cal.rate_to_raw(1.0), None))
    now = run(core, 0.0, 0.3)
    response = core.on_halt_limb1(None, now)
    assert response.success
    here = core.world.position("limb1_joint3")
    run(core, now, 0.5)
    assert core.world.position("limb1_joint3") == pytest.approx(here, abs=0.02)
    assert core.on_recover_limb1(None, now).success


def test_interface_matches_the_core_and_the_motor_interface(assembly) -> None:
    from components.motor_interface.interface import MOTOR_INTERFACE

    a = assembly("dragon")
    built = build_component(
        ComponentPlan("sim", "simulator", "localhost", None, "/sim"), a, {"speed": 2.0}
    )
    try:
        core, spec = built.core, built.spec
        assert isinstance(core, SimulatorCore) and core.config.speed == 2.0
        assert built.namespace == "/sim"
        for handler in [s.handler for s in spec.subscribe] + [s.handler for s in spec.serve]:
            assert callable(getattr(core, handler))
        assert all(callable(getattr(core, e.handler)) for e in spec.every)
        topics = {p.topic: p for p in spec.publish}
        for module in a.modules:
            for theirs in MOTOR_INTERFACE.publish:
                ours = topics[f"{module.namespace}/{theirs.topic}"]
                assert (ours.msg_type, ours.qos) == (theirs.msg_type, theirs.qos)
            subscribed = {s.topic for s in spec.subscribe}
            assert f"{module.namespace}/joint_commands" in subscribed
            served = {s.service for s in spec.serve}
            assert {
                f"{module.namespace}/motors/halt",
                f"{module.namespace}/motors/recover",
            } <= served
        assert "/sim/base_pose" in topics and "/sim/diagnostics" in topics
        # Everything the core publishes is declared.
        run(core, 0.0, 1.1)
        assert {t for t, _ in core.outbox.sent} <= set(topics)
        assert simulator_interface(a, core.config) == spec
    finally:
        built.close()


def test_build_refuses_a_module_plan_and_bad_options(assembly) -> None:
    a = assembly("minimal")
    with pytest.raises(BuildError, match="whole assembly"):
        build_component(ComponentPlan("sim", "simulator", "h", "limb1", "/limb1"), a, {})
    with pytest.raises(BuildError, match="speed"):
        build_component(ComponentPlan("sim", "simulator", "h", None, "/sim"), a, {"speed": 0})


def test_a_model_missing_a_joint_is_named(assembly, tmp_path: Path) -> None:
    a = assembly("minimal")
    text = Path(a.mjcf_path).read_text().replace('name="limb1_joint3"', 'name="renamed"')
    broken = tmp_path / "broken.xml"
    broken.write_text(text)
    with pytest.raises(SimulationError, match="limb1_joint3"):
        SimWorld.from_assembly(a, broken)


def test_max_real_time_factor_is_well_above_real_time(assembly) -> None:
    assert max_real_time_factor(assembly("dragon"), seconds=0.5, settle=0.1) > 2.0


@pytest.mark.parametrize("name", ["minimal", "dragon", "dragon_x4", "tricycle", "two_dragons"])
def test_every_template_simulates_and_each_robot_has_a_pose(assembly, name: str) -> None:
    a = assembly(name)
    core = make(a)
    run(core, 0.0, 0.5)
    assert core.world.finite() and core.world.resets == 0
    assert sorted(core.world.modules) == sorted(m.slot for m in a.modules if m.actuated_joints)
    topics = {p.topic for p in simulator_interface(a).publish}
    assert "/sim/base_pose" in topics
    if len(a.root_links) > 1:
        for root in a.root_links:
            assert f"/sim/{root}/pose" in topics
            assert core.outbox.on(f"/sim/{root}/pose")
    for root in a.root_links:
        assert core.world.root_pose(root)[0][2] > 0.0  # above the ground


def test_a_simulated_module_publishes_at_the_real_motor_interfaces_rate() -> None:
    from components.motor_interface.interface import MOTOR_INTERFACE

    # A drop-in: the joint manager, the recorder and every other subscriber see a simulated
    # module's joint_states as often as a real one's, 100 Hz.
    (tick,) = MOTOR_INTERFACE.every
    assert SimulatorConfig().state_period == tick.period == 0.01
