"""The Dynamixel driver's control table against the emulator's, written from the ROBOTIS e-manual.

The emulated servos keep their own register map (``components.motors.emulation.dynamixel.
datasheet``), copied from the X-series datasheets and never from the driver, so the two can
disagree: a wrong address, size or sign in the driver fails here (and reads the wrong bytes of
an emulated servo in every backend test), instead of agreeing with itself.
"""

from __future__ import annotations

import ast
import dataclasses
import itertools
from pathlib import Path

import pytest

from components.motors.dynamixel import control_table
from components.motors.dynamixel.units import MODELS, DynamixelModel
from components.motors.emulation.dynamixel import datasheet
from components.motors.emulation.dynamixel.datasheet import ServoDatasheet
from components.pysource import parse_source

EMULATION = Path(datasheet.__file__).resolve().parents[1]


def mismatches(
    model: DynamixelModel,
    sheet: ServoDatasheet,
    signed: frozenset[str] = control_table.SIGNED_REGISTERS,
) -> list[str]:
    """Every register of the driver's table that the datasheet places, sizes or signs otherwise
    (``signed``: the registers the driver reads as two's complement)."""
    found = []
    for name, (address, size) in model.registers.items():
        # A model without current sensing has Present Load where the others have Present
        # Current: the driver reads it under the one name and converts it as a load.
        if name == "present_current" and model.effort_register == "load":
            name = "present_load"
        register = sheet.control_table.get(name)
        if register is None:
            found.append(f"{name}: not in the {sheet.name} datasheet")
        elif (register.address, register.size) != (address, size):
            found.append(
                f"{name}: driver {address} ({size} bytes), "
                f"datasheet {register.address} ({register.size} bytes)"
            )
        elif register.signed and name not in {"present_load", *signed}:
            found.append(f"{name}: signed in the datasheet, read unsigned by the driver")
    return found


@pytest.mark.parametrize("name", sorted(MODELS))
def test_the_drivers_table_is_the_datasheets(name: str) -> None:
    model, sheet = MODELS[name], datasheet.MODELS.get(name)
    assert sheet is not None, f"{name} has no datasheet in the emulator"
    assert model.model_number == sheet.model_number
    assert model.ticks_per_rev == sheet.ticks_per_rev
    assert model.velocity_unit_rpm == sheet.velocity_unit_rpm
    assert mismatches(model, sheet) == []


def test_the_block_read_every_cycle_is_present_values_only() -> None:
    # Present Current (or Load) up to Present Temperature: read-only, contiguous, no gap.
    table = datasheet.X_SERIES_TABLE
    start, end = control_table.READ_BLOCK_START, control_table.READ_BLOCK_START
    end += control_table.READ_BLOCK_LENGTH
    inside = sorted(
        (r.address, r.size, r.access) for r in table.values() if start <= r.address < end
    )
    assert inside[0][0] == table["present_current"].address == start
    assert inside[-1][0] + inside[-1][1] == end
    assert all(access == "R" for _, _, access in inside)
    assert all(a + s == b for (a, s, _), (b, _, _) in itertools.pairwise(inside))


def test_a_wrong_address_in_the_driver_is_caught() -> None:
    good = MODELS["XM430-W350"]
    wrong = dataclasses.replace(
        good, registers={**good.registers, "goal_position": (118, 4), "present_velocity": (128, 2)}
    )
    assert mismatches(wrong, datasheet.MODELS["XM430-W350"]) == [
        "goal_position: driver 118 (4 bytes), datasheet 116 (4 bytes)",
        "present_velocity: driver 128 (2 bytes), datasheet 128 (4 bytes)",
    ]
    signed = control_table.SIGNED_REGISTERS - {"present_velocity"}
    assert mismatches(good, datasheet.MODELS["XM430-W350"], signed) == [
        "present_velocity: signed in the datasheet, read unsigned by the driver"
    ]


def test_the_values_the_driver_relies_on_are_the_datasheets() -> None:
    assert control_table.OPERATING_MODES == datasheet.OPERATING_MODES
    assert control_table.BUS_WATCHDOG_UNIT_MS == datasheet.BUS_WATCHDOG_UNIT_MS
    assert control_table.BUS_WATCHDOG_MAX_UNITS == datasheet.BUS_WATCHDOG_MAX_UNITS
    assert control_table.BUS_WATCHDOG_EXPIRED == datasheet.BUS_WATCHDOG_EXPIRED


def test_the_emulator_does_not_import_the_driver() -> None:
    # Otherwise the emulator could take the driver's table again and agree with any mistake.
    for path in sorted(EMULATION.rglob("*.py")):
        for node in ast.walk(parse_source(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom) and node.module:
                assert not node.module.startswith("components.motors.dynamixel"), path
            if isinstance(node, ast.Import):
                assert all(not a.name.startswith("components.motors.dynamixel") for a in node.names)
