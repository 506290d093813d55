"""Link profiles as data: the built-in ``profiles.toml`` and a user's file over it.

A profile is a TOML table of :class:`~msctl.rehearse.link_profile.DirectionProfile` fields, given
once for both directions or in ``up`` / ``down`` tables (which win), plus ``description``
and ``base`` (start from another profile). The file beside this module documents every
field. :func:`load_profiles` reads the built-ins, then the user's file (its profiles add to
the built-ins or replace them by name), and resolves ``base`` chains; every mistake is an
:class:`~msctl.errors.InputError` naming the file, the profile, the field and the rule.
"""

from __future__ import annotations

import os
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from msctl.errors import InputError, NotFoundError, did_you_mean
from msctl.rehearse.link_profile import DirectionProfile, GilbertElliott, LinkProfile, ProfileError

#: The built-in profiles.
BUILTIN_PROFILES = Path(__file__).with_name("profiles.toml")

#: Environment variable naming a user's profiles file, read when no file is given.
PROFILES_ENV = "MSCTL_LINK_PROFILES"

_DIRECTION_FIELDS = tuple(f.name for f in fields(DirectionProfile))
_GILBERT_FIELDS = tuple(f.name for f in fields(GilbertElliott))
_PROFILE_FIELDS = ("description", "base", "up", "down", *_DIRECTION_FIELDS)
_DIRECTIONS = ("up", "down")


@dataclass(frozen=True)
class _Layer:
    """One file's profiles, raw."""

    source: str
    profiles: dict[str, dict[str, Any]]


@dataclass(frozen=True)
class _Set:
    """Where a resolved value was written: the file and profile, and its key there."""

    value: Any
    where: str
    key: str


@dataclass(frozen=True)
class _Resolved:
    description: str
    directions: dict[str, dict[str, _Set]]


def load_profiles(extra: Path | None = None) -> dict[str, LinkProfile]:
    """The link profiles: the built-ins, with a user's file over them.

    Args:
        extra: A user's profiles file; None: the file named by ``$MSCTL_LINK_PROFILES``, or
            none when it is unset or empty.

    Returns:
        Every profile by name, built-ins first, then the user's new ones in file order.

    Raises:
        NotFoundError: When the user's file does not exist.
        InputError: For a file that is not TOML or a profile that breaks a rule (naming the
            file, the profile, the field and the rule).
    """
    layers = [_read(BUILTIN_PROFILES, str(BUILTIN_PROFILES))]
    if extra is None and os.environ.get(PROFILES_ENV):
        path = Path(os.environ[PROFILES_ENV])
        layers.append(_read(path, f"{path} (from ${PROFILES_ENV})"))
    elif extra is not None:
        layers.append(_read(Path(extra), str(extra)))
    top: dict[str, int] = {}
    for index, layer in enumerate(layers):
        for name in layer.profiles:
            top[name] = index
    cache: dict[tuple[int, str], _Resolved] = {}
    out: dict[str, LinkProfile] = {}
    for name, index in top.items():
        resolved = _resolve(layers, index, name, cache, ())
        where = _where(layers[index], name)
        out[name] = LinkProfile(
            name=name,
            up=_build(resolved.directions["up"], where),
            down=_build(resolved.directions["down"], where),
            description=resolved.description,
        )
    return out


def find_profile(profiles: Mapping[str, LinkProfile], name: str) -> LinkProfile:
    """The profile called ``name``.

    Raises:
        NotFoundError: Naming the profile, the nearest known names and all of them.
    """
    try:
        return profiles[name]
    except (KeyError, TypeError):
        pass
    near = did_you_mean(str(name), profiles)
    raise NotFoundError(
        f"no link profile {name!r}"
        + (f" ({near})" if near else "")
        + f"; profiles: {', '.join(profiles)}",
        hint=f"add it to a profiles file (${PROFILES_ENV})",
    )


def _read(path: Path, source: str) -> _Layer:
    try:
        with path.open("rb") as stream:
            data = tomllib.load(stream)
    except FileNotFoundError:
        raise NotFoundError(f"{source}: no such link profiles file") from None
    except tomllib.TOMLDecodeError as error:
        raise InputError(f"{source}: not valid TOML: {error}") from error
    except OSError as error:
        raise InputError(f"{source}: cannot read: {error.strerror or error}") from error
    for name, table in data.items():
        if not isinstance(table, dict):
            raise InputError(f"{source}: profile {name!r} must be a table, got {table!r}")
    return _Layer(source, data)


def _where(layer: _Layer, name: str) -> str:
    return f"{layer.source}: profile {name!r}"


