"""An autonomous operator's script: where it is, what its ``main`` takes, and its checks.

The station's data names a script and its parameters::

    autonomous_operator = [
      { name = "d1_steering", script = "steering", robot = "d1_limb1",
        params = { max_speed = 0.4 } },
      { name = "mapper", script = "/opt/team/mapper.py" },
    ]

``script`` is a shipped operator (a file of :data:`OPERATORS`, by name) or an absolute path
to a Python file. The file defines ``main(robot, ...)`` (``async def`` or not, as for
``msctl run``): its first parameter takes the robot, the others are the operator's
parameters, given from ``params`` as keyword arguments. Everything is read without running
the file (its syntax tree), so ``msctl assemble`` refuses a missing script, a script without
``main``, a parameter ``main`` does not take, one it needs and is not given, or a value of
another type than its default's, naming each.
"""

from __future__ import annotations

import ast
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from components.pysource import parse_source

#: Where the shipped operators are, one file each.
OPERATORS = Path(__file__).resolve().parent / "operators"
_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")
#: A parameter ``main`` takes with no default: the data must give it.
REQUIRED = object()


def shipped() -> list[str]:
    """The shipped operators' names."""
    return sorted(p.stem for p in OPERATORS.glob("*.py") if not p.stem.startswith("_"))


def locate(script: str) -> Path:
    """The file of ``script`` (a shipped operator's name, or an absolute path).

    Raises:
        ValueError: If there is no such operator or file (naming the shipped ones).
    """
    if not isinstance(script, str) or not script:
        raise ValueError(f"script is {script!r}: name a shipped operator or give a path")
    if _NAME.match(script):
        path = OPERATORS / f"{script}.py"
        if not path.is_file():
            raise ValueError(
                f"no shipped operator {script!r}; shipped: {', '.join(shipped())} "
                "(or give the absolute path of a .py file)"
            )
        return path
    path = Path(script).expanduser()
    if not path.is_absolute():
        raise ValueError(
            f"script {script!r} is neither a shipped operator ({', '.join(shipped())}) nor an "
            "absolute path: the station's computer runs it, so give its full path"
        )
    if path.suffix != ".py" or not path.is_file():
        raise ValueError(f"script {script!r}: no Python file there")
    return path


@dataclass(frozen=True)
class MainSignature:
    """What a script's ``main`` takes, read from its syntax tree.

    Attributes:
        path: The script.
        is_async: ``async def main``.
        params: Parameter (after the robot) -> its default (a literal), or
            :data:`REQUIRED`; a default that is not a literal is ``None``.
        any_keyword: ``main`` takes ``**kwargs``.
    """

    path: Path
    is_async: bool
    params: dict[str, Any]
    any_keyword: bool


def read_main(path: Path) -> MainSignature:
    """Read ``main``'s signature from ``path`` without running it.

    Raises:
        ValueError: If the file does not parse, has no top-level ``main``, or ``main`` takes
            no robot.
    """
    try:
        tree = parse_source(path.read_text(encoding="utf-8"), str(path))
    except (OSError, SyntaxError, ValueError) as exc:
        raise ValueError(f"{path}: cannot read it: {exc}") from None
    found = [
        node
        for node in tree.body
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and node.name == "main"
    ]
    if not found:
        raise ValueError(f"{path} defines no main(robot); write `async def main(robot): ...`")
    main = found[-1]
    arguments = main.args
    positional = [*arguments.posonlyargs, *arguments.args]
    if not positional:
        raise ValueError(f"{path}: main takes no robot; write `main(robot, ...)`")
    defaults: list[Any] = [REQUIRED] * (len(positional) - len(arguments.defaults)) + [
        _literal(d) for d in arguments.defaults
    ]
    params = {a.arg: d for a, d in zip(positional[1:], defaults[1:], strict=True)}
    for a, d in zip(arguments.kwonlyargs, arguments.kw_defaults, strict=True):
        params[a.arg] = REQUIRED if d is None else _literal(d)
    return MainSignature(
        path,
        isinstance(main, ast.AsyncFunctionDef),
        params,
        arguments.kwarg is not None,
    )


def _literal(node: ast.expr) -> Any:
    try:
        return ast.literal_eval(node)
    except ValueError:
        return None  # not a literal: any value is taken


def check_script(value: Any) -> None:
    """The ``script`` parameter: a shipped operator or a file, with a ``main(robot)``."""
    read_main(locate(value))


def _same_type(default: Any, value: Any) -> bool:
    if default is None:
        return True
    if isinstance(default, bool) or isinstance(value, bool):
        return isinstance(default, bool) and isinstance(value, bool)
    if isinstance(default, int | float):
        return isinstance(value, int | float)
    if isinstance(default, list | tuple):
        return isinstance(value, list | tuple)
    return isinstance(value, type(default))


def check_arguments(signature: MainSignature, given: Mapping[str, Any]) -> None:
    """``params`` against ``main``'s signature.

    Raises:
        ValueError: Naming the parameter at fault and what ``main`` takes.
    """
    takes = ", ".join(signature.params) or "nothing but the robot"
    for key, value in given.items():
        if key not in signature.params:
            if signature.any_keyword:
                continue
            raise ValueError(f"params.{key}: main of {signature.path.name} takes {takes}")
        default = signature.params[key]
        if default is not REQUIRED and not _same_type(default, value):
            raise ValueError(
                f"params.{key} is {value!r}: main of {signature.path.name} expects a "
                f"{type(default).__name__} (its default is {default!r})"
            )
    missing = [k for k, d in signature.params.items() if d is REQUIRED and k not in given]
    if missing:
        raise ValueError(
            f"main of {signature.path.name} needs {', '.join(missing)}: give "
            + ", ".join(f"params.{k}" for k in missing)
        )


def validate(params: Mapping[str, Any], robots: Sequence[str] | None) -> None:
    """An autonomous operator's parameters as a whole (the kind's ``validate``).

    Raises:
        ValueError: For a missing or bad script, a robot the template does not have, or
            params its ``main`` does not take.
    """
    if "script" not in params:
        raise ValueError(
            f"no script: give script = one of {', '.join(shipped())}, or an absolute path"
        )
    signature = read_main(locate(params["script"]))
    robot = params.get("robot")
    if robot is not None:
        if not isinstance(robot, str):
            raise ValueError(f"robot is {robot!r}: name the robot by its root module")
        if robots is not None and robot not in robots:
            raise ValueError(
                f"robot {robot!r} is not one of the template's robots (named by their root "
                f"module): {', '.join(robots)}"
            )
    given = params.get("params", {})
    if not isinstance(given, Mapping):
        raise ValueError(f"params is {given!r}: give a table of main's keyword arguments")
    check_arguments(signature, given)
