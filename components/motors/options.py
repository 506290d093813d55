"""One typed description per motor backend: its options, motor ids and channel names.

This module is what ``msctl assemble`` checks a module's ``[bus]`` against, on the laptop,
long before ``msctl up`` reaches a robot. It imports only the standard library (no python-can,
canopen, dynamixel-sdk or numpy), so the assembler stays fast; the backend classes themselves
are imported lazily, by name, when a bus is really opened (python-can's ``BACKENDS`` model).

* :class:`CanopenOptions` and :class:`DynamixelOptions` are frozen dataclasses, one field per
  option with its type, default, rule and a one-line doc (``dataclasses.fields(...)[i]
  .metadata["doc"]``).
* :func:`parse_options` turns the mapping from module data into one of them and refuses
  unknown keys and bad values with a :class:`MotorOptionsError` that names the key.
* :data:`BACKENDS` and :func:`backend_info` describe each backend (:class:`BackendInfo`):
  which motor ids and channel names are valid, and where its class lives. Other packages add
  backends through the ``msctl.motor_backends`` entry-point group, each entry loading to a
  :class:`BackendInfo`.
"""

from __future__ import annotations

import dataclasses
import difflib
import importlib
import math
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

#: Entry-point group through which another package registers a motor backend: each entry
#: loads to a :class:`BackendInfo`.
ENTRY_POINT_GROUP = "msctl.motor_backends"


class MotorError(Exception):
    """A motor bus could not be opened or used; the message names the channel and the fix."""


class MotorOptionsError(MotorError, ValueError):
    """A motor bus described wrongly in data: unknown backend, unknown option, bad value.

    Attributes:
        backend: The backend the description was for (``"canopen"``), or the unknown name.
        key: The option at fault, when one is (``"heartbeat_timeout"``).
    """

    def __init__(self, message: str, backend: str = "", key: str | None = None) -> None:
        super().__init__(message)
        self.backend = backend
        self.key = key


# ---------------------------------------------------------------------------- value kinds
# A kind turns a data value (TOML: int, float, bool, str) into the field's type, or raises
# _Invalid with what the value must be.


class _Invalid(Exception):
    """A data value of the wrong kind; the message completes "<key> must be ..."."""