def _resolve(
    layers: list[_Layer],
    index: int,
    name: str,
    cache: dict[tuple[int, str], _Resolved],
    chain: tuple[tuple[int, str], ...],
) -> _Resolved:
    """The profile ``name`` of layer ``index`` with its ``base`` chain applied."""
    if (index, name) in cache:
        return cache[(index, name)]
    layer = layers[index]
    where = _where(layer, name)
    raw = layer.profiles[name]
    for key in raw:
        if key not in _PROFILE_FIELDS:
            _unknown(where, key, _PROFILE_FIELDS)
    description = ""
    directions: dict[str, dict[str, _Set]] = {"up": {}, "down": {}}
    base = raw.get("base")
    if base is not None:
        if not isinstance(base, str):
            raise InputError(f"{where}: base must be a profile's name, got {base!r}")
        found = _find_base(layers, index, name, base, where)
        if found in chain or found == (index, name):
            loop = " -> ".join([*(n for _, n in chain), name, base])
            raise InputError(f"{where}: base must not lead back to itself, got {loop}")
        parent = _resolve(layers, found[0], found[1], cache, (*chain, (index, name)))
        description = parent.description
        directions = {d: dict(values) for d, values in parent.directions.items()}
    if "description" in raw:
        if not isinstance(raw["description"], str):
            raise InputError(f"{where}: description must be text, got {raw['description']!r}")
        description = raw["description"]
    common = {k: v for k, v in raw.items() if k in _DIRECTION_FIELDS}
    for direction in _DIRECTIONS:
        _overlay(directions[direction], common, where, "")
    for direction in _DIRECTIONS:
        table = raw.get(direction)
        if table is None:
            continue
        if not isinstance(table, dict):
            raise InputError(f"{where}: {direction} must be a table, got {table!r}")
        for key in table:
            if key not in _DIRECTION_FIELDS:
                _unknown(
                    where, f"{direction}.{key}", [f"{direction}.{f}" for f in _DIRECTION_FIELDS]
                )
        _overlay(directions[direction], table, where, f"{direction}.")
    resolved = _Resolved(description, directions)
    cache[(index, name)] = resolved
    return resolved


def _find_base(
    layers: list[_Layer], index: int, name: str, base: str, where: str
) -> tuple[int, str]:
    """Where profile ``base`` is defined, as seen from profile ``name`` of layer ``index``.

    A profile's own name as its base means the definition it replaces (in a lower layer);
    any other name means the topmost definition.
    """
    below = range(index - 1, -1, -1) if base == name else range(len(layers) - 1, -1, -1)
    for candidate in below:
        if base in layers[candidate].profiles:
            return candidate, base
    known = sorted({n for layer in layers for n in layer.profiles})
    if base == name:
        raise InputError(
            f"{where}: base {base!r} names the profile itself, and no built-in profile "
            f"{base!r} is there to start from; profiles: {', '.join(known)}"
        )
    near = did_you_mean(base, known)
    raise InputError(
        f"{where}: base must be a known profile, got {base!r}"
        + (f" ({near})" if near else "")
        + f"; profiles: {', '.join(known)}"
    )


def _overlay(target: dict[str, _Set], table: Mapping[str, Any], where: str, prefix: str) -> None:
    """Set ``table``'s direction fields over ``target``.

    ``gilbert_elliott`` and ``loss``/``burst`` are two ways to say the loss model: setting
    one drops what a base said the other way.
    """
    if "gilbert_elliott" in table:
        for other in ("loss", "burst"):
            if other in table:
                raise InputError(
                    f"{where}: {prefix}{other} cannot be given with {prefix}gilbert_elliott "
                    "(two ways to say the loss)"
                )
        target.pop("loss", None)
        target.pop("burst", None)
    elif "loss" in table or "burst" in table:
        target.pop("gilbert_elliott", None)
    for key, value in table.items():
        if key in _DIRECTION_FIELDS:
            target[key] = _Set(value, where, prefix + key)


def _build(values: dict[str, _Set], where: str) -> DirectionProfile:
    """A validated direction profile from resolved values; errors name where each was set."""
    kwargs: dict[str, Any] = {}
    try:
        for key, item in values.items():
            if key == "gilbert_elliott":
                kwargs[key] = _gilbert(item)
            else:
                kwargs[key] = item.value
        return DirectionProfile(**kwargs)
    except ProfileError as error:
        root = error.field.split(".", 1)[0]
        item = values.get(root)
        if item is None:
            raise InputError(f"{where}: {error}") from None
        prefix = item.key[: len(item.key) - len(root)]
        raise InputError(
            f"{item.where}: {prefix}{error.field} {error.rule}, got {error.value!r}"
        ) from None


def _gilbert(item: _Set) -> GilbertElliott:
    table = item.value
    if not isinstance(table, dict):
        raise ProfileError("gilbert_elliott", "must be a table like {p = 0.01, r = 0.25}", table)
    for key in table:
        if key not in _GILBERT_FIELDS:
            _unknown(
                item.where,
                f"{item.key}.{key}",
                [f"{item.key}.{f}" for f in _GILBERT_FIELDS],
            )
    for needed in ("p", "r"):
        if needed not in table:
            raise ProfileError(f"gilbert_elliott.{needed}", "must be given", None)
    return GilbertElliott(**table)


def _unknown(where: str, key: str, known: tuple[str, ...] | list[str]) -> None:
    near = did_you_mean(key, known)
    raise InputError(
        f"{where}: unknown field {key!r}"
        + (f" ({near})" if near else "")
        + f"; fields: {', '.join(known)}"
    )
