"""``msctl recover [MODULE...]``: undo ``msctl estop``; the modules take commands again."""

from __future__ import annotations

import typer

COMMAND_SETTINGS = {
    "help": "Recover every module (or those named) from a halt: they take commands again."
}


def command(
    modules: list[str] = typer.Argument(None, help="Modules to recover (default: every one)."),
    timeout: float = typer.Option(2.0, "--timeout", help="Seconds to wait for each module."),
    json_output: bool = typer.Option(False, "--json", help="Print one JSON document."),
) -> None:
    """Recover MODULES (default: every module) through their joint managers, all at once;
    joints stay held where they are until commanded; exit non-zero naming any module that
    did not acknowledge."""
    from msctl.commands.estop import trigger

    trigger("recover", modules or [], timeout, json_output)