def _number(value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise _Invalid("a number")
    if not math.isfinite(value):
        raise _Invalid("a finite number")
    return float(value)


def _integer(value: Any) -> int:
    if isinstance(value, float) and value.is_integer():
        return int(value)
    if isinstance(value, bool) or not isinstance(value, int):
        raise _Invalid("an integer")
    return value


def _boolean(value: Any) -> bool:
    if not isinstance(value, bool):
        raise _Invalid("true or false")
    return value


def _text(value: Any) -> str:
    if not isinstance(value, str) or not value.strip():
        raise _Invalid("a non-empty string")
    return value


def _object_index(value: Any) -> int:
    """An object dictionary index, as an integer or a string such as ``"0x2100"``."""
    if isinstance(value, str):
        try:
            return int(value, 0)
        except ValueError:
            raise _Invalid('an object index such as "0x2100"') from None
    return _integer(value)


# --------------------------------------------------------------------------------- rules


@dataclass(frozen=True)
class _Rule:
    """A range rule: ``test`` on the converted value, ``text`` completes "<key> must be ..."."""

    text: str
    test: Callable[[Any], bool]


def _above(bound: float) -> _Rule:
    return _Rule(f"> {bound:g}", lambda v: v > bound)


def _at_least(bound: float) -> _Rule:
    return _Rule(f">= {bound:g}", lambda v: v >= bound)


def _between(low: float, high: float, note: str = "") -> _Rule:
    return _Rule(f"between {low:g} and {high:g}{note}", lambda v: low <= v <= high)


def _one_of(values: tuple[Any, ...]) -> _Rule:
    return _Rule("one of " + ", ".join(str(v) for v in values), lambda v: v in values)


def _option(
    default: Any,
    doc: str,
    kind: Callable[[Any], Any],
    rule: _Rule | None = None,
    optional: bool = False,
) -> Any:
    """A dataclass field described for :func:`parse_options`.

    Args:
        default: Value when module data does not give the key.
        doc: One line saying what the option is (and its unit).
        kind: Converter from the data value (see ``_number`` and friends).
        rule: Range rule of the converted value.
        optional: Whether ``None`` (the key given as nothing) is allowed.
    """
    metadata = {"doc": doc, "kind": kind, "rule": rule, "optional": optional}
    return field(default=default, metadata=metadata)


#: CAN bit rates of CiA 301 (the ones a CANopen drive can be set to), bit/s.
CAN_BITRATES = (10_000, 20_000, 50_000, 100_000, 125_000, 250_000, 500_000, 800_000, 1_000_000)
#: Baud rates both X-series servos (register 8) and the dynamixel-sdk's port handler support.
DYNAMIXEL_BAUDRATES = (9_600, 57_600, 115_200, 1_000_000, 2_000_000, 3_000_000, 4_000_000)
#: The largest Dynamixel Bus Watchdog (register 98): 127 units of 20 ms.
BUS_WATCHDOG_MAX_MS = 2540


@dataclass(frozen=True)
class CanopenOptions:
    """Options of the CANopen CiA 402 backend (module data ``[bus] options``, plus ``bitrate``)."""

    interface: str = _option(
        "socketcan",
        "python-can interface (socketcan on a robot, virtual in tests)",
        _text,
        _Rule("a python-can interface name", lambda v: re.fullmatch(r"[a-z][a-z0-9_]*", v)),
    )
    bitrate: int = _option(1_000_000, "CAN bit rate, bit/s", _integer, _one_of(CAN_BITRATES))
    heartbeat_timeout: float = _option(
        0.5, "seconds without a drive's heartbeat before it counts as lost", _number, _above(0)
    )
    heartbeat_ms: int | None = _option(
        None,
        "heartbeat period each drive is set to (0x1017), ms; default a quarter of the timeout",
        _integer,
        _between(1, 65535),
        optional=True,
    )
    sync_period: float | None = _option(
        None,
        "seconds between SYNC frames this backend produces (feedback follows SYNC); 0 or "
        "absent: no SYNC",
        _number,
        _at_least(0),
        optional=True,
    )
    pdo_period: float | None = _option(
        None,
        "event timer of feedback TPDOs without SYNC, s; default the SYNC period or 0.01",
        _number,
        _above(0),
        optional=True,
    )
    master_node_id: int = _option(
        127,
        "node id of this process's heartbeat that the drives watch; 0 turns their watchdog off",
        _integer,
        _between(0, 127),
    )
    eds: str | None = _option(
        None,
        "object dictionary (EDS) file of the drives; default the minimal CiA 402 one shipped",
        _text,
        optional=True,
    )
    temperature_object: int | None = _option(
        None,
        'object holding the drive temperature in 0.1 °C (INTEGER16), e.g. "0x2100"; mapped '
        "to TPDO4",
        _object_index,
        _between(0x1000, 0xFFFF, " (0x1000..0xFFFF)"),
        optional=True,
    )
    sdo_timeout: float = _option(
        0.3, "seconds an SDO request waits for its answer", _number, _above(0)
    )
    enable_timeout: float = _option(
        2.0, "seconds open() waits for the drives to reach OPERATION ENABLED", _number, _above(0)
    )

    def __post_init__(self) -> None:
        if self.sync_period == 0:
            object.__setattr__(self, "sync_period", None)
        if self.heartbeat_ms is not None and self.heartbeat_ms >= self.heartbeat_timeout * 1000:
            raise MotorOptionsError(
                f"canopen option heartbeat_ms must be below heartbeat_timeout "
                f"({self.heartbeat_timeout * 1000:g} ms), not {self.heartbeat_ms}",
                "canopen",
                "heartbeat_ms",
            )

    @property
    def drive_heartbeat_ms(self) -> int:
        """The heartbeat period given to the drives (``heartbeat_ms`` or its default)."""
        if self.heartbeat_ms is not None:
            return self.heartbeat_ms
        return max(10, round(self.heartbeat_timeout * 1000 / 4))

    @property
    def feedback_period(self) -> float:
        """Event timer of feedback TPDOs (``pdo_period`` or its default)."""
        return self.pdo_period or self.sync_period or 0.01


@dataclass(frozen=True)
class DynamixelOptions:
    """Options of the Dynamixel Protocol 2.0 backend (``[bus] options``, plus ``baudrate``)."""

    baudrate: int = _option(
        1_000_000,
        "serial baud rate; servos ship at 57600, set them once with Dynamixel Wizard",
        _integer,
        _one_of(DYNAMIXEL_BAUDRATES),
    )
    protocol: float = _option(
        2.0, "Dynamixel protocol version; this backend speaks 2.0 only", _number, _one_of((2.0,))
    )
    latency_timer_ms: float = _option(
        16.0,
        "the USB adapter's latency timer, ms (16 as FTDI ships); sizes the reply timeout",
        _number,
        _above(0),
    )
    retries: int = _option(
        1,
        "individual re-reads of a servo missing from the group reply before it is not answering",
        _integer,
        _at_least(0),
    )
    reprobe_interval_s: float = _option(
        0.5, "seconds between pings of a servo that is not answering", _number, _above(0)
    )
    status_interval_s: float = _option(
        0.5,
        "seconds between re-reads of Hardware Error Status and checks of an armed bus watchdog",
        _number,
        _above(0),
    )
    boot_timeout_s: float = _option(
        1.0, "seconds recover waits for a rebooted servo to answer", _number, _above(0)
    )
    reopen_interval_s: float = _option(
        1.0, "seconds between attempts to reopen a lost serial port", _number, _above(0)
    )
    hold_on_close: bool = _option(
        False, "keep torque on at close (velocity joints get goal 0 first)", _boolean
    )
    bus_watchdog_ms: float = _option(
        100.0,
        "each servo's own Bus Watchdog in velocity mode, ms (20 ms steps); 0 leaves it off",
        _number,
        _between(0, BUS_WATCHDOG_MAX_MS),
    )
    cycle_period_s: float = _option(
        0.01, "period of the backend's I/O thread: one read cycle of the chain", _number, _above(0)
    )
    stale_after_s: float = _option(
        0.5,
        "a servo state older than this is not returned by read() (the chain stalled)",
        _number,
        _above(0),
    )
    return_delay_us: int = _option(
        0,
        "the servos' Return Delay Time, µs (module data; not used by this backend, which "
        "leaves register 9 as configured)",
        _integer,
        _between(0, 508),
    )
    bulk_read: bool = _option(
        False,
        "read with BULK_READ (module data; not used by this backend: one SYNC_READ block "
        "covers every servo)",
        _boolean,
    )


# ------------------------------------------------------------------------------- parsing


def option_names(options_type: type) -> list[str]:
    """The option keys an options dataclass declares, sorted."""
    return sorted(f.name for f in dataclasses.fields(options_type))


def _parse(backend: str, options_type: type, mapping: Mapping[str, Any]) -> Any:
    fields = {f.name: f for f in dataclasses.fields(options_type)}
    values: dict[str, Any] = {}
    for key, raw in mapping.items():
        spec = fields.get(key)
        if spec is None:
            known = ", ".join(option_names(options_type))
            close = difflib.get_close_matches(str(key), fields, n=1)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise MotorOptionsError(
                f"unknown option {key!r} for {backend}; known: {known}{hint}", backend, str(key)
            )
        meta = spec.metadata
        if raw is None and meta.get("optional"):
            values[key] = None
            continue
        # Fields declared with _option have a kind and a rule; a plain field of another
        # package's options type takes the value as it is.
        kind, rule = meta.get("kind"), meta.get("rule")
        try:
            value = raw if kind is None else kind(raw)
            if rule is not None and not rule.test(value):
                raise _Invalid(rule.text)
        except _Invalid as bad:
            raise MotorOptionsError(
                f"{backend} option {key} must be {bad}, not {raw!r}", backend, str(key)
            ) from None
        values[key] = value
    try:
        return options_type(**values)
    except MotorOptionsError:
        raise
    except (TypeError, ValueError) as exc:
        raise MotorOptionsError(f"{backend} options: {exc}", backend) from exc


def parse_options(
    backend: str,
    mapping: Mapping[str, Any] | Any = None,
    *,
    bitrate: int | None = None,
    baudrate: int | None = None,
) -> Any:
    """The typed options of ``backend`` from module data.

    Args:
        backend: Backend name (``"canopen"``, ``"dynamixel"``, or one from an entry point).
        mapping: The bus's ``options`` table (an options object of the right type is
            returned as it is).
        bitrate: The bus's ``bitrate`` (``[bus] bitrate``), merged as the ``bitrate`` option.
        baudrate: The bus's ``baudrate`` (``[bus] baudrate``), merged as ``baudrate``.

    Returns:
        The backend's options dataclass (:class:`CanopenOptions`, :class:`DynamixelOptions`).

    Raises:
        MotorOptionsError: For an unknown backend, an unknown key (the message lists the
            known ones), a bad value (the message names the key and the rule), or a bus-level
            ``bitrate``/``baudrate`` that contradicts the same key in ``options``.
    """
    options_type = backend_info(backend).options_type
    if isinstance(mapping, options_type) and bitrate is None and baudrate is None:
        return mapping
    if mapping is None:
        merged: dict[str, Any] = {}
    elif isinstance(mapping, Mapping):
        merged = dict(mapping)
    else:
        raise MotorOptionsError(
            f"{backend} options must be a table of key = value, not {type(mapping).__name__}",
            backend,
        )
    for key, value in (("bitrate", bitrate), ("baudrate", baudrate)):
        if value is None:
            continue
        if key in merged and merged[key] != value:
            raise MotorOptionsError(
                f"{backend} {key} given twice: bus {key} = {value!r} but bus options {key} = "
                f"{merged[key]!r}; keep one",
                backend,
                key,
            )
        merged[key] = value
    return _parse(backend, options_type, merged)


# ------------------------------------------------------------------------ backend registry


@dataclass(frozen=True)
class BackendInfo:
    """Everything the assembler knows about a motor backend without importing it.

    Attributes:
        name: Backend name as module data writes it (``[bus] kind``).
        options_type: Its options dataclass (:func:`parse_options` builds it).
        motor_ids: Valid motor ids on one bus (CANopen node ids 1..127, Dynamixel 0..252).
        channel_rule: What a valid channel name must match (``fullmatch``).
        channel_hint: Says what a channel looks like, for error messages.
        class_path: ``"module:Class"`` of the backend, imported only when a bus is opened.
        emulator_path: ``"module:function"`` starting emulated hardware for this bus
            (``(channel, motor specs) -> EmulatedHardware``, see
            :mod:`components.motors.emulation`); empty when the backend has none.
    """

    name: str
    options_type: type
    motor_ids: range
    channel_rule: re.Pattern[str]
    channel_hint: str
    class_path: str
    emulator_path: str = ""

    def parse_options(self, mapping: Mapping[str, Any] | None = None, **bus: Any) -> Any:
        """This backend's typed options (see :func:`parse_options`)."""
        return parse_options(self.name, mapping, **bus)

    def check_channel(self, channel: str) -> None:
        """Raise :class:`MotorOptionsError` unless ``channel`` is valid for this backend."""
        if not isinstance(channel, str) or not self.channel_rule.fullmatch(channel):
            raise MotorOptionsError(
                f"{channel!r} is not a {self.name} channel; {self.channel_hint}",
                self.name,
                "channel",
            )

    def check_motor_id(self, motor_id: int) -> None:
        """Raise :class:`MotorOptionsError` unless ``motor_id`` is valid on this bus."""
        if (
            isinstance(motor_id, bool)
            or not isinstance(motor_id, int)
            or (motor_id not in self.motor_ids)
        ):
            ids = self.motor_ids
            raise MotorOptionsError(
                f"{motor_id!r} is not a {self.name} motor id; use {ids.start}..{ids.stop - 1}",
                self.name,
                "motor_id",
            )

    def load_class(self) -> type:
        """The backend class (imports its module and vendor SDK now).

        Raises:
            MotorError: If the module cannot be imported (with the pip hint) or lacks it.
        """
        return self._load(self.class_path)

    def load_emulator(self) -> Any:
        """The function that starts emulated hardware for this bus.

        Raises:
            MotorError: If the backend has no emulator, or it cannot be imported.
        """
        if not self.emulator_path:
            raise MotorError(
                f"motor backend {self.name!r} has no emulated hardware; "
                "run it on its robot, or in simulation (`msctl up --sim`)"
            )
        return self._load(self.emulator_path)

    def _load(self, path: str) -> Any:
        module_name, _, class_name = path.partition(":")
        try:
            module = importlib.import_module(module_name)
        except ImportError as exc:
            raise MotorError(
                f"motor backend {self.name!r} cannot load ({exc}); reinstall msctl with "
                "`pip install .` (or the package that provides this backend)"
            ) from exc
        try:
            return getattr(module, class_name)
        except AttributeError:
            raise MotorError(
                f"motor backend {self.name!r}: {module_name} has no {class_name}"
            ) from None


#: A python-can channel: an interface name (can0, vcan1) or any name without spaces or shell
#: metacharacters (the virtual bus takes any name; some adapters use numbers or USB paths).
_CAN_CHANNEL = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.:@/+-]{0,63}")
#: A serial device: /dev/ttyUSB0, /dev/ttyACM1, /dev/serial/by-id/..., a pty /dev/pts/N, COMn.
_SERIAL_CHANNEL = re.compile(
    r"/dev/(?:tty[A-Za-z]+[0-9]+|serial/by-(?:id|path)/[A-Za-z0-9_.:@+-]+|pts/[0-9]+)"
    r"|COM[0-9]{1,3}"
)

