"""Every check at ``msctl assemble``, none later: each bad value a review found accepted, now
refused in memory with the file, the field and the rule, before anything is written.

In-process (``resolve`` on a private copy of the shipped data); ``test_assemble_errors`` runs
the real ``msctl`` for a few of the same cases, and shows nothing is written.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest
from test_assemble_errors import append, edit, world  # noqa: F401  (world is a fixture)

from msctl.assembler import resolve
from msctl.errors import InputError

LIMB = "assemblies/modules/hl_limb_v1.toml"
UNIT = "calibration/hlv1-limb-01.toml"
LOCKED = "calibration/hlv1-limb-03.toml"
WITH_03 = {"limb1": "hlv1-limb-03"}
G_LINE = {"limb1": "gl-limb-01", "limb2": "gl-limb-02"}

Mutation = Callable[[dict[str, Path]], None]

#: case -> (mutation, --use choices, pieces the one message must hold)
CASES: dict[str, tuple[Mutation, dict[str, str], list[str]]] = {
    "NaN in a module": (
        edit(LIMB, "lower = -3.05", "lower = nan"),
        {},
        ["hl_limb_v1.toml: field joints[0].lower is nan", "finite"],
    ),
    "inf in a template": (
        edit("assemblies/dragon.toml", "angle = 180.0", "angle = inf"),
        {},
        ["dragon.toml: field connections[0].angle is inf", "finite"],
    ),
    "-inf in a unit": (
        edit(UNIT, "zero_offset = -0.0176", "zero_offset = -inf"),
        {},
        ["hlv1-limb-01.toml: field joints.joint1.zero_offset is -inf", "finite"],
    ),
    "NaN limit in a unit is blamed on the unit": (
        append(UNIT, "lower = nan\n"),
        {},
        ["hlv1-limb-01.toml: field", "is nan"],
    ),
    "negative max_velocity": (
        edit(LIMB, "max_velocity = 1.5", "max_velocity = -5.0"),
        {},
        ["hl_limb_v1.toml: field joints[0].max_velocity is -5.0", "must be > 0"],
    ),
    "zero max_velocity": (
        edit(LIMB, "max_velocity = 1.5", "max_velocity = 0.0"),
        {},
        ["field joints[0].max_velocity is 0.0", "must be > 0"],
    ),
    "max_effort of 1e308": (
        edit(LIMB, "max_effort = 150.0", "max_effort = 1e308"),
        {},
        ["field joints[0].max_effort is 1e+308", "at most"],
    ),
    "limits of ±1e308": (
        edit(LIMB, "lower = -3.05\nupper = 3.05", "lower = -1e308\nupper = 1e308"),
        {},
        ["field joints[0].lower is -1e+308", "outside what a revolute joint allows"],
    ),
    "revolute upper limit of 1000 rad": (
        edit(LIMB, "upper = 3.05", "upper = 1000.0"),
        {},
        ["field joints[0].upper is 1000.0", "revolute"],
    ),
    "lower above upper": (
        edit(LIMB, "lower = -3.05\nupper = 3.05", "lower = 1.0\nupper = -1.0"),
        {},
        ["hl_limb_v1.toml: field joints[0]", "lower"],
    ),
    "duplicate motor ids in a unit": (
        edit(UNIT, "motor_id = 2", "motor_id = 1"),
        {},
        ["hlv1-limb-01.toml: field joints", "joint1 and joint2 both use motor id 1"],
    ),
    "duplicate motor ids in a module": (
        edit("assemblies/modules/gl_limb.toml", "motor_id = 2", "motor_id = 1"),
        {},
        ["gl_limb.toml: field joints", "both use motor id 1"],
    ),
    "motor id -1": (
        edit(UNIT, "motor_id = 2", "motor_id = -1"),
        {},
        ["hlv1-limb-01.toml: field joints.joint2.motor_id is -1", "1..127"],
    ),
    "motor id 2^62": (
        edit(UNIT, "motor_id = 2", f"motor_id = {2**62}"),
        {},
        [f"field joints.joint2.motor_id is {2**62}", "1..127"],
    ),
    "Dynamixel id outside its range": (
        edit("calibration/gl-limb-01.toml", "motor_id = 2", "motor_id = 300"),
        G_LINE,
        ["gl-limb-01.toml: field joints.joint2.motor_id is 300", "dynamixel"],
    ),
    "zero offset of 100 rad": (
        edit(UNIT, "zero_offset = -0.0176", "zero_offset = 100.0"),
        {},
        ["field joints.joint1.zero_offset is 100.0", "outside the joint's reach"],
    ),
    "URDF outside the module folder": (
        edit(LIMB, 'urdf = "urdf/hl_limb_v1.urdf"', 'urdf = "../../../../etc/passwd"'),
        {},
        ["hl_limb_v1.toml: field urdf is '../../../../etc/passwd'", "it leaves"],
    ),
    "absolute URDF path": (
        edit(LIMB, 'urdf = "urdf/hl_limb_v1.urdf"', 'urdf = "/etc/passwd"'),
        {},
        ["field urdf is '/etc/passwd'", "it leaves"],
    ),
    "mesh outside the module folder": (
        edit(
            "assemblies/modules/urdf/hl_wheel_v1.urdf",
            '<geometry><box size="0.2 0.3 0.12"/></geometry>',
            '<geometry><mesh filename="../../../x.stl"/></geometry>',
        ),
        {},
        ["hl_wheel_v1.urdf", "../../../x.stl", "leaves"],
    ),
    "host name that is a shell command": (
        edit(UNIT, 'host = "hl-limb-01"', 'host = "; rm -rf /"'),
        {},
        ["hlv1-limb-01.toml: field host is '; rm -rf /'", "not a valid host name"],
    ),
    "station host name with a space": (
        edit("assemblies/dragon.toml", 'host = "ground1"', 'host = "ground 1"'),
        {},
        ["dragon.toml: field stations[0].host", "not a valid host name"],
    ),
    "bus channel with a shell fragment": (
        edit(UNIT, 'channel = "can0"', 'channel = "can0; reboot"'),
        {},
        ["hlv1-limb-01.toml: field bus.channel", "'can0; reboot'", "not a canopen channel"],
    ),
    "serial channel that is not a device": (
        edit("calibration/gl-limb-01.toml", 'channel = "/dev/ttyUSB0"', 'channel = "ttyUSB0"'),
        G_LINE,
        ["gl-limb-01.toml: field bus.channel", "'ttyUSB0'"],
    ),
    "a station asking for 100,000,000 components": (
        edit("assemblies/dragon.toml", "human_operator = 1", "human_operator = 100000000"),
        {},
        ["dragon.toml: field stations[0].components.human_operator is 100000000", "0 to 64"],
    ),
    "a station running a robot-side kind": (
        edit("assemblies/dragon.toml", "human_operator = 1", "joint_manager = 1"),
        {},
        ["dragon.toml: field stations[0].components", "joint_manager"],
    ),
    "two station components given one name": (
        edit(
            "assemblies/dragon.toml",
            "data_monitor = 1",
            'data_monitor = [{ name = "human_operator" }]',
        ),
        {},
        [
            "dragon.toml: field stations[0].components.data_monitor",
            "two components of station gc1 are named 'human_operator'",
        ],
    ),
    "a named station component with a parameter its kind does not take": (
        edit(
            "assemblies/dragon.toml",
            "data_monitor = 1",
            'data_monitor = [{ name = "watch", period = 1.0 }]',
        ),
        {},
        ["dragon.toml: field stations[0].components.data_monitor[0] (watch)", "'period'"],
    ),
    "a named station component whose name is no ROS name": (
        edit("assemblies/dragon.toml", "data_monitor = 1", 'data_monitor = [{ name = "1st" }]'),
        {},
        ["dragon.toml: field stations[0].components.data_monitor[0].name is '1st'"],
    ),
    "the README tour's override name typo": (
        edit(LOCKED, 'name = "locked_joint"', 'name = "lock_joint"'),
        WITH_03,
        [
            "hlv1-limb-03.toml: field overrides[0].name",
            "no override named 'lock_joint' for joint_manager; known: locked_joint",
        ],
    ),
    "an override aimed at the kinematics manager": (
        edit(
            LOCKED,
            'name = "locked_joint"',
            'name = "locked_joint"\ncomponent = "kinematics_manager"',
        ),
        WITH_03,
        ["hlv1-limb-03.toml: field overrides[0].name", "for kinematics_manager; known: none"],
    ),
    "an override aimed at a kind the module does not run": (
        edit(LOCKED, 'name = "locked_joint"', 'name = "locked_joint"\ncomponent = "simulator"'),
        WITH_03,
        ["hlv1-limb-03.toml: field overrides[0]", "does not run"],
    ),
    "an override parameter of the wrong type": (
        edit(LOCKED, "position = 0.0", 'position = "zero"'),
        WITH_03,
        ["hlv1-limb-03.toml: field overrides[0]", "position"],
    ),
    "an override parameter it does not take": (
        edit(LOCKED, "position = 0.0", "position = 0.0\nspeed = 1.0"),
        WITH_03,
        ["hlv1-limb-03.toml: field overrides[0]", "speed"],
    ),
    "an override without its required parameter": (
        edit(LOCKED, 'joint = "joint5"\n', ""),
        WITH_03,
        ["hlv1-limb-03.toml: field overrides[0]", "joint"],
    ),
    "an injection that does not exist": (
        edit(LIMB, 'injections = [{ name = "rezero",', 'injections = [{ name = "rezro",'),
        {},
        ["hl_limb_v1.toml: field injections[0].name", "'rezro'", "known: rezero"],
    ),
    "a health threshold that is not a number": (
        edit(LIMB, "max_temperature = 70.0", 'max_temperature = "hot"'),
        {},
        ["hl_limb_v1.toml", "max_temperature"],
    ),
    "an unknown bus option": (
        edit(LIMB, "heartbeat_ms = 100", "heartbeat_timout = 100"),
        {},
        ["hl_limb_v1.toml", "heartbeat_timout", "heartbeat_ms"],
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_refused_at_assemble_naming_file_field_and_rule(
    case: str,
    world: dict[str, Path],  # noqa: F811
) -> None:
    mutate, uses, expected = CASES[case]
    mutate(world)
    with pytest.raises(InputError) as caught:
        resolve("dragon", uses)
    message = f"{caught.value} {getattr(caught.value, 'hint', '') or ''}"
    for piece in expected:
        assert piece in message, message


def test_station_components_listed_by_name_take_their_own_parameters(
    world: dict[str, Path],  # noqa: F811
) -> None:
    """A kind given as a list of tables: one component per table, named by it, with its
    parameters over the station's ``params.<kind>``."""
    edit(
        "assemblies/dragon.toml",
        "data_monitor = 1",
        'data_monitor = [{ name = "watch" }, { name = "slow_watch", publish_period = 5.0 }]',
    )(world)
    append("assemblies/dragon.toml", "params = { data_monitor = { max_items = 10 } }\n")(world)
    plans = {c.name: c for c in resolve("dragon").lock.components if c.kind == "data_monitor"}
    assert set(plans) == {"gc1/watch", "gc1/slow_watch"}
    assert plans["gc1/watch"].params == {"max_items": 10}
    assert plans["gc1/slow_watch"].params == {"max_items": 10, "publish_period": 5.0}


def test_the_shipped_data_is_accepted_as_it_is(world: dict[str, Path]) -> None:  # noqa: F811
    """The cases above break one value each; unbroken, the same data resolves."""
    assert resolve("dragon", WITH_03).lock.units["limb1"] == "hlv1-limb-03"
    assert resolve("dragon", G_LINE).lock.modules[0].bus.kind == "dynamixel"
