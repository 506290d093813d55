"""Typed motor backend options and the backend descriptions the assembler checks data against.

Plain calls only: no bus, no SDK import (that is the point of ``components.motors.options``).
"""

from __future__ import annotations

import ast
import dataclasses
import sys
import tomllib
from pathlib import Path
from typing import Any

import pytest

from components.motors import options as options_module
from components.motors.base import MotorBackend, MotorError, backend_class
from components.motors.options import (
    BACKENDS,
    ENTRY_POINT_GROUP,
    BackendInfo,
    CanopenOptions,
    DynamixelOptions,
    MotorOptionsError,
    backend_info,
    backend_names,
    parse_options,
)
from components.pysource import parse_source

MODULES = Path(__file__).resolve().parents[1] / "assemblies" / "modules"


# -- parsing ---------------------------------------------------------------------------------


def test_defaults_are_the_documented_ones() -> None:
    canopen = parse_options("canopen", {})
    assert canopen == CanopenOptions()
    assert (canopen.interface, canopen.bitrate, canopen.heartbeat_timeout) == (
        "socketcan",
        1_000_000,
        0.5,
    )
    assert canopen.drive_heartbeat_ms == 125  # a quarter of the timeout
    assert canopen.feedback_period == 0.01
    dynamixel = parse_options("dynamixel", None)
    assert dynamixel == DynamixelOptions()
    assert (dynamixel.baudrate, dynamixel.bus_watchdog_ms, dynamixel.cycle_period_s) == (
        1_000_000,
        100.0,
        0.01,
    )


def test_values_are_converted_to_the_field_types() -> None:
    canopen = parse_options(
        "canopen", {"temperature_object": "0x2100", "heartbeat_timeout": 1, "sync_period": 0.01}
    )
    assert canopen.temperature_object == 0x2100
    assert canopen.heartbeat_timeout == 1.0 and isinstance(canopen.heartbeat_timeout, float)
    assert canopen.feedback_period == 0.01  # follows SYNC
    assert parse_options("canopen", {"sync_period": 0}).sync_period is None  # 0: no SYNC
    assert parse_options("canopen", {"heartbeat_ms": 100.0}).heartbeat_ms == 100


def test_unknown_key_names_it_and_lists_the_known_ones() -> None:
    with pytest.raises(MotorOptionsError) as info:
        parse_options("canopen", {"heartbeat_timout": 0.5})
    text = str(info.value)
    known = ", ".join(f.name for f in sorted(dataclasses.fields(CanopenOptions), key=_name))
    assert text.startswith(f"unknown option 'heartbeat_timout' for canopen; known: {known}")
    assert "did you mean 'heartbeat_timeout'?" in text
    assert (info.value.backend, info.value.key) == ("canopen", "heartbeat_timout")
    assert isinstance(info.value, ValueError) and isinstance(info.value, MotorError)


def _name(f: dataclasses.Field) -> str:
    return f.name


@pytest.mark.parametrize(
    ("backend", "mapping", "expected"),
    [
        ("canopen", {"heartbeat_timeout": -1}, "heartbeat_timeout must be > 0, not -1"),
        ("canopen", {"sdo_timeout": "fast"}, "sdo_timeout must be a number, not 'fast'"),
        ("canopen", {"heartbeat_timeout": True}, "heartbeat_timeout must be a number, not True"),
        ("canopen", {"bitrate": 1_000_001}, "bitrate must be one of 10000, 20000, 50000"),
        ("canopen", {"bitrate": -5}, "bitrate must be one of"),
        ("canopen", {"interface": "sock can"}, "interface must be a python-can interface name"),
        ("canopen", {"master_node_id": 128}, "master_node_id must be between 0 and 127, not 128"),
        ("canopen", {"temperature_object": "x21"}, "temperature_object must be an object index"),
        ("canopen", {"heartbeat_ms": 600}, "heartbeat_ms must be below heartbeat_timeout"),
        ("canopen", {"enable_timeout": 0}, "enable_timeout must be > 0, not 0"),
        ("dynamixel", {"protocol": 1.0}, "protocol must be one of 2.0, not 1.0"),
        ("dynamixel", {"baudrate": 0}, "baudrate must be one of 9600, 57600"),
        ("dynamixel", {"baudrate": 4_500_000}, "baudrate must be one of"),
        ("dynamixel", {"bus_watchdog_ms": 5000}, "bus_watchdog_ms must be between 0 and 2540"),
        ("dynamixel", {"bus_watchdog_ms": -20}, "bus_watchdog_ms must be between 0 and 2540"),
        ("dynamixel", {"retries": -1}, "retries must be >= 0, not -1"),
        ("dynamixel", {"retries": 1.5}, "retries must be an integer, not 1.5"),
        ("dynamixel", {"latency_timer_ms": 0}, "latency_timer_ms must be > 0, not 0"),
        ("dynamixel", {"cycle_period_s": -0.01}, "cycle_period_s must be > 0"),
        ("dynamixel", {"hold_on_close": "yes"}, "hold_on_close must be true or false"),
        ("dynamixel", {"return_delay_us": 600}, "return_delay_us must be between 0 and 508"),
        ("dynamixel", {"reprobe_interval_s": float("nan")}, "must be a finite number"),
    ],
)
def test_bad_value_names_the_key_and_the_rule(
    backend: str, mapping: dict[str, Any], expected: str
) -> None:
    with pytest.raises(MotorOptionsError) as info:
        parse_options(backend, mapping)
    assert expected in str(info.value)
    assert info.value.key == next(iter(mapping))


