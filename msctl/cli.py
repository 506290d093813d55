"""The ``msctl`` command line: one typer app, one module per command group.

Heavy imports (zenoh, mujoco, pinocchio) stay inside command bodies so ``msctl --help`` is
instant. Every failure goes through :func:`main`, which prints one clear line.
"""

from __future__ import annotations

import importlib
import os
import sys

import typer

from msctl.errors import MsctlError

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


def main() -> None:
    """Entry point: run the app and turn project errors into one red line and an exit code."""
    from rich.markup import escape

    from msctl.console import err

    try:
        # Standalone mode: typer prints its own usage errors and exits with code 2.
        app()
    except MsctlError as exc:
        if os.environ.get("MSCTL_DEBUG") == "1":
            err.print_exception()
        # Escaped: an operator's text such as "[joints.joint3]" must print as written.
        err.print(f"[bold red]error:[/] {escape(str(exc))}", highlight=False)
        sys.exit(exc.exit_code)
    except KeyboardInterrupt:
        err.print("[yellow]interrupted[/]")
        sys.exit(130)
    except Exception as exc:
        if os.environ.get("MSCTL_DEBUG") == "1":
            raise
        err.print(
            f"[bold red]internal error:[/] {type(exc).__name__}: {escape(str(exc))} "
            "(run again with MSCTL_DEBUG=1 for the traceback, and report it)",
            highlight=False,
        )
        sys.exit(70)
