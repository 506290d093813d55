"""The autonomous_operator kind without a robot: scripts and their checks at ``msctl
assemble``, the station data's format, the plan (one process each), the operator's status,
the steering's Twist gate and ramp, the guardian's tilt and limits. The operators on a
simulated Dragon are ``test_operators_e2e``."""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from test_assemble_errors import edit, world  # noqa: F401  (world is a fixture)

from components import kinds
from components.assembly import ResolvedAssembly, from_document
from components.autonomous_operator.core import (
    FAILED,
    RUNNING,
    AutonomousOperatorCore,
    OperatorConfig,
)
from components.autonomous_operator.drive import (
    STILL,
    Ramp,
    TwistGate,
    aligned,
    crab_direction,
)
from components.autonomous_operator.operators.guardian import limits_for, tilt_of
from components.autonomous_operator.script import (
    REQUIRED,
    check_arguments,
    locate,
    read_main,
    shipped,
    validate,
)
from components.build import BuildError, build_component
from components.executor.core import RecordingOutbox
from components.human_operator.core import twist
from components.messages import ERROR, OK, WARN, diagnostic_values
from components.safety import SafetyLimits, robot_limits
from msctl.assembler import resolve
from msctl.errors import InputError
from msctl.launcher.plan import plan_host


@pytest.fixture(scope="module")
def two_dragons() -> ResolvedAssembly:
    return from_document(resolve("two_dragons").document)


# ---------------------------------------------------------------------------- scripts
def test_three_operators_ship_and_each_main_reads_without_running_it() -> None:
    assert {"steering", "posture", "guardian"} <= set(shipped())
    for name in ("steering", "posture", "guardian"):
        signature = read_main(locate(name))
        assert signature.is_async and REQUIRED not in signature.params.values(), name
    assert read_main(locate("steering")).params["max_speed"] == 0.5


def test_a_script_is_a_shipped_name_or_an_absolute_path(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="no shipped operator 'steer'; shipped: guardian"):
        locate("steer")
    with pytest.raises(ValueError, match="nor an absolute path"):
        locate("scripts/mine.py")
    with pytest.raises(ValueError, match="no Python file there"):
        locate(str(tmp_path / "absent.py"))
    script = tmp_path / "mine.py"
    script.write_text("def main(robot, target, speed=0.3, *, label='x', **more):\n    pass\n")
    signature = read_main(locate(str(script)))
    assert not signature.is_async and signature.any_keyword
    assert signature.params == {"target": REQUIRED, "speed": 0.3, "label": "x"}
    bare = tmp_path / "bare.py"
    bare.write_text("x = 1\n")
    with pytest.raises(ValueError, match="defines no main"):
        read_main(bare)
    robotless = tmp_path / "robotless.py"
    robotless.write_text("async def main():\n    pass\n")
    with pytest.raises(ValueError, match="takes no robot"):
        read_main(robotless)


def test_params_are_checked_against_main(tmp_path: Path) -> None:
    script = tmp_path / "mine.py"
    script.write_text("def main(robot, target, speed=0.3, flag=False, name='a'):\n    pass\n")
    signature = read_main(script)
    check_arguments(signature, {"target": [1, 2], "speed": 1})
    with pytest.raises(ValueError, match=r"main of mine.py needs target"):
        check_arguments(signature, {"speed": 1.0})
    with pytest.raises(ValueError, match=r"params.sped: main of mine.py takes target, speed"):
        check_arguments(signature, {"target": 1, "sped": 1.0})
    with pytest.raises(ValueError, match=r"params.speed is 'fast'"):
        check_arguments(signature, {"target": 1, "speed": "fast"})
    with pytest.raises(ValueError, match=r"params.flag is 1"):
        check_arguments(signature, {"target": 1, "flag": 1})
    with pytest.raises(ValueError, match=r"params.name is 3"):
        check_arguments(signature, {"target": 1, "name": 3})


def test_validate_names_the_robot_and_the_script() -> None:
    validate({"script": "steering", "robot": "d1_limb1"}, ("d1_limb1", "d2_limb1"))
    with pytest.raises(ValueError, match="no script"):
        validate({"robot": "d1_limb1"}, ("d1_limb1",))
    with pytest.raises(ValueError, match=r"robot 'd3_limb1' is not one of .*d1_limb1, d2_limb1"):
        validate({"script": "steering", "robot": "d3_limb1"}, ("d1_limb1", "d2_limb1"))
    with pytest.raises(ValueError, match=r"params.max_sped"):
        validate({"script": "steering", "params": {"max_sped": 1.0}}, None)


