"""``msctl restart COMPONENT``: restart one component's process, wherever it runs."""

from __future__ import annotations

import typer

COMMAND_SETTINGS = {"help": "Restart one component (its process), on whichever host runs it."}


def command(component: str = typer.Argument(..., help="Component or process name.")) -> None:
    """Restart the process that runs COMPONENT."""
    from msctl.launcher.remote import control_component

    control_component("restart", component)
