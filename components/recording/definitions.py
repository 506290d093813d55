"""What a bag says about each topic's type and QoS, taken from msctl's own type registry.

Message definitions are written in rosbag2's ``ros2msg`` form: the type's own ``.msg`` text
first, then every type it uses (depth first, each once), each after an empty line, a line of
80 ``=`` and a line ``MSG: pkg/Type``: the dependency named the way the field names it
(``std_msgs/Header header`` -> ``MSG: std_msgs/Header``), exactly as rosbag2 writes it
(rosbag2_cpp's ``LocalMessageDefinitionSource``). Strict readers (Foxglove's ros2msg parser)
match those names exactly; ``pkg/msg/Type`` there makes every nested type unreadable.

QoS profiles are written in the version-9 form (a list of maps, enum values as words,
infinite durations as ``{sec: 9223372036, nsec: 854775807}``), once per publisher: what the
publishers offered, as ``ros2 bag record`` stores it.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping
from typing import Any

from components.comm.qos import QoS

#: The line that separates the definitions of a ``ros2msg`` schema.
SEPARATOR = "=" * 80
#: ROS's infinite duration (RMW_DURATION_INFINITE) as rosbag2 writes it.
INFINITE = {"sec": 9223372036, "nsec": 854775807}


def message_definition(type_name: str) -> str | None:
    """The complete ``ros2msg`` definition of a message type, or ``None`` if msctl has none.

    Args:
        type_name: ``pkg/msg/Name``.
    """
    from components.comm.types import UnknownTypeError, normalize_type_name, registry

    types = registry()
    try:
        canonical = normalize_type_name(type_name)
        types.definition(canonical)
    except UnknownTypeError:
        return None
    seen: set[str] = set()

    # rosbag2_cpp's LocalMessageDefinitionSource, step for step: depth first, each level's
    # dependencies in the sorted order of their names as the fields write them, each once.
    def full_text(name: str) -> str:
        text = _msg_text(types, name)
        for dependency in sorted(_dependencies(types, name)):
            if dependency not in seen:
                seen.add(dependency)
                text += f"\n{SEPARATOR}\nMSG: {dependency}\n"
                text += full_text(normalize_type_name(dependency))
        return text

    return full_text(canonical)


def _dependencies(types: Any, name: str) -> set[str]:
    """The message types a type's fields use, named as the fields name them (``pkg/Name``)."""
    out = set()
    for _, desc in types.definition(name)[1]:
        nested = _nested(desc)
        if nested:
            pkg, _, short = nested.split("/")
            out.add(f"{pkg}/{short}")
    return out


#: A dependency's name line as msctl wrote it before it followed rosbag2 (``MSG: pkg/msg/Type``).
_LONG_MSG_LINE = re.compile(
    r"^MSG: ([A-Za-z][A-Za-z0-9_]*)/msg/([A-Za-z][A-Za-z0-9_]*)[ \t]*$", re.M
)


def needs_fixing(definition: str) -> bool:
    """Whether a ``ros2msg`` definition names a dependency ``pkg/msg/Type`` (Foxglove fails)."""
    return _LONG_MSG_LINE.search(definition) is not None


def fixed_definition(definition: str) -> str:
    """A ``ros2msg`` definition with each ``MSG: pkg/msg/Type`` line written ``MSG: pkg/Type``.

    Only the name lines change: the fields already say ``pkg/Type``, which is what a strict
    reader matches the names against. A definition already in rosbag2's form comes back as it is.
    """
    return _LONG_MSG_LINE.sub(r"MSG: \1/\2", definition)


def _msg_text(types: Any, name: str) -> str:
    consts, fields = types.definition(name)
    lines = [f"{kind} {const}={_constant(value)}" for const, kind, value in consts]
    lines += [f"{_field_type(desc)} {field}" for field, desc in fields]
    return "\n".join(lines) + "\n"


def _constant(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


def _field_type(desc: Any) -> str:
    from rosbags.typesys.base import Nodetype

    node, detail = desc
    if node == Nodetype.BASE:
        base, bound = detail
        return f"{base}<={bound}" if bound else base
    if node == Nodetype.NAME:
        pkg, _, short = detail.split("/")
        return f"{pkg}/{short}"
    inner, size = detail
    if node == Nodetype.ARRAY:
        return f"{_field_type(inner)}[{size}]"
    return f"{_field_type(inner)}[<={size}]" if size else f"{_field_type(inner)}[]"


def _nested(desc: Any) -> str | None:
    from rosbags.typesys.base import Nodetype

    node, detail = desc
    if node in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        return _nested(detail[0])
    return detail if node == Nodetype.NAME else None


def qos_profile(qos: QoS) -> dict[str, Any]:
    """One offered QoS profile in the version-9 ``metadata.yaml`` form."""
    return {
        "history": qos.history,
        "depth": qos.depth if qos.history == "keep_last" else 0,
        "reliability": qos.reliability,
        "durability": qos.durability,
        "deadline": dict(INFINITE),
        "lifespan": dict(INFINITE),
        "liveliness": "automatic",
        "liveliness_lease_duration": dict(INFINITE),
        "avoid_ros_namespace_conventions": False,
    }


def qos_profiles(offered: Iterable[QoS]) -> list[dict[str, Any]]:
    """The profiles of every publisher, in the order given."""
    return [qos_profile(q) for q in offered]


def profiles_to_qos(profiles: Iterable[Mapping[str, Any]]) -> list[QoS]:
    """Profiles read back from a bag (ours, or another tool's: words or rmw enum numbers).

    Unknown or ``system_default`` values fall back to ROS's defaults (reliable, volatile).
    """
    out = []
    for profile in profiles:
        reliability = _word(profile.get("reliability"), {1: "reliable", 2: "best_effort"})
        durability = _word(profile.get("durability"), {1: "transient_local", 2: "volatile"})
        history = _word(profile.get("history"), {1: "keep_last", 2: "keep_all"})
        depth = profile.get("depth", 10)
        out.append(
            QoS(
                reliability="best_effort" if reliability == "best_effort" else "reliable",
                durability="transient_local" if durability == "transient_local" else "volatile",
                history="keep_all" if history == "keep_all" else "keep_last",
                depth=depth if isinstance(depth, int) and depth > 0 else 10,
            )
        )
    return out


def _word(value: Any, numbers: Mapping[int, str]) -> str:
    if isinstance(value, int) and not isinstance(value, bool):
        return numbers.get(value, "")
    return str(value or "").lower()


def profiles_yaml(profiles: list[dict[str, Any]]) -> str:
    """Profiles as the YAML text MCAP channel metadata carries (``offered_qos_profiles``)."""
    import yaml

    return yaml.safe_dump(profiles, sort_keys=False, default_flow_style=False)