def test_bus_bitrate_and_baudrate_go_through_the_same_type() -> None:
    assert parse_options("canopen", {}, bitrate=500_000).bitrate == 500_000
    assert parse_options("dynamixel", {"protocol": 2.0}, baudrate=4_000_000).baudrate == 4_000_000
    # The same value twice is fine; two different values are a mistake in the data.
    assert parse_options("canopen", {"bitrate": 250_000}, bitrate=250_000).bitrate == 250_000
    with pytest.raises(MotorOptionsError, match=r"bitrate given twice") as info:
        parse_options("canopen", {"bitrate": 250_000}, bitrate=500_000)
    assert info.value.key == "bitrate"
    with pytest.raises(MotorOptionsError, match=r"bitrate must be one of"):
        parse_options("canopen", {}, bitrate=123)
    # A CAN bit rate on a serial chain is not a Dynamixel option.
    with pytest.raises(MotorOptionsError, match=r"unknown option 'bitrate' for dynamixel"):
        parse_options("dynamixel", {}, bitrate=1_000_000)


def test_options_are_frozen_documented_and_passed_through() -> None:
    parsed = parse_options("dynamixel", {"retries": 2})
    with pytest.raises(dataclasses.FrozenInstanceError):
        parsed.retries = 3  # type: ignore[misc]
    assert parse_options("dynamixel", parsed) is parsed
    for options_type in (CanopenOptions, DynamixelOptions):
        for f in dataclasses.fields(options_type):
            assert f.metadata["doc"], f"{options_type.__name__}.{f.name} has no doc"
    with pytest.raises(MotorOptionsError, match="must be a table"):
        parse_options("canopen", ["bitrate"])


def test_module_data_keys_are_declared_not_silently_ignored() -> None:
    doc = dataclasses.fields(DynamixelOptions)
    notes = {f.name: f.metadata["doc"] for f in doc}
    assert "not used by this backend" in notes["return_delay_us"]
    assert "not used by this backend" in notes["bulk_read"]


@pytest.mark.parametrize("path", sorted(MODULES.glob("*.toml")), ids=lambda p: p.stem)
def test_every_shipped_bus_parses(path: Path) -> None:
    bus = tomllib.loads(path.read_text())["bus"]
    kind, options = bus["kind"], bus.get("options", {})
    parsed = parse_options(kind, options, bitrate=bus.get("bitrate"), baudrate=bus.get("baudrate"))
    assert isinstance(parsed, backend_info(kind).options_type)
    for key, value in options.items():
        assert getattr(parsed, key) == value or key == "temperature_object"


def test_the_module_imports_only_the_standard_library() -> None:
    # The assembler imports it at `msctl assemble` time: no python-can, canopen, SDK, numpy.
    tree = parse_source(Path(options_module.__file__).read_text())
    imported = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            imported.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            imported.add(node.module.split(".")[0])
    assert imported, "no imports found"
    assert imported <= set(sys.stdlib_module_names) | {"__future__"}, imported


# -- backend descriptions --------------------------------------------------------------------


@pytest.mark.parametrize(
    ("backend", "good", "bad"),
    [
        (
            "canopen",
            ["can0", "vcan1", "can-left", "PCAN_USBBUS1", "cia402-0af3", "0"],
            ["", "can 0", "can0;reboot", "$(rm)", "can0\n", "-can0"],
        ),
        (
            "dynamixel",
            [
                "/dev/ttyUSB0",
                "/dev/ttyACM1",
                "/dev/serial/by-id/usb-FTDI_USB__-__Serial_Converter_FT4TFSV1-if00-port0",
                "/dev/serial/by-path/pci-0000:00:14.0-usb-0:2:1.0-port0",
                "/dev/pts/7",
                "COM3",
            ],
            ["ttyUSB0", "/dev/ttyUSB0 ", "/dev/pts/x", "/tmp/ttyUSB0", "/dev/sda", "COM", "can0"],
        ),
    ],
)
def test_channel_rule(backend: str, good: list[str], bad: list[str]) -> None:
    info = backend_info(backend)
    for channel in good:
        assert info.channel_rule.fullmatch(channel), channel
        info.check_channel(channel)
    for channel in bad:
        assert not info.channel_rule.fullmatch(channel), channel
        with pytest.raises(MotorOptionsError) as raised:
            info.check_channel(channel)
        assert repr(channel) in str(raised.value) and info.channel_hint in str(raised.value)


