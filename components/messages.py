"""Small, typed helpers for the standard ROS 2 messages msctl cores use.

Cores build and read messages through these so that the conventions (SI units, empty arrays
meaning "not given", stamps as ``builtin_interfaces/Time``) live in one place.
"""

from __future__ import annotations

import enum
import functools
import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np

from components.comm.types import registry

JOINT_STATE = "sensor_msgs/msg/JointState"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
TWIST = "geometry_msgs/msg/Twist"
TRIGGER = "std_srvs/srv/Trigger"


class Level(enum.IntEnum):
    """A ``diagnostic_msgs/DiagnosticStatus`` level, with the message's byte values.

    The values are the wire bytes (OK 0, WARN 1, ERROR 2, STALE 3), so a ``Level`` goes into
    a message as is. They are not an order of badness: ERROR (a known failure) outranks STALE
    (no news), because "the joint manager is halted" must not hide behind "no joint_states
    for 2 s". Order levels by :attr:`severity` or with :func:`worst`, never with ``max()``,
    ``<`` or ``>`` on the numbers.
    """

    OK = 0
    WARN = 1
    ERROR = 2
    STALE = 3

    @classmethod
    def of(cls, value: int) -> Level:
        """The level of a received byte; a value diagnostic_msgs does not define is ERROR.

        A sender that invents a level is broken, and a broken sender is an error to show,
        not something to rank below OK.
        """
        try:
            return cls(value)
        except ValueError:
            return cls.ERROR

    @property
    def severity(self) -> int:
        """Rank of badness, higher is worse: OK < WARN < STALE < ERROR."""
        return _SEVERITY[self]


_SEVERITY = {Level.OK: 0, Level.WARN: 1, Level.STALE: 2, Level.ERROR: 3}

#: The levels under their diagnostic_msgs names (aliases of the :class:`Level` members).
OK, WARN, ERROR, STALE = Level.OK, Level.WARN, Level.ERROR, Level.STALE
LEVEL_NAMES = {level: level.name for level in Level}


def worst(levels: Iterable[int]) -> Level:
    """The most severe of ``levels`` by :attr:`Level.severity` (OK for none).

    Plain ints (a received ``status.level``) are read with :meth:`Level.of`.
    """
    return max((Level.of(level) for level in levels), key=_SEVERITY.__getitem__, default=Level.OK)


def msg(type_name: str, **fields: Any) -> Any:
    """Construct any registered message with the given fields (others at their defaults)."""
    cls, makers = _factory(type_name)
    for name, make in makers:
        if name not in fields:
            fields[name] = make()
    return cls(**fields)


@functools.cache
def _factory(type_name: str) -> tuple[type, tuple[tuple[str, Callable[[], Any]], ...]]:
    # Built once per type: msg() is on every hot path (joint commands at 100+ Hz).
    reg = registry()
    makers = tuple((name, _default_maker(desc)) for name, desc in reg.fields(type_name))
    return reg.msg_class(type_name), makers


def _default_maker(desc: Any) -> Callable[[], Any]:
    from rosbags.typesys.base import Nodetype

    node, detail = desc
    if node == Nodetype.BASE:
        base = detail[0]
        value: Any = 0
        if base in ("string", "wstring"):
            value = ""
        elif base == "bool":
            value = False
        elif base in ("float32", "float64"):
            value = 0.0
        return lambda: value
    if node == Nodetype.NAME:
        return lambda: msg(detail)
    inner, size = detail
    if inner[0] == Nodetype.BASE and inner[1][0] not in ("string", "wstring", "bool"):
        dtype = _NUMPY_TYPES.get(inner[1][0], np.float64)
        length = size if node == Nodetype.ARRAY else 0
        return lambda: np.zeros(length, dtype=dtype)
    if node == Nodetype.ARRAY:
        element = _default_maker(inner)
        return lambda: [element() for _ in range(size)]
    return list


_NUMPY_TYPES = {
    "float64": np.float64,
    "float32": np.float32,
    "int8": np.int8,
    "uint8": np.uint8,
    "char": np.uint8,
    "byte": np.uint8,
    "octet": np.uint8,
    "int16": np.int16,
    "uint16": np.uint16,
    "int32": np.int32,
    "uint32": np.uint32,
    "int64": np.int64,
    "uint64": np.uint64,
}