#: Station data mistakes -> the pieces of the one message.
STATION_CASES = {
    "a count for a named kind": (
        "autonomous_operator = 2",
        ["stations[0].components.autonomous_operator is 2", "each autonomous_operator is named"],
    ),
    "an operator with no script": (
        'autonomous_operator = [{ name = "steering" }]',
        ["stations[0].components.autonomous_operator[0] (steering)", "no script"],
    ),
    "a script that does not exist": (
        'autonomous_operator = [{ name = "s", script = "stearing" }]',
        ["autonomous_operator[0] (s)", "no shipped operator 'stearing'", "steering"],
    ),
    "a parameter main does not take": (
        'autonomous_operator = [{ name = "s", script = "steering", params = { speed = 1 } }]',
        ["autonomous_operator[0] (s)", "params.speed: main of steering.py takes cmd_vel"],
    ),
    "a parameter of the wrong type": (
        'autonomous_operator = [{ name = "s", script = "steering", params = { crab = 1 } }]',
        ["autonomous_operator[0] (s)", "params.crab is 1", "bool"],
    ),
    "a robot the template does not have": (
        'autonomous_operator = [{ name = "s", script = "steering", robot = "wheel1" }]',
        ["autonomous_operator[0] (s)", "robot 'wheel1' is not one of", "limb1"],
    ),
    "an operator kind parameter out of range": (
        'autonomous_operator = [{ name = "s", script = "guardian", connect_timeout = 0 }]',
        ["autonomous_operator[0] (s)", "connect_timeout must be > 0"],
    ),
}


@pytest.mark.parametrize("case", list(STATION_CASES))
def test_station_operators_refused_at_assemble_naming_file_and_field(
    case: str,
    world: dict[str, Path],  # noqa: F811
) -> None:
    line, pieces = STATION_CASES[case]
    edit(
        "assemblies/dragon.toml",
        "components = { human_operator = 1, data_monitor = 1 }",
        f"components = {{ human_operator = 1, data_monitor = 1, {line} }}",
    )(world)
    with pytest.raises(InputError) as caught:
        resolve("dragon")
    message = f"{caught.value} {getattr(caught.value, 'hint', '') or ''}"
    assert "dragon.toml: field" in message, message
    for piece in pieces:
        assert piece in message, message


# ---------------------------------------------------------------------------- the plan
def test_two_dragons_names_three_operators_per_dragon_each_in_a_process_of_its_own(
    two_dragons: ResolvedAssembly,
) -> None:
    operators = {c.name: c for c in two_dragons.components if c.kind == "autonomous_operator"}
    assert set(operators) == {
        f"{station}/d{d}_{script}"
        for station, d in (("gc_front", 1), ("gc_rear", 2))
        for script in ("steering", "posture", "guardian")
    }
    assert operators["gc_rear/d2_guardian"].params == {"script": "guardian", "robot": "d2_limb1"}
    plan = plan_host(two_dragons, "a-laptop")
    assert not plan.not_built
    processes = {p.name: [c.name for c in p.components] for p in plan.processes}
    for name in operators:
        assert processes[name.replace("/", "_")] == [name]
    # 52 components started and the simulator for the 8 motor interfaces: all 60 run.
    started = [c for c in plan.components if c.kind != "simulator"]
    motors = [c for c in two_dragons.components if kinds.replaced_in_simulation(c.kind)]
    assert len(started) + len(motors) == len(two_dragons.components) == 60


def test_an_operator_builds_over_its_robot_s_modules(two_dragons: ResolvedAssembly) -> None:
    built = build_component(two_dragons.component("gc_rear/d2_steering"), two_dragons, {})
    try:
        runner = built.on_bound
        assert sorted(runner.slots) == ["d2_limb1", "d2_limb2", "d2_wheel1", "d2_wheel2"]
        assert runner.root_link == "d2_limb1_base_link" and runner.path.name == "steering.py"
        assert (built.namespace, built.node_name) == ("/gc_rear", "d2_steering")
    finally:
        built.close()


