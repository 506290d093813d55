"""The ``msctl`` typer app: one module per command group, registered by name.

Heavy imports (zenoh, mujoco, pinocchio) stay inside command bodies so ``msctl --help`` is
instant. Run it through :func:`msctl.cli.main`, which turns every failure into one line.
"""

from __future__ import annotations

import importlib
from typing import Any, get_args, get_origin

import typer
import typer.main

app = typer.Typer(
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
    "health": "msctl.commands.health",
    "teleop": "msctl.commands.teleop",
    "claims": "msctl.commands.claims",
    "estop": "msctl.commands.estop",
    "recover": "msctl.commands.recover",
    "update": "msctl.commands.update",
    "build": "msctl.commands.build",
}


def _register() -> None:
    for name, module_name in _GROUPS.items():
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name == module_name:
                continue  # a command group not written yet
            raise
        app.add_typer(module.app, name=name)
    for name, module_name in _COMMANDS.items():
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name == module_name:
                continue
            raise
        app.command(name=name, **getattr(module, "COMMAND_SETTINGS", {}))(module.command)


_register()


#: Plain words for option values in ``--help`` (typer would print ``<bool>``, ``<list[str]>``).
_VALUE_WORDS: dict[type, str] = {int: "N", float: "NUMBER", str: "TEXT"}


def command() -> Any:
    """The click command of :data:`app`, with plain-word metavars throughout its help."""
    root = typer.main.get_command(app)
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
