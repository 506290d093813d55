"""A motor interface built with ``emulate`` runs its real backend against emulated hardware.

This is how ``msctl rehearse`` runs a robot computer (``MSCTL_HOME`` of its own,
``MSCTL_EMULATE_HARDWARE=1``): the registry entry of each shipped backend names its
emulator, the emulator starts in the motor interface's process, and the backend opens the
emulator's channel. The units' own data is resolved by the real assembler.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from components.assembly import load_assembly
from components.build import BuildError, build_component
from components.motors.options import BACKENDS, BackendInfo, MotorError

#: One unit per shipped backend: an H-line limb (CANopen) and a G-line limb (Dynamixel).
UNITS = {"canopen": "hlv1-limb-01", "dynamixel": "gl-limb-01"}


def _resolve(home: Path, unit: str) -> object:
    env = {**os.environ, "MSCTL_HOME": str(home)}
    command = [sys.executable, "-m", "msctl", "assemble", "minimal", "--use", f"limb1={unit}"]
    done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    return load_assembly(home / "assembly")


@pytest.mark.parametrize("backend", sorted(UNITS))
def test_every_shipped_backend_names_its_emulator(backend: str) -> None:
    emulator = BACKENDS[backend].load_emulator()
    assert callable(emulator)


def test_a_backend_without_an_emulator_says_so() -> None:
    info = BackendInfo(
        name="vendorbus",
        options_type=object,
        motor_ids=range(1, 2),
        channel_rule=BACKENDS["canopen"].channel_rule,
        channel_hint="",
        class_path="x:y",
    )
    with pytest.raises(MotorError, match="'vendorbus' has no emulated hardware"):
        info.load_emulator()


@pytest.mark.parametrize("backend", sorted(UNITS))
def test_motor_interface_reads_every_emulated_motor(backend: str, tmp_path: Path) -> None:
    assembly = _resolve(tmp_path, UNITS[backend])
    plan = assembly.component("limb1/motor_interface")
    module = assembly.module("limb1")
    built = build_component(plan, assembly, {"emulate": True})
    try:
        backend_object = built.resources[-1]
        # The channel opened is the emulator's, never the unit's own device.
        assert backend_object.channel != module.bus.channel
        backend_object.open()
        states = backend_object.read()
        assert sorted(states) == sorted(j.raw_name for j in module.actuated_joints)
        assert all(math.isfinite(s.position) for s in states.values())
    finally:
        built.close()


def test_without_emulate_the_units_own_channel_is_used(tmp_path: Path) -> None:
    assembly = _resolve(tmp_path, UNITS["dynamixel"])
    plan = assembly.component("limb1/motor_interface")
    built = build_component(plan, assembly, {})
    try:
        assert built.resources[-1].channel == assembly.module("limb1").bus.channel
    finally:
        built.close()


def test_an_emulator_that_fails_is_a_build_error_naming_the_module(tmp_path: Path) -> None:
    assembly = _resolve(tmp_path, UNITS["canopen"])
    plan = assembly.component("limb1/motor_interface")
    # An option the backend refuses: the emulator already started must be stopped again.
    with pytest.raises(BuildError, match="limb1/motor_interface: bus of module limb1"):
        build_component(plan, assembly, {"emulate": True, "bus_options": {"sync_period": -1}})
