"""Decoding a data file's table into its typed model, with the operator's wording on failure.

msgspec checks every type, presence and pattern of a model (:mod:`msctl.assembler.models`) and
says where it failed as a path (``$.joints[0].max_velocity``). :func:`decode` turns that into
the line an operator can act on: ``<file>: field joints[0].max_velocity is 'fast'`` with a hint
saying what the field must be, taken from the field's own ``Meta`` (its ``description``, and
an ``extra`` ``hint`` or ``problem`` for a value of the right type breaking a rule).
"""

from __future__ import annotations

import re
import typing
from pathlib import Path
from typing import Any, TypeVar

import msgspec
from msgspec import Meta

from msctl.errors import InputError

M = TypeVar("M")

#: ``<reason> - at `$<path>``` as msgspec words a validation error.
_ERROR = re.compile(r"^(?P<reason>.*) - at `\$(?P<path>.*)`$", re.S)
_MISSING = re.compile(r"^Object missing required field `(?P<key>[^`]*)`$")
#: One step of a msgspec path: ``.key``, ``[3]`` or ``[...]`` (a dict key it does not name).
_STEP = re.compile(r"\.([^.\[]+)|\[(\d+|\.\.\.)\]")
#: How msgspec names the type it expected, in an operator's words.
_EXPECTED = {
    "str": "a string",
    "int": "an integer",
    "float": "a number",
    "bool": "true or false",
    "array": "a list",
    "object": "a table",
}
_ABSENT = object()


def decode(path: Path, table: Any, model: type[M], at: str = "") -> M:
    """``table`` (parsed TOML) as ``model``.

    Args:
        path: The file the table comes from, for the error.
        table: The parsed table.
        model: A msgspec Struct type.
        at: Where ``table`` sits in the file (``"stations[0].components.data_monitor[1]."``).

    Raises:
        InputError: Naming the file and the field, what it is and what it must be.
    """
    if not isinstance(table, dict):
        raise InputError(f"{path}: field {at.rstrip('.') or '(root)'} must be a table")
    try:
        return msgspec.convert(table, model)
    except msgspec.ValidationError as exc:
        raise _input_error(path, table, model, str(exc), at) from None


def missing(path: Path, where: str, key: str, what: str) -> InputError:
    """The error for a field a file must have: ``<file>: field <where><key> is missing``."""
    return InputError(f"{path}: field {where}{key} is missing", hint=f"add {key} = <{what}>")


def _input_error(path: Path, table: Any, model: type, text: str, at: str) -> InputError:
    match = _ERROR.match(text)
    # msgspec names no path for the table itself (a field missing at the top).
    reason, steps = (match.group("reason"), match.group("path")) if match else (text, "")
    node = _walk(table, model, steps, at)
    absent = _MISSING.match(reason)
    if absent:
        key = absent.group("key")
        meta = _meta(_field_type(node.type, key))
        what = meta.description if meta and meta.description else "a value"
        return missing(path, node.where, key, what)
    where, value, meta = node.described or (node.where.rstrip("."), node.value, None)
    what = meta.description if meta and meta.description else _expected(reason)
    extra = (meta.extra or {}) if meta else {}
    # The right type, but a pattern or a bound fails; or a part of it is wrong (an item of
    # a list of 3 numbers): the field's own rule says what to do.
    broken_rule = ", got `" not in reason or where != node.where.rstrip(".")
    problem = f": {extra['problem']}" if broken_rule and "problem" in extra else ""
    hint = extra.get("hint") if broken_rule and "hint" in extra else f"it must be {what}"
    return InputError(f"{path}: field {where} is {value!r}{problem}", hint=hint)


class _Node:
    """Where a walk down a msgspec path has got to."""

    def __init__(self, value: Any, type_: Any, where: str):
        self.value = value
        self.type = type_
        self.where = where
        #: The deepest field on the way with words of its own: ``(where, value, Meta)``.
        self.described: tuple[str, Any, Meta] | None = None


def _walk(table: Any, model: type, steps: str, at: str) -> _Node:
    """Follow ``steps`` (``.joints[0].name``) through the document and the model at once."""
    node = _Node(table, model, at)
    for key, index in _STEP.findall(steps):
        container = _bare(node.type)
        if key:
            node.type = _field_type(container, key)
            node.value = node.value.get(key, _ABSENT) if isinstance(node.value, dict) else _ABSENT
            node.where = f"{node.where}{key}"
        elif index == "...":
            key = _failing_key(node.value, _args(container)[-1])
            node.type = _args(container)[-1]
            node.value = node.value[key]
            node.where = f"{node.where}{key}"
        else:
            node.type = _item_type(container, int(index))
            node.value = node.value[int(index)]
            node.where = f"{node.where.rstrip('.')}[{index}]"
        meta = _meta(node.type)
        if meta is not None and meta.description:
            node.described = (node.where, node.value, meta)
        node.where += "."
    if _is_struct(node.type) and node.value is not _ABSENT:
        node.described = None  # a table that is not one: say so of it, not of its list
    return node


def _failing_key(table: dict[str, Any], value_type: Any) -> str:
    """The key of ``table`` whose value ``value_type`` refuses (msgspec writes ``[...]``)."""
    for key, value in table.items():
        try:
            msgspec.convert(value, value_type)
        except msgspec.ValidationError:
            return key
    return next(iter(table))


def _bare(type_: Any) -> Any:
    """``type_`` without ``Annotated`` and without ``| None``."""
    if typing.get_origin(type_) is typing.Annotated:
        type_ = typing.get_args(type_)[0]
    args = [a for a in _args(type_) if a is not type(None)]
    if type(None) in _args(type_) and len(args) == 1:
        return _bare(args[0])
    return type_


def _args(type_: Any) -> tuple[Any, ...]:
    return typing.get_args(type_)


def _is_struct(type_: Any) -> bool:
    bare = _bare(type_)
    return isinstance(bare, type) and issubclass(bare, msgspec.Struct)


def _field_type(struct: Any, key: str) -> Any:
    struct = _bare(struct)
    if _is_struct(struct):
        return typing.get_type_hints(struct, include_extras=True).get(key, Any)
    if typing.get_origin(struct) is dict:
        return _args(struct)[1]
    return Any


def _item_type(container: Any, index: int) -> Any:
    args = _args(container)
    if typing.get_origin(container) is tuple and args and args[-1] is not Ellipsis:
        return args[index]
    return args[0] if args else Any


def _meta(type_: Any) -> Meta | None:
    """The ``Meta`` a type is annotated with (the first with a description), if any; of
    ``X | None``, X's."""
    if typing.get_origin(type_) is not typing.Annotated:
        inner = [_meta(a) for a in _args(type_) if a is not type(None)]
        return inner[0] if len(inner) == 1 and type(None) in _args(type_) else None
    metas = [m for m in type_.__metadata__ if isinstance(m, Meta)]
    return next((m for m in metas if m.description), metas[0] if metas else None)


def _expected(reason: str) -> str:
    found = re.match(r"Expected `([^`|]*)", reason)
    name = found.group(1).strip() if found else ""
    return _EXPECTED.get(name, f"as msgspec says: {reason}")