def test_motor_id_ranges() -> None:
    canopen, dynamixel = backend_info("canopen"), backend_info("dynamixel")
    assert (canopen.motor_ids.start, canopen.motor_ids.stop) == (1, 128)
    assert (dynamixel.motor_ids.start, dynamixel.motor_ids.stop) == (0, 253)
    canopen.check_motor_id(127)
    dynamixel.check_motor_id(0)
    for info, bad in ((canopen, 0), (canopen, 128), (dynamixel, 253), (dynamixel, True)):
        with pytest.raises(MotorOptionsError, match="motor id"):
            info.check_motor_id(bad)


def test_unknown_backend_names_the_known_ones() -> None:
    with pytest.raises(MotorOptionsError) as info:
        backend_info("canbus")
    assert str(info.value) == "unknown motor backend 'canbus'; known: canopen, dynamixel"
    with pytest.raises(MotorError, match="unknown motor backend 'canbus'"):
        backend_class("canbus")
    with pytest.raises(MotorOptionsError, match="unknown motor backend"):
        parse_options("canbus", {})


def test_shipped_backends_load_lazily_by_class_path() -> None:
    assert set(BACKENDS) == {"canopen", "dynamixel"}
    for name, info in BACKENDS.items():
        assert info.name == name
        loaded = backend_class(name)
        assert loaded.__name__ == info.class_path.rpartition(":")[2]
        assert loaded.backend_name == name


# -- another package's backend, through the entry-point group --------------------------------


@dataclasses.dataclass(frozen=True)
class StepperOptions:
    """Options of a stepper driver package (the kind another package would ship)."""

    microsteps: int = dataclasses.field(default=16, metadata={"doc": "microsteps per step"})


class StepperBackend(MotorBackend):
    """A backend from another package (nothing behind it: only its lookup is tested)."""

    backend_name = "stepper"

    def _open(self) -> None: ...
    def _close(self) -> None: ...
    def _read(self) -> dict:
        return {}

    def _write(self, commands: list) -> None: ...
    def _halt(self) -> None: ...
    def _diagnostics(self) -> list:
        return []


STEPPER = BackendInfo(
    name="stepper",
    options_type=StepperOptions,
    motor_ids=range(0, 8),
    channel_rule=BACKENDS["canopen"].channel_rule,
    channel_hint="use the driver's name",
    class_path=f"{__name__}:StepperBackend",
)


class FakeEntryPoint:
    """What ``importlib.metadata.entry_points`` yields: a name, a value, ``load()``."""

    def __init__(self, name: str, value: str, loaded: Any) -> None:
        self.name, self.value, self._loaded = name, value, loaded

    def load(self) -> Any:
        if isinstance(self._loaded, Exception):
            raise self._loaded
        return self._loaded


@pytest.fixture
def plugins(monkeypatch: pytest.MonkeyPatch) -> list[FakeEntryPoint]:
    """Entry points of the motor backend group, as installed packages would declare them."""
    import importlib.metadata

    found: list[FakeEntryPoint] = []
    asked: list[str] = []

    def entry_points(*, group: str) -> list[FakeEntryPoint]:
        asked.append(group)
        return list(found) if group == ENTRY_POINT_GROUP else []

    monkeypatch.setattr(importlib.metadata, "entry_points", entry_points)
    yield found
    assert set(asked) <= {ENTRY_POINT_GROUP}


def test_an_entry_point_adds_a_backend(plugins: list[FakeEntryPoint]) -> None:
    plugins.append(FakeEntryPoint("stepper", "stepper_pkg.motors:STEPPER", STEPPER))
    assert backend_names() == ["canopen", "dynamixel", "stepper"]
    assert backend_info("stepper") is STEPPER
    parsed = parse_options("stepper", {"microsteps": 32})
    assert parsed == StepperOptions(32)
    with pytest.raises(MotorOptionsError, match=r"unknown option 'steps' for stepper; known"):
        parse_options("stepper", {"steps": 1})
    assert backend_class("stepper") is StepperBackend
    backend = StepperBackend("drv0", [], {"microsteps": 8})
    assert backend.options == StepperOptions(8)
    with pytest.raises(MotorOptionsError) as info:
        backend_info("servo")
    assert "known: canopen, dynamixel, stepper" in str(info.value)


def test_a_broken_entry_point_breaks_only_its_backend(plugins: list[FakeEntryPoint]) -> None:
    plugins.append(FakeEntryPoint("broken", "gone_pkg:INFO", ImportError("No module gone_pkg")))
    plugins.append(FakeEntryPoint("wrong", "other_pkg:INFO", {"name": "wrong"}))
    with pytest.raises(MotorOptionsError, match=r"'broken' \(entry point gone_pkg:INFO\)"):
        backend_info("broken")
    with pytest.raises(MotorOptionsError, match=r"must load to a BackendInfo"):
        backend_info("wrong")
    assert backend_info("canopen") is BACKENDS["canopen"]


def test_a_missing_backend_module_is_a_motor_error_with_the_pip_hint() -> None:
    info = dataclasses.replace(STEPPER, class_path="no_such_pkg.motors:Driver")
    with pytest.raises(MotorError, match=r"cannot load .*pip install"):
        info.load_class()
