"""``msctl restart COMPONENT``: restart one component's process, wherever it runs."""

from __future__ import annotations

import typer

COMMAND_SETTINGS = {"help": "Restart one component (its process), on whichever host runs it."}


def command(
    component: str = typer.Argument(..., help="Component or process name."),
    only: bool = typer.Option(
        False,
        "--only",
        help="Rebuild just this component inside its process; the components sharing the "
        "process run on untouched.",
    ),
) -> None:
    """Restart the process that runs COMPONENT (and so every component sharing it), or with
    --only just COMPONENT."""
    from msctl.launcher.remote import control_component

    control_component("restart", component, only=only)