def to_time(seconds: float) -> Any:
    """A ``builtin_interfaces/Time`` for a float number of seconds."""
    sec = math.floor(seconds)
    return msg("builtin_interfaces/msg/Time", sec=int(sec), nanosec=int((seconds - sec) * 1e9))


def from_time(stamp: Any) -> float:
    """Seconds as a float from a ``builtin_interfaces/Time``."""
    return stamp.sec + stamp.nanosec * 1e-9


def header(stamp: float, frame_id: str = "") -> Any:
    """A ``std_msgs/Header``."""
    return msg("std_msgs/msg/Header", stamp=to_time(stamp), frame_id=frame_id)


class JointSample(NamedTuple):
    """One joint's entry in a JointState; ``None`` where the message did not carry that field."""

    name: str
    position: float | None = None
    velocity: float | None = None
    effort: float | None = None


def joint_state(samples: Iterable[JointSample], stamp: float = 0.0, frame_id: str = "") -> Any:
    """Build one JointState from samples that all carry the same fields.

    A field (position, velocity, effort) is carried when the samples have it; an empty array
    means "not given", as in ROS. NaN is never invented for a missing value, because receivers
    (the joint manager) refuse NaN as a bad value.

    Raises:
        ValueError: If some samples carry a field and others do not (use
            :func:`joint_state_batches` for mixed samples).
    """
    rows = list(samples)
    columns = []
    for index, field in ((1, "position"), (2, "velocity"), (3, "effort")):
        values = [s[index] for s in rows]
        given = [v is not None for v in values]
        if any(given) and not all(given):
            raise ValueError(
                f"joint_state: {field} is given for some joints and not others; "
                "send them as separate messages (joint_state_batches)"
            )
        columns.append(np.array(values, dtype=np.float64) if rows and all(given) else np.zeros(0))
    return msg(
        JOINT_STATE,
        header=header(stamp, frame_id),
        name=[s.name for s in rows],
        position=columns[0],
        velocity=columns[1],
        effort=columns[2],
    )


def joint_state_batches(
    samples: Iterable[JointSample], stamp: float = 0.0, frame_id: str = ""
) -> list[Any]:
    """JointStates for mixed samples: one message per set of carried fields, in order."""
    groups: dict[tuple[bool, bool, bool], list[JointSample]] = {}
    for sample in samples:
        key = (sample.position is not None, sample.velocity is not None, sample.effort is not None)
        groups.setdefault(key, []).append(sample)
    return [joint_state(rows, stamp, frame_id) for rows in groups.values()]


def joint_samples(message: Any) -> list[JointSample]:
    """Read a JointState into samples; empty or short arrays mean "not given".

    ROS allows position/velocity/effort arrays to be empty; a non-empty array shorter than
    ``name`` is malformed, and its missing entries are read as not given rather than guessed.
    """
    names: Sequence[str] = message.name
    pos, vel, eff = message.position, message.velocity, message.effort
    out = []
    for i, name in enumerate(names):
        out.append(
            JointSample(
                name,
                float(pos[i]) if i < len(pos) else None,
                float(vel[i]) if i < len(vel) else None,
                float(eff[i]) if i < len(eff) else None,
            )
        )
    return out


def diagnostic_status(
    name: str,
    level: int,
    message: str,
    hardware_id: str = "",
    values: Mapping[str, Any] | None = None,
) -> Any:
    """A ``diagnostic_msgs/DiagnosticStatus`` with key/value pairs as strings."""
    pairs = [
        msg("diagnostic_msgs/msg/KeyValue", key=str(k), value=str(v))
        for k, v in (values or {}).items()
    ]
    return msg(
        "diagnostic_msgs/msg/DiagnosticStatus",
        level=int(level),
        name=name,
        message=message,
        hardware_id=hardware_id,
        values=pairs,
    )


def diagnostic_array(statuses: Iterable[Any], stamp: float = 0.0) -> Any:
    """A ``diagnostic_msgs/DiagnosticArray`` of statuses."""
    return msg(DIAGNOSTIC_ARRAY, header=header(stamp), status=list(statuses))


def diagnostic_values(status: Any) -> dict[str, str]:
    """The key/value pairs of a DiagnosticStatus as a dict."""
    return {kv.key: kv.value for kv in status.values}


def trigger_response(success: bool, message: str = "") -> Any:
    """A ``std_srvs/Trigger`` response."""
    return msg("std_srvs/srv/Trigger_Response", success=success, message=message)