#: The backends msctl ships. Others come from the ``msctl.motor_backends`` entry points.
BACKENDS: dict[str, BackendInfo] = {
    "canopen": BackendInfo(
        name="canopen",
        options_type=CanopenOptions,
        motor_ids=range(1, 128),
        channel_rule=_CAN_CHANNEL,
        channel_hint="use the CAN interface name (can0, vcan1) or the python-can channel, "
        "without spaces",
        class_path="components.motors.canopen.backend:CanopenBackend",
        emulator_path="components.motors.emulation:cia402_drives",
    ),
    "dynamixel": BackendInfo(
        name="dynamixel",
        options_type=DynamixelOptions,
        motor_ids=range(0, 253),
        channel_rule=_SERIAL_CHANNEL,
        channel_hint="use the serial device of the chain: /dev/ttyUSB0, "
        "/dev/serial/by-id/<adapter>, a pty /dev/pts/N, or COMn",
        class_path="components.motors.dynamixel.backend:DynamixelBackend",
        emulator_path="components.motors.emulation:dynamixel_chain",
    ),
}


def _entry_points() -> list[Any]:
    # Imported here: importlib.metadata costs tens of ms, and the shipped backends need none.
    import importlib.metadata

    return list(importlib.metadata.entry_points(group=ENTRY_POINT_GROUP))


def backend_names() -> list[str]:
    """Every backend name: the shipped ones and those registered by entry points, sorted."""
    return sorted({*BACKENDS, *(ep.name for ep in _entry_points())})


def backend_info(name: str) -> BackendInfo:
    """The description of backend ``name`` (shipped, or from an entry point, loaded now).

    Raises:
        MotorOptionsError: If no backend has that name (the message lists the known ones),
            or its entry point does not load to a :class:`BackendInfo`.
    """
    info = BACKENDS.get(name)
    if info is not None:
        return info
    for ep in _entry_points():
        if ep.name != name:
            continue
        try:
            loaded = ep.load()
        except Exception as exc:
            raise MotorOptionsError(
                f"motor backend {name!r} (entry point {ep.value}) cannot load: {exc}", name
            ) from exc
        if not isinstance(loaded, BackendInfo) or loaded.name != name:
            raise MotorOptionsError(
                f"motor backend {name!r}: entry point {ep.value} must load to a BackendInfo "
                f"named {name!r}, not {loaded!r}",
                name,
            )
        return loaded
    raise MotorOptionsError(
        f"unknown motor backend {name!r}; known: {', '.join(backend_names())}", name
    )