def test_the_script_is_imported_at_build_before_the_executor_beats(
    two_dragons: ResolvedAssembly, tmp_path: Path
) -> None:
    """Importing a script (Pinocchio's C++ start holds the GIL) happens while the worker
    builds, before its heartbeat is judged, not on the script's thread beside a running
    executor, where a loaded machine made it look frozen; a script that fails to import is a
    build error naming its line, which the supervisor does not retry."""
    plan = two_dragons.component("gc_rear/d2_steering")
    built = build_component(plan, two_dragons, {})
    try:
        main = built.on_bound.main
        assert main.__name__ == "main" and main.__module__ == "_msctl_operator_gc_rear_d2_steering"
    finally:
        built.close()
    script = tmp_path / "broken.py"
    script.write_text(
        "import math\n\nraise RuntimeError('no robot here')\n\n\ndef main(robot):\n    pass\n"
    )
    broken = dataclasses.replace(plan, params={"script": str(script), "robot": "d2_limb1"})
    with pytest.raises(
        BuildError, match=r"gc_rear/d2_steering: broken\.py:3 \(<module>\): RuntimeError: no robot"
    ):
        build_component(broken, two_dragons, {})


# ---------------------------------------------------------------------------- the status
def test_the_status_says_what_became_of_the_script_and_what_it_reported() -> None:
    stopped = []
    core = AutonomousOperatorCore(
        "gc1/steering", "steering", OperatorConfig(status_period=1.0), "ground1", stopped.append
    )
    outbox = RecordingOutbox()
    core.bind(outbox)
    core.start(0.0)
    core.on_state(RUNNING, OK, "steering.py running on limb1", 0.1)
    core.on_report(WARN, "2 Twists refused", {"refused": 2}, 0.2)  # worse: published at once
    core.tick(0.5)  # not due
    core.tick(1.3)
    statuses = [m.status[0] for m in outbox.take("diagnostics")]
    assert [s.level for s in statuses] == [OK, WARN, WARN]
    assert statuses[-1].name == "gc1/steering" and statuses[-1].hardware_id == "ground1"
    assert diagnostic_values(statuses[-1]) == {
        "script": "steering",
        "state": RUNNING,
        "refused": "2",
    }
    core.on_state(FAILED, ERROR, "steering.py:12 (main): ValueError: bad", 2.0)
    assert outbox.take("diagnostics")[0].status[0].message.startswith("steering.py:12")
    core.on_report(OK, "x" * 5000, {f"k{i}": i for i in range(100)}, 3.0)
    assert len(core.message) <= 400 and len(core.values) <= 32
    with pytest.raises(ValueError, match="level must be one of ok, warn, error"):
        from components.autonomous_operator.core import level_of

        level_of("fine")


# ---------------------------------------------------------------------------- steering
def test_the_twist_gate_refuses_nan_and_inf_and_clamps_without_ever_raising() -> None:
    gate = TwistGate(max_speed=0.5, max_turn=1.0)
    assert gate.take(twist(0.2, 0.0, 0.3)) == (0.2, 0.0, 0.3)
    for bad in (twist(math.nan), twist(0.1, math.inf), twist(0.0, 0.0, -math.inf)):
        assert gate.take(bad) is None
    assert gate.take(SimpleNamespace(linear=None)) is None  # not even a Twist
    vx, vy, wz = gate.take(twist(3.0, 4.0, -9.0))  # 5 m/s, direction kept
    assert math.hypot(vx, vy) == pytest.approx(0.5) and vx / vy == pytest.approx(0.75)
    assert wz == -1.0
    odd = twist(0.1)
    odd.linear.z = 1.0
    assert gate.take(odd) == (0.1, 0.0, 0.0)
    assert (gate.taken, gate.refused, gate.clamped, gate.ignored) == (3, 4, 1, 1)
    with pytest.raises(ValueError, match="max_speed must be a positive number"):
        TwistGate(max_speed=math.inf, max_turn=1.0)


@pytest.mark.parametrize(
    ("script", "params", "why"),
    [
        ("steering", {"timeout": 0.0}, "steering: timeout must be a positive number, not 0.0"),
        ("steering", {"rate": math.nan}, "steering: rate must be a positive number, not nan"),
        ("guardian", {"period": -1.0}, "guardian: period must be a positive number, not -1.0"),
        ("guardian", {"stale_after": math.inf}, "stale_after must be a positive number, not inf"),
    ],
)
def test_an_operator_refuses_a_parameter_that_is_not_a_positive_number(
    script: str, params: dict[str, float], why: str
) -> None:
    import asyncio
    import importlib

    main = importlib.import_module(f"components.autonomous_operator.operators.{script}").main
    with pytest.raises(ValueError, match=re.escape(why)):
        asyncio.run(main(SimpleNamespace(), **params))  # refused before the robot is touched


