"""The ``msctl`` typer app: one module per command group, registered by name.

Heavy imports (zenoh, mujoco, pinocchio) stay inside command bodies so ``msctl --help`` is
instant. Run it through :func:`msctl.cli.main`, which turns every failure into one line.
"""

from __future__ import annotations

import importlib
from typing import Any, get_args, get_origin

import typer
import typer.main


def _new_app() -> typer.Typer:
    return typer.Typer(
        name="msctl",
        help="Field operations for modular, multi-computer robots: assemble, launch, monitor, "
        "teleoperate and record, over a ROS 2-compatible Zenoh data plane.",
        no_args_is_help=True,
        add_completion=False,
        pretty_exceptions_enable=False,
    )


# Command groups and single commands, registered by module name so that adding a command is
# adding a module. Each module exposes ``app`` (a group) or ``command`` (a single command).
_GROUPS: dict[str, str] = {
    "topic": "msctl.commands.topic",
    "node": "msctl.commands.node",
    "service": "msctl.commands.service",
    "assemble": "msctl.commands.assemble",
    "agent": "msctl.commands.agent",
    "bag": "msctl.commands.bag",
    "net": "msctl.commands.net",
    "rehearse": "msctl.commands.rehearse",
}
_COMMANDS: dict[str, str] = {
    "up": "msctl.commands.up",
    "down": "msctl.commands.down",
    "ps": "msctl.commands.ps",
    "logs": "msctl.commands.logs",
    "restart": "msctl.commands.restart",
    "stop": "msctl.commands.stop",
    "router": "msctl.commands.router",
    "run": "msctl.commands.run",
    "record": "msctl.commands.record",
    "bridge": "msctl.commands.bridge",
    "health": "msctl.commands.health",
    "view": "msctl.commands.view",
    "teleop": "msctl.commands.teleop",
    "claims": "msctl.commands.claims",
    "estop": "msctl.commands.estop",
    "recover": "msctl.commands.recover",
    "update": "msctl.commands.update",
    "build": "msctl.commands.build",
    "doctor": "msctl.commands.doctor",
}


def _register(target: typer.Typer, only: str | None = None) -> typer.Typer:
    """Register every command on ``target``, or only the one named ``only``."""
    for name, module_name in _GROUPS.items():
        if only is None or name == only:
            target.add_typer(importlib.import_module(module_name).app, name=name)
    for name, module_name in _COMMANDS.items():
        if only is None or name == only:
            module = importlib.import_module(module_name)
            target.command(name=name, **getattr(module, "COMMAND_SETTINGS", {}))(module.command)
    return target


_full: typer.Typer | None = None


def __getattr__(name: str) -> Any:
    """``app``: the typer app with every command, made when first asked for."""
    global _full
    if name != "app":
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    if _full is None:
        _full = _register(_new_app())
    return _full


#: Plain words for option values in ``--help`` (typer would print ``<bool>``, ``<list[str]>``).
_VALUE_WORDS: dict[type, str] = {int: "N", float: "NUMBER", str: "TEXT"}


def command(argv: list[str] | None = None) -> Any:
    """The click command of the app, with plain-word metavars throughout its help.

    Args:
        argv: The command line's arguments: when the first names a command, only that
            command's module is imported (``msctl ps`` started in 0.39 s with every command
            imported, 0.14 s with its own), a lone group or command with every other one
            absent; otherwise (``--help``, a typo) every command is there to list or suggest.
    """
    first = argv[0] if argv else None
    if first in _GROUPS or first in _COMMANDS:
        # A group of one is flattened by typer (`msctl ps` would become `msctl`): a hidden
        # no-op beside it keeps the command's name on the command line.
        only = _register(_new_app(), first)
        only.command(name="-", hidden=True)(lambda: None)
        root = typer.main.get_command(only)
    else:
        root = typer.main.get_command(__getattr__("app"))
    _plain_metavars(root)
    return root


def _plain_metavars(command: Any) -> None:
    help_option = command.get_help_option(typer.Context(command))
    for param in [*command.params, *([help_option] if help_option else [])]:
        if param.param_type_name == "argument":
            _plain_argument(param)
        elif param.metavar is None:
            param.metavar = _value_word(param)
    for sub in getattr(command, "commands", {}).values():
        _plain_metavars(sub)


def _value_word(option: Any) -> str:
    from pathlib import Path

    if getattr(option, "is_flag", False):
        return ""  # a switch takes no value
    descriptor = getattr(option, "type_descriptor", None)
    annotation = descriptor.annotation if descriptor is not None else str
    if get_origin(annotation) is list:
        (annotation,) = get_args(annotation)
    if isinstance(annotation, type) and issubclass(annotation, Path):
        return "PATH"
    return _VALUE_WORDS.get(annotation, "VALUE")


def _plain_argument(argument: Any) -> None:
    """``TOPIC`` and ``[VALUES]`` in the usage line, no ``<str>`` beside the name."""
    word = argument.metavar or argument.name.upper()
    shown = word if argument.required else f"[{word}]"
    if argument.nargs != 1:
        shown += "..."
    # typer has no setting for these two; instance attributes override its methods.
    argument.metavar = word
    argument._usage_display_name = lambda: shown
    argument.display_type_rich = lambda ctx: None