def test_the_ramp_moves_toward_the_target_at_bounded_accelerations() -> None:
    ramp = Ramp(acceleration=0.5, angular_acceleration=1.0)
    for _ in range(4):
        ramp.step((0.2, 0.0, 0.0), 0.1)
    assert ramp.current == pytest.approx((0.2, 0.0, 0.0))
    ramp.step((0.0, 0.2, 0.5), 0.1)  # the linear part along a straight line
    v, u, w = ramp.current
    assert math.hypot(0.2 - v, u) == pytest.approx(0.05) and v + u == pytest.approx(0.2)
    assert w == pytest.approx(0.1)
    while not ramp.still:
        ramp.step(STILL, 0.1)
    assert ramp.current == STILL


def test_crab_directions_and_alignment() -> None:
    assert crab_direction((0.2, 0.0, 0.0)) == crab_direction((-0.2, 0.0, 0.3)) == 0.0
    assert crab_direction((0.1, 0.1, 0.0)) == pytest.approx(math.pi / 4)
    assert crab_direction((0.0, 0.0, 0.5)) is None  # a turn on the spot steers nothing
    assert aligned(math.pi, 0.0, 0.01) and aligned(math.pi / 4 + 0.005, -3 * math.pi / 4, 0.01)
    assert not aligned(0.2, 0.0, 0.05)


# ---------------------------------------------------------------------------- guardian
def test_tilt_is_the_angle_of_the_body_s_up_axis_from_the_vertical() -> None:
    assert tilt_of(1.0, 0.0, 0.0, 0.0) == 0.0
    half = math.radians(20.0) / 2
    assert tilt_of(math.cos(half), math.sin(half), 0.0, 0.0) == pytest.approx(math.radians(20))
    # A turn about the vertical is no tilt; an unnormalised quaternion is normalised.
    assert tilt_of(2 * math.cos(0.7), 0.0, 0.0, 2 * math.sin(0.7)) == pytest.approx(0.0)
    assert math.isnan(tilt_of(0.0, 0.0, 0.0, 0.0))


def test_safety_limits_come_from_module_data_tightest_first() -> None:
    limits = robot_limits([{"max_tilt": 0.26, "max_tracking_error": 0.5}, {"max_tilt": 0.35}])
    assert limits == SafetyLimits(max_tilt=0.26, max_tracking_error=0.5, tracking_grace=0.5)
    assert robot_limits([{}]) == SafetyLimits()
    for table, why in (
        ({"max_tlit": 0.3}, "unknown key"),
        ({"max_tilt": -1.0}, "positive finite"),
        ({"max_tilt": math.nan}, "positive finite"),
        ({"max_tilt": "steep"}, "give a number"),
        ({"max_tilt": 4.0}, "less than pi"),
    ):
        with pytest.raises(ValueError, match=why):
            SafetyLimits.from_mapping(table)


def test_the_guardian_s_parameters_only_tighten_the_module_data() -> None:
    dragon = from_document(resolve("dragon").document)
    robot = SimpleNamespace(assembly=dragon, modules={m.slot: None for m in dragon.modules})
    assert limits_for(robot, {}).max_tilt == 0.26  # the limbs' 15 degrees
    assert limits_for(robot, {"max_tilt": 0.1}).max_tilt == 0.1
    assert limits_for(robot, {"max_tilt": 1.0}).max_tilt == 0.26
    assert limits_for(robot, {"max_tracking_error": 0.2}).max_tracking_error == 0.2


def test_a_bad_safety_table_is_refused_at_assemble(world: dict[str, Path]) -> None:  # noqa: F811
    edit("assemblies/modules/hl_limb_v1.toml", "max_tilt = 0.26", "max_tilt = -0.26")(world)
    with pytest.raises(InputError, match=r"hl_limb_v1.toml: field safety: \[safety\].max_tilt"):
        resolve("dragon")


def test_a_component_that_fails_ends_its_process_for_the_supervisor_to_restart(
    session_settings,
) -> None:
    """What the runner does when a script raises: mark the component failed and stop the
    executor; ``run_built`` then raises, and the worker exits 1 (restarted, not final)."""
    from components.build import BuiltComponent
    from components.executor.core import Core
    from components.executor.interface import InterfaceSpec
    from components.executor.runner import ComponentFailed, run_built

    class Giving(Core):
        def start(self, now: float) -> None:
            built.failed = "gc1/twice: twice.py:11 (main): RuntimeError: boom"
            executors[0].stop()

    executors: list[Any] = []
    built = BuiltComponent(Giving("gc1/twice"), InterfaceSpec(), "/gc1", "twice")
    built.on_bound = lambda executor, component: executors.append(executor)
    with pytest.raises(ComponentFailed, match=r"twice\.py:11"):
        run_built([built], session_settings, duration=30.0)
